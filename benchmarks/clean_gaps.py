"""The gap-filling protocol of the clean benchmark (``benchmarks/clean.py``, METRICS.md §3).

The same deletion masks for every method: gaps of given lengths at a share of
the markers at once, placed independently or clustered around one marker,
repeated, on the simulated dense capture (with its real occlusion, perfectly
merged), on the same capture without occlusion and on the real C3D files.
Datasets (:func:`gap_datasets`) are frozen beside the results
(:func:`save_datasets`); one case (:func:`run_case`) runs the methods on one
mask and scores them (simulated data against the true positions, real files
against the deleted measurements); results are appended as JSON lines
(:func:`save_result`), pooled per configuration and printed
(:func:`summarise`); :func:`run_protocol` runs the cases, resumable, on worker
processes.  Methods: ours (:func:`fill_ours`, the ``clean`` stage without
merging) and the baselines of ``clean_baselines.py``.
"""

from __future__ import annotations

import collections
import hashlib
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
from clean_baselines import (
    GFFailure,
    fill_gloersen_federolf,
    fill_gloersen_federolf_direct,
    fill_rigid_body,
    fill_spline,
)

from mocapflow.pipeline import Context
from mocapflow.stages.metrics.cleaning import gap_mask
from mocapflow.stages.motion.datatypes import Markers
from mocapflow.stages.motion.formats.c3d import read_c3d
from mocapflow.stages.skin.clean import clean
from mocapflow.stages.skin.predict import choose_reference_frame, reference_pose
from mocapflow.stages.skin.surface import build_marker_surface

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "c3d"


REAL = [
    "pyomeca_markers_analogs.c3d",
    "ezc3d-testFiles_Qualisys.c3d",
    "btkdata_c3dorg_Eb015pr.c3d",
    "ktk_kinematics_racing_full.c3d",
    "ktk_kinematics_basket_sprint.c3d",
    "btkdata_PiG_Calibration-FlatFoot-Hole.c3d",
]


METHODS = {"ours": "ours", "spline": "cubic spline", "gf": "G&F 2016 R2",
           "rigid": "rigid body (gapfill)"}


BASELINES = ("spline", "gf", "rigid")


# --------------------------------------------------------------------------- methods and datasets


def fill_ours(markers: Markers) -> np.ndarray:
    """The ``clean`` stage without merging (default fill and smoothing)."""
    return clean(markers, merge=False, ctx=Context())["markers"].positions


def perfectly_merged(sim) -> Markers:
    """The capture with every measured sample under its true label (no fragments)."""
    m, tr = sim.markers, sim.truth
    obs = m.positions.copy()
    fm = tr["fragment_marker"]
    fv = np.isfinite(m.fragments).all(-1)
    for u in np.flatnonzero(fm >= 0):
        obs[fv[:, u], fm[u]] = m.fragments[fv[:, u], u]
    return m.replace(positions=obs, fragments=np.zeros((m.n_frames, 0, 3)), fragment_labels=[])


def gap_datasets(sim, quick: bool) -> list[dict]:
    base = perfectly_merged(sim)
    noisy_full = sim.truth["positions"] + np.random.default_rng(7).normal(
        0.0, sim.truth["noise"], sim.truth["positions"].shape)
    sets = [
        {"name": "sim dense (occluded)", "markers": base, "truth": sim.truth["positions"]},
        {"name": "sim dense (no occlusion)", "markers": base.replace(positions=noisy_full),
         "truth": sim.truth["positions"]},
    ]
    for name in REAL[:3] if quick else REAL:
        p = DATA / name
        if p.exists():
            m = read_c3d(p)
            m = m.replace(fragments=np.zeros((m.n_frames, 0, 3)), fragment_labels=[])
            sets.append({"name": name, "markers": m, "truth": None})
    for s in sets:
        m = s["markers"]
        ref, _, _ = reference_pose(m.positions, choose_reference_frame(m.positions))
        surf = build_marker_surface(ref, positions=m.positions, labels=m.labels)
        s["reference"] = ref
        s["dbar"] = surf.mean_distance
        s["neighbours"] = surf.neighbours
    return sets


