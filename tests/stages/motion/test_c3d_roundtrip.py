"""Whole C3D round trips: ingest -> clean -> export keeps the analogs and every parameter
group of the source, POINT data equal to the clean output, residuals that say measured /
merged / filled; TRC read back by OpenSim's own reader.

Prints nothing; ``python tests/stages/motion/test_c3d_roundtrip.py`` prints the numbers.
"""

from __future__ import annotations

import os
import stat
import sys
from pathlib import Path

import ezc3d
import numpy as np
import pytest

from mocapflow.pipeline import Context
from mocapflow.stages.motion.datatypes import Markers
from mocapflow.stages.motion.export import export_markers_c3d, export_markers_trc
from mocapflow.stages.motion.formats.c3d import read_c3d
from mocapflow.stages.motion.ingest import ingest_c3d
from mocapflow.stages.skin.clean import clean

DATA = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "c3d"
VICON = "pyomeca_markers_analogs.c3d"
QUALISYS = "ezc3d-testFiles_Qualisys.c3d"
#: Parameters the writer sets itself (points, labels, units, scale, sizes) or ezc3d
#: rewrites (ANALOG:OFFSET becomes 0 with the offset applied to float samples).
REWRITTEN = {
    "POINT": {"LABELS", "DESCRIPTIONS", "UNITS", "SCALE", "RATE", "USED", "FRAMES",
              "DATA_START"},
    "ANALOG": {"LABELS", "USED", "OFFSET"},
}
#: A marker of the Vicon file cut into an unlabelled fragment over these frames.
CUT_MARKER, CUT = 10, slice(200, 260)


def _ctx() -> Context:
    return Context(part="test")


@pytest.fixture(scope="module")
def c3d_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip("shared data not available")
    return DATA


def _with_fragment(m: Markers) -> Markers:
    """The markers with frames ``CUT`` of marker ``CUT_MARKER`` moved to fragment ``*1``."""
    pos = m.positions.copy()
    frag = np.full((m.n_frames, 1, 3), np.nan)
    frag[CUT, 0] = pos[CUT, CUT_MARKER]
    pos[CUT, CUT_MARKER] = np.nan
    res = m.residuals.copy()
    res[CUT, CUT_MARKER] = np.nan
    return m.replace(positions=pos, residuals=res, fragments=frag, fragment_labels=["*1"])


@pytest.fixture(scope="module")
def vicon(c3d_dir, tmp_path_factory):
    """Source, cleaned markers (fast params) and the exported C3D / TRC."""
    src = ingest_c3d(str(c3d_dir / VICON), ctx=_ctx())["markers"]
    cleaned = clean(_with_fragment(src), smooth_iterations=2, ctx=_ctx())["markers"]
    d = tmp_path_factory.mktemp("vicon")
    return src, cleaned, export_markers_c3d(cleaned, d / "clean.c3d"), export_markers_trc(
        cleaned, d / "clean.trc")


def _param_differences(src: dict, out: dict) -> list[str]:
    """``GROUP:NAME`` of every source parameter missing or changed in ``out``."""
    bad = []
    for g in src:
        for name, prm in src[g].items():
            if name == "__METADATA__" or name in REWRITTEN.get(g, ()) or name[-1].isdigit():
                continue
            got = out.get(g, {}).get(name)
            # ezc3d writes byte parameters as int16 (same values)
            if got is None or {got["type"], prm["type"]} not in ({prm["type"]}, {1, 2}):
                bad.append(f"{g}:{name}")
            elif isinstance(prm["value"], list):
                if [s.strip() for s in got["value"]] != [s.strip() for s in prm["value"]]:
                    bad.append(f"{g}:{name}")
            elif np.shape(got["value"]) != np.shape(prm["value"]) or not np.allclose(
                got["value"], prm["value"], rtol=1e-6, atol=0, equal_nan=True
            ):
                bad.append(f"{g}:{name}")
    return bad


