"""C3D read/write: PROVENANCE.md statistics, units, labels > 255, model outputs, bad files."""

from __future__ import annotations

import struct
from pathlib import Path

import ezc3d
import numpy as np
import pytest

from mocapflow.stages.motion.datatypes import Markers
from mocapflow.stages.motion.formats.c3d import C3DError, classify_points, read_c3d, write_c3d
from mocapflow.stages.motion.ingest import gap_statistics, markers_report

DATA = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "c3d"


@pytest.fixture(scope="module")
def c3d_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip("shared data not available")
    return DATA


# PROVENANCE.md, c3d table.  "markers" = labelled markers kept in Markers.positions;
# "fragments" = '*N' unlabelled trajectories; "virtual"/"model" = points kept out.
# missing % = PROVENANCE figure, within half a unit of its last digit ("37 %" for PiG,
# one decimal for the others), over the point set it names: every point
# for the files without model outputs, "non-model points" (markers + fragments +
# virtual segment points = 177) for the Plug-in-Gait file.
# fmt: off
PROVENANCE = {
    "pyomeca_markers_analogs.c3d": dict(
        frames=580, rate=100.0, markers=51, fragments=0, virtual=0, model=0, missing=1.0,
        unit="mm", first=0, gaps=(34, 4, 71, 13),
    ),
    "ezc3d-testFiles_Qualisys.c3d": dict(
        frames=340, rate=200.0, markers=55, fragments=0, virtual=0, model=0, missing=0.0,
        unit="mm", first=704, gaps=(0, None, None, 0),
    ),
    "ktk_kinematics_basket_sprint.c3d": dict(
        frames=3678, rate=120.0, markers=26, fragments=0, virtual=0, model=0, missing=38.8,
        unit="m", first=0, gaps=(780, 3, 1760, None),
    ),
    "ktk_kinematics_racing_full.c3d": dict(
        frames=700, rate=69.9926, markers=46, fragments=0, virtual=0, model=0, missing=19.8,
        unit="m", first=0, gaps=(224, 7, 290, None),
    ),
    "btkdata_PiG_Calibration-FlatFoot-Hole.c3d": dict(
        frames=300, rate=100.0, markers=35, fragments=66, virtual=76, model=26, missing=37.0,
        unit="mm", first=0, gaps=(0, None, None, 0),
    ),
    "btkdata_c3dorg_Eb015pr.c3d": dict(
        frames=450, rate=50.0, markers=26, fragments=0, virtual=0, model=0, missing=1.9,
        unit="mm", first=0, gaps=(1, 12, 12, 1),
    ),
}
# fmt: on


@pytest.fixture(scope="module")
def read_all(c3d_dir):
    return {name: read_c3d(c3d_dir / name) for name in PROVENANCE}


@pytest.mark.parametrize("name", sorted(PROVENANCE))
def test_provenance_statistics(read_all, name):
    exp = PROVENANCE[name]
    m = read_all[name]
    rep = markers_report(m)
    assert m.n_frames == exp["frames"]
    assert m.rate == pytest.approx(exp["rate"], abs=5e-5)
    assert m.first_frame == exp["first"]
    assert m.attrs["source_unit"] == exp["unit"]
    assert (m.n_markers, m.fragments.shape[1]) == (exp["markers"], exp["fragments"])
    assert rep["excluded"].get("virtual_segment", 0) == exp["virtual"]
    assert rep["excluded"].get("model_output", 0) == exp["model"]
    total = exp["markers"] + exp["fragments"] + exp["virtual"] + exp["model"]
    assert m.attrs["n_points"] == total
    key = "missing_fraction_non_model" if exp["virtual"] else "missing_fraction"
    tol = 0.5 if name.startswith("btkdata_PiG") else 0.05
    assert abs(100 * rep[key] - exp["missing"]) <= tol + 1e-9
    count, median, longest, n_markers = exp["gaps"]
    g = rep["interior_gaps"]
    assert (g["count"], g["median"], g["max"]) == (count, median, longest)
    if n_markers is not None:
        assert g["markers"] == n_markers