def _frozen_datasets_path(results: str) -> Path:
    p = Path(results)
    return p.with_name(p.stem + ".datasets.npz")


def save_datasets(path: str | Path, sets: list[dict]) -> None:
    """Freeze the gap-protocol datasets (observed and true positions, layout, mean
    neighbour distances, neighbours) so later runs score on exactly the same data."""
    arrays, meta = {}, []
    for k, s in enumerate(sets):
        m = s["markers"]
        meta.append({"name": s["name"], "labels": list(m.labels), "rate": float(m.rate),
                     "truth": s["truth"] is not None})
        arrays[f"{k}_positions"] = m.positions
        arrays[f"{k}_reference"] = s["reference"]
        arrays[f"{k}_dbar"] = s["dbar"]
        arrays[f"{k}_neighbours"] = s["neighbours"]
        if s["truth"] is not None:
            arrays[f"{k}_truth"] = s["truth"]
    arrays["meta"] = np.array(json.dumps(meta))
    tmp = Path(str(path) + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)


def load_datasets(path: str | Path) -> list[dict]:
    """The datasets written by :func:`save_datasets`."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        sets = []
        for k, mt in enumerate(meta):
            sets.append({
                "name": mt["name"],
                "markers": Markers(positions=z[f"{k}_positions"], labels=mt["labels"],
                                   rate=mt["rate"]),
                "truth": z[f"{k}_truth"] if mt["truth"] else None,
                "reference": z[f"{k}_reference"], "dbar": z[f"{k}_dbar"],
                "neighbours": z[f"{k}_neighbours"]})
    return sets


def dataset_digest(ds: dict) -> str:
    """Short digest of what a dataset's scores depend on (data, truth, layout, normaliser)."""
    h = hashlib.sha1()
    for a in (ds["markers"].positions, ds["truth"], ds["reference"], ds["dbar"],
              ds["neighbours"]):
        if a is not None:
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:12]


# --------------------------------------------------------------------------- one case


def _scores(est: np.ndarray, truth: np.ndarray, mask: np.ndarray, dbar: np.ndarray) -> dict:
    e = np.linalg.norm(est - truth, axis=-1)[mask]
    n = (np.linalg.norm(est - truth, axis=-1) / dbar[None])[mask]
    ok = np.isfinite(e)
    return {"err": e[ok], "norm": n[ok & np.isfinite(n)], "unfilled": int((~ok).sum()),
            "n": int(mask.sum()), "filled": ok, "err_all": e}


def case_mask(ds: dict, duration: float, fraction: float, clustered: bool,
              rep: int) -> np.ndarray:
    """The deterministic deletion mask of one case, (F, M) bool (same for every method)."""
    m = ds["markers"]
    rng = np.random.default_rng([rep, int(duration * 10), int(fraction * 100), int(clustered)])
    return gap_mask(m.visible, ds["reference"], rate=m.rate, duration=duration,
                    fraction=fraction, clustered=clustered, rng=rng)


def mask_digest(mask: np.ndarray) -> str:
    return hashlib.sha1(np.packbits(mask).tobytes() + str(mask.shape).encode()).hexdigest()[:12]


