"""Benchmark of the texture graph (Moradoff 2002) against the GenMM baseline, copy and shuffle.

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
default parameters (``variety`` 0.45: jumps drawn within the 45 % quantile of
the input's own jump costs; ``max_run`` 0.25 of the input; seams cross-faded over
0.33 s; foot IK) and with a higher ``variety``.

Baselines, measured in the same run on the same inputs and seeds:

* *GenMM baseline (reimplementation)* — ``benchmarks/genmm_baseline.py``, a NumPy
  reimplementation of GenMM (Li et al., SIGGRAPH 2023: multi-scale generative patch
  matching with patch averaging, the paper's defaults), not GenMM's code, computed as
  GenMM's released code computes it (its CPU time within 13 % of the released code's
  on every row, calibration in that module's docstring); its
  seams and verbatim runs are read from the centre of the patch matched around each
  frame (its frames are blends, so they are approximate).  It has no pose
  constraints and no path control: the constrained and path cases print "n/a".
  *GenMM baseline (reimplementation, lean)*: the same algorithm, matches and outputs
  (float32 rounding) computed leanly (one distance matrix per step, strided patch
  views), in a fifth to a quarter of the time; timed beside it, so nothing is hidden.
* *copy* — the input played again and again; *shuffle* — random 30-frame chunks,
  no blending (same root integration as ours, no search, no smoothing).

GenMM's released code is not part of this repository (it is not on PyPI and needs
PyTorch); two ways to measure it against the same metrics, both reading its output
BVHs with the rate set to the input's (its BVH writer writes ``Frame Time: 1.0``) and
evaluating them with the same :func:`evaluate` as every row:

* ``--genmm-command "CMD"`` — an extra row *GenMM (released code, external command)*
  in the main table and columns *CPU s ours/GenMM released*, *CPU s
  reimpl./GenMM released* and *CPU s reimpl. lean/GenMM released* in the summary.
  For every (input, output length, seed)
  of the main table (the reimplementation's seeds, ``--genmm-seeds``), right after
  ours and the reimplementation on that seed (so machine load falls on all three
  alike), the benchmark runs, as a subprocess::

      CMD INPUT.bvh LENGTH SEED OUTPUT.bvh

  ``CMD`` split as a shell would (``shlex``); ``INPUT.bvh`` the row's input exactly
  as ours gets it (resampled to 30 fps, cropped for the 1024-frame rows; written by
  this package's BVH writer to a temporary folder); ``LENGTH`` output frames; ``SEED``
  an int; ``OUTPUT.bvh`` where to write the result (in the same temporary folder).
  The environment is passed on (``OMP_NUM_THREADS=1`` unless set otherwise); the
  command must itself run on one thread, as ours does.  It prints (the last stdout
  line starting with ``{``) one JSON object with at least ``"cpu"``: CPU seconds of
  its synthesis only (no imports, no file I/O), and optionally ``"path"``: the BVH
  written, if not ``OUTPUT.bvh``.  The command — a script that calls GenMM's code —
  lives and runs outside this repository.
* ``--calibrate FILE`` — the same comparison from runs made earlier: ``FILE`` holds
  one such JSON object per line, ``{"input": "bvh/….bvh", "length": 1024, "seed": 0,
  "cpu": seconds, "path": "GenMM's output BVH"}`` (``input`` relative to the data
  folder; GenMM run on it at 30 fps), set beside the reimplementation on the same
  seeds.

Run::

    .venv/bin/python benchmarks/texture.py            # 5 seeds, all rows
    .venv/bin/python benchmarks/texture.py --quick    # 2 seeds, 2× rows only
    .venv/bin/python benchmarks/texture.py --quick --level-weights 2/1/0.5   # + weighted rows
    .venv/bin/python benchmarks/texture.py --quick --graph-path   # + graph-path rows
    .venv/bin/python benchmarks/texture.py --quick --smooth-levels every   # + rows smoothing
                                                   # every level (the thesis, §3.8)
    .venv/bin/python benchmarks/texture.py --calibrate runs.jsonl   # vs GenMM itself
    .venv/bin/python benchmarks/texture.py --no-cases --no-speed \
        --genmm-command "/path/to/venv/bin/python /path/to/run_genmm.py"   # + GenMM's code
    .venv/bin/python benchmarks/texture.py --seeds 3 --no-cases --no-speed \
        --genmm-command "CMD"   # the calibration in benchmarks/genmm_baseline.py
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from mocapflow.pipeline import Context  # noqa: E402
from mocapflow.stages.metrics import quality as M  # noqa: E402
from mocapflow.stages.motion.contacts import contact_thresholds, toe_indices  # noqa: E402
from mocapflow.stages.motion.formats.bvh import read_bvh, write_bvh  # noqa: E402
from mocapflow.stages.motion.kinematics import motion_positions, resample_motion  # noqa: E402
from mocapflow.stages.texture.assemble import assemble_motion  # noqa: E402
from mocapflow.stages.texture.pyramid import build_pyramid, levels_for_rate  # noqa: E402
from mocapflow.stages.texture.root import PathCurve, figure_eight  # noqa: E402
from mocapflow.stages.texture.search import SearchParams  # noqa: E402
from mocapflow.stages.texture.synth import synth  # noqa: E402

if str(Path(__file__).resolve().parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
from genmm_baseline import GenMMParams, genmm_synthesize  # noqa: E402

DATA = Path(os.environ.get("MOCAPFLOW_DATA", Path(__file__).parents[1] / ".." / "shared" / "data"))
INPUTS = {
    "salsa cmu_60_01": "bvh/cmu_60_01_scaled.bvh",
    "walk cmu_131_02": "bvh/cmu_131_02.bvh",
    "8-walk pymo_AV": "bvh/pymo_AV_8Walk_Meredith_HVHA_Rep1.bvh",
}
HEADING_FREE = True
MORE_VARIED = 0.6
TARGETS = "targets: ≤3 s/1024 frames, coverage ≥0.95, jerk ratio ≤1.3, skate ratio ≤1.1"
GENMM = "GenMM baseline (reimplementation)"
GENMM_LEAN = "GenMM baseline (reimplementation, lean)"
RELEASED = "GenMM (released code, external command)"
NA = "n/a (no constraints/path in GenMM)"
#: constrained case: [input frame at the source rate (120 fps), output frame], as in
#: tests/stages/texture/test_constraints.py
CONSTRAINED = ("salsa cmu_60_01", 1024, [[100, 10], [300, 512], [450, 1000]])
#: path case: a closed figure-8 (spline, 2 m loops) followed by the walks
PATH_INPUTS = ("walk cmu_131_02", "8-walk pymo_AV")
PATH_LENGTH = 1024


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


def evaluate(ref: Reference, out, src: np.ndarray | None, seconds: float) -> dict[str, float]:
    """All metrics of one output (``src`` None: no source track, seam metrics NaN)."""
    rate = ref.motion.rate
    pos = motion_positions(out)
    feat = M.rotation_features(out, heading_free=HEADING_FREE)
    seams = M.seams_from_source(src) if src is not None else np.zeros(0, dtype=np.int64)
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
        "verbatim": float(M.longest_verbatim_run(src)) if src is not None else np.nan,
        "seams": float(seams.size) if src is not None else np.nan,
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


def run_genmm(ref: Reference, motion, length: int, seed: int,
              computation: str = "released") -> dict[str, float]:
    """The GenMM baseline (reimplementation) on one seed, timed like ours; ``computation``
    ``"lean"``: its lean variant (:class:`genmm_baseline.GenMMParams`)."""
    t0 = time.process_time()
    r = genmm_synthesize(motion, length, seed, GenMMParams(computation=computation))
    seconds = time.process_time() - t0
    return evaluate(ref, r["motion"], r["source_index"], seconds)


def evaluate_released(ref: Reference, rec: dict) -> dict[str, float]:
    """Metrics of one output of GenMM's released code, read back at the input's rate.

    ``rec``: its JSON record, with ``"path"`` (the output BVH), ``"cpu"`` (seconds) and
    ``"length"`` (frames asked for; a shorter output is reported on stderr).
    """
    out = read_bvh(rec["path"]).replace(rate=ref.motion.rate)  # GenMM writes Frame Time 1.0
    if out.skeleton.names != ref.motion.skeleton.names:
        raise SystemExit(f"{rec['path']}: skeleton differs from the input's")
    if out.n_frames != int(rec["length"]):
        print(f"note: {rec['path']}: {out.n_frames} frames, {rec['length']} asked",
              file=sys.stderr)
    return evaluate(ref, out, None, float(rec["cpu"]))


def run_released(command: str, ref: Reference, src: Path, length: int,
                 seed: int) -> dict[str, float]:
    """GenMM's released code on one seed: ``command src length seed output`` (a subprocess,
    see the module docstring), its JSON line read and its output evaluated."""
    out = src.with_name(f"{src.stem}.{length}.seed{seed}.bvh")
    argv = [*shlex.split(command), str(src), str(length), str(seed), str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.lstrip().startswith("{")]
    if proc.returncode or not lines:
        raise SystemExit(f"--genmm-command failed (exit {proc.returncode}, no JSON line: "
                         f"{not lines}): {shlex.join(argv)}\n{proc.stderr[-3000:]}")
    rec = {"path": str(out), **json.loads(lines[-1]), "length": length}
    return evaluate_released(ref, rec)


def run_row(motion, length: int, seeds: list[int], levels: int, variants: dict,
            genmm_seeds: list[int] | None = None, genmm_command: str | None = None):
    """Metrics of our variants, the GenMM baseline, copy and shuffle; ``{method: [dict]}``.

    ``variants``: method name -> ``synth`` params; ``genmm_seeds``: the seeds the
    baseline runs with (default ``seeds``); ``genmm_command``: also GenMM's released
    code on those seeds, run by this command (:func:`run_released`).
    """
    ref = Reference(motion)
    res: dict[str, list[dict]] = {name: [] for name in variants}
    res.update({GENMM: [], GENMM_LEAN: [], **({RELEASED: []} if genmm_command else {}),
                "copy": [], "shuffle": []})
    genmm_seeds = seeds if genmm_seeds is None else genmm_seeds
    if genmm_command:  # the row's input as ours gets it, in a folder removed at the end
        tmp = tempfile.TemporaryDirectory(prefix="texture-genmm-")  # (or when collected)
        src_bvh = write_bvh(motion, Path(tmp.name) / f"input{motion.n_frames}.bvh")
    for seed in seeds:
        for name, params in variants.items():
            t0 = time.process_time()  # CPU seconds: robust to other jobs on the machine
            pyr = build_pyramid(motion, levels=levels)
            # output at the synthesis rate, as the inputs it is measured against (the stage
            # exports at the source file's rate by default)
            r = synth(pyr, motion, length=length, seed=seed, ctx=seeded_context(seed),
                      output_rate=motion.rate, **params)
            seconds = time.process_time() - t0
            res[name].append({**evaluate(ref, r["motion"], r["source_index"], seconds),
                              "seed": seed})
        if seed in genmm_seeds:
            res[GENMM].append({**run_genmm(ref, motion, length, seed), "seed": seed})
            res[GENMM_LEAN].append({**run_genmm(ref, motion, length, seed, "lean"),
                                    "seed": seed})
            if genmm_command:
                res[RELEASED].append({**run_released(genmm_command, ref, src_bvh, length,
                                                     seed), "seed": seed})
        rng = np.random.default_rng(1000 + seed)
        for name, src in (
            ("copy", copy_source(motion.n_frames, length)),
            ("shuffle", shuffle_source(motion.n_frames, length, rng)),
        ):
            t0 = time.process_time()
            out, _ = assemble_motion(pyr, motion, src, smoothing=False, plant=False, foot_ik=False)
            res[name].append(evaluate(ref, out, src, time.process_time() - t0))
    if genmm_command:
        tmp.cleanup()
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


def _mean(values: list[dict], key: str) -> float:
    v = np.array([d[key] for d in values], dtype=float)
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


def time_ratio(a: list[dict], b: list[dict]) -> tuple[float, str]:
    """CPU time of ``a`` over ``b``: the ratio of the means, and as a cell with the
    per-seed ratios' min–max (seeds run by both)."""
    by_seed = {d["seed"]: d["time"] for d in b}
    ratios = np.array([d["time"] / by_seed[d["seed"]] for d in a if d["seed"] in by_seed])
    r = _mean(a, "time") / _mean(b, "time")
    return r, (f"{r:.2f} ({ratios.min():.2f}–{ratios.max():.2f})" if ratios.size else "—")


