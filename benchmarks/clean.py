"""Cleaning dense marker captures (Park & Hodgins 2006 §4) against ground truth and peers.

One run prints:

1. **Table 1** (paper's Table 1) on simulated 350-marker captures (900 frames;
   the dynamic treadmill run, a walk and a range of motion): trajectories
   before / after merging, merges, wrong merges (against the simulator's true
   fragment → marker map), ghosts merged, real fragments left, holes, filled,
   left unfilled, seconds.
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
   default; the paper's local PCA is ``fill_model="pca"``) + local-frame
   smoothing), cubic spline
   interpolation, the whole-body PCA of Gløersen & Federolf 2016 (strategy R2,
   implemented from the paper), and Vicon-style rigid-body fill (PyPI
   ``gapfill``, 3 nearest donors visible through the gap).  Per configuration:
   mean / RMSE / p95 / max in mm, mean normalised by the mean neighbour
   distance, % unfilled, % of the samples with >= 3 visible neighbours left
   unfilled (ours must be 0), seconds per run, and ours ÷ each baseline.
   Simulated data are scored against the true positions, real files against
   the deleted measurements.  The baselines fill only the gaps that contain
   deleted samples (their other fills are independent of these and unscored);
   ours cleans the whole capture, so its seconds include every real hole too.
4. **Throughput**: 350 markers x 1000 frames cleaned (merge + fill + smooth),
   in one process and with 2 worker processes behind ``ctx.map``.
5. **The real fragmented file** ``btkdata_PiG_Calibration-FlatFoot-Hole.c3d``:
   which fragments were merged into which labels, and why the others were not.

Run: ``python benchmarks/clean.py --quick`` (a small run of every section),
``--tables-only`` (sections 1, 2, 4, 5), or
the gap protocol alone, cached and resumable (one JSON line per case and
method; the datasets, masks and normalisers are frozen in
``<results>.datasets.npz`` on the first run, so later runs of other methods
use exactly the same data and masks)::

    python benchmarks/clean.py --gaps-only --methods baselines --results R.jsonl
    python benchmarks/clean.py --gaps-only --methods ours --results O.jsonl \
        --frozen R.datasets.npz
    python benchmarks/clean.py --summarise R.jsonl,O.jsonl

BLAS runs single-threaded (``--blas-threads``): on two shared cores a
multi-threaded BLAS made the whole-body PCA ~10x slower.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import json
import os
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from scipy.interpolate import CubicSpline

from mocapflow.pipeline import Context
from mocapflow.stages.motion.datatypes import Markers
from mocapflow.stages.motion.simulate.capture import (
    gap_mask,
    region_errors,
    score_merges,
    simulate_capture,
)
from mocapflow.stages.skin.clean import choose_reference_frame, clean_markers, reference_pose
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
TABLE2_REGIONS = ("abdomen", "elbow", "thigh", "knee", "all")
METHODS = {"ours": "ours", "spline": "cubic spline", "gf": "G&F 2016 R2",
           "rigid": "rigid body (gapfill)"}
BASELINES = ("spline", "gf", "rigid")


# --------------------------------------------------------------------------- baselines


def _gaps(missing: np.ndarray) -> list[tuple[int, int]]:
    """``(start, stop)`` of the runs of True in a (F,) bool array."""
    d = np.diff(np.concatenate([[0], missing.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def fill_spline(positions: np.ndarray, rate: float, support: int = 10, *,
                mask: np.ndarray | None = None) -> np.ndarray:
    """Cubic spline fill per gap through ``support`` samples on each side (interior gaps
    only; edge gaps stay NaN), as interactive tools do.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        NaN where missing.
    rate : float
    support : int
    mask : (F, M) bool ndarray, optional
        Fill only the gaps containing one of these samples (every gap is filled
        independently, so the result there is the same).
    """
    out = positions.copy()
    F, M, _ = positions.shape
    for m in range(M):
        if mask is not None and not mask[:, m].any():
            continue
        ok = np.isfinite(positions[:, m]).all(1)
        if ok.all() or ok.sum() < 4:
            continue
        for a, b in _gaps(~ok):
            if a == 0 or b >= F or (mask is not None and not mask[a:b, m].any()):
                continue
            left = np.flatnonzero(ok[:a])[-support:]
            right = b + np.flatnonzero(ok[b:])[:support]
            idx = np.concatenate([left, right])
            if len(left) < 2 or len(right) < 2:
                continue
            out[a:b, m] = CubicSpline(idx, positions[idx, m], axis=0)(np.arange(a, b))
    return out


class GFFailure(RuntimeError):
    """The whole-body PCA cannot run (no marker or frame without gaps)."""


def _gf_n_components(s: np.ndarray, min_cum_sv: float) -> int:
    """Components reaching ``min_cum_sv`` of the summed singular values ``s`` (descending)."""
    return int(np.searchsorted(np.cumsum(s) / s.sum(), min_cum_sv) + 1)


def _gf_solve(y: np.ndarray, g: np.ndarray, gap_rows: np.ndarray, *,
              min_cum_sv: float) -> np.ndarray:
    """The R2 reconstruction of one marker from its weighted, standardised data.

    With ``V`` (``Vz``) the first ``n`` principal directions of ``y`` (of ``y``
    with the gapped marker's columns zeroed), the estimate is
    ``gap_rows · Vz · (Vᵀ Vz)ᵀ · Vᵀ`` (Federolf 2013, Eq. 5-8).  The directions
    come from the eigendecomposition of the smaller Gram matrix in float64
    (one ``eigh`` of ≤ 1050² instead of an SVD of the data; the product only
    depends on the spanned subspaces, so signs and bases do not matter).

    Parameters
    ----------
    y : (R, C) float ndarray
        Complete frames, centred, divided by the SD and multiplied by the weights.
    g : (3,) int ndarray
        Columns of the gapped marker in ``y``.
    gap_rows : (Q, C) float ndarray
        Frames to reconstruct, same transform, the gapped marker's columns zero.
    min_cum_sv : float

    Returns
    -------
    (Q, 3) float ndarray
        The gapped marker's columns, in the transformed units.
    """
    R, C = y.shape
    if R <= C:
        gram = y @ y.T
        yg = y[:, g]
        gram_z = gram - yg @ yg.T
    else:
        gram = y.T @ y
        gram_z = gram.copy()
        gram_z[g, :] = 0.0
        gram_z[:, g] = 0.0
    lam, u = np.linalg.eigh(gram)
    lam_z, u_z = np.linalg.eigh(gram_z)
    s = np.sqrt(np.clip(lam[::-1], 0.0, None))
    s_z = np.sqrt(np.clip(lam_z[::-1], 0.0, None))
    n = max(_gf_n_components(s, min_cum_sv), _gf_n_components(s_z, min_cum_sv))
    u, u_z = u[:, ::-1][:, :n], u_z[:, ::-1][:, :n]
    if R <= C:
        yz = y.copy()
        yz[:, g] = 0.0
        v = (y.T @ u) / s[:n]
        v_z = (yz.T @ u_z) / s_z[:n]
    else:
        v, v_z = u, u_z
    return (gap_rows @ v_z) @ (v_z.T @ v) @ v[g].T


def _gf_moving_origin(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gapped markers and the mean trajectory of the gap-free ones (G&F's moving origin).

    Raises
    ------
    GFFailure
        Every marker has gaps.
    """
    gap_markers = np.flatnonzero(np.isnan(positions).any((0, 2)))
    if len(gap_markers) == 0:
        return gap_markers, np.zeros((len(positions), 3))
    full = np.setdiff1d(np.arange(positions.shape[1]), gap_markers)
    if len(full) == 0:
        raise GFFailure("every marker has gaps: no mean trajectory")
    return gap_markers, positions[:, full].mean(1)


def fill_gloersen_federolf(positions: np.ndarray, *, sigma: float = 0.2, mm_weight: float = 0.02,
                           distal_threshold: float = 0.5, min_cum_sv: float = 0.99,
                           only: np.ndarray | None = None) -> np.ndarray:
    """Whole-body PCA gap filling, strategy R2 (Gløersen & Federolf 2016), metres.

    Per gapped marker: the markers with gaps that are distal (farther than
    ``distal_threshold`` × the mean distance) or missing during its gaps are
    zeroed; the rest, relative to the mean trajectory of the gap-free markers,
    standardised and weighted by ``exp(-d²/2σ²)`` (the marker itself
    ``mm_weight``), give the PCA over the complete frames (``min_cum_sv`` of the
    summed singular values) that reconstructs it.  Zeroed markers are dropped
    from the matrices (zero columns change no principal direction), and the PCA
    runs on the Gram matrix (see :func:`_gf_solve`); equal to
    :func:`fill_gloersen_federolf_direct` within 1e-7 m.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        NaN where missing.
    only : (K,) int ndarray, optional
        Reconstruct only these markers (R2 reconstructs every gapped marker
        independently from the gapped data, so the others' results are
        unaffected; the benchmark scores only the deleted samples).

    Returns
    -------
    (F, M, 3) float ndarray

    Raises
    ------
    GFFailure
        No marker without gaps (the moving coordinate system) or no complete frame.
    """
    F, M, _ = positions.shape
    gap_markers, mean_traj = _gf_moving_origin(positions)
    if len(gap_markers) == 0:
        return positions.copy()
    x = positions - mean_traj[:, None]
    out = x.copy()
    sub_f = np.unique(np.linspace(0, F - 1, min(F, 500)).round().astype(int))
    x_sub = x[sub_f]
    has_gap = np.zeros(M, bool)
    has_gap[gap_markers] = True
    nan_x = np.isnan(x[:, :, 0])
    todo = gap_markers if only is None else gap_markers[np.isin(gap_markers, only)]
    for i in todo:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            di = np.nanmean(np.linalg.norm(x_sub[:, i, None] - x_sub, axis=-1), 0)  # (M,)
            thresh = distal_threshold * np.nanmean(di)
        gi = nan_x[:, i]
        zero = has_gap & ((di > thresh) | nan_x[gi].any(0))
        zero[i] = False
        keep = np.flatnonzero(~zero)
        xk = x[:, keep].reshape(F, 3 * len(keep))
        ki = int(np.flatnonzero(keep == i)[0])
        g = np.arange(3 * ki, 3 * ki + 3)
        fin = np.isfinite(xk)
        fin[:, g] = True
        rows_ok = fin.all(1) & ~gi
        if not rows_ok.any():
            raise GFFailure(f"no complete frame for marker {i}")
        n_mat = xk[rows_ok]
        if len(n_mat) < 2:
            raise GFFailure("no complete frame for the PCA")
        w = np.exp(-(np.nan_to_num(di[keep], nan=1e3) ** 2) / (2 * sigma**2))
        w[ki] = mm_weight
        mean = n_mat.mean(0)
        sd = n_mat.std(0)
        sd[sd == 0] = 1.0
        scale = np.repeat(w, 3) / sd
        gap_rows = (np.nan_to_num(xk[gi]) - mean) * scale
        gap_rows[:, g] = 0.0
        rec = _gf_solve((n_mat - mean) * scale, g, gap_rows, min_cum_sv=min_cum_sv)
        out[gi, i] = mean[g] + rec / scale[g]
    return out + mean_traj[:, None]


def _pca(data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = (data / np.sqrt(max(len(data) - 1, 1))).astype(np.float32)
    _, s, vt = np.linalg.svd(y, full_matrices=False)
    return vt.T.astype(np.float64), s.astype(np.float64)


def _gf_reconstruct(sub: np.ndarray, dist_i: np.ndarray, gap_cols: np.ndarray, *,
                    sigma: float, mm_weight: float, min_cum_sv: float) -> np.ndarray:
    """Federolf 2013 / Gløersen & Federolf 2016 reconstruction of one sub-matrix."""
    w = np.exp(-(dist_i**2) / (2 * sigma**2))
    w[gap_cols[::3] // 3] = mm_weight
    w3 = np.repeat(w, 3)
    complete = ~np.isnan(sub).any(1)
    N = sub[complete]
    if len(N) < 2:
        raise GFFailure("no complete frame for the PCA")
    Mz = np.where(np.isnan(sub), 0.0, sub)
    Mz[:, gap_cols] = 0.0
    Nz = N.copy()
    Nz[:, gap_cols] = 0.0
    mean, meanz = N.mean(0), Nz.mean(0)
    sd = N.std(0)
    sd[sd == 0] = 1.0
    Mz = (Mz - meanz) / sd * w3
    Nn = (N - mean) / sd * w3
    Nzn = (Nz - meanz) / sd * w3
    V, s = _pca(Nn)
    Vz, sz = _pca(Nzn)
    n = max(_gf_n_components(s, min_cum_sv), _gf_n_components(sz, min_cum_sv))
    V, Vz = V[:, :n], Vz[:, :n]
    rec = Mz @ Vz @ (V.T @ Vz).T @ V.T
    return mean + rec * sd / w3


def fill_gloersen_federolf_direct(positions: np.ndarray, *, sigma: float = 0.2,
                                  mm_weight: float = 0.02, distal_threshold: float = 0.5,
                                  min_cum_sv: float = 0.99,
                                  only: np.ndarray | None = None) -> np.ndarray:
    """The literal R2 implementation (full matrices, float32 SVDs): the reference that
    ``--check-gf`` compares :func:`fill_gloersen_federolf` with (~3-10x slower)."""
    F, M, _ = positions.shape
    gap_markers, mean_traj = _gf_moving_origin(positions)
    if len(gap_markers) == 0:
        return positions.copy()
    D = (positions - mean_traj[:, None]).reshape(F, 3 * M)
    out = D.copy()
    sub_f = np.unique(np.linspace(0, F - 1, min(F, 500)).round().astype(int))
    P = D[sub_f].reshape(len(sub_f), M, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        dist = np.nanmean(np.linalg.norm(P[:, gap_markers, None] - P[:, None], axis=-1), 0)
    has_gap = np.zeros(M, bool)
    has_gap[gap_markers] = True
    for k, i in enumerate(gap_markers):
        if only is not None and i not in only:
            continue
        di = dist[k]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            thresh = distal_threshold * np.nanmean(di)
        zero = has_gap & (di > thresh)
        gi = np.isnan(D[:, 3 * i])
        for j in gap_markers:
            if j != i and np.isnan(D[gi, 3 * j]).any():
                zero[j] = True
        zero[i] = False
        sub = D.copy()
        sub[:, np.repeat(zero, 3)] = 0.0
        rows_ok = ~np.isnan(np.delete(sub, np.s_[3 * i: 3 * i + 3], axis=1)).any(1) & ~gi
        rows = np.concatenate([np.flatnonzero(rows_ok), np.flatnonzero(gi)])
        if not rows_ok.any():
            raise GFFailure(f"no complete frame for marker {i}")
        rec = _gf_reconstruct(sub[rows], np.nan_to_num(di, nan=1e3),
                              np.arange(3 * i, 3 * i + 3), sigma=sigma, mm_weight=mm_weight,
                              min_cum_sv=min_cum_sv)
        out[gi, 3 * i: 3 * i + 3] = rec[rows_ok.sum():, 3 * i: 3 * i + 3]
    return out.reshape(F, M, 3) + mean_traj[:, None]


def fill_rigid_body(positions: np.ndarray, reference: np.ndarray, n_donors: int = 3, *,
                    mask: np.ndarray | None = None) -> np.ndarray:
    """Vicon-style rigid-body fill (PyPI ``gapfill``): per gap, the nearest donors visible
    through it (and at both ends); edge gaps and gaps without donors stay NaN.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        NaN where missing.
    reference : (M, 3) float ndarray
        Layout that ranks the donors by distance.
    n_donors : int
    mask : (F, M) bool ndarray, optional
        Fill only the gaps containing one of these samples (each gap is filled
        from its two ends and the donors alone, so the result there is the same).
    """
    import gapfill.gapfill as gf

    if not hasattr(np, "int"):
        np.int = int  # type: ignore[attr-defined]  # noqa: NPY001  (gapfill uses np.int)
    out = positions.copy()
    F, M, _ = positions.shape
    vis = np.isfinite(positions).all(-1)
    order = np.argsort(np.linalg.norm(reference[:, None] - reference[None], axis=-1), axis=1)
    for m in range(M):
        miss = ~vis[:, m]
        if not miss.any() or not vis[:, m].any():
            continue
        if mask is not None and not mask[:, m].any():
            continue
        for a, b in _gaps(miss):
            if a == 0 or b >= F:
                continue  # edge gap
            if mask is not None and not mask[a:b, m].any():
                continue
            donors = [j for j in order[m, 1:] if vis[a - 1: b + 1, j].all()][:n_donors]
            if len(donors) < 3:
                continue
            # the gap and its two ends only: gapfill interpolates between them
            tgt = np.full((b - a + 2, 3), np.nan)
            tgt[0], tgt[-1] = positions[a - 1, m], positions[b, m]
            ok, _ = gf.fill_marker_gap_rbt(
                tgt, np.stack([positions[a - 1: b + 1, j] for j in donors]))
            if ok:
                out[a:b, m] = tgt[1:-1]
    return out


def fill_ours(markers: Markers) -> np.ndarray:
    out, _, _ = clean_markers(markers, merge=False, ctx=Context())
    return out.positions


# --------------------------------------------------------------------------- datasets


def simulated(n_markers: int, n_frames: int, motion: str, seed: int, **kw) -> SimpleNamespace:
    """The ``simulate_capture`` stage on ``default_rng(seed)`` (the stream of earlier tables)."""
    out = simulate_capture(n_markers=n_markers, n_frames=n_frames, motion=motion,
                           ctx=Context(rng=np.random.default_rng(seed)), **kw)
    return SimpleNamespace(**out)


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
    from mocapflow.stages.motion.formats.c3d import read_c3d

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


# --------------------------------------------------------------------------- protocol


def _scores(est: np.ndarray, truth: np.ndarray, mask: np.ndarray, dbar: np.ndarray) -> dict:
    e = np.linalg.norm(est - truth, axis=-1)[mask]
    n = (np.linalg.norm(est - truth, axis=-1) / dbar[None])[mask]
    ok = np.isfinite(e)
    return {"err": e[ok], "norm": n[ok & np.isfinite(n)], "unfilled": int((~ok).sum()),
            "n": int(mask.sum())}


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
    """One JSON-able row per method of a :func:`run_case` result."""
    key = {k: r[k] for k in ("dataset", "duration", "fraction", "clustered", "rep")}
    return [{**key, "method": name, "mask": r.get("mask"), "data": data,
             "n_gapped": r.get("n_gapped"), **score_stats(sc)}
            for name, sc in r["methods"].items()]


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
                   long_first: float | None = 0.5) -> list[tuple]:
    """``(dataset index, duration, fraction, clustered, rep)`` in run order: dataset by
    dataset; within one, repetition-major over the gaps >= ``long_first`` s first,
    then the shorter gaps (so a partial run covers every long-gap configuration)."""
    out = []
    for k, ds in enumerate(datasets):
        m = ds["markers"]
        durs = [d for d in durations if d * m.rate <= 0.5 * m.n_frames]  # keep half the take
        groups = ([[d for d in durs if d >= long_first], [d for d in durs if d < long_first]]
                  if long_first is not None else [durs])
        for group in groups:
            for r in range(reps):
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


# --------------------------------------------------------------------------- tables 1 and 2


def table1(sims: dict) -> dict:
    print("\n## 1. Table 1: merging on simulated 350-marker captures")
    print("| motion | frames | markers | trajectories before | after | merged | wrong merges | "
          "ghosts merged | real fragments left | holes | filled | left unfilled | "
          "mean neighbour distance mm | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    cleaned = {}
    for motion, sim in sims.items():
        m, tr = sim.markers, sim.truth
        t0 = time.perf_counter()
        out, rep, surf = clean_markers(m, ctx=Context())
        dt = time.perf_counter() - t0
        sc = score_merges(rep["merges"], m.fragment_labels, tr["fragment_marker"], m.labels)
        t1 = rep["table1"]
        print(f"| {motion} | {m.n_frames} | {m.n_markers} | {t1['fragments_before']} | "
              f"{t1['fragments_after']} | {sc['merged']} | {sc['wrong']} | "
              f"{sc['ghosts_merged']} | {sc['missed']} | {t1['holes']} | {t1['filled']} | "
              f"{t1['left_unfilled']} | {rep['surface']['mean_neighbour_distance_mm']} | "
              f"{dt:.1f} |")
        if sc["wrong_list"]:
            print(f"  wrong merges: {sc['wrong_list'][:10]}")
        cleaned[motion] = (out, rep, surf)
    return cleaned


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
        out, _, surf = clean_markers(base.replace(positions=np.where(mask[..., None], np.nan,
                                                                     base.positions)),
                                     merge=False, ctx=Context())
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
    t0 = time.perf_counter()
    _, rep, _ = clean_markers(m, ctx=Context())
    dt = time.perf_counter() - t0
    print(f"| in process (1 worker) | {dt:.1f} | {rep['table1']['merged']} | "
          f"{rep['table1']['left_unfilled']} |")
    runs = []
    with ProcessPoolExecutor(2) as pool:
        pool.submit(int, 0).result()  # workers up
        ctx = Context(mapper=_pool_mapper(pool), workers=2)
        for _ in range(3):  # a shared 2-core machine: wall times vary by ~10 %
            t0 = time.perf_counter()
            _, rep2, _ = clean_markers(m, ctx=ctx)
            runs.append((time.perf_counter() - t0, rep2))
    for k, (dt2, rep2) in enumerate(runs):
        print(f"| 2 worker processes (ctx.map), run {k + 1} | {dt2:.1f} | "
              f"{rep2['table1']['merged']} | {rep2['table1']['left_unfilled']} |")
    times = sorted(dt for dt, _ in runs)
    print(f"2 workers: median {times[1]:.1f} s, best {times[0]:.1f} s, worst {times[-1]:.1f} s "
          f"(target <= 10 s on this 2-core machine); stage timings of the median run: "
          f"{next(r for dt, r in runs if dt == times[1])['timings_s']}")


def pig_report() -> None:
    p = DATA / "btkdata_PiG_Calibration-FlatFoot-Hole.c3d"
    if not p.exists():
        print("\n## 5. PiG fragmented file: not found (../shared/data absent)")
        return
    from mocapflow.stages.motion.formats.c3d import read_c3d

    m = read_c3d(p)
    ctx = Context(part=p.name)
    out, rep, surf = clean_markers(m, ctx=ctx)
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
                           placements=placements, reps=reps)
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
