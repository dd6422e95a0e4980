"""Variation graph benchmark (Lau, Bar-Joseph & Kuffner 2009), one run: issue 17's "Must show".

Prints, with the shipped configs (``configs/variation.yaml``: ingest, clips,
learn, sample and ik params; the walk model is learned once from the files):

1. streams: 20 seeds x 10 s (600 frames) of the walk model at sigma 0, 0.15,
   the config's sigma and 1 (the config's ``noise_time``; and sigma 1 white, the
   paper): cadence of each hip flexion DOF over the inputs' (target within
   +-15 %), cycles made, frozen half-second windows (a hip flexion range below
   half the inputs' smallest; target 0) -- :mod:`mocapflow.stages.metrics.gait`;
   and the crowd mode at sigma 0 and the config's, with the one-step error of its
   conditional mean against the exact search;
2. exported variants of ``cmu_131_02.bvh`` and of the figure-8 walk after IK
   (at the model's rate, as the inputs): jerk p99 and toe skate over the
   input's (targets <= 1.5, <= 1.2), the largest excess of a BVH rotation
   channel beyond the inputs' range (target <= 0.05 rad) and the novelty
   criteria; jerk and skate after IK also for the draws of :data:`OTHER_DRAWS`;
3. chaining: 5 consecutive cycles of one variant stream (the ``sample``
   stage's ``loop``, else a long stream cut where the hip passes the inputs'
   start phase): jerk p99 at the joins over the inputs' p99 (target <= 1.5), after
   IK also for three other chains;
4. speed, BLAS pinned to one thread per process (env vars set before NumPy is
   imported, threadpoolctl when installed): learning the shipped walk on 1 and
   2 workers (targets <= 30 s on 2, >= 1.6x), streaming 1,000 agents of the walk
   model frame by frame (timed after the prior's two frames), with the exact neighbour
   search and in the crowd mode (:data:`CROWD_WINDOW`; target <= 30 us per
   agent-frame), and 15 variants per call as the ``sample`` stage makes them, each
   measured in a fresh subprocess, for this checkout and -- with
   ``--baseline DIR`` -- for the code importable from DIR (``PYTHONPATH=DIR``,
   run outside the repository), as ratios;
5. strokes: 15 variants of two UCI characters (``'a'`` and
   :data:`SECOND_LETTER`, ``configs/variation_strokes.yaml``), novelty per letter;
6. quality of the walk variants against the noise baselines at matched
   amplitude (jerk, skate, DTW distance; before and after IK).

Run: ``.venv/bin/python benchmarks/variation.py [--quick] [--baseline DIR] [--sections 2,3]``
from the repository root (needs ``../shared/data`` or ``MOCAPFLOW_DATA``).
``--quick``: 5 streams, 5 variants, 4 cmu clips of 20 DOFs, the speed run on
4 clips of 20 DOFs; it checks the run end to end, not the targets.  ``--sections 2,3``:
only those sections (numbered as above).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
           "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"  # before NumPy is imported, inherited by every subprocess

import argparse  # noqa: E402
import inspect  # noqa: E402
import itertools  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

try:  # noqa: SIM105
    from threadpoolctl import threadpool_limits  # noqa: E402

    threadpool_limits(1)
except ImportError:  # pragma: no cover
    pass

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("MOCAPFLOW_DATA", REPO / ".." / "shared" / "data")).resolve()
os.environ["MOCAPFLOW_DATA"] = str(DATA)  # configs' parts, also from another checkout's configs
WALK_CONFIG = REPO / "configs" / "variation.yaml"
STROKES_CONFIG = REPO / "configs" / "variation_strokes.yaml"
#: the second character of section 5 (the strokes config with its ``letter`` replaced)
SECOND_LETTER = "b"
#: stream length, frames (10 s at 60 fps)
STREAM_FRAMES = 600
#: the other ``sample`` seeds of sections 2 and 3 (section 2 draws seed 1, section 3 seed 3;
#: the other chains are seeds 4-6), each after IK, so a target met is not one draw's luck
OTHER_DRAWS = (2, 3, 4)
CROWD_WINDOW = 64
"""``Sampler(model, window=...)`` of the crowd-mode rows: each agent searches its k nearest
among the 64 instances nearest to it in cycle phase (of ~360 on the walk)."""


# ----------------------------------------------------------------------------- config


def _nodes(config: Path) -> dict[str, dict]:
    """Resolved params of every node of a graph config."""
    from mocapflow.pipeline.config import load_config

    c = load_config(config)
    out = {n: dict(c.nodes[n].params) for n in c.nodes}
    out["_parts"] = [str(p) for p in c.parts]
    return out


def _part(nodes: dict, name: str | None = None, sub: str = "bvh") -> Path:
    """A shared data file: ``name``, else the config's first part (its file name under DATA)."""
    return DATA / sub / (name or Path(nodes["_parts"][0]).name)


