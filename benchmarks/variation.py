"""Variation graph benchmark (Lau, Bar-Joseph & Kuffner 2009), one run.

Prints:

1. structure-learning time for 4 gait cycles cut from ``cmu_131_02.bvh``
   (72 varying DOFs at 60 fps) with 1 and 2 worker processes (per-node
   scoring through ``ctx.map``); paper: 0.5-2 h, target <= 2 min;
2. synthesis time per second of motion before IK (paper 0.1 s, target
   <= 0.01 s), wall and CPU, one variant per call and 15 per call;
3. quality of 15 variants of the figure-8 walk (``pymo_AV_8Walk...bvh``; k,
   kernel width, sigma and noise correlation time from configs/variation.yaml),
   their sigma = 0 mean motion and white-noise variants, against
   the inputs and the two noise baselines (strawman: time-warped inputs plus
   smoothed noise; Perlin noise) at matched spatial variation (noise amplitude
   bisected so the mean DTW-aligned distance to the inputs equals ours):
   jerk p99 (m/s^3) and foot skate (m/s, thresholds from the inputs), before
   and after IK, and the novelty criteria;
4. novelty of 15 variants of the UCI letter 'a' (5 single-writer examples).

Run: ``/work/venv/bin/python benchmarks/variation.py [--quick]`` from the
repository root (needs ``../shared/data``).
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from mocapflow.pipeline import Context
from mocapflow.pipeline.config import load_config
from mocapflow.stages.metrics.novelty import novelty_report
from mocapflow.stages.metrics.quality import foot_skate, jerk_p99
from mocapflow.stages.motion.contacts import contact_thresholds, toe_indices
from mocapflow.stages.motion.formats.bvh import read_bvh
from mocapflow.stages.motion.formats.strokes import read_uci_chartraj
from mocapflow.stages.motion.kinematics import motion_positions, resample_motion
from mocapflow.stages.variation.clips import clips_to_motions
from mocapflow.stages.variation.ik import ik
from mocapflow.stages.variation.inputs import clips as clips_stage
from mocapflow.stages.variation.learn import learn
from mocapflow.stages.variation.sample import Sampler, matched_amplitude, sample, sample_noise

DATA = Path(os.environ.get("MOCAPFLOW_DATA", Path(__file__).resolve().parents[1] / ".."
                           / "shared" / "data"))


def _take_clips(name: str, rate: float, n: int | None):
    m = resample_motion(read_bvh(DATA / "bvh" / name), rate)
    return clips_stage(m, max_clips=n, ctx=Context())["clips"]


def _subset(c, n_clips: int, n_dofs: int | None = None):
    keep = np.arange(c.n_dofs) if n_dofs is None else np.argsort(
        -np.concatenate(c.trajectories).std(axis=0))[:n_dofs]
    keep = np.sort(keep)
    return c.replace(trajectories=[t[:, keep] for t in c.trajectories[:n_clips]],
                     varying=_mask(c, keep), constant_values=c.constant_values,
                     origins=c.origins[:n_clips], names=c.names[:n_clips])


def _mask(c, keep):
    idx = np.flatnonzero(c.varying)[keep]
    m = np.zeros_like(c.varying)
    m[idx] = True
    return m


def _learn_time(c, workers: int) -> tuple[float, object, dict]:
    """Wall seconds, the model and the stage's step timings (``ctx.timings``)."""
    t0 = time.perf_counter()
    if workers == 1:
        ctx = Context()
        m = learn(c, ctx=ctx)["model"]
    else:
        with ProcessPoolExecutor(workers) as pool:
            ctx = Context(mapper=lambda fn, items: list(pool.map(fn, items)), workers=workers)
            m = learn(c, ctx=ctx)["model"]
    return time.perf_counter() - t0, m, ctx.timings


def _variants(model, seed: int, **params):
    """The ``sample`` stage's variants drawn from ``numpy.random.default_rng(seed)``."""
    return sample(model, **params, ctx=Context(rng=np.random.default_rng(seed)))["variants"]