def summary_line(name: str, n_in: int, length: int, res: dict) -> str:
    """Ours vs the GenMM baseline on one row: time ratio and the must-show checks; with
    GenMM's released code in ``res``, also ours and the baseline over it in CPU time."""
    ours, base = res["ours"], res[GENMM]
    t_ratio, rr = time_ratio(ours, base)
    released = ""
    if RELEASED in res:
        t_rel, cell = time_ratio(ours, res[RELEASED])
        released = (f" {cell} | {time_ratio(base, res[RELEASED])[1]} | "
                    f"{time_ratio(res[GENMM_LEAN], res[RELEASED])[1]} |")
    cover = min(d["coverage"] for d in ours)
    g_o, g_b = _mean(ours, "global_diversity"), _mean(base, "global_diversity")
    l_o, l_b = _mean(ours, "local_diversity"), _mean(base, "local_diversity")
    j_o, j_b = _mean(ours, "jerk"), _mean(base, "jerk")
    s_o, s_b = _mean(ours, "skate"), _mean(base, "skate")
    checks = [
        ("≥2× faster", t_ratio <= 0.5),
        ("jerk", j_o <= j_b),
        ("skate", s_o <= s_b),
        ("cover≥0.95", cover >= 0.95),
        ("global", g_o >= g_b),
        ("local≤1.2×", l_o <= 1.2 * l_b),
    ]
    if released:
        checks.insert(1, ("≥2× faster than released", t_rel <= 0.5))
    verdict = ", ".join(f"{k} {'ok' if ok else 'NO'}" for k, ok in checks)
    return (f"| {name} ({n_in}) | {length} | {rr} |{released} {cover:.2f} | "
            f"{g_o:.3f} / {g_b:.3f} | "
            f"{l_o:.3f} / {l_b:.3f} = {l_o / l_b:.2f} | {j_o:.2f} / {j_b:.2f} | "
            f"{s_o:.2f} / {s_b:.2f} | {verdict} |")