def test_provenance_details(read_all):
    racing = read_all["ktk_kinematics_racing_full.c3d"]
    assert racing.rate == pytest.approx(69.99261, abs=1e-5)  # non-integer rate kept
    assert markers_report(racing)["never_seen"] == [f"Probe{i}" for i in range(1, 7)]
    assert read_all["btkdata_c3dorg_Eb015pr.c3d"].n_markers == 26  # 48 labels, 26 used
    eb_gaps = markers_report(read_all["btkdata_c3dorg_Eb015pr.c3d"])["interior_gaps"]
    assert eb_gaps["edge_gap_markers"] == 10
    pig = read_all["btkdata_PiG_Calibration-FlatFoot-Hole.c3d"]
    rasi = pig.labels.index("RASI")
    assert np.flatnonzero(~pig.visible[:, rasi]).tolist() == list(range(291, 300))
    assert pig.visible[:, [i for i in range(35) if i != rasi]].all()


def test_units_are_metres(read_all, c3d_dir):
    for name, m in read_all.items():
        seen = m.positions[m.visible.any(axis=1)]
        extent = np.nanmedian(np.nanmax(seen, 1) - np.nanmin(seen, 1), axis=0)
        assert 0.3 < extent.max() < 2.5, name  # a body / wheelchair, in metres
        raw = ezc3d.c3d(str(c3d_dir / name))
        lab = raw["parameters"]["POINT"]["LABELS"]["value"]
        i = lab.index(m.labels[0])
        k = {"mm": 1e-3, "m": 1.0}[m.attrs["source_unit"]]
        np.testing.assert_array_equal(m.positions[:, 0], raw["data"]["points"][:3, i].T * k)
    pig = read_all["btkdata_PiG_Calibration-FlatFoot-Hole.c3d"]
    heads = pig.positions[:, [pig.labels.index(n) for n in ("LFHD", "RFHD", "LBHD", "RBHD")], 2]
    toes = pig.positions[:, [pig.labels.index(n) for n in ("LTOE", "RTOE")], 2]
    assert 1.55 < heads.mean() < 1.80 and 0.0 < toes.mean() < 0.15


def test_residuals_in_metres(read_all, c3d_dir):
    m = read_all["btkdata_c3dorg_Eb015pr.c3d"]
    raw = ezc3d.c3d(str(c3d_dir / "btkdata_c3dorg_Eb015pr.c3d"))
    r = raw["data"]["meta_points"]["residuals"][0, :26].T
    vis = r >= 0
    np.testing.assert_allclose(m.residuals[vis], r[vis] * 1e-3, rtol=0, atol=1e-15)
    assert np.isnan(m.residuals[~vis]).all() and np.isnan(m.positions[~vis]).all()
    assert 0 < np.nanmax(m.residuals) < 0.01


def test_pig_excluded_points(read_all):
    m = read_all["btkdata_PiG_Calibration-FlatFoot-Hole.c3d"]
    ex = m.attrs["excluded_points"]
    virtual = {e["label"] for e in ex if e["kind"] == "virtual_segment"}
    assert {"PELO", "PELA", "PELL", "PELP", "LFEO", "RTOP", "HEDO", "TRXP"} <= virtual
    assert {lb[:3] for lb in virtual} == {
        "PEL", "HED", "TRX", "LCL", "RCL", "LHU", "RHU", "LRA", "RRA",
        "LHN", "RHN", "LFE", "RFE", "LTI", "RTI", "LFO", "RFO", "LTO", "RTO",
    }  # fmt: skip
    model = [e for e in ex if e["kind"] == "model_output"]
    assert all(e["reason"] == "listed in POINT:ANGLES" for e in model)
    assert {"LHipAngles", "RFootProgressAngles"} <= {e["label"] for e in model}
    assert m.fragment_labels == [f"*{i}" for i in range(1, 67)]
    lengths = np.isfinite(m.fragments).all(-1).sum(0)
    assert lengths.min() == 1 and lengths.max() == 43  # every fragment seen at least once
    assert not set(m.labels) & ({e["label"] for e in ex} | set(m.fragment_labels))


