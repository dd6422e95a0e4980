"""C3D validation before ezc3d: the layout ezc3d reads, and the files it would crash on.

``check_file`` is pure Python, so these tests never hand a hostile file to ezc3d (the
fuzz test does that, in child processes).
"""

from __future__ import annotations

import struct
from pathlib import Path

import ezc3d
import pytest

from mocapflow.stages.motion.formats.c3d import read_c3d, write_c3d
from mocapflow.stages.motion.formats.c3d_check import C3DError, check_file

from .test_c3d import _synthetic


def test_layout_is_what_ezc3d_reads(shared_data, tmp_path):
    files = sorted((shared_data / "c3d").glob("*.c3d"))
    files.append(write_c3d(_synthetic(300, 4, n_fragments=2), tmp_path / "wide.c3d"))
    for p in files:
        layout = check_file(p)
        h = ezc3d.ezc3d.c3d(str(p)).header()
        assert (layout.n_frames, layout.first_frame, layout.n_points) == (
            h.nbFrames(), h.firstFrame(), h.nb3dPoints()), p.name
        assert layout.n_analog_per_frame == h.nbAnalogs() * h.nbAnalogByFrame(), p.name


def _edited(fuzz, tmp_path: Path, name: str, base: bytes | None = None) -> Path:
    buf = bytearray(base if base is not None else write_c3d(
        _synthetic(5, 30, seed=3), tmp_path / "ok.c3d").read_bytes())
    fuzz.c3d_built()[name](buf, fuzz.c3d_entries(bytes(buf)))
    p = tmp_path / f"{name}.c3d"
    p.write_bytes(bytes(buf))
    return p


@pytest.mark.parametrize(("name", "pattern"), [
    # each of these made ezc3d crash (SIGSEGV), throw, or allocate/read without bound
    ("char_param_no_dims", r"corrupt parameter POINT:USED: character data without dimensions"),
    ("description_length_200", r"parameter section: group 'POINT' has description length 200"),
    ("frames_float", r"POINT:FRAMES is stored as float data; a C3D int parameter"),
    ("frames_65535", r"the data block needs \d+ \(65535 frames of 5 points; only 32 complete"),
    ("analog_rate_1e30", r"ANALOG:RATE 1e\+30 / POINT:RATE 69.99\d+ is 1.43e\+28 analog samples"),
    ("point_rate_nan", r"POINT:RATE is nan: a rate must be finite"),
    ("point_scale_zero", r"POINT:SCALE is 0.0: the points cannot be scaled"),
    ("processor_mips", r"processor type 86 \(MIPS\), which ezc3d refuses"),
])
def test_files_ezc3d_would_crash_on_are_refused_first(fuzz, tmp_path, name, pattern):
    p = _edited(fuzz, tmp_path, name)
    with pytest.raises(C3DError, match=pattern) as e:
        check_file(p)
    assert str(e.value).startswith(f"{p}: ")


def test_entries_must_chain_exactly_and_analog_lists_cover_the_channels(fuzz, tmp_path,
                                                                          shared_data):
    data = (shared_data / "c3d" / "pyomeca_markers_analogs.c3d").read_bytes()
    ents = {e["full"]: e for e in fuzz.c3d_entries(data)}
    buf = bytearray(data)
    off = ents["POINT:RATE"]["off_at"]
    struct.pack_into("<H", buf, off, struct.unpack_from("<H", buf, off)[0] + 2)
    (tmp_path / "gap.c3d").write_bytes(bytes(buf))
    with pytest.raises(C3DError, match=r"parameter POINT:RATE at byte \d+ ends at byte (\d+) "
                                       r"but its offset points to byte \d+"):
        check_file(tmp_path / "gap.c3d")
    buf = bytearray(data)
    struct.pack_into("<h", buf, ents["ANALOG:USED"]["data_at"], 200)  # 38 scales, 38 offsets
    (tmp_path / "used.c3d").write_bytes(bytes(buf))
    with pytest.raises(C3DError, match=r"ANALOG:SCALE has 38 entries for 200 analog channels"):
        check_file(tmp_path / "used.c3d")