def _accepted(fn, params: dict) -> dict:
    """The params ``fn`` takes (another checkout may lack some)."""
    sig = inspect.signature(fn).parameters
    return {k: v for k, v in params.items() if k in sig}


def _walk_clips(nodes: dict, part: Path | None = None):
    """ingest_bvh + clips of the config on one BVH part."""
    from mocapflow.pipeline import Context
    from mocapflow.stages.motion.ingest import ingest_bvh
    from mocapflow.stages.variation.inputs import clips as clips_stage

    motion = ingest_bvh(str(part or _part(nodes)), **_accepted(ingest_bvh, nodes["ingest"]),
                        ctx=Context())["motion"]
    return motion, clips_stage(motion, **_accepted(clips_stage, nodes["clips"]),
                               ctx=Context())["clips"]


def _learn(clips, nodes: dict, workers: int = 1):
    """The config's ``learn`` on ``workers`` processes: (model, wall seconds)."""
    from concurrent.futures import ProcessPoolExecutor

    from mocapflow.pipeline import Context
    from mocapflow.stages.variation.learn import learn

    lp = _accepted(learn, nodes["learn"])
    t0 = time.perf_counter()
    if workers == 1:
        model = learn(clips, **lp, ctx=Context())["model"]
    else:
        with ProcessPoolExecutor(workers) as pool:
            ctx = Context(mapper=lambda fn, items: list(pool.map(fn, items)), workers=workers)
            model = learn(clips, **lp, ctx=ctx)["model"]
    return model, time.perf_counter() - t0


def _subset(c, n_clips: int, n_dofs: int | None = None):
    """The first ``n_clips`` clips and the ``n_dofs`` DOFs of largest std (quick runs)."""
    keep = np.arange(c.n_dofs) if n_dofs is None else np.argsort(
        -np.concatenate(c.trajectories).std(axis=0))[:n_dofs]
    keep = np.sort(keep)
    idx = np.flatnonzero(c.varying)[keep]
    mask = np.zeros_like(c.varying)
    mask[idx] = True
    return c.replace(trajectories=[t[:, keep] for t in c.trajectories[:n_clips]],
                     varying=mask, constant_values=c.constant_values,
                     origins=c.origins[:n_clips], names=c.names[:n_clips])


# ----------------------------------------------------------------------------- adapters


def streams(model, rng, *, count: int, length: int, sigma: float,
            noise_time: float | None, window: int | None = None) -> np.ndarray:
    """``(count, length, D)`` streams: ``Sampler.stream`` (frame by frame) when it exists,
    else ``Sampler.run``; ``window``: the crowd mode.  Columns are ``model.clips.labels``."""
    from mocapflow.stages.variation.sample import Sampler

    s = Sampler(model, window=window)
    if hasattr(s, "stream"):
        gen = s.stream(rng, count=count, sigma=sigma, noise_time=noise_time)
        return np.stack(list(itertools.islice(gen, length)), axis=1)
    return s.run(rng, count=count, length=length, sigma=sigma, noise_time=noise_time)


def _strip(clips):
    try:
        from mocapflow.stages.variation.sample import _strip_internal
    except ImportError:  # a checkout without phase DOFs
        return clips
    return _strip_internal(clips)