def round_trip_numbers(source: Path, written: Path, markers: Markers) -> dict:
    """Analog max |difference| (source units), point max |difference| (m) against
    ``markers``, the source's groups and those missing, and both file sizes."""
    a, b = ezc3d.c3d(str(source)), ezc3d.c3d(str(written))
    back = read_c3d(written)
    ok = np.isfinite(markers.positions)
    return {
        "analog_max_abs": float(np.abs(a["data"]["analogs"] - b["data"]["analogs"]).max()),
        "point_max_abs_m": float(np.abs(back.positions[ok] - markers.positions[ok]).max()),
        "groups": list(a["parameters"]),
        "groups_missing": [g for g in a["parameters"] if g not in b["parameters"]],
        "parameters_changed": _param_differences(a["parameters"], b["parameters"]),
        "bytes": (source.stat().st_size, written.stat().st_size),
    }


def test_cleaned_vicon_keeps_analogs_and_every_group(c3d_dir, vicon):
    src, cleaned, path, _ = vicon
    n = round_trip_numbers(c3d_dir / VICON, path, cleaned)
    assert n["groups_missing"] == [] and n["parameters_changed"] == []
    assert {"TRIAL", "SUBJECTS", "FORCE_PLATFORM", "EVENT", "MANUFACTURER"} <= set(n["groups"])
    assert n["analog_max_abs"] == 0.0  # float32 samples, ANALOG:SCALE 1: bit-exact
    # POINT data are float32 in the file: within half an ulp of ~2 m, in metres
    assert n["point_max_abs_m"] <= 2.0 * 2**-24
    back = read_c3d(path)
    assert back.labels == cleaned.labels
    np.testing.assert_array_equal(back.visible, cleaned.visible)
    assert back.analogs.shape == src.analogs.shape == (11600, 38)
    np.testing.assert_array_equal(back.analogs, src.analogs)
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o666 & ~_umask()


def test_analogs_read_back_by_kineticstoolkit_in_source_units(c3d_dir, vicon):
    import kineticstoolkit as ktk  # noqa: PLC0415

    src, _, path, _ = vicon
    an = ktk.read_c3d(str(path), convert_point_unit=False)["Analogs"]
    raw = ezc3d.c3d(str(c3d_dir / VICON))["parameters"]["ANALOG"]
    labels = raw["LABELS"]["value"]
    assert list(an.data) == labels and an.time.size == 11600
    assert an.time[1] - an.time[0] == pytest.approx(1 / 2000.0, rel=1e-9)
    # ktk gives (raw - offset) * scale * gen_scale: compare with ezc3d on the source
    for j in (0, 17, 37):
        np.testing.assert_allclose(an.data[labels[j]], src.analogs[:, j], rtol=0, atol=1e-7)
    assert [u.strip() for u in raw["UNITS"]["value"]] == list(
        ezc3d.c3d(str(path))["parameters"]["ANALOG"]["UNITS"]["value"])


def test_residuals_say_measured_merged_filled(vicon):
    _, cleaned, path, _ = vicon
    st = cleaned.status
    assert (st[CUT, CUT_MARKER] == 1).all(), "the cut fragment was not merged back"
    assert (st == 2).sum() > 100 and (st == 0).sum() > 20_000
    c = ezc3d.c3d(str(path))
    res = c["data"]["meta_points"]["residuals"][0].T[:, : cleaned.n_markers]  # (F, M)
    step = abs(c["parameters"]["POINT"]["SCALE"]["value"][0])
    assert (res[st == 0] >= step * (1 - 1e-6)).all()
    assert (res[st == 1] == 0).all() and (res[st == 2] == 0).all()
    assert ((res < 0) == (st == -1)).all()
    src_res = cleaned.residuals[st == 0] * 1000  # mm, as in the file
    np.testing.assert_allclose(np.maximum(res[st == 0], src_res), src_res, atol=step)
    mf = c["parameters"]["MOCAPFLOW"]
    assert mf["CLEANED"]["value"][0] == 1
    runs = np.concatenate([mf[k]["value"] for k in sorted(mf) if k.startswith("FILLED")], 1)
    filled = np.zeros_like(st, bool)
    for p, a, b in runs.astype(int).T:
        filled[a - cleaned.first_frame : b - cleaned.first_frame + 1, p - 1] = True
    np.testing.assert_array_equal(filled, st == 2)
    # the status belongs to these samples: kept by take_frames, dropped for other markers
    np.testing.assert_array_equal(cleaned.take_frames(slice(5, 9)).status, st[5:9])
    assert cleaned.replace(positions=cleaned.positions[:, :3], labels=cleaned.labels[:3],
                           residuals=None).status is None


