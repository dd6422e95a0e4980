"""Cleaning dense marker captures (Park & Hodgins 2006 §4) against ground truth and peers.

One run prints:

1. **Table 1** (paper's Table 1) on simulated 350-marker captures (900 frames;
   the dynamic treadmill run, a walk and a range of motion): trajectories
   before / after merging, merges, wrong merges (against the simulator's true
   fragment → marker map), ghosts merged, real fragments left, the share of
   the real fragments' measured samples merged, holes, filled, left unfilled,
   the filled samples' error against the truth (mean / p95 mm), seconds.
2. **Table 2** (paper's Table 2) on the dynamic capture: hole-filling error per
   body region normalised by each marker's mean neighbour distance (mean and
   max) — (a) 0.5 s gaps deleted from 10 % of the markers of the perfectly
   merged capture (the paper's protocol: known values removed), placed in the
   motion (after the capture's 0.5 s calibration pose, which is not part of
   the motion under test), (a') the same masks' placement anywhere, the
   calibration pose included (markers seen only in the calibration pose are
   then extrapolated from a handful of frames), (b) every real occlusion hole
   of the capture after our merging, against the true positions.
3. **Gap filling protocol** (METRICS.md §3), the same masks for every method:
   gaps of 0.1 / 0.5 / 1 / 2 s at 1 / 10 / 30 % of the markers at once, placed
   independently or clustered around one marker, ``--reps`` repetitions, on
   the simulated dense capture (with its real occlusion, perfectly merged), on
   the same capture without occlusion (so the whole-body PCA has complete
   frames), and on the real C3D files.  Methods: ours (``clean`` without
   merging: local ridge-regression fill (``fill_model="regression"``, the
   default; the paper's local PCA is ``fill_model="pca"``; on captures of at
   most 120 markers blended with a whole-body PCA, a spline and a rigid-body
   fill, weighted by validation on the take itself) + local-frame
   smoothing), cubic spline
   interpolation, the whole-body PCA of Gløersen & Federolf 2016 (strategy R2,
   implemented from the paper), and Vicon-style rigid-body fill (PyPI
   ``gapfill``, 3 nearest donors visible through the gap).  Per configuration:
   mean / RMSE / p95 / max in mm, mean normalised by the mean neighbour
   distance, % unfilled, % of the samples with >= 3 visible neighbours left
   unfilled (ours must be 0), seconds per run, and ours ÷ each baseline.
   Simulated data are scored against the true positions, real files against
   the deleted measurements.  Each method's mean is over the samples it filled;
   the issue-15 summary per real file also compares ours with every baseline on
   the samples that baseline filled (a spline leaves a gap at the take's edge).
   The baselines fill only the gaps that contain deleted samples (their other
   fills are independent of these and unscored); ours cleans the whole
   capture, so its seconds include every real hole too.
4. **Throughput**: 350 markers x 1000 frames cleaned (merge + fill + smooth),
   in one process and with 2 worker processes behind ``ctx.map``.
5. **The real fragmented file** ``btkdata_PiG_Calibration-FlatFoot-Hole.c3d``:
   which fragments were merged into which labels, and why the others were not.

Run: ``python benchmarks/clean.py --quick`` (a small run of every section),
``--tables-only`` (sections 1, 2, 4, 5), ``--throughput-only`` (section 4), or
the gap protocol alone, cached and resumable (one JSON line per case and
method; the datasets, masks and normalisers are frozen in
``<results>.datasets.npz`` on the first run, so later runs of other methods
use exactly the same data and masks)::

    python benchmarks/clean.py --gaps-only --methods baselines --results R.jsonl
    python benchmarks/clean.py --gaps-only --methods ours --results O.jsonl \
        --frozen R.datasets.npz
    python benchmarks/clean.py --summarise R.jsonl,O.jsonl

``--first-rep N`` starts the repetitions (the mask seeds) at N: tune on some
seeds, report on others (issue 15 reports on seeds 100 and up).

The baselines are in ``clean_baselines.py``, the gap protocol (datasets, masks,
cases, results, summary table, runner) in ``clean_gaps.py``; this script holds
tables 1 and 2, the throughput, the PiG report and the command line.

BLAS runs single-threaded (``--blas-threads``): on two shared cores a
multi-threaded BLAS made the whole-body PCA ~10x slower.
"""

from __future__ import annotations