def run_case(args: tuple) -> dict:
    """One (dataset, gap configuration, repetition): the methods on the same mask.

    ``args`` is ``(ds, duration, fraction, clustered, rep, gf_max)`` or the same
    with a seventh item, the method names to run (keys or values of
    ``METHODS``; default all).  ``gf_max`` (None: no limit) skips the whole-body
    PCA when more markers are gapped.
    """
    ds, duration, fraction, clustered, rep, gf_max = args[:6]
    methods = [METHODS.get(n, n) for n in (args[6] if len(args) > 6 and args[6] is not None
                                           else METHODS)]
    m = ds["markers"]
    mask = case_mask(ds, duration, fraction, clustered, rep)
    truth = ds["truth"] if ds["truth"] is not None else m.positions
    gapped = np.where(mask[..., None], np.nan, m.positions)
    nb = ds["neighbours"]
    gvis = np.isfinite(gapped).all(-1)
    seen3 = (gvis[:, np.maximum(nb, 0)] & (nb >= 0)[None]).sum(-1) >= 3
    seen3 &= gvis.any(0)[None]  # a marker deleted over the whole take has no position at all
    out = {}
    gapped_markers = np.flatnonzero(mask.any(0))
    fns = {
        "ours": lambda: fill_ours(m.replace(positions=gapped)),
        "cubic spline": lambda: fill_spline(gapped, m.rate, mask=mask),
        "G&F 2016 R2": lambda: fill_gloersen_federolf(gapped, only=gapped_markers),
        "rigid body (gapfill)": lambda: fill_rigid_body(gapped, ds["reference"], mask=mask),
    }
    for name in methods:
        if name.startswith("G&F") and gf_max is not None and len(gapped_markers) > gf_max:
            continue  # too slow for this many gapped markers (see --gf-max-gapped)
        t0 = time.perf_counter()
        try:
            est = fns[name]()
            status = "ok"
        except GFFailure as e:
            est = gapped
            status = f"failed: {e}"
        dt = time.perf_counter() - t0
        sc = _scores(est, truth, mask, ds["dbar"])
        sc["seconds"] = dt
        sc["status"] = status
        est_ok = np.isfinite(est).all(-1)
        sc["unfilled_3nb"] = int((mask & seen3 & ~est_ok).sum())
        sc["n_3nb"] = int((mask & seen3).sum())
        out[name] = sc
    return {"dataset": ds["name"], "duration": duration, "fraction": fraction,
            "clustered": clustered, "rep": rep, "mask": mask_digest(mask),
            "n_gapped": len(gapped_markers), "methods": out}


# --------------------------------------------------------------------------- results


# error histogram for pooled percentiles: bin k holds errors in [1e-6·1.01^k, 1e-6·1.01^(k+1))
_HIST_LO, _HIST_STEP = 1e-6, np.log(1.01)


def score_stats(sc: dict) -> dict:
    """Poolable summary of one method's scores on one case (sums, max, error histogram)."""
    err, nrm = np.asarray(sc["err"], float), np.asarray(sc["norm"], float)
    k = np.floor(np.log(np.maximum(err, _HIST_LO) / _HIST_LO) / _HIST_STEP).astype(int)
    bins, counts = np.unique(k, return_counts=True)
    return {"n": sc["n"], "unfilled": sc["unfilled"], "n_3nb": sc["n_3nb"],
            "unfilled_3nb": sc["unfilled_3nb"], "seconds": sc["seconds"], "status": sc["status"],
            "n_err": int(len(err)), "sum_err": float(err.sum()),
            "sumsq_err": float((err**2).sum()), "max_err": float(err.max()) if len(err) else None,
            "n_norm": int(len(nrm)), "sum_norm": float(nrm.sum()),
            "max_norm": float(nrm.max()) if len(nrm) else None,
            "hist_bins": bins.tolist(), "hist_counts": counts.tolist()}


def result_rows(r: dict, data: str | None = None) -> list[dict]:
    """One JSON-able row per method of a :func:`run_case` result.

    Every row carries which of the case's deleted samples the method filled
    (``filled``: hex of the packed bits, in the mask's order) and every sample's error
    in micrometres (``err_um``, -1 where unfilled), so ours can be compared with a
    baseline on the samples both filled (:func:`same_sample_ratios`)."""
    key = {k: r[k] for k in ("dataset", "duration", "fraction", "clustered", "rep")}
    rows = []
    for name, sc in r["methods"].items():
        row = {**key, "method": name, "mask": r.get("mask"), "data": data,
               "n_gapped": r.get("n_gapped"), **score_stats(sc)}
        if "filled" in sc:
            row["filled"] = np.packbits(sc["filled"]).tobytes().hex()
        if "err_all" in sc:
            row["err_um"] = np.round(np.nan_to_num(sc["err_all"], nan=-1e-6) * 1e6
                                     ).astype(np.int64).tolist()
        rows.append(row)
    return rows