def _synthesis_time(model, seconds: float, count: int) -> tuple[float, float]:
    s = Sampler(model)
    n = int(round(seconds * model.clips.rate))
    rng = np.random.default_rng(0)
    s.run(rng, count=count, length=20)  # warm-up
    w0, c0 = time.perf_counter(), time.process_time()
    s.run(rng, count=count, length=n)
    w, c = time.perf_counter() - w0, time.process_time() - c0
    return w / (count * seconds), c / (count * seconds)


def _motion_metrics(clips, toes, thr):
    jerk, skate = [], []
    for m in clips_to_motions(clips):
        p = motion_positions(m)
        jerk.append(jerk_p99(p, m.rate))
        skate.append(foot_skate(p, toes, m.rate, height_threshold=thr[0],
                                speed_threshold=thr[1]))
    return float(np.mean(jerk)), float(np.nanmean(skate))


def _novelty_row(rep) -> str:
    d = np.array(rep["aligned_distance"])
    inside = np.mean((d > 0) & (d < rep["input_distance_p95"]))
    wr = np.mean(rep["warp_slope_std"]) / rep["input_warp_slope_std"]
    return (f"equal poses {rep['equal_poses']:3d} | longest copied run {max(rep['copied_run']):2d}"
            f" (inputs among themselves {rep['input_copied_run']:2d}) | DTW dist median "
            f"{np.median(d):.3f}, max {d.max():.3f} vs input p95 {rep['input_distance_p95']:.3f}"
            f" ({100 * inside:.0f}% inside) | warp-slope std ratio {wr:.2f}")


def _config() -> dict:
    """``k``, ``kernel_width``, ``sigma`` and ``noise_time`` of configs/variation.yaml."""
    c = load_config(Path(__file__).resolve().parents[1] / "configs" / "variation.yaml")
    lp, sp = c.nodes["learn"].params, c.nodes["sample"].params
    return {"k": int(lp["k"]), "kernel_width": lp["kernel_width"],
            "sigma": float(sp["sigma"]), "noise_time": sp["noise_time"]}


