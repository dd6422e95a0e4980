"""Pen strokes: UCI Character Trajectories, Omniglot, mocapflow strokes CSV."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from mocapflow.pipeline.codecs import decode, encode
from mocapflow.stages.motion.datatypes import Strokes, StrokesSet
from mocapflow.stages.motion.formats.strokes import (
    StrokesFileError,
    read_omniglot,
    read_strokes_csv,
    read_strokes_file,
    read_uci_chartraj,
    write_strokes_csv,
)

DATA = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "strokes"


@pytest.fixture(scope="module")
def strokes_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip("shared data not available")
    return DATA


@pytest.fixture(scope="module")
def uci(strokes_dir):
    return read_uci_chartraj(strokes_dir / "uci_chartraj_mv_subset.csv")


def _same(a: Strokes, b: Strokes) -> bool:
    times_ok = (a.times is None and b.times is None) or np.array_equal(a.times, b.times)
    rate_ok = a.rate == b.rate or (math.isnan(a.rate) and math.isnan(b.rate))
    return (
        np.array_equal(a.points, b.points)
        and np.array_equal(a.stroke_starts, b.stroke_starts)
        and times_ok
        and rate_ok
        and a.attrs == b.attrs
    )


def test_uci_counts_and_values(uci, strokes_dir):
    assert len(uci) == 100 and sum(len(s.points) for s in uci) == 12239  # PROVENANCE
    letters = sorted({s.attrs["letter"] for s in uci})
    assert len(letters) == 20 and all(
        sum(s.attrs["letter"] == x for s in uci) == 5 for x in letters
    )
    lengths = [len(s.points) for s in uci]
    assert min(lengths) == 77 and max(lengths) == 204
    a = [s for s in uci if s.attrs["letter"] == "a"]
    assert [s.attrs["example"] for s in a] == [1, 2, 3, 4, 5]
    assert [len(s.points) for s in a] == [138, 143, 138, 136, 139]  # 136–143
    assert all(s.rate == 200.0 and s.stroke_starts.tolist() == [0] for s in uci)
    # independent parse of the CSV: x, y columns of 'a' example 2
    raw = np.genfromtxt(
        strokes_dir / "uci_chartraj_mv_subset.csv", delimiter=",", names=True, dtype=None,
        encoding="utf-8",
    )  # fmt: skip
    sel = (raw["letter"] == "a") & (raw["example"] == 2)
    np.testing.assert_array_equal(a[1].points, np.c_[raw["x"][sel], raw["y"][sel]])
    np.testing.assert_array_equal(a[1].times, raw["sample"][sel] / 200.0)
    # x, y are the cumulative sums of vx, vy (PROVENANCE)
    np.testing.assert_allclose(a[1].points[:, 0], np.cumsum(raw["vx"][sel]), atol=1e-3)


def test_uci_letter_filter(strokes_dir):
    q = read_uci_chartraj(strokes_dir / "uci_chartraj_mv_subset.csv", letter="q")
    assert [s.attrs["example"] for s in q] == [1, 2, 3, 4, 5]
    with pytest.raises(StrokesFileError, match="no rows for letter 'x'"):
        read_uci_chartraj(strokes_dir / "uci_chartraj_mv_subset.csv", letter="x")


def test_omniglot_every_file(strokes_dir):
    files = sorted((strokes_dir / "omniglot_latin").glob("character*/*.txt"))
    assert len(files) == 520
    for f in files:
        lines = [ln.strip() for ln in f.read_text().splitlines() if ln.strip()]
        s = read_omniglot(f)
        assert len(s.stroke_starts) == lines.count("BREAK")
        assert len(s.points) == len(lines) - 1 - lines.count("BREAK")
        assert s.rate > 0 and s.times is not None
    first = read_omniglot(strokes_dir / "omniglot_latin" / "character01" / "0683_01.txt")
    assert first.stroke_starts.tolist() == [0, 14] and len(first.points) == 67
    assert first.points[0].tolist() == [68.75, -25.859438] and first.times[1] == 0.14
    assert first.attrs["letter"] == "a" and first.attrs["drawer"] == 1
    z = read_omniglot(next((strokes_dir / "omniglot_latin" / "character26").glob("*.txt")))
    assert z.attrs["letter"] == "z"


def test_csv_round_trip_exact(uci, strokes_dir, tmp_path):
    omni = read_omniglot(strokes_dir / "omniglot_latin" / "character09" / "0691_01.txt")
    bare = Strokes(points=[[0.1, 0.2], [1 / 3, 2e-300]], stroke_starts=[0, 1], rate=math.nan)
    items = uci[:3] + [omni, bare]
    path = write_strokes_csv(items, tmp_path / "s.csv")
    back = read_strokes_csv(path)
    assert len(back) == 5 and all(_same(a, b) for a, b in zip(items, back))
    assert all(_same(a, b) for a, b in zip(items, read_strokes_file(path)))


def test_strokes_set_codec_exact(uci, strokes_dir):
    omni = read_omniglot(strokes_dir / "omniglot_latin" / "character02" / "0684_01.txt")
    ss = StrokesSet(uci[:5] + [omni, Strokes(points=[[1.0, 2.0]], stroke_starts=[0], rate=3)])
    back = decode(encode(ss))
    assert isinstance(back, StrokesSet) and len(back) == 7
    assert all(_same(a, b) for a, b in zip(ss, back))
    with pytest.raises(TypeError):
        StrokesSet([1, 2])


def test_dispatch_by_content(strokes_dir):
    items = read_strokes_file(strokes_dir / "uci_chartraj_mv_subset.csv", letter="a")
    assert len(items) == 5
    o = read_strokes_file(strokes_dir / "omniglot_latin" / "character03" / "0685_01.txt")
    assert len(o) == 1 and o[0].attrs["letter"] == "c"


@pytest.mark.parametrize(
    ("name", "text", "msg"),
    [
        ("empty.csv", "", "empty file"),
        ("cols.csv", "letter,example,sample,x\na,1,0,0\n", r"lacks column\(s\) \['y'\]"),
        ("fields.csv", "letter,example,sample,x,y\na,1,0,0,0\na,1,1,0\n", "line 3: expected 5"),
        ("nan.csv", "letter,example,sample,x,y\na,1,0,0,zz\n", "line 2: column 'y'"),
        ("gap.csv", "letter,example,sample,x,y\na,1,0,0,0\na,1,2,0,0\n", "sample 2, expected 1"),
        ("int.csv", "letter,example,sample,x,y\na,one,0,0,0\n", "line 2: example and sample"),
        ("nostart.txt", "1,2,3\nBREAK\n", "starts with START"),
        ("row.txt", "START\n1,2,3\n1,2\nBREAK\n", "line 3: expected 'x,y,t_ms'"),
        ("nostroke.txt", "START\nBREAK\n", "no stroke samples"),
        ("twostart.txt", "START\n1,2,3\nSTART\n", "line 3: second START"),
        ("inf.csv", "letter,example,sample,x,y\na,1,0,0,inf\n", "line 2: column 'y': 'inf' is not"),
        ("empty_x.csv", "letter,example,sample,x,y\na,1,0,,1\n", "line 2: column 'x': '' is not"),
        ("inf.txt", "START\n1,2,3\n1,nan,4\nBREAK\n", "line 3: stroke sample 'x,y,t_ms' is not"),
        ("junk.dat", "hello\n", "line 1: not a stroke file"),
    ],
)
def test_malformed_files(tmp_path, name, text, msg):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(StrokesFileError, match=msg) as e:
        read_strokes_file(p)
    assert str(p) in str(e.value)


def test_malformed_mocapflow_csv(tmp_path, uci):
    path = write_strokes_csv(uci[:1], tmp_path / "ok.csv")
    lines = path.read_text().splitlines()
    bad_meta = tmp_path / "meta.csv"
    bad_meta.write_text("\n".join([lines[0], "# example 0 {not json", *lines[2:]]))
    with pytest.raises(StrokesFileError, match="line 2: malformed '# example' line"):
        read_strokes_csv(bad_meta)
    orphan = tmp_path / "orphan.csv"
    orphan.write_text("\n".join([*lines, "7,0,1.0,2.0,0.5"]))
    with pytest.raises(StrokesFileError, match="example 7 has no '# example' line"):
        read_strokes_csv(orphan)
    with pytest.raises(StrokesFileError, match="not a mocapflow strokes CSV"):
        read_strokes_csv(_write(tmp_path, "x.csv", "a,b\n"))
    for meta, msg in [
        ("[" * 100_000 + "]" * 100_000, "malformed '# example' line"),  # was a RecursionError
        ("[]", "'# example' line: expected a JSON object, got list"),
        ('{"rate": -1}', "'# example' line: rate -1 is not a finite number > 0"),
        ('{"rate": "abc"}', "'# example' line: rate 'abc' is not a number"),
        ('{"rate": 100, "attrs": 5}', "'# example' line: attrs is a int, not an object"),
        ('{"rate": 100, "times": "yes"}', "'# example' line: times is 'yes', not true or"),
    ]:
        bad_meta.write_text("\n".join([lines[0], f"# example 0 {meta}", *lines[2:]]))
        with pytest.raises(StrokesFileError, match=rf"meta\.csv, line 2: {re.escape(msg)}"):
            read_strokes_csv(bad_meta)
    inf_x = lines[:4] + [lines[4].replace(lines[4].split(",")[2], "inf", 1)] + lines[5:]
    with pytest.raises(StrokesFileError, match=r"line 5: column 'x': 'inf' is not finite"):
        read_strokes_csv(_write(tmp_path, "inf.csv", "\n".join(inf_x)))


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p