def test_classify_points_rules():
    labels = ["PELO", "LASI", "Sub:LKneeMoment", "X1", "*3", "LFEO", "LFEA", "LFEL", "RHipPower"]
    kinds = [k for k, _ in classify_points(labels, ["", "", "", "Angle"], {})]
    # a lone PELO is a real marker (no PEL A/L/P companions); LFE O/A/L are virtual
    assert kinds == [
        "marker", "marker", "model_output", "model_output", "fragment",
        "virtual_segment", "virtual_segment", "virtual_segment", "model_output",
    ]  # fmt: skip
    assert classify_points(["CoM"], [], {"CoM": "POINT:SCALARS"})[0] == (
        "model_output",
        "listed in POINT:SCALARS",
    )


def test_gap_statistics_synthetic():
    vis = np.ones((10, 3), bool)
    vis[2:5, 0] = False  # interior, 3
    vis[0:2, 1] = False  # edge
    vis[7:8, 1] = False  # interior, 1
    vis[6:10, 2] = False  # edge
    g = gap_statistics(vis)
    assert (g["count"], g["median"], g["max"], g["markers"], g["edge_gap_markers"]) == (
        2, 2.0, 3, 2, 2,
    )  # fmt: skip


# --------------------------------------------------------------------------- writing


def _synthetic(n_markers: int, n_frames: int, *, n_fragments: int = 0, seed: int = 0) -> Markers:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-1.5, 1.5, (n_frames, n_markers, 3)) + [0, 0, 1.5]
    pos[rng.random((n_frames, n_markers)) < 0.05] = np.nan
    res = np.where(np.isnan(pos[..., 0]), np.nan, rng.uniform(0, 2e-3, (n_frames, n_markers)))
    frag = np.full((n_frames, n_fragments, 3), np.nan)
    for j in range(n_fragments):
        frag[j : j + 3, j] = rng.uniform(-1, 1, (3, 3))
    return Markers(
        positions=pos,
        labels=[f"M{i:03d}" for i in range(n_markers)],
        rate=69.9926,
        first_frame=17,
        residuals=res,
        fragments=frag,
        fragment_labels=[f"*{j + 1}" for j in range(n_fragments)],
    )


def test_write_400_markers_reads_back_everywhere(tmp_path):
    import kineticstoolkit as ktk

    m = _synthetic(400, 12, n_fragments=5)
    path = write_c3d(m, tmp_path / "dense.c3d")
    back = read_c3d(path)
    assert back.labels == m.labels and back.fragment_labels == m.fragment_labels
    np.testing.assert_allclose(back.positions, m.positions, atol=1e-6, rtol=0)
    np.testing.assert_allclose(back.fragments, m.fragments, atol=1e-6, rtol=0)
    np.testing.assert_array_equal(back.visible, m.visible)
    assert back.first_frame == 17
    assert back.rate == pytest.approx(69.9926, rel=1e-7)  # POINT:RATE is float32
    quantum = np.nanmax(m.residuals) / 255
    np.testing.assert_allclose(back.residuals, m.residuals, atol=quantum / 2 + 1e-12, rtol=0)

    raw = ezc3d.c3d(str(path))
    P = raw["parameters"]["POINT"]
    assert P["USED"]["value"][0] == 405
    assert len(P["LABELS"]["value"]) == 255 and len(P["LABELS2"]["value"]) == 150
    assert P["LABELS"]["value"] + P["LABELS2"]["value"] == m.labels + m.fragment_labels
    res = raw["data"]["meta_points"]["residuals"][0].T
    assert ((res < 0) == ~np.concatenate([m.visible, np.isfinite(m.fragments[..., 0])], 1)).all()

    with pytest.warns(UserWarning):  # ktk warns that it converts mm to m
        pts = ktk.read_c3d(str(path))["Points"]
    assert list(pts.data) == m.labels + m.fragment_labels
    assert pts.time[0] == pytest.approx(17 / 69.9926, rel=1e-6)
    for i in (0, 254, 255, 399):
        np.testing.assert_allclose(pts.data[m.labels[i]][:, :3], m.positions[:, i], atol=1e-6)


@pytest.mark.parametrize("unit", ["m", "cm", "mm"])
def test_write_units(tmp_path, unit):
    m = _synthetic(7, 9, seed=2)
    back = read_c3d(write_c3d(m, tmp_path / f"u_{unit}.c3d", unit=unit))
    assert back.attrs["source_unit"] == unit
    np.testing.assert_allclose(back.positions, m.positions, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="unknown unit"):
        write_c3d(m, tmp_path / "bad.c3d", unit="furlong")