def same_sample_ratios(common: list[dict]) -> dict[str, float]:
    """Ours' mean error over the samples both ours and each baseline filled ÷ that
    baseline's mean error over the same samples, pooled over the repetitions ``common``
    (``{method: row}`` per repetition, one mask; a baseline that failed on one is left
    out); empty when a row lacks ``filled`` / ``err_um``.  A baseline row written before
    baselines carried ``err_um`` is taken over all the samples it filled (ours' unfilled
    ones then count in the baseline's mean only)."""
    num: dict = collections.defaultdict(float)
    cnt: dict = collections.defaultdict(int)
    base: dict = collections.defaultdict(float)
    base_n: dict = collections.defaultdict(int)
    failed: set = set()
    for ms in common:
        ours = ms.get("ours")
        if ours is None or "err_um" not in ours:
            return {}
        e = np.asarray(ours["err_um"], float) * 1e-6
        for name, row in ms.items():
            if name == "ours":
                continue
            if row["status"] != "ok":  # failed (G&F without a complete frame): no ratio
                failed.add(name)
                continue
            if "filled" not in row:
                return {}
            f = np.unpackbits(np.frombuffer(bytes.fromhex(row["filled"]), np.uint8))[:len(e)]
            f = f.astype(bool) & (e >= 0)
            num[name] += float(e[f].sum())
            cnt[name] += int(f.sum())
            if "err_um" in row:  # the baseline on the same samples
                b = np.asarray(row["err_um"], float) * 1e-6
                base[name] += float(b[f].sum())
                base_n[name] += int(f.sum())
            else:
                base[name] += float(row["sum_err"])
                base_n[name] += int(row["n_err"])
    return {n: (num[n] / cnt[n]) / (base[n] / base_n[n]) for n in num
            if n not in failed and cnt[n] and base[n] > 0}


def row_key(row: dict) -> tuple:
    return (row["dataset"], float(row["duration"]), float(row["fraction"]),
            bool(row["clustered"]), int(row["rep"]), row["method"])


def save_result(path: str, r: dict, data: str | None = None) -> None:
    """Append a :func:`run_case` result to a JSON-lines file (one line per method)."""
    text = "".join(json.dumps(row) + "\n" for row in result_rows(r, data)).encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:  # one write on an O_APPEND descriptor: concurrent runs never interleave lines
        os.write(fd, text)
    finally:
        os.close(fd)


def load_results(path: str) -> list[dict]:
    """Rows of results files (comma-separated paths; the last row wins for a repeated
    case and method)."""
    rows: dict = {}
    bad = 0
    lines = [ln for p in path.split(",") if p.strip() for ln in
             Path(p.strip()).read_text().splitlines()]
    for line in lines:
        if line.strip():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:  # a run killed while writing
                bad += 1
                continue
            rows[row_key(row)] = row
    if bad:
        print(f"({path}: {bad} unreadable line(s) skipped)")
    return list(rows.values())


def _pool(rows: list[dict]) -> dict:
    n = sum(r["n"] for r in rows)
    ne = sum(r["n_err"] for r in rows)
    hist: collections.Counter = collections.Counter()
    for r in rows:
        hist.update(dict(zip(r["hist_bins"], r["hist_counts"])))
    out = {"reps": len(rows), "n": n, "unfilled": sum(r["unfilled"] for r in rows),
           "n_3nb": sum(r["n_3nb"] for r in rows),
           "unfilled_3nb": sum(r["unfilled_3nb"] for r in rows),
           "seconds": float(np.mean([r["seconds"] for r in rows])),
           "failed": sum(r["status"] != "ok" for r in rows), "n_err": ne}
    if ne:
        bins = np.array(sorted(hist))
        cum = np.cumsum([hist[b] for b in bins])
        b95 = bins[np.searchsorted(cum, 0.95 * ne)]
        out.update(mean=sum(r["sum_err"] for r in rows) / ne,
                   rmse=np.sqrt(sum(r["sumsq_err"] for r in rows) / ne),
                   p95=_HIST_LO * np.exp((b95 + 0.5) * _HIST_STEP),
                   max=max(r["max_err"] for r in rows if r["max_err"] is not None),
                   norm=sum(r["sum_norm"] for r in rows) / max(sum(r["n_norm"] for r in rows),
                                                                1))
    return out