#: (rate, output frames) of the speed table: the same 34 s of output at 30 and 120 fps
SPEED = ((30.0, 1024), (120.0, 4096))


def speed_table(seeds: list[int], levels: int | None, only: str | None) -> None:
    """CPU seconds of ours (pyramid + synthesis, default params) per output, at 30 fps and
    at 120 fps.  ``levels`` ``None``: the pyramid's default, by rate (one level more per
    doubling, :func:`~mocapflow.stages.texture.pyramid.levels_for_rate`: its coarsest
    level keeps its duration per node); at 120 fps the 30 fps level count is timed
    beside it, in the same run (the default before levels went by rate)."""
    rule = "by rate (4 at 30 fps, + log2(rate / 30))" if levels is None else f"{levels}"
    print(f"\nSpeed: CPU s of ours (pyramid + synth stage, one core) per output; levels "
          f"{rule}; at 120 fps also with the 30 fps level count, paired per seed\n")
    print("| input | rate | levels | output frames | CPU s (mean, min–max over seeds) | "
          "CPU vs 30 fps levels |")
    print("|---|---|---|---|---|---|")
    for name, rel in INPUTS.items():
        if only and only not in name:
            continue
        for rate, length in SPEED:
            motion = load(rel, rate)
            lv = levels_for_rate(rate, motion.n_frames) if levels is None else levels
            lv30 = levels_for_rate(30.0) if levels is None else levels
            runs = [lv] if lv == lv30 else [lv, lv30]
            times: dict[int, list] = {k: [] for k in runs}
            for seed in seeds:
                for k in runs:
                    t0 = time.process_time()
                    synth(build_pyramid(motion, levels=k), motion, length=length, seed=seed,
                          ctx=seeded_context(seed), output_rate=motion.rate)
                    times[k].append({"time": time.process_time() - t0})
            for k in runs:
                ratio = "—"
                if k != lv30:
                    r = [a["time"] / b["time"] for a, b in zip(times[k], times[lv30])]
                    ratio = f"{np.mean(r):.2f} ({min(r):.2f}–{max(r):.2f})"
                print(f"| {name} | {rate:g} | {k} | {length} | "
                      f"{fmt(times[k], 'time', '{:.2f}')} | {ratio} |", flush=True)