def test_real_file_round_trip(read_all, tmp_path):
    m = read_all["btkdata_PiG_Calibration-FlatFoot-Hole.c3d"]
    back = read_c3d(write_c3d(m, tmp_path / "pig.c3d", unit="mm"))
    assert back.labels == m.labels and back.fragment_labels == m.fragment_labels
    np.testing.assert_allclose(back.positions, m.positions, atol=1e-6, rtol=0)
    np.testing.assert_allclose(back.fragments, m.fragments, atol=1e-6, rtol=0)
    assert back.attrs["excluded_points"] == []  # model outputs are not written back


# --------------------------------------------------------------------------- bad files


def _small_file(tmp_path: Path) -> bytes:
    return write_c3d(_synthetic(5, 30, seed=3), tmp_path / "ok.c3d").read_bytes()


def _bad(tmp_path: Path, name: str, data: bytes) -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


def test_empty_and_garbage_files(tmp_path):
    for name, data, msg in [
        ("empty.c3d", b"", "empty file"),
        ("short.c3d", b"\x02\x50" + bytes(100), "truncated"),
        ("text.c3d", b"hello world\n" * 100, "not a C3D file"),
    ]:
        p = _bad(tmp_path, name, data)
        with pytest.raises(C3DError, match=msg) as e:
            read_c3d(p)
        assert str(p) in str(e.value)
    with pytest.raises(C3DError, match="cannot read"):
        read_c3d(tmp_path / "absent.c3d")


def test_truncated_copies_raise_not_crash(tmp_path, c3d_dir):
    for data in (_small_file(tmp_path), (c3d_dir / "btkdata_c3dorg_Eb015pr.c3d").read_bytes()):
        pstart = (data[0] - 1) * 512
        cuts = sorted(
            {1, 511, pstart + 3, pstart + 10, pstart + 300, pstart + 700}
            | {int(x) for x in np.linspace(pstart + 800, len(data) - 512, 12)}
        )  # (the last block is padding: cuts stop 512 bytes before the end)
        for cut in cuts:
            p = _bad(tmp_path, f"cut{cut}.c3d", data[:cut])
            with pytest.raises(C3DError, match="truncated|corrupt|not a C3D") as e:
                read_c3d(p)
            assert str(p) in str(e.value)


def test_corrupt_parameter_section(tmp_path):
    data = bytearray(_small_file(tmp_path))
    pstart = (data[0] - 1) * 512
    cases = {}
    d = bytearray(data)
    d[pstart + 3] = 99  # processor type
    cases["proc"] = (d, "processor type")
    d = bytearray(data)
    d[1] = 0x51  # header key
    cases["key"] = (d, "not a C3D file")
    d = bytearray(data)
    nchar = abs(struct.unpack_from("b", d, pstart + 4)[0])
    struct.pack_into("<H", d, pstart + 6 + nchar, 1)  # first offset points backwards
    cases["offset"] = (d, "bad offset|runs past|corrupt")
    d = bytearray(data)
    struct.pack_into("<H", d, 2, 6)  # header point count != POINT:USED
    cases["used"] = (d, "POINT:USED")
    for name, (blob, msg) in cases.items():
        p = _bad(tmp_path, f"{name}.c3d", bytes(blob))
        with pytest.raises(C3DError, match=msg) as e:
            read_c3d(p)
        assert str(p) in str(e.value)


def test_random_corruption_never_crashes(tmp_path):
    data = _small_file(tmp_path)
    pstart = (data[0] - 1) * 512
    rng = np.random.default_rng(11)
    for k in range(60):
        d = bytearray(data)
        for i in rng.integers(0, pstart + 512, size=rng.integers(1, 6)):
            d[i] = int(rng.integers(0, 256))
        p = _bad(tmp_path, f"flip{k}.c3d", bytes(d))
        try:
            read_c3d(p)  # some flips are harmless (descriptions, padding)
        except C3DError as e:
            assert str(p) in str(e)


def _edited(tmp_path: Path, m: Markers, name: str, **point: list[str]) -> Path:
    """``m`` written, then its POINT parameters ``point`` (LABELS, UNITS …) set by ezc3d."""
    c = ezc3d.c3d(str(write_c3d(m, tmp_path / f"{name}_src.c3d", unit="m")))
    for key, value in point.items():
        c["parameters"]["POINT"][key]["value"] = value
    c.write(str(tmp_path / f"{name}.c3d"))
    return tmp_path / f"{name}.c3d"