def chained_cycles(model, rng, *, count: int, sigma: float, noise_time: float | None):
    """``count`` consecutive cycles of one variant stream, as motions.

    The ``sample`` stage's ``loop`` when it has it and accepts the model (each
    cycle a variant with chained origins); else one long stream cut where the right hip flexion DOF
    passes the inputs' mean start value in their start direction (the start
    phase), the cycles played from one motion.

    Returns
    -------
    motions : list of Motion
        One per cycle, in playing order (fewer when the stream stalls; none
        when it makes fewer than two).
    how : str
    out : dict or None
        The ``sample`` stage's output (``variants``, ``predicted``) with ``loop``.
    """
    from mocapflow.pipeline import Context
    from mocapflow.stages.metrics.gait import hip_flexion_columns
    from mocapflow.stages.variation.clips import clips_to_motions
    from mocapflow.stages.variation.sample import sample

    why = "the sample stage has no loop option"
    if "loop" in inspect.signature(sample).parameters:
        try:
            out = sample(model, count=count, loop=True, sigma=sigma, noise_time=noise_time,
                         ctx=Context(rng=rng))
            return clips_to_motions(out["variants"]), "sample(loop=True)", out
        except ValueError as e:  # SampleError: e.g. a model without the cycle phase
            why = f"sample(loop=True) refused: {e}"
    c = model.clips
    col = hip_flexion_columns(c.labels, c.trajectories)["right"]
    start = np.mean([t[0, col] for t in c.trajectories])
    up = np.mean([t[1, col] - t[0, col] for t in c.trajectories]) >= 0
    n = int(c.lengths.max()) * (3 * count + 5)
    x = streams(model, rng, count=1, length=n, sigma=sigma, noise_time=noise_time)[0]
    h = x[:, col] - start
    cross = np.flatnonzero((h[:-1] < 0) & (h[1:] >= 0) if up else (h[:-1] > 0) & (h[1:] <= 0)) + 1
    cuts, gap = [], 0.5 * int(c.lengths.min())
    for f in cross:
        if not cuts or f - cuts[-1] >= gap:
            cuts.append(int(f))
    if len(cuts) < count + 1:
        why += f"; the stream passed the start phase only {len(cuts)} times in {n} frames"
        if len(cuts) < 3:
            return [], why, None
        count = len(cuts) - 1
    seg = x[cuts[0]:cuts[count]]
    one = _strip(c.replace(trajectories=[seg], origins=c.origins[:1], names=["chain"]))
    m = clips_to_motions(one)[0]
    lengths = np.diff(cuts[: count + 1])
    bounds = np.concatenate([[0], np.cumsum(lengths)])
    tr = m.translations

    def part(a, b):
        kw = {} if tr is None or np.ndim(tr) < 3 else {"translations": tr[a:b]}
        return m.replace(root_position=m.root_position[a:b], rotations=m.rotations[a:b], **kw)

    return ([part(a, b) for a, b in itertools.pairwise(bounds)],
            f"one Sampler stream cut where the right hip passes the inputs' start; {why}", None)


# ----------------------------------------------------------------------------- metrics


def _positions(motions):
    from mocapflow.stages.motion.kinematics import motion_positions

    return [motion_positions(m) for m in motions]


def _pooled_jerk_p99(positions, rate: float, trim: int = 2) -> float:
    """p99 of the per-frame jerk pooled over clips (``trim`` frames dropped at each end)."""
    from mocapflow.stages.metrics.quality import jerk_per_frame

    j = np.concatenate([jerk_per_frame(p, rate)[trim:len(p) - trim] for p in positions])
    return float(np.percentile(j[np.isfinite(j)], 99))


def _novelty_row(rep) -> str:
    d = np.array(rep["aligned_distance"])
    inside = np.mean((d > 0) & (d < rep["input_distance_p95"]))
    wr = np.mean(rep["warp_slope_std"]) / rep["input_warp_slope_std"]
    ok = (rep["equal_poses"] == 0 and max(rep["copied_run"]) < 5 and inside == 1.0
          and 0.5 <= wr <= 2.0)
    return (f"equal poses {rep['equal_poses']:3d} | longest copied run {max(rep['copied_run']):2d}"
            f" (inputs among themselves {rep['input_copied_run']:2d}) | DTW dist median "
            f"{np.median(d):.3f}, max {d.max():.3f} vs input p95 {rep['input_distance_p95']:.3f}"
            f" ({100 * inside:.0f}% inside) | warp-slope std ratio {wr:.2f} | "
            f"{'met' if ok else 'NOT met'}")


def _ik(variants, predicted, nodes: dict, rate: float):
    """The config's ``ik`` at the model's rate (``predicted`` passed when the stage takes it)."""
    from mocapflow.pipeline import Context
    from mocapflow.stages.variation.ik import ik

    p = _accepted(ik, {**nodes["ik"], "output_rate": rate})
    if "predicted" in inspect.signature(ik).parameters and predicted is not None:
        p["predicted"] = predicted
    return ik(variants, **p, ctx=Context())


# ----------------------------------------------------------------------------- sections