def run_cases(seeds: list[int], levels: int, only: str | None) -> list[str]:
    """Constrained and path cases: our rows; the GenMM baseline has no answer."""
    lines = []
    cases = [("constrained (3 poses)", CONSTRAINED[0], CONSTRAINED[1],
              {"constraints": CONSTRAINED[2]})]
    curve_pts = figure_eight(2.0)
    curve = PathCurve.from_points(curve_pts, mode="spline")
    for name in PATH_INPUTS:
        cases.append(("path (figure-8, 2 m)", name, PATH_LENGTH,
                      {"path": curve_pts.tolist(), "path_mode": "spline"}))
    for case, name, length, params in cases:
        if only and only not in name:
            continue
        motion = load(INPUTS[name])
        ref = Reference(motion)
        rows, extra = [], []
        for seed in seeds:
            t0 = time.process_time()
            pyr = build_pyramid(motion, levels=levels)
            r = synth(pyr, motion, length=length, seed=seed, ctx=seeded_context(seed),
                      output_rate=motion.rate, **params)
            seconds = time.process_time() - t0
            rows.append(evaluate(ref, r["motion"], r["source_index"], seconds))
            if "constraints" in params:
                extra.append(float(r["report"]["constraint_max_angle_deg"]))
            else:
                d, _ = curve.closest(r["motion"].root_position[:, [0, 2]])
                extra.append(float(d.mean()))
        cells = " | ".join(fmt(rows, k, sp) for k, _, sp in COLS)
        what = "max constraint error °" if "constraints" in params else "mean path distance m"
        e = np.array(extra)
        lines.append(f"| {case} | {name} ({motion.n_frames}) | {length} | ours | {cells} | "
                     f"{what} {e.mean():.3f} ({e.min():.3f}–{e.max():.3f}) |")
        lines.append(f"| {case} | {name} ({motion.n_frames}) | {length} | {GENMM} | "
                     + " | ".join([NA] + ["—"] * (len(COLS) - 1)) + f" | {NA} |")
        for line in lines[-2:]:
            print(line, flush=True)
    return lines