def test_shared_labels_are_joined_when_apart_and_renamed_when_together(tmp_path):
    # was: C3DError "POINT:LABELS: 'A' names points 1 and 3" for the whole file
    # (btk_Gait.c3d: cut 4-letter names; Qualisys ktk_duplicate_labels.c3d: pieces)
    m = _synthetic(5, 10, seed=7)
    m.positions[:] = 1 + np.arange(5)[:, None] + 0.01 * np.arange(10)[:, None, None]
    m.positions[4:, 0] = np.nan  # A: frames 0-3 from point 1 ...
    m.positions[:4, 2] = np.nan  # ... and 4-9 from point 3, never seen together
    m.residuals[:] = 1e-3
    p = _edited(tmp_path, m, "shared", LABELS=["A", "B", "A", "B", "B_2"],
                DESCRIPTIONS=["", "", "", "B.Medial", ""])
    back = read_c3d(p)
    assert back.labels == ["A", "B", "B_3", "B_2"]  # B_2 taken: the next free name
    joined = np.concatenate([m.positions[:4, 0], m.positions[4:, 2]])
    np.testing.assert_allclose(back.positions[:, 0], joined, atol=1e-6, rtol=0)
    assert back.visible.all()
    np.testing.assert_allclose(back.positions[:, 1:], m.positions[:, [1, 3, 4]], atol=1e-6)
    assert back.attrs["read_notes"] == [
        "POINT:LABELS 'A' names points 1, 3: 1, 3 joined into one trajectory "
        "(never visible in the same frame)",
        "POINT:LABELS 'B' names points 2, 4: 4 ('B.Medial') renamed 'B_3' "
        "(seen together with point 2)",
    ]
    assert "read_notes" not in read_c3d(tmp_path / "shared_src.c3d").attrs
    # the ingest says what the reader did, one warning per note
    from mocapflow.pipeline import Context  # noqa: PLC0415
    from mocapflow.stages.motion.ingest import ingest_c3d  # noqa: PLC0415

    ctx = Context()
    ingest_c3d(p, ctx=ctx)
    assert [w for w in ctx.warnings if "POINT:LABELS" in w] == [
        f"{p.name}: {note}" for note in back.attrs["read_notes"]]


@pytest.mark.parametrize(("units", "unit", "k"), [
    ("mete", "m", 1.0), ("meters", "m", 1.0), ("mill", "mm", 1e-3), ("cent", "cm", 1e-2),
])
def test_cut_unit_words_are_read(tmp_path, units, unit, k):
    # was: C3DError "unsupported POINT:UNITS 'mete'" (btk_FP1.C3D: "meters" cut to 4 chars)
    m = _synthetic(3, 4, seed=5)
    back = read_c3d(_edited(tmp_path, m, "cut", UNITS=[units]))
    assert back.attrs["source_unit"] == unit
    assert back.attrs["read_notes"] == [f"POINT:UNITS {units!r} read as {unit!r}"]
    np.testing.assert_allclose(back.positions, m.positions * k, atol=1e-6 * k, rtol=0)
    with pytest.raises(C3DError, match="unsupported POINT:UNITS 'me'"):
        read_c3d(_edited(tmp_path, m, "short", UNITS=["me"]))  # too short to say which


def test_samples_exactly_at_the_origin_are_missing(tmp_path):
    # was: read as seen (btk_FunctionalLHip.c3d: 38 of 74 points at (0, 0, 0) throughout)
    m = _synthetic(4, 6, seed=9)
    m.positions[:] = 1.0
    m.positions[:, 1] = 0.0  # every frame
    m.positions[[2, 4], 2] = 0.0  # two frames
    m.positions[3, 3] = [0.0, 0.0, 1.0]  # one coordinate 0: a real position
    m.residuals[:] = 1e-3
    back = read_c3d(write_c3d(m, tmp_path / "zeros.c3d"))
    seen = np.ones((6, 4), bool)
    seen[:, 1] = False
    seen[[2, 4], 2] = False
    np.testing.assert_array_equal(back.visible, seen)
    assert np.isnan(back.residuals[~seen]).all() and (back.residuals[seen] > 0).all()
    assert back.attrs["read_notes"] == [
        "8 samples of 2 points exactly at (0, 0, 0) read as missing; "
        "at (0, 0, 0) in every frame: M001"
    ]


