"""The baselines of the clean benchmark's gap protocol (``benchmarks/clean.py``).

Each fills the gaps of ``(F, M, 3)`` positions (NaN where missing), metres:

* :func:`fill_spline` — cubic spline interpolation per gap through 10 samples
  on each side (interior gaps only), as interactive tools do;
* :func:`fill_gloersen_federolf` — the whole-body PCA of Gløersen & Federolf
  2016, strategy R2 (implemented from the paper; on the Gram matrix), with
  :func:`fill_gloersen_federolf_direct`, the literal implementation it is
  checked against (``--check-gf``);
* :func:`fill_rigid_body` — Vicon-style rigid-body fill (PyPI ``gapfill``,
  the 3 nearest donors visible through the gap).
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.interpolate import CubicSpline


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