def calibrate(path: str) -> int:
    """Real GenMM outputs (``path``: JSON lines) vs the reimplementation, same functions."""
    recs = [json.loads(line) for line in open(path) if line.strip().startswith("{")]
    groups: dict[tuple[str, int], list[dict]] = {}
    for r in recs:
        groups.setdefault((r["input"], int(r["length"])), []).append(r)
    print("calibration: GenMM itself (outputs read back, rate set to the input's) vs the "
          "reimplementation, same inputs, lengths and seeds; CPU s on one thread\n")
    keys = [("time", "CPU s", "{:.2f}"), ("coverage", "cover", "{:.3f}"),
            ("global_diversity", "global", "{:.3f}"), ("local_diversity", "local", "{:.3f}"),
            ("jerk", "jerk×", "{:.2f}"), ("skate", "skate×", "{:.2f}")]
    print("| input (frames) | output | seeds | method | " + " | ".join(k[1] for k in keys) + " |")
    print("|" + "---|" * (4 + len(keys)))
    for (rel, length), runs in groups.items():
        motion = load(rel)
        ref = Reference(motion)
        real, ours, lean = [], [], []
        for r in sorted(runs, key=lambda r: r["seed"]):
            real.append(evaluate_released(ref, r))
            ours.append(run_genmm(ref, motion, length, int(r["seed"])))
            lean.append(run_genmm(ref, motion, length, int(r["seed"]), "lean"))
        seeds = ",".join(str(r["seed"]) for r in sorted(runs, key=lambda r: r["seed"]))
        for method, vals in (("GenMM (released code)", real), (GENMM, ours), (GENMM_LEAN, lean)):
            cells = " | ".join(fmt(vals, k, sp) for k, _, sp in keys)
            print(f"| {rel} ({motion.n_frames}) | {length} | {seeds} | {method} | {cells} |")
        ratio = " | ".join(f"{_mean(ours, k) / _mean(real, k):.2f}" for k, _, _ in keys)
        print(f"| {rel} ({motion.n_frames}) | {length} | {seeds} | reimpl. / GenMM (means) "
              f"| {ratio} |", flush=True)
    return 0