import argparse
import collections
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from clean_gaps import (
    BASELINES,
    DATA,
    METHODS,
    _dataset_rank,
    _frozen_datasets_path,
    _limit_blas,
    _order,
    check_gf,
    dataset_digest,
    gap_datasets,
    load_datasets,
    load_results,
    perfectly_merged,
    protocol_cases,
    run_protocol,
    save_datasets,
    summarise,
)

from mocapflow.pipeline import Context
from mocapflow.stages.metrics.cleaning import (
    gap_mask,
    region_errors,
    score_merges,
    score_unlabelled,
    strip_labels,
)
from mocapflow.stages.motion.formats.c3d import read_c3d
from mocapflow.stages.motion.simulate.capture import simulate_capture
from mocapflow.stages.skin.clean import clean
from mocapflow.stages.skin.predict import choose_reference_frame, reference_pose
from mocapflow.stages.skin.surface import MarkerSurface

TABLE2_REGIONS = ("abdomen", "elbow", "thigh", "knee", "all")


# --------------------------------------------------------------------------- datasets


def simulated(n_markers: int, n_frames: int, motion: str, seed: int, **kw) -> SimpleNamespace:
    """The ``simulate_capture`` stage on ``default_rng(seed)`` (the stream of earlier tables)."""
    out = simulate_capture(n_markers=n_markers, n_frames=n_frames, motion=motion,
                           ctx=Context(rng=np.random.default_rng(seed)), **kw)
    return SimpleNamespace(**out)


# --------------------------------------------------------------------------- tables 1 and 2