def section_streams(model, nodes: dict, n_seeds: int) -> None:
    from mocapflow.stages.metrics.gait import (
        cadence,
        clip_cadence,
        frozen_threshold,
        frozen_windows,
        hip_flexion_columns,
        swing_hysteresis,
    )
    from mocapflow.stages.variation.dofs import motion_to_dofs

    c = model.clips
    rate = c.rate
    hips = hip_flexion_columns(c.labels, c.trajectories)
    sides = sorted(hips)
    cols = [hips[s] for s in sides]
    ins = [t[:, cols] for t in c.trajectories]
    width = int(round(0.5 * rate))
    thr = frozen_threshold(ins, width)
    hyst = swing_hysteresis(ins)
    ref = clip_cadence(c.lengths, rate)
    # the metric on the input take itself (a check of the crossing count)
    motion, _ = _walk_clips(nodes)
    dofs, names, _, _ = motion_to_dofs(motion, root="heading")
    take = [cadence(dofs[:, names.index(c.labels[k])], motion.rate, hysteresis=h)[0]
            for k, h in zip(cols, hyst)]
    sp = nodes["sample"]
    sigma, nt = float(sp["sigma"]), sp["noise_time"]
    print(f"\n## 1. streams: {n_seeds} seeds x {STREAM_FRAMES / rate:.0f} s of the walk model "
          f"({c.n_clips} cycles, {c.n_dofs} DOFs); hip flexion "
          f"{', '.join(f'{s} {c.labels[k]}' for s, k in zip(sides, cols))}")
    print(f"inputs: cadence {ref:.3f} Hz (rate / mean cycle length); the crossing count on the "
          f"whole take: {', '.join(f'{s} {v:.3f}' for s, v in zip(sides, take))} Hz; frozen "
          f"below {', '.join(f'{v:.3f}' for v in thr)} rad per {width} frames; hysteresis "
          f"{', '.join(f'{v:.3f}' for v in hyst)} rad")
    print("| sigma | noise_time s | Sampler window | "
          + " | ".join(f"cadence {s} / inputs' (median, min-max)" for s in sides)
          + " | streams within +-15 % (both hips) | "
          "cycles per stream (median, min; both hips) | frozen windows (total, worst stream) "
          "| target | seconds |")
    print("|---|---|---|---|" + "---|" * (len(sides) - 1) + "---|---|---|---|---|")
    # the sigma 0, 0.15 and 1, the config's, white noise, and the crowd mode
    rows = ([(s_, nt, None) for s_ in sorted({0.0, 0.15, sigma, 1.0})] + [(1.0, None, None)]
            + [(s_, nt, CROWD_WINDOW) for s_ in sorted({0.0, sigma})])
    for s_, nt_, win in rows:
        ratios, cycles, frozen = [], [], []
        t0 = time.perf_counter()
        for seed in range(n_seeds):
            x = streams(model, np.random.default_rng(seed), count=1, length=STREAM_FRAMES,
                        sigma=s_, noise_time=nt_, window=win)[0]
            cad = [cadence(x[:, k], rate, hysteresis=h) for k, h in zip(cols, hyst)]
            ratios.append([v / ref for v, _ in cad])
            cycles.append([n for _, n in cad])
            frozen.append(int(frozen_windows(x[:, cols], thr, width).sum()))
        r, cy, fr = np.array(ratios), np.array(cycles), np.array(frozen)
        within = int(np.all(np.abs(r - 1) <= 0.15, axis=1).sum())
        cells = " | ".join(f"{np.median(r[:, i]):.2f} ({r[:, i].min():.2f}-{r[:, i].max():.2f})"
                           for i in range(len(sides)))
        n_win = STREAM_FRAMES // width
        print(f"| {s_:g} | {nt_} | {win or 'all (exact)'} | {cells} | {within} / {n_seeds} | "
              f"{np.median(cy):.0f}, {cy.min()} | {fr.sum()} of {n_seeds * n_win}, {fr.max()} "
              f"| +-15 %, 0 frozen | {time.perf_counter() - t0:.1f} |")
    _crowd_error(model, sigma, nt)


def _crowd_error(model, sigma: float, noise_time: float | None) -> None:
    """One-step error of the crowd mode's conditional mean, in the exact std's units."""
    from mocapflow.stages.variation.sample import Sampler

    exact = Sampler(model)
    if not hasattr(exact, "stats"):
        return
    x = exact.run(np.random.default_rng(5), count=200, length=60, sigma=sigma,
                  noise_time=noise_time)
    z = (x - exact.stats["mean"]) / exact.stats["std"]
    m0, s0 = exact.transition(z[:, 40], z[:, 41])
    m1, s1 = Sampler(model, window=CROWD_WINDOW).transition(z[:, 40], z[:, 41])
    d = np.abs(m1 - m0) / s0
    print(f"crowd mode (window {CROWD_WINDOW}) vs exact, 200 states x {z.shape[-1]} DOFs: "
          f"|mean difference| / exact std median {np.median(d):.3f}, p99 "
          f"{np.percentile(d, 99):.3f}; std ratio median {np.median(s1 / s0):.3f}")