def test_unfilled_samples_are_minus_one(c3d_dir, tmp_path):
    src = ingest_c3d(str(c3d_dir / VICON), ctx=_ctx())["markers"]
    out = clean(_with_fragment(src), fill=False, smooth_iterations=0, ctx=_ctx())["markers"]
    st = out.status
    assert (st == -1).sum() > 100 and (st == 2).sum() == 0
    res = ezc3d.c3d(str(export_markers_c3d(out, tmp_path / "unfilled.c3d")))
    r = res["data"]["meta_points"]["residuals"][0].T[:, : out.n_markers]
    np.testing.assert_array_equal(r < 0, st == -1)
    assert (r[st == 1] == 0).all()


@pytest.mark.parametrize(("rate", "subframes", "source_rate"), [
    (100.0, 1, 1.0),  # ktk_many_analogs.c3d: ANALOG:RATE 1 at 100 Hz
    (69.9926, 11, None),  # 11 x rate rounds to a float32 that reads back as 10.99...
    (119.88, 7, 839.16),
])
def test_analog_rate_is_the_point_rate_times_the_samples_per_frame(tmp_path, rate, subframes,
                                                                   source_rate):
    # was: ezc3d "Number of frames in the data set must match the analog rate X point
    # frame" (the source's ANALOG:RATE kept), or a file read back with 10 samples per
    # frame, so every point after the first frame from the wrong bytes
    rng = np.random.default_rng(4)
    F = 30
    tree = {} if source_rate is None else {"ANALOG": {"description": "", "is_locked": False,
            "parameters": {"RATE": {"type": "float", "description": "", "is_locked": False,
                                    "dimension": [1], "value": [source_rate]}}}}
    m = Markers(positions=rng.uniform(0.1, 1, (F, 3, 3)), labels=["A", "B", "C"], rate=rate,
                analogs=rng.uniform(-1, 1, (F * subframes, 2)), attrs={"c3d_parameters": tree})
    p = tmp_path / "analogs.c3d"
    back = read_c3d(export_markers_c3d(m, p))
    np.testing.assert_allclose(back.positions, m.positions, atol=1e-6, rtol=0)
    np.testing.assert_allclose(back.analogs, m.analogs, atol=1e-6, rtol=0)
    params = ezc3d.c3d(str(p))["parameters"]
    point, analog = (np.float32(params[g]["RATE"]["value"][0]) for g in ("POINT", "ANALOG"))
    assert int(float(analog) / float(point)) == subframes
    assert float(analog) == pytest.approx(rate * subframes, rel=1e-6)