def _json_or_str(text: str):
    """``--variant`` values: JSON (numbers, booleans, lists) or else the string itself."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 seeds, 2× rows only")
    ap.add_argument("--seeds", type=int, default=None, help="number of seeds (default 5)")
    ap.add_argument("--genmm-seeds", type=int, default=None,
                    help="number of seeds the GenMM baseline runs (default: all)")
    ap.add_argument("--levels", type=int, default=None,
                    help="pyramid levels (default: by rate, 4 at 30 fps)")
    ap.add_argument("--only", default=None, help="substring of the input names to run")
    ap.add_argument("--no-cases", action="store_true",
                    help="skip the constrained and path cases")
    ap.add_argument("--level-weights", action="append", default=[], metavar="A/C/F",
                    help="extra rows of ours with these (ancestor/current/finer) level "
                         "weights, e.g. 2/1/0.5 (the thesis weights the coarser level higher)")
    ap.add_argument("--graph-path", action="store_true",
                    help="extra rows of ours with method=graph_path (the transition-graph "
                         "gap filler, same variety / max_run / usage_weight)")
    ap.add_argument("--smooth-levels", action="append", default=[],
                    choices=("finest", "every"),
                    help="extra rows of ours with this smooth_levels (every: each level "
                         "smoothed before the next finer one is refined from it, as the "
                         "thesis; finest: the output only)")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:K=V,...",
                    help="extra rows of ours with these synth params, e.g. "
                         "'thesis smoothing:transition_blend=0,pose_weight=0' (values read "
                         "as JSON, else as strings)")
    ap.add_argument("--no-speed", action="store_true",
                    help="skip the speed table (1,024 frames at 30 fps, 4,096 at 120 fps)")
    ap.add_argument("--calibrate", default=None, metavar="FILE",
                    help="compare the GenMM reimplementation with GenMM's own outputs "
                         "(JSON lines: input, length, seed, cpu, path) and exit")
    ap.add_argument("--genmm-command", default=None, metavar="CMD",
                    help="also run GenMM's released code (outside this repository) on "
                         "every input, length and seed of the main table as 'CMD INPUT.bvh "
                         "LENGTH SEED OUTPUT.bvh'; CMD prints a JSON line with 'cpu' "
                         "(synthesis CPU seconds, one thread); see the module docstring")
    args = ap.parse_args(argv)
    if not DATA.exists():
        print(f"data directory {DATA} not found (set MOCAPFLOW_DATA)", file=sys.stderr)
        return 1
    if args.calibrate:
        return calibrate(args.calibrate)
    n_seeds = args.seeds or (2 if args.quick else 5)
    seeds = list(range(n_seeds))
    genmm_seeds = seeds[: args.genmm_seeds] if args.genmm_seeds is not None else seeds
    variants = {"ours": {}, f"ours variety={MORE_VARIED}": {"variety": MORE_VARIED}}
    if args.graph_path:
        variants["ours graph_path"] = {"method": "graph_path"}
    for sl in args.smooth_levels:
        variants[f"ours smooth_levels={sl}"] = {"smooth_levels": sl}
    for w in args.level_weights:
        a, c, f = (float(x) for x in w.split("/"))
        variants[f"ours weights {w}"] = {"ancestor_weight": a, "current_weight": c,
                                        "finer_weight": f}
    for spec in args.variant:
        vname, _, kvs = spec.partition(":")
        variants[f"ours {vname}"] = {k: _json_or_str(v) for k, v in
                                     (kv.split("=", 1) for kv in kvs.split(",") if kv)}
    print(f"texture benchmark — {n_seeds} seeds ({len(genmm_seeds)} for the GenMM baseline), "
          f"{args.levels or levels_for_rate(30.0)} levels, 30 fps; {TARGETS}")
    print(
        "cells: mean (min–max over seeds); ratios are output/input; CPU s = pyramid + "
        "synthesis on one core; patch metrics on 6-D rotations with the root heading removed"
    )
    d = SearchParams()
    print(f"ours = defaults (variety {d.variety}, max_run {d.max_run}, usage_weight "
          f"{d.usage_weight}, foot IK); 'ours variety={MORE_VARIED}' draws among more "
          f"alternatives; '{GENMM}' = benchmarks/genmm_baseline.py (GenMM's algorithm and "
          "defaults reimplemented in NumPy, not GenMM's code; seams read from its patch "
          "matches)" + (f"; '{RELEASED}' = GenMM's own code run outside this repository "
                        f"by: {args.genmm_command}" if args.genmm_command else "") + "\n")
    header = "| input (frames) | output | method | " + " | ".join(c[1] for c in COLS) + " |"
    print(header)
    print("|" + "---|" * (3 + len(COLS)))
    t_all = time.perf_counter()
    summary = []
    for name, rel in INPUTS.items():
        if args.only and args.only not in name:
            continue
        full = load(rel)
        rows = [] if args.quick else [(crop(full, min(512, full.n_frames)), 1024)]
        rows.append((full, 2 * full.n_frames))
        for motion, length in rows:
            res = run_row(motion, length, seeds, args.levels, variants, genmm_seeds,
                          args.genmm_command)
            for method in res:
                cells = " | ".join(fmt(res[method], k, sp) for k, _, sp in COLS)
                print(
                    f"| {name} ({motion.n_frames}) | {length} | {method} | {cells} |", flush=True
                )
            summary.append(summary_line(name, motion.n_frames, length, res))
    print(f"\nOurs vs the {GENMM}, same inputs and seeds (means; time ratio per seed "
          "min–max):\n")
    released = (" CPU s ours/GenMM released | CPU s reimpl./GenMM released | CPU s reimpl. "
                "lean/GenMM released |" if args.genmm_command else "")
    print(f"| input (frames) | output | CPU s ours/baseline |{released} cover (ours, min) | "
          "global ours / baseline | local ours / baseline | jerk× ours / baseline | skate× "
          "ours / baseline | checks |")
    print("|" + "---|" * (12 if released else 9))
    for line in summary:
        print(line)
    if not args.no_speed:
        speed_table(seeds, args.levels, args.only)
    if not args.no_cases:
        print(f"\nConstrained and path cases ({n_seeds} seeds; the {GENMM} has no answer):\n")
        print("| case | input (frames) | output | method | " + " | ".join(c[1] for c in COLS)
              + " | case metric |")
        print("|" + "---|" * (5 + len(COLS)))
        run_cases(seeds, args.levels, args.only)
    print(f"\n(wall time {time.perf_counter() - t_all:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
