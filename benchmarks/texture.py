"""Benchmark of the texture graph (Moradoff 2002) against a copy and a shuffle baseline.

Protocol (``shared/METRICS.md`` §1): inputs from ``../shared/data/bvh`` resampled
to 30 fps; outputs of 1024 frames from the first 512 input frames (the whole
clip when shorter) and of 2× the whole clip; every method with the same seeds.
Metrics: synthesis time (CPU seconds of pyramid + synthesis, one core),
GANimator coverage, global and local diversity on 6-D joint rotations (the
root's heading removed: our outputs and both baselines integrate the heading,
so an absolute heading would only measure where the walk has turned to),
output/input p99 jerk ratio
overall and within ±5 frames of the seams, toe-skate ratio (input contact
thresholds), longest verbatim run, number of seams.  Ours runs with the
default search parameters (``variety`` 0.3: jumps drawn within the 30 %
quantile of the input's own jump costs; ``max_run`` 0.3 of the input; foot IK)
and with a higher ``variety``.

Baselines (same root integration, no search, no smoothing): *copy* — the input
played again and again; *shuffle* — random 30-frame chunks, no blending.

Run::

    /work/venv/bin/python benchmarks/texture.py            # 5 seeds, all rows
    /work/venv/bin/python benchmarks/texture.py --quick    # 2 seeds, 2× rows only
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from mocapflow.pipeline import Context  # noqa: E402
from mocapflow.stages.metrics import quality as M  # noqa: E402
from mocapflow.stages.motion.contacts import contact_thresholds, toe_indices  # noqa: E402
from mocapflow.stages.motion.formats.bvh import read_bvh  # noqa: E402
from mocapflow.stages.motion.kinematics import motion_positions, resample_motion  # noqa: E402
from mocapflow.stages.texture.assemble import assemble_motion  # noqa: E402
from mocapflow.stages.texture.pyramid import build_pyramid  # noqa: E402
from mocapflow.stages.texture.search import SearchParams  # noqa: E402
from mocapflow.stages.texture.synth import synth  # noqa: E402

DATA = Path(os.environ.get("MOCAPFLOW_DATA", Path(__file__).parents[1] / ".." / "shared" / "data"))
INPUTS = {
    "salsa cmu_60_01": "bvh/cmu_60_01_scaled.bvh",
    "walk cmu_131_02": "bvh/cmu_131_02.bvh",
    "8-walk pymo_AV": "bvh/pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh",
}
HEADING_FREE = True
MORE_VARIED = 0.6
PEER = [
    "| salsa cmu_60_01 (561) | 2× | GenMM | ≈1.6 | 1.00 | 0.09–0.12 | 0.09–0.10 | 0.99–2.11 | — |",
    "| walk cmu_131_02 (312) | 2× | GenMM | ≈0.4 | 0.97–1.00 | 0.11–0.17 | 0.09–0.14 "
    "| 0.94–1.22 | 1.02–1.12 |",
    "| 8-walk pymo_AV (266) | 2× | GenMM | ≈0.2 | 1.00 | 0.16–0.32 | 0.16–0.22 | 2.7–13.7 "
    "| 1.30–1.48 |",
    "(columns: synth s, coverage, global, local, jerk-p99 ratio, toe-skate ratio; GenMM's",
    " features keep the root heading, ours remove it — see the copy rows for the offset)",
]
TARGETS = "targets: ≤3 s/1024 frames, coverage ≥0.95, jerk ratio ≤1.3, skate ratio ≤1.1"


def load(rel: str, rate: float = 30.0):
    """Read a BVH and resample it to ``rate``."""
    return resample_motion(read_bvh(DATA / rel), rate)


def crop(motion, n: int):
    """First ``n`` frames."""
    tr = None if motion.translations is None else motion.translations[:n]
    return motion.replace(
        root_position=motion.root_position[:n], rotations=motion.rotations[:n], translations=tr
    )


class Reference:
    """Input-side quantities every output is compared with."""

    def __init__(self, motion):
        self.motion = motion
        self.pos = motion_positions(motion)
        self.feat = M.rotation_features(motion, heading_free=HEADING_FREE)
        self.toes = toe_indices(motion.skeleton)
        self.h_thr, self.s_thr = contact_thresholds(self.pos, self.toes, motion.rate)
        self.jerk = M.jerk_p99(self.pos, motion.rate)
        self.skate = M.foot_skate(
            self.pos, self.toes, motion.rate, height_threshold=self.h_thr,
            speed_threshold=self.s_thr,
        )


def evaluate(ref: Reference, out, src: np.ndarray, seconds: float) -> dict[str, float]:
    """All metrics of one output."""
    rate = ref.motion.rate
    pos = motion_positions(out)
    feat = M.rotation_features(out, heading_free=HEADING_FREE)
    seams = M.seams_from_source(src)
    mask = M.seam_mask(out.n_frames, seams, radius=5)
    pm = M.patch_metrics(feat, ref.feat)
    skate = M.foot_skate(
        pos, ref.toes, rate, height_threshold=ref.h_thr, speed_threshold=ref.s_thr
    )
    return {
        "time": seconds,
        **pm,
        "jerk": M.jerk_p99(pos, rate) / ref.jerk,
        "jerk_seam": (M.jerk_p99(pos, rate, mask=mask) / ref.jerk) if seams.size else np.nan,
        "skate": skate / ref.skate,
        "verbatim": float(M.longest_verbatim_run(src)),
        "seams": float(seams.size),
    }


def copy_source(n_in: int, length: int) -> np.ndarray:
    """Copy baseline: the input again and again."""
    return np.arange(length) % n_in


def shuffle_source(n_in: int, length: int, rng: np.random.Generator, chunk: int = 30):
    """Shuffle baseline: random ``chunk``-frame pieces of the input."""
    starts = rng.integers(0, n_in - chunk + 1, size=-(-length // chunk))
    return (starts[:, None] + np.arange(chunk)[None, :]).ravel()[:length]


def seeded_context(seed: int) -> Context:
    """A stage context drawing from ``np.random.default_rng(seed)``."""
    ctx = Context(seed=seed)
    ctx.rng = np.random.default_rng(seed)
    return ctx


def run_row(motion, length: int, seeds: list[int], levels: int, variants: dict):
    """Metrics of our variants, copy and shuffle over the seeds; ``{method: [dict]}``.

    ``variants``: method name -> ``synth`` params.
    """
    ref = Reference(motion)
    res: dict[str, list[dict]] = {name: [] for name in variants}
    res.update(copy=[], shuffle=[])
    for seed in seeds:
        for name, params in variants.items():
            t0 = time.process_time()  # CPU seconds: robust to other jobs on the machine
            pyr = build_pyramid(motion, levels=levels)
            # output at the synthesis rate, as the inputs it is measured against (the stage
            # exports at the source file's rate by default)
            r = synth(pyr, motion, length=length, seed=seed, ctx=seeded_context(seed),
                      output_rate=motion.rate, **params)
            seconds = time.process_time() - t0
            res[name].append(evaluate(ref, r["motion"], r["source_index"], seconds))
        rng = np.random.default_rng(1000 + seed)
        for name, src in (
            ("copy", copy_source(motion.n_frames, length)),
            ("shuffle", shuffle_source(motion.n_frames, length, rng)),
        ):
            t0 = time.process_time()
            out, _ = assemble_motion(pyr, motion, src, smoothing=False, plant=False, foot_ik=False)
            res[name].append(evaluate(ref, out, src, time.process_time() - t0))
    return res


COLS = [
    ("time", "CPU s", "{:.2f}"),
    ("coverage", "cover", "{:.2f}"),
    ("global_diversity", "global", "{:.3f}"),
    ("local_diversity", "local", "{:.3f}"),
    ("jerk", "jerk×", "{:.2f}"),
    ("jerk_seam", "jerk× seams", "{:.2f}"),
    ("skate", "skate×", "{:.2f}"),
    ("verbatim", "verbatim", "{:.0f}"),
    ("seams", "seams", "{:.0f}"),
]


def fmt(values: list[dict], key: str, spec: str) -> str:
    v = np.array([d[key] for d in values], dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return "—"
    lo, hi, mean = v.min(), v.max(), v.mean()
    if np.isclose(lo, hi, rtol=0.005, atol=1e-4):
        return spec.format(mean)
    return f"{spec.format(mean)} ({spec.format(lo)}–{spec.format(hi)})"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 seeds, 2× rows only")
    ap.add_argument("--seeds", type=int, default=None, help="number of seeds (default 5)")
    ap.add_argument("--levels", type=int, default=4)
    ap.add_argument("--only", default=None, help="substring of the input names to run")
    args = ap.parse_args(argv)
    if not DATA.exists():
        print(f"data directory {DATA} not found (set MOCAPFLOW_DATA)", file=sys.stderr)
        return 1
    n_seeds = args.seeds or (2 if args.quick else 5)
    seeds = list(range(n_seeds))
    variants = {"ours": {}, f"ours variety={MORE_VARIED}": {"variety": MORE_VARIED}}
    print(f"texture benchmark — {n_seeds} seeds, {args.levels} levels, 30 fps; {TARGETS}")
    print(
        "cells: mean (min–max over seeds); ratios are output/input; CPU s = pyramid + "
        "synthesis on one core; patch metrics on 6-D rotations with the root heading removed"
    )
    d = SearchParams()
    print(f"ours = defaults (variety {d.variety}, max_run {d.max_run}, usage_weight "
          f"{d.usage_weight}, foot IK); 'ours variety={MORE_VARIED}' draws among more "
          "alternatives\n")
    header = "| input (frames) | output | method | " + " | ".join(c[1] for c in COLS) + " |"
    print(header)
    print("|" + "---|" * (3 + len(COLS)))
    t_all = time.perf_counter()
    for name, rel in INPUTS.items():
        if args.only and args.only not in name:
            continue
        full = load(rel)
        rows = [] if args.quick else [(crop(full, min(512, full.n_frames)), 1024)]
        rows.append((full, 2 * full.n_frames))
        for motion, length in rows:
            res = run_row(motion, length, seeds, args.levels, variants)
            for method in res:
                cells = " | ".join(fmt(res[method], k, sp) for k, _, sp in COLS)
                print(
                    f"| {name} ({motion.n_frames}) | {length} | {method} | {cells} |", flush=True
                )
    print(f"\n(wall time {time.perf_counter() - t_all:.0f} s)")
    print("\nPeer (GenMM, SIGGRAPH 2023; shared/METRICS.md §1, measured there, 2× rows):")
    for line in PEER:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