def _order(name: str) -> int:
    names = list(METHODS.values())
    return names.index(name) if name in names else len(names)


def summarise(results: list[dict]) -> None:
    """Print the per-configuration gap-filling table of result rows (or of
    :func:`run_case` results), ours ÷ each baseline, and where ours beats them all.

    Within a configuration every method is pooled over the repetitions that all
    its methods ran with the same mask; cases whose masks differ between methods
    (the data or mask generation changed between runs) are left out and counted.
    """
    rows = [row for r in results for row in (result_rows(r) if "methods" in r else [r])]
    cases: dict = collections.defaultdict(dict)
    for row in rows:
        cases[row_key(row)[:5]][row["method"]] = row
    configs: dict = collections.defaultdict(list)
    for key, meths in cases.items():
        configs[key[:4]].append((key[4], meths))
    n_bad = 0
    table = []
    same: dict = {}
    for cfg in sorted(configs, key=lambda c: (_dataset_rank(c[0]), c[0], c[1], c[2], c[3])):
        reps = configs[cfg]
        names = sorted({n for _, ms in reps for n in ms}, key=_order)
        common = []
        for _rep, ms in reps:
            if set(ms) != set(names):
                continue
            if len({ms[n]["mask"] for n in names}) > 1 or \
                    len({ms[n].get("data") for n in names}) > 1:
                n_bad += 1
                continue
            common.append(ms)
        if common:
            same[cfg] = same_sample_ratios(common)
            table.append((cfg, {n: _pool([ms[n] for ms in common]) for n in names}))
    print("\n## 3. Gap filling (same masks for every method; each configuration pooled over "
          "the repetitions every method ran)")
    print("| dataset | gap s | markers | placement | method | reps | mean mm | RMSE mm | p95 mm | "
          "max mm | mean/d | % unfilled | % unfilled (>=3 nb) | s/run | failed | "
          "ours ÷ method (mean / RMSE / p95 / max) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for (ds, dur, frac, cl), st in table:
        ours = st.get("ours")
        for name, s in st.items():
            if s["n_err"]:
                val = (f"{s['mean'] * 1e3:.2f} | {s['rmse'] * 1e3:.2f} | {s['p95'] * 1e3:.2f} | "
                       f"{s['max'] * 1e3:.1f} | {s['norm']:.4f}")
            else:
                val = "— | — | — | — | —"
            ratio = "—"
            if ours is not None and name != "ours" and ours["n_err"] and s["n_err"]:
                ratio = " / ".join(f"{ours[k] / s[k]:.2f}" if s[k] > 0 else "—"
                                   for k in ("mean", "rmse", "p95", "max"))
            print(f"| {ds} | {dur} | {100 * frac:g} % | {'clustered' if cl else 'independent'} "
                  f"| {name} | {s['reps']} | {val} | {100 * s['unfilled'] / max(s['n'], 1):.1f} | "
                  f"{100 * s['unfilled_3nb'] / max(s['n_3nb'], 1):.1f} | {s['seconds']:.2f} | "
                  f"{s['failed']}/{s['reps']} | {ratio} |")
    if n_bad:
        print(f"\n{n_bad} case(s) left out: their methods ran on different masks or data.")
    criteria(table, common_reps={cfg: reps for cfg, reps in configs.items()}, same=same)
    print("\nOurs vs every baseline on the simulated dense capture, gaps >= 0.5 s (mean error "
          "over the samples each method filled; p95 in brackets):")
    beats, loses = [], []
    for (ds, dur, frac, cl), st in table:
        if not ds.startswith("sim dense") or dur < 0.5:
            continue
        label = f"{ds} {dur} s {100 * frac:g} % {'clustered' if cl else 'independent'}"
        others = {n: s for n, s in st.items() if n != "ours" and s["n_err"]}
        ours = st.get("ours")
        if ours is None or not ours["n_err"] or not others:
            continue
        worst = [n for n, s in others.items() if s["mean"] <= ours["mean"]]
        if worst:
            best = min(others, key=lambda n: others[n]["mean"])
            loses.append(f"{label}: ours {ours['mean'] * 1e3:.2f} ({ours['p95'] * 1e3:.1f}) mm "
                         f"vs {best} {others[best]['mean'] * 1e3:.2f} "
                         f"({others[best]['p95'] * 1e3:.1f}) mm")
        else:
            beats.append(label)
    n_cfg = len(beats) + len(loses)
    if n_cfg == 0:
        print("- no configuration has both ours and a baseline yet")
        return
    print(f"- ours beats every baseline on {len(beats)}/{n_cfg} configurations"
          + (f": {'; '.join(beats)}" if beats else ""))
    for line in loses:
        print(f"- does NOT beat on {line}")


def criteria(table: list, common_reps: dict | None = None, same: dict | None = None) -> None:
    """Issue 15 item 6 per real file: the configurations where ours has the lowest mean
    error or is within 5 % of the lowest (target >= 90 %), and ours ÷ the best other
    method (target <= 1.2 everywhere); the reference is the best baseline that ran on
    every repetition (G&F fails without a complete frame).  The spread is the
    repetitions' standard deviation of ours' mean error over the pooled mean.

    Each method's mean is over the samples it filled: a spline or rigid-body fill that
    leaves a gap at the take's edge unfilled is compared on the rest.  ``same``
    (``{configuration: {baseline: ratio}}``, :func:`same_sample_ratios`) adds the
    comparison on the same samples: ours' mean over the samples each baseline filled ÷
    that baseline's, the worst baseline per configuration (results files written
    before these fields existed have none: "—")."""
    per: dict = collections.defaultdict(list)
    for (ds, dur, frac, cl), st in table:
        ours = st.get("ours")
        others = {n: s for n, s in st.items()
                  if n != "ours" and s.get("n_err") and s["failed"] == 0}
        if ds.startswith("sim") or ours is None or not ours.get("n_err") or not others:
            continue
        best = min(others, key=lambda n: others[n]["mean"])
        spread = float("nan")
        if common_reps is not None:
            reps = [ms["ours"] for _, ms in common_reps.get((ds, dur, frac, cl), [])
                    if "ours" in ms and ms["ours"]["n_err"]]
            if len(reps) > 1:
                spread = float(np.std([r["sum_err"] / r["n_err"] for r in reps])) / ours["mean"]
        ss = {n: r for n, r in (same or {}).get((ds, dur, frac, cl), {}).items() if n in others}
        worst_same = max(ss.values()) if len(ss) == len(others) else float("nan")
        per[ds].append((ours["mean"] / others[best]["mean"], f"{dur} s {100 * frac:g} % "
                        f"{'clustered' if cl else 'independent'}", best, ours["reps"], spread,
                        worst_same))
    if not per:
        return
    print("\nIssue 15 item 6 on the real files (ours' mean error ÷ the best other method's, "
          "per configuration; targets: <= 1.05 in >= 90 % of them, <= 1.2 in all):")
    print("| dataset | configurations | ours lowest or within 5 % | share | worst ratio "
          "(configuration, best other) | median ratio | repetitions | median spread of "
          "ours' mean over repetitions | on the same samples: within 5 % of every baseline "
          "| share | worst ratio (configuration) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for ds, rows in per.items():
        r = np.array([x[0] for x in rows])
        w = rows[int(np.argmax(r))]
        ok = int((r <= 1.05).sum())
        reps = sorted({x[3] for x in rows})
        sp = [x[4] for x in rows if np.isfinite(x[4])]
        sp_txt = f"{100 * np.median(sp):.0f} %" if sp else "—"
        rs = np.array([x[5] for x in rows])
        if np.isfinite(rs).all():
            ws = rows[int(np.argmax(rs))]
            ok_s = int((rs <= 1.05).sum())
            same_txt = (f"{ok_s} | {100 * ok_s / len(rs):.0f} % | {ws[5]:.2f} ({ws[1]})")
        else:
            same_txt = "— | — | —"
        print(f"| {ds} | {len(r)} | {ok} | {100 * ok / len(r):.0f} % | {w[0]:.2f} ({w[1]}, "
              f"{w[2]}) | {np.median(r):.2f} | {'-'.join(str(x) for x in (reps[0], reps[-1]))} "
              f"| {sp_txt} | {same_txt} |")


def _dataset_rank(name: str) -> int:
    if name == "sim dense (occluded)":
        return 0
    if name.startswith("sim"):
        return 2
    return 1


# --------------------------------------------------------------------------- protocol runner


_WORKER: dict = {}


def _limit_blas(threads: int | None) -> None:
    if threads is None:
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
        return
    _WORKER["blas"] = threadpool_limits(threads)


def _init_worker(datasets: list[dict], blas_threads: int | None) -> None:
    _WORKER["datasets"] = datasets
    _limit_blas(blas_threads)


def _run_indexed(task: tuple) -> dict:
    k, *rest = task
    return run_case((_WORKER["datasets"][k], *rest))


def protocol_cases(datasets: list[dict], *, durations, fractions, placements, reps: int,
                   long_first: float | None = 0.5, first_rep: int = 0) -> list[tuple]:
    """``(dataset index, duration, fraction, clustered, rep)`` in run order: dataset by
    dataset; within one, repetition-major over the gaps >= ``long_first`` s first,
    then the shorter gaps (so a partial run covers every long-gap configuration).
    Repetitions are ``first_rep, ..., first_rep + reps - 1`` (each one seeds its masks:
    report on repetitions not used while tuning)."""
    out = []
    for k, ds in enumerate(datasets):
        m = ds["markers"]
        durs = [d for d in durations if d * m.rate <= 0.5 * m.n_frames]  # keep half the take
        groups = ([[d for d in durs if d >= long_first], [d for d in durs if d < long_first]]
                  if long_first is not None else [durs])
        for group in groups:
            for r in range(first_rep, first_rep + reps):
                for d in group:
                    for f in fractions:
                        for c in placements:
                            out.append((k, d, f, c, r))
    return out


def run_protocol(datasets: list[dict], cases: list[tuple], methods: list[str], *,
                 results: str | None, workers: int, gf_max: int | None,
                 blas_threads: int | None) -> list[dict]:
    """Run the cases (skipping the (case, method) pairs already in ``results``), append
    each finished case to ``results``, print one progress line per case; returns the
    results of this run (in completion order)."""
    done: dict = {}
    if results and Path(results).exists():
        done = {row_key(r): r for r in load_results(results)}
    digests = [dataset_digest(ds) for ds in datasets]
    tasks = []
    for k, d, f, c, r in cases:
        todo = [n for n in methods
                if (datasets[k]["name"], float(d), float(f), bool(c), int(r), n) not in done]
        old = [done[(datasets[k]["name"], float(d), float(f), bool(c), int(r), n)]
               for n in methods if n not in todo]
        old += [v for key, v in done.items()
                if key[:5] == (datasets[k]["name"], float(d), float(f), bool(c), int(r))
                and key[5] not in methods]
        if old and todo:
            md = mask_digest(case_mask(datasets[k], d, f, c, r))
            if any(o["mask"] != md or o.get("data") != digests[k] for o in old):
                print(f"WARNING: {datasets[k]['name']} {d} s {f} {c} rep {r}: mask or data "
                      "differ from the cached methods' (left out of the comparison)",
                      flush=True)
        if todo:
            tasks.append((k, d, f, c, r, gf_max, todo))
    n_skip = len(cases) - len(tasks)
    print(f"(gap protocol: {len(cases)} cases, {n_skip} already in {results}, {len(tasks)} to "
          f"run with {', '.join(methods)} on {workers} process(es))", flush=True)
    out = []
    t_start = time.perf_counter()
    left = collections.Counter(datasets[t[0]]["name"] for t in tasks)
    spent: dict = collections.defaultdict(lambda: [0.0, 0])

    def report(i: int, task: tuple, r: dict) -> None:
        out.append(r)
        if results:
            save_result(results, r, digests[task[0]])
        el = time.perf_counter() - t_start
        name = r["dataset"]
        left[name] -= 1
        case_s = sum(sc["seconds"] for sc in r["methods"].values())
        spent[name][0] += case_s
        spent[name][1] += 1
        eta = spent[name][0] / spent[name][1] * left[name] * el / max(
            sum(v[0] for v in spent.values()), 1e-9)  # wall-clock per compute second
        secs = ", ".join(f"{n} {sc['seconds']:.1f} s" for n, sc in r["methods"].items())
        print(f"[{i}/{len(tasks)}] {name} {r['duration']} s {100 * r['fraction']:g} % "
              f"{'clustered' if r['clustered'] else 'independent'} rep {r['rep']} "
              f"({r['n_gapped']} markers): {secs} | elapsed {el / 60:.1f} min; this dataset: "
              f"{left[name]} cases left, ~{eta / 60:.0f} min "
              f"({time.strftime('%H:%M', time.gmtime(time.time() + eta))} UTC)", flush=True)

    if workers <= 1:
        _init_worker(datasets, blas_threads)
        for i, t in enumerate(tasks, 1):
            report(i, t, _run_indexed(t))
    else:
        with ProcessPoolExecutor(workers, initializer=_init_worker,
                                 initargs=(datasets, blas_threads)) as pool:
            futs = {pool.submit(_run_indexed, t): t for t in tasks}
            for i, fut in enumerate(as_completed(futs), 1):
                report(i, futs[fut], fut.result())
    return out


def check_gf(datasets: list[dict], cases: list[tuple]) -> None:
    """Time :func:`fill_gloersen_federolf` against the literal implementation on the same
    masks and print the largest difference on the deleted samples."""
    print("\n## G&F 2016 R2: fast vs literal implementation (same masks)")
    print("| dataset | gap s | markers | placement | rep | gapped | literal s | fast s | "
          "speed-up | max abs diff m |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for k, d, f, c, r in cases:
        ds = datasets[k]
        mask = case_mask(ds, d, f, c, r)
        gapped = np.where(mask[..., None], np.nan, ds["markers"].positions)
        only = np.flatnonzero(mask.any(0))
        res, secs = [], []
        for fn in (fill_gloersen_federolf_direct, fill_gloersen_federolf):
            t0 = time.perf_counter()
            try:
                res.append(fn(gapped, only=only)[mask])
            except GFFailure as e:
                res.append(str(e))
            secs.append(time.perf_counter() - t0)
        if isinstance(res[0], str) or isinstance(res[1], str):
            diff = "both failed" if res[0] == res[1] else f"{res[0]!s:.30} / {res[1]!s:.30}"
        else:
            same_nan = np.array_equal(np.isnan(res[0]), np.isnan(res[1]))
            diff = f"{np.nanmax(np.abs(res[0] - res[1])):.1e}" + ("" if same_nan else " NaN!")
        print(f"| {ds['name']} | {d} | {100 * f:g} % | {'clustered' if c else 'independent'} | "
              f"{r} | {len(only)} | {secs[0]:.2f} | {secs[1]:.2f} | {secs[0] / secs[1]:.1f}x | "
              f"{diff} |", flush=True)