def table1(sims: dict) -> dict:
    print("\n## 1. Table 1: merging on simulated 350-marker captures")
    print("| motion | frames | markers | trajectories before | after | merged | wrong merges | "
          "ghosts merged | real fragments left | real samples merged % | holes | filled | "
          "left unfilled | fill error mean / p95 mm | mean neighbour distance mm | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    cleaned = {}
    for motion, sim in sims.items():
        m, tr = sim.markers, sim.truth
        t0 = time.perf_counter()
        res = clean(m, ctx=Context())
        out, rep = res["markers"], res["report"]
        surf = MarkerSurface.from_mesh(res["surface"])
        dt = time.perf_counter() - t0
        sc = score_merges(rep["merges"], m.fragment_labels, tr["fragment_marker"], m.labels)
        t1 = rep["table1"]
        share, fill_err = _kept_samples(m, tr, rep, out)
        print(f"| {motion} | {m.n_frames} | {m.n_markers} | {t1['fragments_before']} | "
              f"{t1['fragments_after']} | {sc['merged']} | {sc['wrong']} | "
              f"{sc['ghosts_merged']} | {sc['missed']} | {100 * share:.2f} | {t1['holes']} | "
              f"{t1['filled']} | {t1['left_unfilled']} | {fill_err[0]:.2f} / {fill_err[1]:.1f} | "
              f"{rep['surface']['mean_neighbour_distance_mm']} | {dt:.1f} |")
        if sc["wrong_list"]:
            print(f"  wrong merges: {sc['wrong_list'][:10]}")
        cleaned[motion] = (out, rep, surf)
    table1_unlabelled(sims, cleaned)
    return cleaned


def table1_unlabelled(sims: dict, cleaned: dict) -> None:
    """Table 1 again with every label stripped (issue 15 item 2): the clean stage
    labels the take by its reference frame, then merges; real samples kept counts
    a label's own trajectory and merged fragments, beside the labelled run's share
    by the same count."""
    print("\n### 1b. The same captures with every label stripped (clean labels them)")
    print("| motion | labels made | wrong labels | merged | wrong merges | ghosts merged | "
          "real samples kept % (stripped) | (labelled input) | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for motion, sim in sims.items():
        m, tr = sim.markers, sim.truth
        take, true = strip_labels(m, tr["fragment_marker"])
        t0 = time.perf_counter()
        res = clean(take, ctx=Context())
        dt = time.perf_counter() - t0
        sc = score_unlabelled(take, true, res["markers"], res["report"]["merges"])
        fm = np.asarray(tr["fragment_marker"])
        idx = {f: u for u, f in enumerate(m.fragment_labels)}
        merged = np.zeros(len(fm), dtype=bool)
        merged[[idx[g["fragment"]] for g in cleaned[motion][1]["merges"]]] = True
        n = np.isfinite(m.fragments).all(-1).sum(0)
        lab = np.isfinite(m.positions).all(-1).sum()
        share = (lab + n[(fm >= 0) & merged].sum()) / (lab + n[fm >= 0].sum())
        print(f"| {motion} | {sc['labels']} | {sc['wrong_labels']} | {sc['merged']} | "
              f"{sc['wrong']} | {sc['ghosts_merged']} | {100 * sc['kept_share']:.2f} | "
              f"{100 * share:.2f} | {dt:.1f} |")


def _kept_samples(m, tr, rep, out) -> tuple[float, tuple[float, float]]:
    """Share of the real (non-ghost) fragments' samples in merged fragments, and the
    mean / p95 error (mm) of the filled samples against the truth."""
    fm = np.asarray(tr["fragment_marker"])
    n_samples = np.isfinite(m.fragments).all(-1).sum(0)
    idx = {f: u for u, f in enumerate(m.fragment_labels)}
    merged = np.zeros(len(fm), dtype=bool)
    merged[[idx[mg["fragment"]] for mg in rep["merges"]]] = True
    real = fm >= 0
    share = float(n_samples[real & merged].sum() / max(n_samples[real].sum(), 1))
    err = np.linalg.norm(out.positions - tr["positions"], axis=-1)[rep["status"] == 2] * 1e3
    err = err[np.isfinite(err)]
    return share, ((float(err.mean()), float(np.percentile(err, 95))) if len(err)
                   else (float("nan"), float("nan")))


def _table2_gaps(sim, reps: int, first_frame: int) -> tuple[dict, dict]:
    """Table 2 (a): ``reps`` masks of 0.5 s gaps in 10 % of the markers (gaps in
    frames ``first_frame`` and later), each cleaned without merging; returns the
    per-region normalised and mm errors, and the worst case (value, marker, frames)."""
    tr = sim.truth
    base = perfectly_merged(sim)
    rng = np.random.default_rng(0)
    ref, _, _ = reference_pose(base.positions, choose_reference_frame(base.positions))
    acc: dict = collections.defaultdict(lambda: {"norm": [], "mm": []})
    worst = {"value": -1.0}
    for _ in range(reps):
        mask = gap_mask(base.visible, ref, rate=base.rate, duration=0.5, fraction=0.1,
                        clustered=False, rng=rng, first_frame=first_frame)
        res = clean(base.replace(positions=np.where(mask[..., None], np.nan, base.positions)),
                    merge=False, ctx=Context())
        out = res["markers"]
        surf = MarkerSurface.from_mesh(res["surface"])
        err = np.linalg.norm(out.positions - tr["positions"], axis=-1)
        nrm = err / surf.mean_distance[None]
        for k, name in enumerate(tr["region_names"]):
            sel = mask & (tr["region"] == k)[None]
            acc[name]["norm"].append(nrm[sel])
            acc[name]["mm"].append(err[sel])
        acc["all"]["norm"].append(nrm[mask])
        acc["all"]["mm"].append(err[mask])
        f, m = np.unravel_index(np.nanargmax(np.where(mask, nrm, -1.0)), mask.shape)
        if nrm[f, m] > worst["value"]:
            g = np.flatnonzero(mask[:, m])
            worst = {"value": float(nrm[f, m]), "mm": float(err[f, m] * 1e3),
                     "marker": base.labels[m], "region": tr["region_names"][tr["region"][m]],
                     "gap": (int(g[0]), int(g[-1])), "measured": int(base.visible[:, m].sum())}
    stats = {}
    for name, d in acc.items():
        a = np.concatenate(d["norm"]) if d["norm"] else np.zeros(0)
        amm = np.concatenate(d["mm"]) if d["mm"] else np.zeros(0)
        ok = np.isfinite(a)
        if ok.any():
            stats[name] = {"n": int(ok.sum()), "mean": float(a[ok].mean()),
                           "max": float(a[ok].max()), "mean_mm": float(amm[ok].mean() * 1e3),
                           "max_mm": float(amm[ok].max() * 1e3)}
    return stats, worst


def table2(sim, cleaned, reps: int) -> None:
    tr = sim.truth
    calib = int(sim.motion.attrs.get("calibration_frames", 0))
    motion, w_motion = _table2_gaps(sim, reps, calib)
    anywhere, w_any = _table2_gaps(sim, reps, 0)
    out, rep, surf = cleaned
    holes = rep["status"] == 2
    real = region_errors(out.positions, tr["positions"], holes, tr["region"], surf.mean_distance)
    print("\n## 2. Table 2: hole-filling error per region, normalised by the mean neighbour "
          "distance (dynamic capture)")
    print(f"(a) 0.5 s gaps in 10 % of the markers, {reps} masks, perfectly merged capture, "
          f"gaps in the motion (frames >= {calib}, after the {calib / sim.markers.rate:.2f} s "
          "calibration pose); (a') the same with gaps anywhere, the calibration pose included; "
          "(b) all real occlusion holes after our merging, vs truth")
    print("| region | (a) n | (a) mean | (a) max | (a) mean mm | (a) max mm | (a') mean | "
          "(a') max | (b) n | (b) mean | (b) max |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    names = list(TABLE2_REGIONS) + [r for r in tr["region_names"] if r not in TABLE2_REGIONS]
    for name in names:
        a, a2, b = motion.get(name), anywhere.get(name), real.get(name)
        sa = (f"{a['n']} | {a['mean']:.4f} | {a['max']:.4f} | {a['mean_mm']:.2f} | "
              f"{a['max_mm']:.1f}") if a else "0 | — | — | — | —"
        sa2 = f"{a2['mean']:.4f} | {a2['max']:.4f}" if a2 else "— | —"
        sb = f"{b['n']} | {b['mean']:.4f} | {b['max']:.4f}" if b else "0 | — | —"
        print(f"| {name} | {sa} | {sa2} | {sb} |")
    four = [r for r in TABLE2_REGIONS if r != "all"]
    for label, st, w in (("(a)", motion, w_motion), ("(a')", anywhere, w_any)):
        mx4 = max(st[r]["max"] for r in four if r in st)
        mn4 = max(st[r]["mean"] for r in four if r in st)
        print(f"{label} paper's regions ({', '.join(four)}): worst mean {mn4:.4f}, worst max "
              f"{mx4:.4f} -> {'meets' if mn4 <= 0.02 and mx4 <= 0.06 else 'misses'} the target; "
              f"all regions: max {st['all']['max']:.4f}, worst sample {w['value']:.3f} "
              f"({w['mm']:.1f} mm) at {w['marker']} ({w['region']}, gap frames "
              f"{w['gap'][0]}-{w['gap'][1]}, measured in {w['measured']} frames)")
    print("Paper (punching): mean 0.017-0.023, max 0.045-0.062 over abdomen, elbow, thigh, knee; "
          "target here: mean <= 0.02, max <= 0.06.")


# --------------------------------------------------------------------------- throughput, PiG


def _pool_mapper(pool):
    def mapper(fn, items):
        return list(pool.map(fn, items))

    return mapper


def throughput(seed: int) -> None:
    sim = simulated(350, 1000, "dynamic", seed)
    m = sim.markers
    print("\n## 4. Throughput: 350 markers x 1000 frames, full clean (merge + fill + smooth)")
    print("| executor | seconds | merged | left unfilled |")
    print("|---|---|---|---|")
    t0, c0 = time.perf_counter(), time.process_time()
    res = clean(m, ctx=Context())
    rep = res["report"]
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    print(f"| in process (1 worker; CPU {dc:.1f} s) | {dt:.1f} | {rep['table1']['merged']} | "
          f"{rep['table1']['left_unfilled']} |")
    runs = []
    with ProcessPoolExecutor(2) as pool:
        pool.submit(int, 0).result()  # workers up
        for _ in range(3):  # a shared 2-core machine: wall times vary by ~10 %
            ctx = Context(mapper=_pool_mapper(pool), workers=2)
            t0, c0 = time.perf_counter(), time.process_time()
            res = clean(m, ctx=ctx)
            runs.append((time.perf_counter() - t0, res["report"], ctx.timings,
                         time.process_time() - c0))
    for k, (dt2, rep2, _, dc2) in enumerate(runs):
        print(f"| 2 worker processes (ctx.map), run {k + 1}; main process CPU {dc2:.1f} s | "
              f"{dt2:.1f} | {rep2['table1']['merged']} | {rep2['table1']['left_unfilled']} |")
    times = sorted(r[0] for r in runs)
    steps = next(r[2] for r in runs if r[0] == times[1])
    print(f"2 workers: median {times[1]:.1f} s, best {times[0]:.1f} s, worst {times[-1]:.1f} s "
          f"(issue 15 target <= 5 s); step seconds of the median run (ctx.timer): "
          + ", ".join(f"{k} {v:.2f}" for k, v in steps.items()))


def pig_report() -> None:
    p = DATA / "btkdata_PiG_Calibration-FlatFoot-Hole.c3d"
    if not p.exists():
        print("\n## 5. PiG fragmented file: not found (../shared/data absent)")
        return
    m = read_c3d(p)
    ctx = Context(part=p.name)
    res = clean(m, ctx=ctx)
    out, rep = res["markers"], res["report"]
    print(f"\n## 5. {p.name}: {m.n_markers} labelled markers, {m.fragments.shape[1]} unlabelled "
          f"fragments, {m.n_frames} frames")
    print(f"table 1: {rep['table1']}")
    print(f"merges ({len(rep['merges'])}):")
    for mg in rep["merges"]:
        print(f"- {mg['fragment']} -> {mg['label']} (frames {mg['first_frame']}-"
              f"{mg['last_frame']}, entry {mg['entry_mm']} mm < eps1 {mg['eps1_mm']} mm)")
    why = collections.defaultdict(list)
    for r in rep["rejections"]:
        key = r["reason"].split(" (")[0] if r["reason"].startswith("overlaps") else r["reason"]
        why[key].append(f"{r['fragment']}[{r['first_frame']}+{r['n_frames']}]")
    print("not merged:")
    for reason, frs in why.items():
        print(f"- {len(frs)} fragment(s): {reason}: {', '.join(frs[:12])}"
              + (" …" if len(frs) > 12 else ""))
    rasi = m.labels.index("RASI")
    hole = ~m.visible[:, rasi]
    print(f"RASI hole (frames {np.flatnonzero(hole).min()}-{np.flatnonzero(hole).max()}): "
          f"{int(np.isfinite(out.positions[hole, rasi]).all(1).sum())}/{int(hole.sum())} "
          "samples filled")
    for w in ctx.warnings:
        print(f"warning: {w}")


# --------------------------------------------------------------------------- main


def parse_methods(spec: str) -> list[str]:
    """``all``, ``baselines`` or a comma list of ``ours, spline, gf, rigid`` (or the full
    names) → full method names in table order."""
    out: list[str] = []
    for tok in (t.strip() for t in spec.split(",")):
        if tok == "all":
            out += list(METHODS.values())
        elif tok == "baselines":
            out += [METHODS[k] for k in BASELINES]
        elif tok in METHODS or tok in METHODS.values():
            out.append(METHODS.get(tok, tok))
        elif tok:
            raise SystemExit(f"--methods: unknown method {tok!r} (all, baselines, "
                             f"{', '.join(METHODS)})")
    return sorted(set(out), key=_order)


def _floats(spec: str | None, default: list[float]) -> list[float]:
    return default if spec is None else [float(x) for x in spec.split(",") if x.strip()]


def protocol_datasets(args, sims: dict | None = None) -> list[dict]:
    """The gap-protocol datasets: frozen beside ``--results`` (built and frozen on the first
    run), filtered by ``--datasets`` and ordered dense capture, real files, the rest."""
    frozen = (Path(args.frozen) if args.frozen else
              _frozen_datasets_path(args.results) if args.results else None)
    if frozen is not None and frozen.exists():
        sets = load_datasets(frozen)
        print(f"(datasets frozen in {frozen})")
    else:
        sim = (sims or {}).get("dynamic")
        if sim is None:
            sim = simulated(350, 900, "dynamic", args.seed)
        sets = gap_datasets(sim, args.quick)
        if frozen is not None:
            save_datasets(frozen, sets)
            print(f"(datasets frozen in {frozen})")
    if args.datasets:
        want = [w.strip() for w in args.datasets.split(",") if w.strip()]
        sets = [s for w in want for s in sets if w in s["name"]]
    sets = sorted(sets, key=lambda s: _dataset_rank(s["name"]))
    seen = set()
    sets = [s for s in sets if not (s["name"] in seen or seen.add(s["name"]))]
    for s in sets:
        m = s["markers"]
        print(f"- {s['name']}: {m.n_frames} frames x {m.n_markers} markers at {m.rate:g} Hz, "
              f"data {dataset_digest(s)}")
    return sets


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small run")
    ap.add_argument("--reps", type=int, default=None, help="repetitions of the gap protocol")
    ap.add_argument("--first-rep", type=int, default=0,
                    help="first repetition (mask seed) of the gap protocol: report on seeds "
                         "not used while tuning")
    ap.add_argument("--workers", type=int, default=1,
                    help="processes for the gap protocol (one case per task)")
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS threads per process (0: leave as is)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--gf-max-gapped", type=int, default=None,
                    help="run the whole-body PCA (G&F) only on cases with at most this many "
                         "gapped markers (default: all)")
    ap.add_argument("--methods", type=str, default="all",
                    help="gap-protocol methods: all, baselines, or a comma list of "
                         "ours, spline, gf, rigid")
    ap.add_argument("--datasets", type=str, default=None,
                    help="comma list of substrings of the gap-protocol dataset names")
    ap.add_argument("--durations", type=str, default=None, help="gap lengths, s (comma list)")
    ap.add_argument("--fractions", type=str, default=None,
                    help="shares of the markers gapped at once (comma list)")
    ap.add_argument("--placements", type=str, default="independent,clustered")
    ap.add_argument("--gaps-only", action="store_true",
                    help="run only the gap protocol (no tables 1-2, throughput, PiG report)")
    ap.add_argument("--tables-only", action="store_true",
                    help="run only tables 1-2, throughput and the PiG report (no gap protocol)")
    ap.add_argument("--throughput-only", action="store_true",
                    help="run only the throughput (section 4)")
    ap.add_argument("--results", type=str, default=None,
                    help="JSON-lines cache of the gap-protocol cases (one line per case and "
                         "method; cases already there are skipped; the datasets are frozen "
                         "in <results>.datasets.npz)")
    ap.add_argument("--frozen", type=str, default=None,
                    help="frozen datasets file to use or create (default "
                         "<results>.datasets.npz)")
    ap.add_argument("--summarise", type=str, default=None,
                    help="only print the gap-protocol table of results files (comma list)")
    ap.add_argument("--check-gf", type=int, default=0, metavar="N",
                    help="only compare the fast G&F with the literal one on N cases")
    args = ap.parse_args()
    if args.summarise:
        summarise(load_results(args.summarise))
        return
    _limit_blas(args.blas_threads or None)
    if args.throughput_only:
        throughput(args.seed)
        return
    quick = args.quick
    reps = args.reps if args.reps is not None else (2 if quick else 20)
    methods = parse_methods(args.methods)
    durations = _floats(args.durations, [0.5, 2.0] if quick else [0.1, 0.5, 1.0, 2.0])
    fractions = _floats(args.fractions, [0.1] if quick else [0.01, 0.1, 0.3])
    placements = [{"independent": False, "clustered": True}[p.strip()]
                  for p in args.placements.split(",")]
    t_all = time.perf_counter()
    print(f"# clean benchmark ({'quick' if quick else 'full'}; {reps} repetitions)", flush=True)
    sims = None
    if not args.gaps_only and not args.check_gf:
        motions = ["dynamic"] if quick else ["dynamic", "walk", "range_of_motion"]
        sims = {mo: simulated(350, 900, mo, args.seed) for mo in motions}
        cleaned = table1(sims)
        table2(sims["dynamic"], cleaned["dynamic"], reps=3 if quick else 10)
    if args.tables_only:
        throughput(args.seed)
        pig_report()
        print(f"\ntotal {time.perf_counter() - t_all:.0f} s")
        return
    datasets = protocol_datasets(args, sims)
    cases = protocol_cases(datasets, durations=durations, fractions=fractions,
                           placements=placements, reps=reps, first_rep=args.first_rep)
    if args.check_gf:
        pick = np.unique(np.linspace(0, len(cases) - 1, args.check_gf).round().astype(int))
        check_gf(datasets, [cases[i] for i in pick])
        return
    results = run_protocol(datasets, cases, methods, results=args.results,
                           workers=args.workers, gf_max=args.gf_max_gapped,
                           blas_threads=args.blas_threads or None)
    summarise(load_results(args.results) if args.results else results)
    if not args.gaps_only:
        throughput(args.seed)
        pig_report()
    print(f"\ntotal {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
