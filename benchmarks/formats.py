"""Read/write throughput of our C3D and BVH I/O against other Python readers.

Every row is measured in this one run: best of ``--repeat`` interleaved rounds
of wall-clock timings (one core; results freed outside the timer), reported in
frames per second.  Files from ``../shared/data``:

* C3D: ``ktk_kinematics_basket_sprint.c3d`` (largest: 3678 frames × 26 markers),
  plus (full run) a synthetic dense take of 400 markers × 6000 frames written by
  our writer.
  - read:  ours ``read_c3d`` (validation + ezc3d + conversion to Markers) vs the
    baseline ``ezc3d.c3d(path)`` alone vs peer ``kineticstoolkit.read_c3d``;
  - write: ours ``write_c3d`` vs ``ezc3d`` writing the object it read vs
    ``kineticstoolkit.write_c3d``.
* BVH: ``cmu_60_01_scaled.bvh`` (largest: 2242 frames × 43 joints) and
  ``cmu_01_01.bvh`` (2752 frames × 31 joints).
  - read:  ours ``read_bvh`` (to quaternions, metres) vs ``bvhio.readAsBvh`` vs
    PyPI ``bvh`` 0.3 (``Bvh(text)`` + frames to a float array);
  - write: ours ``write_bvh`` vs ``bvhio.writeBvh``.

The ratio column is ours / baseline throughput (> 1: ours faster).

Run::

    /work/venv/bin/python benchmarks/formats.py           # 5 repeats, + dense C3D
    /work/venv/bin/python benchmarks/formats.py --quick   # 2 repeats, real files only
"""

from __future__ import annotations

import argparse
import gc
import os
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import bvhio  # noqa: E402
import ezc3d  # noqa: E402
import kineticstoolkit as ktk  # noqa: E402
import numpy as np  # noqa: E402

from mocapflow.stages.motion.datatypes import Markers  # noqa: E402
from mocapflow.stages.motion.formats.bvh import read_bvh, write_bvh  # noqa: E402
from mocapflow.stages.motion.formats.c3d import read_c3d, write_c3d  # noqa: E402

DATA = Path(os.environ.get("MOCAPFLOW_DATA", Path(__file__).parents[1] / ".." / "shared" / "data"))
C3D_FILE = "c3d/ktk_kinematics_basket_sprint.c3d"
BVH_FILES = ["bvh/cmu_60_01_scaled.bvh", "bvh/cmu_01_01.bvh"]


def best_times(fns: list[Callable[[], object]], repeat: int) -> list[float]:
    """Best wall-clock time (seconds) of each function over ``repeat`` interleaved rounds.

    Rounds alternate between the functions (so machine-load drift hits all alike),
    and each result is freed after its timer stops (deallocation is not timed).
    """
    best = [float("inf")] * len(fns)
    for _ in range(repeat):
        for i, fn in enumerate(fns):
            gc.collect()
            t = time.perf_counter()
            out = fn()
            best[i] = min(best[i], time.perf_counter() - t)
            del out
    return best


def _rows_c3d(path: Path, frames: int, repeat: int, tmp: Path) -> list[tuple]:
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t_ours, t_ez, t_ktk = best_times(
            [
                lambda: read_c3d(path),
                lambda: ezc3d.c3d(str(path)),
                lambda: ktk.read_c3d(str(path), convert_point_unit=True),
            ],
            repeat,
        )
    rows.append(("read", "ezc3d.c3d (raw)", frames, t_ours, t_ez, "ktk.read_c3d", t_ktk))

    markers = read_c3d(path)
    raw = ezc3d.c3d(str(path))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        points = ktk.read_c3d(str(path), convert_point_unit=True)["Points"]
    labels = list(raw["parameters"]["POINT"]["LABELS"]["value"])

    def ezc3d_write():
        # ezc3d's write() extends POINT:LABELS in place with LABELS2 (> 255 points): reset it
        raw["parameters"]["POINT"]["LABELS"]["value"] = list(labels)
        raw.write(str(tmp / "ezc3d.c3d"))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t_ours, t_ez, t_ktk = best_times(
            [
                lambda: write_c3d(markers, tmp / "ours.c3d"),
                ezc3d_write,
                lambda: ktk.write_c3d(str(tmp / "ktk.c3d"), points),
            ],
            repeat,
        )
    rows.append(("write", "ezc3d write", frames, t_ours, t_ez, "ktk.write_c3d", t_ktk))
    return rows