def main(quick: bool = False) -> None:
    n_var = 5 if quick else 15
    print(f"# variation benchmark ({'quick' if quick else 'full'}); data {DATA}")
    print(f"# machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")

    # 1. structure learning time ------------------------------------------------------
    cmu = _take_clips("cmu_131_02.bvh", 60.0, None)
    c4 = _subset(cmu, 4, 20 if quick else None)
    print(f"\n## 1. structure learning: {c4.n_clips} clips, {c4.n_dofs} DOFs, "
          f"{int(c4.lengths.sum())} frames (cmu_131_02 cycles, 60 fps)")
    t1, m1, s1 = _learn_time(c4, 1)
    t2, m2, s2 = _learn_time(c4, 2)
    same = m1.transition_parents == m2.transition_parents and m1.prior_parents == m2.prior_parents
    print("| workers | seconds | transition s | prior s | evaluations | target |")
    print("|---|---|---|---|---|---|")
    for w, t, m, s in ((1, t1, m1, s1), (2, t2, m2, s2)):
        ev = m.attrs["evaluations"]
        print(f"| {w} | {t:.1f} | {s['transition']:.1f} | {s['prior']:.1f} | "
              f"{ev['transition']} + {ev['prior']} | <= 120 |")
    print(f"speed-up 2 vs 1 worker: {t1 / t2:.2f}x; same structure: {same}; "
          "mean parents per transition node "
          f"{np.mean([len(p) + 2 for p in m1.transition_parents]):.1f}"
          f" (incl. 2 self), max prior parents {max(len(p) for p in m1.prior_parents)}")

    # 2. synthesis time --------------------------------------------------------------
    print(f"\n## 2. synthesis time per second of motion (before IK), {m1.n_dofs} DOFs, 60 fps")
    print("| variants per call | wall ms / s | CPU ms / s | paper | target |")
    print("|---|---|---|---|---|")
    for count in (1, 15):
        w, c = _synthesis_time(m1, 2.0 if quick else 10.0, count)
        print(f"| {count} | {1000 * w:.1f} | {1000 * c:.1f} | 100 | <= 10 |")

    # 3. quality against the noise baselines ---------------------------------------------
    walk = _take_clips("pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh", 60.0, 6)
    if quick:
        walk = _subset(walk, 4, None)
    t0 = time.perf_counter()
    cfg = _config()
    model = learn(walk, k=cfg["k"], kernel_width=cfg["kernel_width"])["model"]
    t_learn = time.perf_counter() - t0
    sigma, nt = cfg["sigma"], cfg["noise_time"]
    mean_motion = _variants(model, 1, count=1, sigma=0.0)
    white = _variants(model, 1, count=n_var, sigma=sigma)
    ours = _variants(model, 1, count=n_var, sigma=sigma, noise_time=nt)
    L = int(np.median(walk.lengths))
    toes = toe_indices(walk.skeleton)
    pin = np.concatenate([motion_positions(m) for m in clips_to_motions(walk)])
    thr = contact_thresholds(pin, toes, walk.rate)

    def dist(v):
        return float(np.mean(novelty_report(v.trajectories, walk.trajectories,
                                            cyclic=True)["aligned_distance"]))

    rep_ours = novelty_report(ours.trajectories, walk.trajectories, cyclic=True)
    d_ours = np.array(rep_ours["aligned_distance"])
    rows = [("inputs", walk, None), ("ours mean motion (sigma 0)", mean_motion, None),
            (f"ours, white noise as the paper (sigma {sigma})", white, None),
            (f"ours (sigma {sigma}, noise_time {nt} s)", ours, None)]
    t0 = time.perf_counter()
    cleaned = ik(ours, ctx=Context())
    ours_ik, ik_rep = cleaned["variants"], cleaned["report"]
    t_ik = time.perf_counter() - t0
    rows.append(("ours + IK", ours_ik, None))
    for method in ("strawman", "perlin"):
        def make(a, method=method):
            return sample_noise(walk, method=method, count=n_var, length=L, amplitude=a,
                                ctx=Context(rng=np.random.default_rng(2)))["variants"]

        a = matched_amplitude(make, dist, float(d_ours.mean()), iterations=7 if quick else 10)
        rows.append((f"{method} (amplitude {a:.3f} std)", make(a), a))
    print(f"\n## 3. walk quality: {walk.n_clips} cycles of the figure-8 walk, {walk.n_dofs} DOFs;"
          f" configs/variation.yaml: k {cfg['k']}, kernel_width {cfg['kernel_width']};"
          f" {n_var} variants of {L} frames; learn {t_learn:.0f} s, IK {t_ik:.1f} s")
    print("| motion | jerk p99 (m/s^3) | foot skate (m/s) | DTW dist to inputs (mean +- std) |")
    print("|---|---|---|---|")
    for name, c, _ in rows:
        j, s = _motion_metrics(c, toes, thr)
        if name == "inputs":
            dd = np.array(novelty_report(c.trajectories, c.trajectories)["input_distances"])
        else:
            dd = np.array(novelty_report(c.trajectories, walk.trajectories,
                                         cyclic=True)["aligned_distance"])
        print(f"| {name} | {j:.0f} | {s:.3f} | {dd.mean():.2f} +- {dd.std():.2f} |")
    unreached = sum(len(r["unreachable"]) for r in ik_rep["clips"])
    frames = sum(sum(r["constrained_frames"].values()) for r in ik_rep["clips"])
    reached = max(e for r in ik_rep["clips"] for e in r["max_error_reached"].values())
    print(f"IK: {frames} constrained effector-frames, {unreached} unreachable (best effort, "
          f"warned); max end-effector error on reached frames {1000 * reached:.3f} mm")
    print("novelty (ours, walk):", _novelty_row(rep_ours))

    # 4. strokes ------------------------------------------------------------------------
    if not quick:
        ss = read_uci_chartraj(DATA / "strokes" / "uci_chartraj_mv_subset.csv", letter="a")
        sc = clips_stage(ss, ctx=Context())["clips"]
        t0 = time.perf_counter()
        sm = learn(sc)["model"]
        tl = time.perf_counter() - t0
        sv = _variants(sm, 0, count=15)
        print(f"\n## 4. strokes: UCI 'a', {sc.n_clips} examples -> 15 variants (learn {tl:.1f} s)")
        print("novelty:", _novelty_row(novelty_report(sv.trajectories, sc.trajectories)))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small run (20 DOFs, 5 variants)")
    main(ap.parse_args().quick)