def test_unknown_unit_is_an_error(tmp_path):
    path = write_c3d(_synthetic(3, 4, seed=5), tmp_path / "u.c3d")
    c = ezc3d.c3d(str(path))
    c["parameters"]["POINT"]["UNITS"]["value"] = ["furlong"]
    c.write(str(tmp_path / "furlong.c3d"))
    with pytest.raises(C3DError, match="furlong"):
        read_c3d(tmp_path / "furlong.c3d")


@pytest.mark.parametrize(("name", "pattern"), [
    # was a UnicodeEncodeError in store.commit naming no label
    ("label_not_utf8", r"POINT:LABELS entry 2 is not UTF-8: b'\\xff\\xe4BB'"),
    ("coordinate_1e30", r"POINT data: point 'M000' is 1e\+27 m from the origin in frame 0"),
    ("coordinate_inf", r"POINT data: point 'M000' is inf m from the origin in frame 0"),
])
def test_labels_and_coordinates_are_checked_at_read_time(fuzz, tmp_path, name, pattern):
    buf = bytearray(_small_file(tmp_path))
    fuzz.c3d_built()[name](buf, fuzz.c3d_entries(bytes(buf)))
    p = _bad(tmp_path, f"{name}.c3d", bytes(buf))
    with pytest.raises(C3DError, match=pattern) as e:
        read_c3d(p)
    assert str(e.value).startswith(f"{p}: ")



def test_written_files_pass_the_reader_checks_at_every_section_size(tmp_path, fuzz):
    # a kept text parameter one byte longer each time walks the parameter section's end
    # over every byte of a block, including the case where its one-byte terminator is
    # the block's last byte (which ezc3d reads, and the reader once refused)
    m = _synthetic(3, 2, n_fragments=0)
    at_last_byte = 0
    for n in range(700):
        notes = {f"NOTE{k}": {"type": "char", "description": "", "is_locked": False,
                              "dimension": [1], "value": ["x" * (100 if k < n // 100 else
                                                                 n % 100 + 1)]}
                 for k in range(n // 100 + 1)}  # C3D text entries: at most 255 bytes
        tree = {"TRIAL": {"description": "", "is_locked": False, "parameters": notes}}
        p = write_c3d(m.replace(attrs={"c3d_parameters": tree}), tmp_path / "n.c3d")
        back = read_c3d(p)  # raises if the file fails the reader's checks
        np.testing.assert_allclose(back.positions, m.positions, atol=1e-6, rtol=0)
        params = ezc3d.c3d(str(p))["parameters"]
        assert [params["TRIAL"][k]["value"] for k in notes] == [v["value"] for v in
                                                                 notes.values()]
        buf = p.read_bytes()
        start = (buf[0] - 1) * 512
        last = fuzz.c3d_entries(buf)[-1]
        nxt = last["off_at"] + int.from_bytes(buf[last["off_at"]:last["off_at"] + 2], "little")
        at_last_byte += nxt == start + 512 * buf[start + 2] - 1
    assert at_last_byte > 0, "no section ended at a block's last byte: the test no longer covers it"


def test_a_file_the_reader_would_reject_is_not_written(tmp_path):
    # a 300-byte text entry does not fit C3D's byte-sized dimensions: ezc3d writes a
    # broken parameter section; write_c3d says so for the target and leaves nothing
    note = {"type": "char", "description": "", "is_locked": False, "dimension": [1],
            "value": ["x" * 300]}
    tree = {"TRIAL": {"description": "", "is_locked": False, "parameters": {"NOTE": note}}}
    m = _synthetic(3, 2, n_fragments=0).replace(attrs={"c3d_parameters": tree})
    out = tmp_path / "long.c3d"
    with pytest.raises(C3DError, match=r"long\.c3d: ezc3d wrote a file the reader rejects: "
                       r"corrupt parameter section: parameter TRIAL:NOTE"):
        write_c3d(m, out)
    assert list(tmp_path.iterdir()) == []