def section_variants(label: str, model, clips, nodes: dict, n_var: int) -> None:
    from mocapflow.pipeline import Context
    from mocapflow.stages.metrics.gait import channel_range, range_excess
    from mocapflow.stages.metrics.novelty import novelty_report
    from mocapflow.stages.metrics.quality import foot_skate
    from mocapflow.stages.motion.contacts import contact_thresholds, toe_indices
    from mocapflow.stages.variation.clips import clips_to_motions
    from mocapflow.stages.variation.dofs import rotation_channels
    from mocapflow.stages.variation.sample import sample

    sp = nodes["sample"]
    out = sample(model, count=n_var, sigma=float(sp["sigma"]), noise_time=sp["noise_time"],
                 ctx=Context(rng=np.random.default_rng(1)))
    t0 = time.perf_counter()
    cleaned = _ik(out["variants"], out.get("predicted"), nodes, clips.rate)
    t_ik = time.perf_counter() - t0
    ins = clips_to_motions(clips)
    pin = _positions(ins)
    toes = toe_indices(clips.skeleton)
    thr = contact_thresholds(np.concatenate(pin), toes, clips.rate)
    up = "z" if str(ins[0].attrs.get("up", "+y")).lstrip("+-").lower() == "z" else "y"
    ch_in = [rotation_channels(m, up=up)[0] for m in ins]
    lo, hi, mu = channel_range(ch_in)
    names = rotation_channels(ins[0], up=up)[1]

    def skate(ps):
        return float(np.nanmean([foot_skate(p, toes, clips.rate, height_threshold=thr[0],
                                            speed_threshold=thr[1]) for p in ps]))

    j_in, s_in = _pooled_jerk_p99(pin, clips.rate), skate(pin)
    print(f"\n### {label}: {clips.n_clips} input cycles, {clips.n_dofs} DOFs; {n_var} variants "
          f"(sigma {sp['sigma']}, noise_time {sp['noise_time']} s), IK {t_ik:.1f} s, "
          f"at {clips.rate:g} fps")
    print(f"inputs: jerk p99 {j_in:.0f} m/s^3, toe skate {s_in:.3f} m/s")
    print("| variants | jerk p99 / input's | toe skate / input's | max range excess rad "
          "(channel; variants over 0.05) | target |")
    print("|---|---|---|---|---|")
    for name, v in (("sampled", out["variants"]), ("after IK (exported)", cleaned["variants"])):
        ms = clips_to_motions(v)
        ps = _positions(ms)
        ex = np.stack([range_excess(rotation_channels(m, up=up)[0], lo, hi, mu) for m in ms])
        worst = np.unravel_index(np.argmax(ex), ex.shape)
        print(f"| {name} | {_pooled_jerk_p99(ps, clips.rate) / j_in:.2f} | "
              f"{skate(ps) / s_in:.2f} | {ex.max():.3f} ({names[worst[1]]}; "
              f"{int((ex.max(axis=1) > 0.05).sum())} of {len(ms)}) | <= 1.5, <= 1.2, <= 0.05 |")
    rep = novelty_report(cleaned["variants"].trajectories, clips.trajectories,
                         cyclic=bool(clips.cyclic))
    print("novelty after IK:", _novelty_row(rep))
    cells = []
    for seed in OTHER_DRAWS:  # the same after IK on other draws: not one seed's luck
        o = sample(model, count=n_var, sigma=float(sp["sigma"]), noise_time=sp["noise_time"],
                   ctx=Context(rng=np.random.default_rng(seed)))
        ps = _positions(clips_to_motions(_ik(o["variants"], o.get("predicted"), nodes,
                                             clips.rate)["variants"]))
        cells.append(f"seed {seed}: {_pooled_jerk_p99(ps, clips.rate) / j_in:.2f}, "
                     f"{skate(ps) / s_in:.2f}")
    print("other draws after IK (jerk p99 / input's, toe skate / input's; targets <= 1.5, "
          "<= 1.2):", "; ".join(cells))