def test_parameters_of_an_undefined_group_are_skipped(fuzz, tmp_path):
    # was: C3DError "parameter 'IS_STATIC' belongs to undefined group id 7" (btk_TYPE-2.C3D),
    # which ezc3d reads
    src = write_c3d(_synthetic(5, 30, seed=3), tmp_path / "ok.c3d")
    buf = bytearray(src.read_bytes())
    ents = {e["full"]: e for e in fuzz.c3d_entries(bytes(buf))}
    buf[ents["MOCAPFLOW:SOFTWARE"]["pos"] + 1] = 77  # no group has id 77
    (tmp_path / "orphan.c3d").write_bytes(bytes(buf))
    assert check_file(tmp_path / "orphan.c3d") == check_file(src)
    m, ref = read_c3d(tmp_path / "orphan.c3d"), read_c3d(src)
    assert m.attrs["read_notes"] == ["parameters of an undefined group skipped: SOFTWARE"]
    assert "SOFTWARE" not in m.attrs["c3d_parameters"]["MOCAPFLOW"]["parameters"]
    assert (m.positions.tobytes(), m.labels) == (ref.positions.tobytes(), ref.labels)


def test_frames_with_analog_words_the_parameters_do_not_size(fuzz, tmp_path):
    """A file whose frames hold analog words that ezc3d does not count (here ANALOG:RATE 0;
    c3d.org sample28 has no ANALOG:RATE at all) is read with the header's frame size:
    ezc3d alone reads every frame after the first from the wrong place (c3d.org
    sample28 ``standing.C3D``: every step of every marker over 10 cm)."""
    import dataclasses

    import numpy as np

    m = _synthetic(5, 30, seed=4)
    m = dataclasses.replace(m, analogs=np.arange(30 * 2 * 3, dtype=float).reshape(60, 3))
    buf = bytearray(write_c3d(m, tmp_path / "analog.c3d").read_bytes())
    rate = next(e for e in fuzz.c3d_entries(bytes(buf)) if e["full"] == "ANALOG:RATE")
    struct.pack_into("<f", buf, rate["data_at"], 0.0)
    p = tmp_path / "analog_rate_0.c3d"
    p.write_bytes(bytes(buf))
    h = ezc3d.ezc3d.c3d(str(p)).header()
    assert h.nbAnalogByFrame() == 0 and check_file(p).header_analog_words == 6
    plain = np.asarray(ezc3d.c3d(str(p))["data"]["points"])[:3].transpose(2, 1, 0) / 1000
    seen = np.isfinite(m.positions).all(-1) & np.isfinite(plain).all(-1)
    assert np.abs(plain[seen] - m.positions[seen]).max() > 0.1  # ezc3d alone: misread
    back = read_c3d(p)
    assert back.labels == m.labels
    assert back.attrs["read_notes"] == ["points read with the header's frame size: 6 analog "
                                        "words a frame that the ANALOG parameters do not size "
                                        "(no analog data read)"]
    np.testing.assert_array_equal(np.isnan(back.positions), np.isnan(m.positions))
    np.testing.assert_allclose(back.positions, m.positions, atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(back.residuals, m.residuals, atol=1e-4, equal_nan=True)


def test_a_file_without_a_point_group_says_what_it_holds(fuzz, tmp_path):
    """No POINT group: a file of analog data only (ezc3d's Kistler.c3d) says so; a file
    whose header still counts points (c3d.org sample20, PhaseSpace: 40) says they cannot
    be read."""
    buf = bytearray(write_c3d(_synthetic(5, 30, seed=3), tmp_path / "ok.c3d").read_bytes())
    group = next(e for e in fuzz.c3d_entries(bytes(buf)) if e["full"] == "POINT")
    buf[group["pos"] + 2 : group["pos"] + 7] = b"PXINT"  # the group renamed
    p = tmp_path / "no_point_group.c3d"
    p.write_bytes(bytes(buf))
    with pytest.raises(C3DError, match=r"no POINT group in the parameter section: the "
                       r"header's 5 points have no labels, rate or unit to read them with$"):
        check_file(p)
    struct.pack_into("<H", buf, 2, 0)  # the header's point count 0: no marker data
    p.write_bytes(bytes(buf))
    with pytest.raises(C3DError, match=r"no POINT group in the parameter section: no marker "
                       r"data \(the file holds ANALOG, FORCE_PLATFORM, ROTATION only\)$"):
        check_file(p)