def test_trc_read_by_opensim(vicon):
    osim = pytest.importorskip("opensim", reason="opensim (OpenSim's TRC reader) not installed")
    _, cleaned, _, trc = vicon
    t = osim.TimeSeriesTableVec3(str(trc))
    assert list(t.getColumnLabels()) == cleaned.labels
    assert t.getTableMetaDataAsString("Units") == "mm"
    assert float(t.getTableMetaDataAsString("DataRate")) == 100.0
    time = np.array(t.getIndependentColumn())
    np.testing.assert_allclose(time, (cleaned.first_frame + np.arange(580)) / 100.0, atol=1e-12)
    flat = t.flatten()  # kept: the matrix is a view into it
    mat = flat.getMatrix()
    xyz = mat.to_numpy().reshape(580, -1, 3) / 1000.0
    # 12 significant digits in mm; OpenSim parses them to within a nanometre
    np.testing.assert_allclose(xyz, cleaned.positions, rtol=0, atol=1e-9, equal_nan=True)
    assert stat.S_IMODE(os.stat(trc).st_mode) == 0o666 & ~_umask()
    # a missing sample is an empty field, NaN to OpenSim; metres as the file unit
    pos = cleaned.positions.copy()
    pos[3, 2] = np.nan
    gap = export_markers_trc(cleaned.replace(positions=pos), trc.with_name("gap.trc"), unit="m")
    g = osim.TimeSeriesTableVec3(str(gap))
    assert g.getTableMetaDataAsString("Units") == "m"
    gflat = g.flatten()
    gmat = gflat.getMatrix()
    got = gmat.to_numpy().reshape(580, -1, 3)
    np.testing.assert_allclose(got, pos, rtol=0, atol=1e-9, equal_nan=True)
    assert np.isnan(got[3, 2]).all() and np.isfinite(got[2, 2]).all()
    with pytest.raises(ValueError, match="unknown unit 'furlong'"):
        export_markers_trc(cleaned, trc.with_name("bad.trc"), unit="furlong")


def test_qualisys_ingest_export_equal(c3d_dir, tmp_path):
    m = ingest_c3d(str(c3d_dir / QUALISYS), ctx=_ctx())["markers"]
    path = export_markers_c3d(m, tmp_path / "qualisys.c3d")
    n = round_trip_numbers(c3d_dir / QUALISYS, path, m)
    assert n["groups_missing"] == [] and n["parameters_changed"] == []
    assert {"FORCE_PLATFORM", "EVENT", "MANUFACTURER", "SEG", "PROCESSING"} <= set(n["groups"])
    assert n["analog_max_abs"] == 0.0 and n["point_max_abs_m"] == 0.0
    back = read_c3d(path)
    assert back.first_frame == 704 and back.rate == 200.0 and back.labels == m.labels
    np.testing.assert_array_equal(back.analogs, m.analogs)
    quantum = np.nanmax(m.residuals) / 255
    np.testing.assert_allclose(back.residuals, m.residuals, atol=quantum / 2 + 1e-12, rtol=0)
    assert ezc3d.c3d(str(path))["parameters"]["MOCAPFLOW"]["CLEANED"]["value"][0] == 0


def test_markers_entry_keeps_analogs_and_parameters(c3d_dir):
    from mocapflow.pipeline.codecs import decode, encode  # noqa: PLC0415

    m = ingest_c3d(str(c3d_dir / QUALISYS), ctx=_ctx())["markers"]
    enc = encode(m)
    assert enc.arrays["analogs"][1] == ("analog_sample", "channel")
    back = decode(enc)
    np.testing.assert_array_equal(back.analogs, m.analogs)
    assert back.attrs["c3d_parameters"] == m.attrs["c3d_parameters"]
    assert "status" not in enc.arrays  # raw captures: no status array, as before
    cut = m.take_frames(slice(10, 20))
    np.testing.assert_array_equal(cut.analogs, m.analogs[100:200])


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


if __name__ == "__main__":  # the numbers of the report
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        s = ingest_c3d(str(DATA / VICON), ctx=_ctx())["markers"]
        cl = clean(_with_fragment(s), smooth_iterations=2, ctx=_ctx())["markers"]
        for name, mk in ((VICON, cl), (QUALISYS, ingest_c3d(str(DATA / QUALISYS),
                                                            ctx=_ctx())["markers"])):
            p = export_markers_c3d(mk, Path(d) / name)
            t = export_markers_trc(mk, Path(d) / (name[:-4] + ".trc"))
            print(name, round_trip_numbers(DATA / name, p, mk), "trc bytes",
                  t.stat().st_size, file=sys.stdout)