def section_chaining(model, clips, nodes: dict, count: int = 5) -> None:
    from mocapflow.stages.metrics.gait import join_jerk_p99
    from mocapflow.stages.variation.clips import clips_to_motions

    sp = nodes["sample"]
    rate = clips.rate
    j_in = _pooled_jerk_p99(_positions(clips_to_motions(clips)), rate)
    motions, how, out = chained_cycles(model, np.random.default_rng(3), count=count,
                                       sigma=float(sp["sigma"]), noise_time=sp["noise_time"])
    if len(motions) < 2:
        print(f"\n## 3. chaining: NOT measured, fewer than 2 cycles ({how})")
        return
    ps = _positions(motions)
    lengths = [len(p) for p in ps]
    chain = np.concatenate(ps)
    jj = join_jerk_p99(chain, lengths, rate)
    print(f"\n## 3. chaining: {len(ps)} consecutive cycles of one variant stream ({how}; "
          f"lengths {lengths}), joins +-3 frames")
    print("| motion | jerk p99 at the joins / inputs' p99 | jerk p99 overall / inputs' | "
          "target |")
    print("|---|---|---|---|")
    print(f"| chained cycles | {jj / j_in:.2f} | {_pooled_jerk_p99([chain], rate) / j_in:.2f} | "
          f"<= 1.5 |")
    if out is not None:  # the loop variants through the config's IK (cleaned as one chain)
        ps = _positions(clips_to_motions(
            _ik(out["variants"], out.get("predicted"), nodes, rate)["variants"]))
        chain = np.concatenate(ps)
        print(f"| chained cycles after IK | "
              f"{join_jerk_p99(chain, [len(p) for p in ps], rate) / j_in:.2f} | "
              f"{_pooled_jerk_p99([chain], rate) / j_in:.2f} | <= 1.5 |")
    else:
        print("| chained cycles after IK | not measured (no loop variants) | - | <= 1.5 |")
    print(f"inputs' jerk p99 {j_in:.0f} m/s^3")
    cells = []
    for seed in OTHER_DRAWS:  # other chains, through the config's IK (sample(loop=True) only)
        ms, _, o = chained_cycles(model, np.random.default_rng(seed + 2), count=count,
                                  sigma=float(sp["sigma"]), noise_time=sp["noise_time"])
        if o is None:
            break
        ps = _positions(clips_to_motions(
            _ik(o["variants"], o.get("predicted"), nodes, rate)["variants"]))
        cells.append(f"seed {seed + 2}: "
                     f"{join_jerk_p99(np.concatenate(ps), [len(p) for p in ps], rate) / j_in:.2f}")
    if cells:
        print("other chains after IK (joins jerk p99 / inputs' p99; target <= 1.5):",
              "; ".join(cells))


def _speed_worker(config: str, quick: bool) -> dict:
    """Timings of the code importable in this process (run as a subprocess)."""
    import mocapflow
    from mocapflow.stages.variation.sample import Sampler

    nodes = _nodes(Path(config))
    _, clips = _walk_clips(nodes)
    if quick:
        clips = _subset(clips, 4, 20)
    c0 = time.process_time()
    model, t1 = _learn(clips, nodes, 1)
    sp = nodes["sample"]
    sigma, nt = float(sp["sigma"]), sp["noise_time"]
    res = {"code": str(Path(mocapflow.__file__).resolve().parent), "learn_1": t1,
           "cpu_learn_1": time.process_time() - c0,
           "dofs": int(model.n_dofs), "clips": int(clips.n_clips)}
    # sampling is timed before the 2-worker learning (whose processes may linger)
    frames = 5 if quick else 40
    for key, win in (("", None), ("_crowd", CROWD_WINDOW)):
        s = Sampler(model, window=win)
        # streaming: 1,000 agents advanced frame by frame, timed after the prior's two frames
        gen = s.stream(np.random.default_rng(0), count=1000, sigma=sigma, noise_time=nt)
        for _ in range(4):
            next(gen)
        w0, c0 = time.perf_counter(), time.process_time()
        for _ in range(frames):
            next(gen)
        w, c = time.perf_counter() - w0, time.process_time() - c0
        res[f"us_1000{key}"] = 1e6 * w / (1000 * frames)
        res[f"cpu_us_1000{key}"] = 1e6 * c / (1000 * frames)
    # variants as the sample stage makes them (exact search): 15 per call, prior included
    s = Sampler(model)
    n = 60 if quick else 600
    rng = np.random.default_rng(0)
    s.run(rng, count=15, length=4, sigma=sigma, noise_time=nt)
    w0 = time.perf_counter()
    s.run(rng, count=15, length=n, sigma=sigma, noise_time=nt)
    res["us_15"] = 1e6 * (time.perf_counter() - w0) / (15 * n)
    # CPU of the 2-worker learning: this process and its (reaped) worker processes
    c0, k0 = time.process_time(), _children_cpu()
    _, res["learn_2"] = _learn(clips, nodes, 2)
    res["cpu_learn_2"] = time.process_time() - c0 + _children_cpu() - k0
    return res