def _rows_bvh(path: Path, repeat: int, tmp: Path) -> list[tuple]:
    motion = read_bvh(path)
    frames = motion.n_frames
    rows = []
    fns: list[Callable[[], object]] = [lambda: read_bvh(path), lambda: bvhio.readAsBvh(str(path))]
    try:
        import bvh as bvh_pkg

        def read_bvh_pkg():
            b = bvh_pkg.Bvh(path.read_text())
            return np.asarray(b.frames, dtype=np.float64)

        fns.append(read_bvh_pkg)
        peer = "bvh 0.3"
    except ImportError:
        peer = "bvh (not installed)"
    t_ours, t_io, *t_pkg = best_times(fns, repeat)
    t_pkg = t_pkg[0] if t_pkg else float("nan")
    rows.append(("read", "bvhio.readAsBvh", frames, t_ours, t_io, peer, t_pkg))

    container = bvhio.readAsBvh(str(path))
    t_ours, t_io = best_times(
        [
            lambda: write_bvh(motion, tmp / "ours.bvh"),
            lambda: bvhio.writeBvh(str(tmp / "bvhio.bvh"), container),
        ],
        repeat,
    )
    rows.append(("write", "bvhio.writeBvh", frames, t_ours, t_io, "", float("nan")))
    return rows


def dense_markers(n_markers: int, n_frames: int, seed: int = 0) -> Markers:
    """A synthetic dense take (random walk per marker, 3 % missing)."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(-0.5, 0.5, (1, n_markers, 3)) + [0.0, 0.0, 1.0]
    pos = base + np.cumsum(rng.normal(0, 1e-3, (n_frames, n_markers, 3)), axis=0)
    pos[rng.random((n_frames, n_markers)) < 0.03] = np.nan
    return Markers(pos, [f"M{i:03d}" for i in range(n_markers)], rate=120.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="2 repeats, real files only")
    ap.add_argument("--repeat", type=int, default=None)
    args = ap.parse_args()
    repeat = args.repeat or (2 if args.quick else 5)

    rows: list[tuple] = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        c3d = DATA / C3D_FILE
        n = read_c3d(c3d).n_frames
        rows += [("C3D " + c3d.stem, *r) for r in _rows_c3d(c3d, n, repeat, tmp)]
        if not args.quick:
            dense = write_c3d(dense_markers(400, 6000), tmp / "dense400.c3d")
            rows += [("C3D dense 400 markers", *r) for r in _rows_c3d(dense, 6000, repeat, tmp)]
        for rel in BVH_FILES:
            p = DATA / rel
            rows += [("BVH " + p.stem, *r) for r in _rows_bvh(p, repeat, tmp)]

    head = (
        f"{'file':30s} {'op':5s} {'frames':>6s} {'ours f/s':>10s} "
        f"{'baseline':18s} {'base f/s':>10s} {'ours/base':>9s}   {'peer':18s} {'peer f/s':>10s}"
    )
    print(f"best of {repeat} runs, one process, wall clock")
    print(head)
    print("-" * len(head))
    for name, op, base, frames, t_o, t_b, peer, t_p in rows:
        fo, fb = frames / t_o, frames / t_b
        fp = frames / t_p if np.isfinite(t_p) else float("nan")
        fp_s = f"{fp:10.0f}" if np.isfinite(fp) else f"{'-':>10s}"
        print(
            f"{name[:30]:30s} {op:5s} {frames:6d} {fo:10.0f} {base:18s} {fb:10.0f} "
            f"{fo / fb:9.2f}   {peer:18s} {fp_s}"
        )


if __name__ == "__main__":
    main()