def _children_cpu() -> float:
    """User + system seconds of this process's finished child processes."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _run_worker(layout: Path | None, config: Path, quick: bool) -> dict:
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    cwd = REPO
    if layout is not None:
        env["PYTHONPATH"] = str(layout)
        cwd = Path("/tmp")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--speed-worker", "--config",
           str(config)] + (["--quick"] if quick else [])
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(f"speed worker ({layout or 'this checkout'}) failed:\n{r.stderr}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def section_speed(quick: bool, baseline: Path | None) -> None:
    ours = _run_worker(None, WALK_CONFIG, quick)
    base = None
    if baseline is not None:
        cfg = baseline / "mocapflow" / "configs" / "variation.yaml"
        base = _run_worker(baseline, cfg if cfg.exists() else WALK_CONFIG, quick)
    print(f"\n## 4. speed, BLAS 1 thread per process: the shipped walk config, "
          f"{ours['clips']} clips, {ours['dofs']} DOFs ({ours['code']}"
          + (f"; baseline {base['code']}, {base['dofs']} DOFs" if base else
             "; no --baseline: ratio columns skipped") + ")")
    rows = [("learn, 1 worker (s)", "learn_1", "-"), ("learn, 2 workers (s)", "learn_2", "<= 30"),
            ("learn, 1 worker (CPU s)", "cpu_learn_1", "-"),
            ("learn, 2 workers (CPU s, workers included)", "cpu_learn_2", "-"),
            ("stream 1,000 agents, exact search (us / agent-frame, wall)", "us_1000", "-"),
            ("stream 1,000 agents, exact search (CPU us / agent-frame)", "cpu_us_1000", "-"),
            (f"stream 1,000 agents, crowd mode window {CROWD_WINDOW} (us / agent-frame, wall)",
             "us_1000_crowd", "<= 30"),
            ("stream 1,000 agents, crowd mode (CPU us / agent-frame)", "cpu_us_1000_crowd", "-"),
            ("sample 15 per call, prior included (us / agent-frame, wall)", "us_15", "-")]
    print("| measure | ours |" + (" baseline | ours / baseline |" if base else "") + " target |")
    print("|---|---|" + ("---|---|" if base else "") + "---|")
    for name, key, target in rows:
        cell = f"| {name} | {ours[key]:.2f} |"
        if base and key in base:  # an older checkout's worker may lack a measure
            cell += f" {base[key]:.2f} | {ours[key] / base[key]:.2f} |"
        elif base:
            cell += " - | - |"
        print(cell + f" {target} |")
    su = ours["learn_1"] / ours["learn_2"]
    line = f"speed-up 2 vs 1 worker: ours {su:.2f}x (target >= 1.6x)"
    if base:
        line += f", baseline {base['learn_1'] / base['learn_2']:.2f}x"
    print(line)


def section_strokes(n_var: int) -> None:
    from mocapflow.pipeline import Context
    from mocapflow.stages.metrics.novelty import novelty_report
    from mocapflow.stages.motion.ingest import ingest_strokes_set
    from mocapflow.stages.variation.inputs import clips as clips_stage
    from mocapflow.stages.variation.sample import sample

    nodes = _nodes(STROKES_CONFIG)
    path = _part(nodes, sub="strokes")
    print(f"\n## 5. strokes: {n_var} variants per character ({STROKES_CONFIG.name}, "
          f"letter replaced)")
    for letter in ("a", SECOND_LETTER):
        ex = ingest_strokes_set(str(path), letter=letter, ctx=Context())["examples"]
        sc = clips_stage(ex, **_accepted(clips_stage, nodes["clips"]), ctx=Context())["clips"]
        sm, tl = _learn(sc, nodes, 1)
        sp = nodes["sample"]
        sv = sample(sm, count=n_var, **_accepted(sample, {"sigma": sp["sigma"],
                                                          "noise_time": sp.get("noise_time")}),
                    ctx=Context(rng=np.random.default_rng(0)))["variants"]
        print(f"'{letter}': {sc.n_clips} examples, learn {tl:.1f} s; novelty:",
              _novelty_row(novelty_report(sv.trajectories, sc.trajectories)))


def section_quality(model, walk, nodes: dict, n_var: int, quick: bool) -> None:
    from mocapflow.pipeline import Context
    from mocapflow.stages.metrics.novelty import novelty_report
    from mocapflow.stages.metrics.quality import foot_skate, jerk_p99
    from mocapflow.stages.motion.contacts import contact_thresholds, toe_indices
    from mocapflow.stages.variation.clips import clips_to_motions
    from mocapflow.stages.variation.sample import matched_amplitude, sample, sample_noise

    sp = nodes["sample"]
    sigma, nt = float(sp["sigma"]), sp["noise_time"]

    def draw(**p):
        return sample(model, **p, ctx=Context(rng=np.random.default_rng(1)))

    ours_out = draw(count=n_var, sigma=sigma, noise_time=nt)
    ours = ours_out["variants"]
    rows = [("inputs", walk), ("ours mean motion (sigma 0)", draw(count=1, sigma=0.0)["variants"]),
            ("ours, white noise, sigma 1 (the paper)", draw(count=n_var, sigma=1.0)["variants"]),
            (f"ours (sigma {sigma}, noise_time {nt} s)", ours),
            ("ours + IK", _ik(ours, ours_out.get("predicted"), nodes, walk.rate)["variants"])]
    L = int(np.median(walk.lengths))
    toes = toe_indices(walk.skeleton)
    pin = np.concatenate(_positions(clips_to_motions(walk)))
    thr = contact_thresholds(pin, toes, walk.rate)

    def dist(v):
        return float(np.mean(novelty_report(v.trajectories, walk.trajectories,
                                            cyclic=True)["aligned_distance"]))

    d_ours = dist(ours)
    for method in ("strawman", "perlin"):
        def make(a, method=method):
            return sample_noise(walk, method=method, count=n_var, length=L, amplitude=a,
                                ctx=Context(rng=np.random.default_rng(2)))["variants"]

        a = matched_amplitude(make, dist, d_ours, iterations=6 if quick else 10)
        rows.append((f"{method} (amplitude {a:.3f} std)", make(a)))
    print(f"\n## 6. walk quality against the noise baselines at matched DTW distance: "
          f"{walk.n_clips} cycles, {n_var} variants of {L} frames")
    print("| motion | jerk p99 (m/s^3) | foot skate (m/s) | DTW dist to inputs (mean +- std) |")
    print("|---|---|---|---|")
    for name, c in rows:
        ps = _positions(clips_to_motions(c))
        j = np.mean([jerk_p99(p, c.rate) for p in ps])
        s = np.nanmean([foot_skate(p, toes, c.rate, height_threshold=thr[0],
                                   speed_threshold=thr[1]) for p in ps])
        if name == "inputs":
            dd = np.array(novelty_report(c.trajectories, c.trajectories)["input_distances"])
        else:
            dd = np.array(novelty_report(c.trajectories, walk.trajectories,
                                         cyclic=True)["aligned_distance"])
        print(f"| {name} | {j:.0f} | {s:.3f} | {dd.mean():.2f} +- {dd.std():.2f} |")


def main(quick: bool = False, baseline: Path | None = None,
         sections: set[int] | None = None) -> None:
    """Run the sections numbered in ``sections`` (``None``: all six)."""
    def want(k: int) -> bool:
        return sections is None or k in sections

    n_var = 5 if quick else 15
    t_all = time.perf_counter()
    print(f"# variation benchmark ({'quick' if quick else 'full'}); data {DATA}"
          + ("" if sections is None else f"; sections {sorted(sections)}"))
    print(f"# machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; BLAS threads "
          f"pinned to 1 per process")
    nodes = _nodes(WALK_CONFIG)
    if any(want(k) for k in (1, 2, 3, 6)):
        _, walk = _walk_clips(nodes)
        model, t_learn = _learn(walk, nodes, 1)
        print(f"# walk model ({WALK_CONFIG.name}): {walk.n_clips} cycles, {model.n_dofs} DOFs, "
              f"learned in {t_learn:.1f} s")
    if want(1):
        section_streams(model, nodes, 5 if quick else 20)
    if want(2):
        print("\n## 2. exported variants after IK")
        _, cmu = _walk_clips(nodes, DATA / "bvh" / "cmu_131_02.bvh")
        if quick:
            cmu = _subset(cmu, 4, 20)
        cmu_model, t_cmu = _learn(cmu, nodes, 1)
        print(f"(cmu_131_02 learned in {t_cmu:.1f} s)")
        section_variants("cmu_131_02.bvh", cmu_model, cmu, nodes, n_var)
        section_variants("figure-8 walk (pymo_AV_8Walk)", model, walk, nodes, n_var)
    if want(3):
        section_chaining(model, walk, nodes)
    if want(4):
        section_speed(quick, baseline)
    if want(5):
        section_strokes(n_var)
    if want(6):
        section_quality(model, walk, nodes, n_var, quick)
    print(f"\n# total {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="small run (5 streams, 5 variants, 20-DOF cmu and speed models)")
    ap.add_argument("--baseline", type=Path, default=None,
                    help="layout dir of today's code (PYTHONPATH for the speed subprocess)")
    ap.add_argument("--sections", default=None,
                    help="comma-separated section numbers to run, e.g. 2,3 (default: all)")
    ap.add_argument("--speed-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--config", default=str(WALK_CONFIG), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.speed_worker:
        print(json.dumps(_speed_worker(a.config, a.quick)))
    else:
        picked = None
        if a.sections:
            try:
                picked = {int(k) for k in a.sections.split(",") if k.strip()}
            except ValueError:
                ap.error(f"--sections: comma-separated numbers 1-6, got {a.sections!r}")
            if not picked <= set(range(1, 7)):
                ap.error(f"--sections: numbers 1-6, got {a.sections!r}")
        main(a.quick, a.baseline, picked)
