"""GenMM baseline for ``benchmarks/texture.py`` — a NumPy reimplementation, not GenMM's code.

GenMM (Li, Chen, Li, Sorkine-Hornung, Chen, "Example-based Motion Synthesis via
Generative Motion Matching", ACM TOG 42(4), SIGGRAPH 2023) is not on PyPI.  This
module reimplements its published algorithm, with the defaults of the paper and of
its released configuration, by default computed as its released code computes it (see
*Two computations* below), so that the benchmark can run it in the same process, on
the same inputs and seeds, as ours and its CPU time stands for GenMM's:

1. **Features** per frame: the 6-D rotation of every joint (the first two rows of its
   local rotation matrix), the root's height, and the root's horizontal velocity
   (frame-to-frame displacement); positions divided by ``ceil`` of the largest
   bone-offset component in the file's own unit (the released code's auto scale).
2. **Pyramids**: the coarsest input level has ``5 × patch_size`` frames; every
   finer level is ``1 / 0.75`` times longer until the input's length; the output
   pyramid uses the same ratio (coarsest ``length · 5 · patch_size / F_in``
   frames).  Every input level is the input linearly resampled to that length.
3. **Initial guess** at the coarsest level: the coarsest input level stretched to
   the output's coarsest length, plus zero-mean Gaussian noise of σ = 10, wrapped
   with ``fmod(·, 1)`` (so essentially uniform noise in (-1, 1)).
4. At every level (the guess linearly upsampled from the previous one), **3 steps
   of generative patch matching**: all overlapping 11-frame patches of the guess
   (stride 1), squared Euclidean distance to every input patch divided by the patch
   dimension, each input patch's column normalised by ``alpha + `` its smallest
   distance to any output patch (``alpha = 0.01``: the completeness/diversity
   trade-off), nearest neighbour per output patch; then **blending**: every output
   frame becomes the average of the frames that the overlapping matched patches
   put at it.
5. **Output**: 6-D rotations to rotation matrices by Gram–Schmidt, the root's
   horizontal velocity integrated from the input's first position.

Defaults (:class:`GenMMParams`): patch size 11, alpha 0.01, 3 steps per level,
pyramid factor 0.75, coarsest level 5 × patch size, noise σ 10.

Two computations of the same algorithm (``GenMMParams.computation``):

* ``"released"`` (the default, the benchmark's *GenMM baseline (reimplementation)*):
  a port of the released code's computation (commit fae65cd: ``GenMM.run``,
  ``nearest_neighbor/losses.py`` and ``utils.py``), step for step, float32, in its
  ``(channels, frames)`` layout: every level of the input pyramid resampled at the
  start, the input patches extracted once per level (``PatchCoherentLoss``'s cache);
  at every step the output's patches extracted by :func:`unfold` (``unfoldNd``: a
  convolution with one one-hot ``(p, p)`` kernel per channel, built on every call;
  here summed directly by ``np.einsum`` over sliding windows, the same multiply-adds)
  and copied patch-major as the released ``reshape``; two distance passes as
  ``get_NNs_Dists`` (:func:`nearest_released`: the column minima over 1024-column
  blocks of the input patches, then the normalised matches over 1024-row blocks of
  the output patches, every block recomputing both squared norms as
  ``efficient_cdist``; minimum and its index per row, the mean distance as the step's
  loss); the matched patches gathered whole (``y_patches[:, nnf, :]``), folded back
  by :func:`fold` (``foldNd``: the unfolded ``arange`` as indices, a scatter-add) and
  divided by the fold of the unfolded ones, recomputed at every step.
* ``"lean"`` (the benchmark's row *GenMM baseline (reimplementation, lean)*, timed
  beside it): one distance matrix per step, the input patches' norms once per level,
  patches as strided views, blending by shifted adds — the same matches and blended
  frames up to float32 rounding (``tests/benchmarks/test_genmm_baseline.py``) in a
  fifth to a quarter of the CPU time.

Departures from the released code (none changes the algorithm):

* frame 0's root velocity is set to frame 1's (the released code stores frame 1's
  absolute position there); porting that changes the benchmark's jerk× on 1,024
  frames, seeds 0–2: salsa 1.15 → 1.13, walk 1.10 → 1.17, 8-walk 2.64 → 3.06;
* when the output pyramid would have a different number of levels than the input's
  (the released code then stops short of the requested length), the output lengths
  are the input lengths scaled by ``length / F_in``, the last one exactly ``length``;
* NumPy (OpenBLAS) instead of PyTorch (MKL, oneDNN) on the CPU, NumPy's random
  generator for the initial noise (drawn frame-major; the same noise for both
  computations);
* non-root joint translations, when the input has them, are not synthesised: the
  output keeps the rest offsets (GenMM's features have none either);
* the up axis is ``y`` (the released default, and the convention of every BVH in
  ``shared/data``);
* the benchmark times :func:`genmm_synthesize` whole: with the features and the
  conversion back to a motion (at most 12 ms on these inputs, about 1 %); the
  released runner times ``GenMM.run`` only (features are built before it).

Where the time goes, walk ``cmu_131_02`` 312 → 1,024 frames, seed 0, one thread,
under cProfile (CPU s; released code / this port): one-hot unfolds 0.22 (``conv1d``)
/ 0.41 (``einsum``), distances 0.36 / 0.29, patch copies 0.08 / 0.10, scatter-adds
0.04 / 0.04; total 0.80 / 0.88.  The one-hot convolution is where the two libraries
differ most: on 189 channels × 1,024 frames a call takes 11 ms in oneDNN, 14 ms by
``einsum``, 1.4 ms by a batched matrix product (the same products; with it this port
took 0.55–0.65 of the released code's time).

Calibrated against GenMM itself (commit fae65cd, the authors' last before a
third-party key-frame patch that breaks ``GenMM.run``; PyTorch 2.13 CPU, one thread,
run outside this repository on the benchmark's 30 fps input as written by this
package's BVH writer, GenMM's ``configs/default.yaml``; its output BVHs read back with
the rate set to 30 fps), in the same run, interleaved per seed, by::

    benchmarks/texture.py --seeds 3 --no-cases --no-speed --genmm-command CMD

``CMD`` a script outside the repository calling GenMM's code (one JSON line: CPU s of
``GenMM.run`` only).  On ``cmu_131_02`` at 30 fps, 312 → 1024 frames, seeds 0–2
(means, min–max over seeds; CPU s of the first of two runs, the second in brackets)::

    method                 CPU s                    cover  global  local  jerk×  skate×
    GenMM (released code)  0.80 (0.76–0.87) [0.80]  1.000  0.150   0.117  1.04   1.15
    this port (released)   0.83 (0.82–0.85) [0.86]  1.000  0.157   0.129  1.10   1.17
    lean computation       0.18 (0.17–0.19) [0.17]  1.000  0.157   0.129  1.10   1.17
    port / released code   1.03 [1.07]              1.00   1.05    1.10   1.06   1.02

All inputs (the benchmark's 3 inputs, first 512 frames → 1,024, and the whole clip →
2×; seeds 0–2; both draw their own random numbers, so per-seed outputs differ): this
port / released code, ratio of the means (CPU: the summary's column *CPU s
reimpl./GenMM released*, two runs; lean: *CPU s reimpl. lean/GenMM released*)::

    input (frames)  output  CPU s      lean CPU s  cover  global  local  jerk×  skate×
    salsa (512)     1024    1.05 1.03  0.26 0.26   1.00   1.18    1.02   0.69   1.05
    salsa (561)     1122    1.09 1.08  0.28 0.28   1.00   1.00    1.14   0.65   1.13
    walk (312)      1024    1.03 1.07  0.22 0.22   1.00   1.05    1.10   1.06   1.02
    walk (312)       624    1.05 1.04  0.23 0.22   1.01   1.15    1.15   1.01   0.99
    8-walk (266)    1024    0.98 0.94  0.20 0.19   1.00   1.00    1.06   0.83   1.02
    8-walk (266)     532    0.93 0.87  0.19 0.18   1.00   1.06    1.02   0.52   1.05

CPU time within 13 % of the released code's on every row (per seed 0.82–1.17);
coverage, diversity and skate within 18 %.  jerk× is not: the released code's is
higher on salsa (1.67 and 1.59 vs 1.15 and 1.04) and on the 8-walk (3.18 vs 2.64; 6.40
vs 3.33 on 532 frames, one seed 13.7×); its frame-0 channel (above) explains part of
the 8-walk's, not salsa's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mocapflow.stages.motion.rotations import quat_conjugate, quat_from_6d, quat_to_matrix

__all__ = ["GenMMParams", "genmm_features", "genmm_synthesize", "pyramid_lengths"]

@dataclass(frozen=True)
class GenMMParams:
    """GenMM's defaults (paper and released ``configs/default.yaml``)."""

    patch_size: int = 11
    alpha: float = 0.01
    num_steps: int = 3
    noise_sigma: float = 10.0
    coarse_patches: float = 5.0  # coarsest input level: 5 × patch_size frames
    pyr_factor: float = 0.75
    block: int = 1024  # rows (and columns) of the distance matrix per matrix product
    #: ``"released"``: the released code's computation step for step (two distance
    #: passes, one-hot unfold/fold, divisor every step); ``"lean"``: the same algorithm
    #: with one distance matrix per step and strided patch views (same matches and
    #: output up to float32 rounding, a fifth to a quarter of the CPU time)
    computation: str = "released"

    def __post_init__(self):
        if self.computation not in ("released", "lean"):
            raise ValueError(f"GenMMParams.computation: 'released' or 'lean', not "
                             f"{self.computation!r}")


# --------------------------------------------------------------------------- features


def _position_scale(motion) -> float:
    """Metres → GenMM's units: file units divided by ``ceil(max offset component)``."""
    file_unit = float(
        motion.attrs.get("source_scale", motion.skeleton.attrs.get("source_scale", 1.0))
    )
    biggest = float(np.max(motion.skeleton.offsets)) / file_unit
    return 1.0 / (file_unit * max(1.0, math.ceil(biggest)))


def genmm_features(motion) -> tuple[np.ndarray, dict]:
    """Per-frame GenMM features ``(F, 6 J + 3)`` float32 and what is needed to invert them.

    Columns: 6-D rotations of the joints (rows 0 and 1 of each local rotation
    matrix), then root ``x`` velocity, ``y`` height, ``z`` velocity (scaled).
    """
    F, J = motion.rotations.shape[:2]
    R = quat_to_matrix(motion.rotations)  # (F, J, 3, 3)
    rot6 = R[..., :2, :].reshape(F, J * 6)
    s = _position_scale(motion)
    p = motion.root_position * s
    root = p.copy()
    if F > 1:
        root[1:, [0, 2]] = p[1:, [0, 2]] - p[:-1, [0, 2]]
        root[0, [0, 2]] = root[1, [0, 2]]
    else:
        root[:, [0, 2]] = 0.0
    feat = np.concatenate([rot6, root], axis=1).astype(np.float32)
    return feat, {"scale": s, "start": motion.root_position[0].copy(), "J": J}


def features_to_motion(feat: np.ndarray, template, info: dict):
    """Motion on ``template``'s skeleton from GenMM features."""
    L, J = feat.shape[0], info["J"]
    f = np.asarray(feat, dtype=np.float64)
    rows = f[:, : 6 * J].reshape(L, J, 6)
    # quat_from_6d takes the first two *columns*; rows of R are the columns of Rᵀ
    q = quat_conjugate(quat_from_6d(rows))
    q = np.where(q[..., :1] < 0, -q, q)
    root = f[:, 6 * J:] / info["scale"]
    pos = np.empty((L, 3))
    pos[:, 1] = root[:, 1]
    for ax in (0, 2):
        pos[:, ax] = info["start"][ax] + np.concatenate([[0.0], np.cumsum(root[1:, ax])])
    attrs = dict(template.attrs)
    attrs["synthesis"] = "GenMM baseline (reimplementation)"
    return template.replace(root_position=pos, rotations=q, translations=None, attrs=attrs)


# --------------------------------------------------------------------------- pyramid


def pyramid_lengths(final: int, coarse_ratio: float, factor: float) -> list[int]:
    """Lengths from ``round(final · coarse_ratio)`` growing by ``1 / factor`` up to ``final``."""
    lengths = [int(np.round(final * coarse_ratio))]
    while lengths[-1] < final:
        nxt = int(np.round(lengths[-1] / factor))
        lengths.append(nxt if nxt != lengths[-1] else nxt + 1)
    lengths[-1] = final
    return lengths


def resample_linear(x: np.ndarray, n: int, *, align_corners: bool = False) -> np.ndarray:
    """Linear resampling of ``(F, C)`` frames to ``n`` frames (no anti-aliasing).

    ``align_corners=False``: frame ``i`` samples the input at ``(i + ½)·F/n − ½``
    (clamped at 0); ``True``: at ``i·(F − 1)/(n − 1)``.
    """
    F = x.shape[0]
    if n == F:
        return x.copy()
    if align_corners:
        u = np.arange(n) * ((F - 1) / (n - 1)) if n > 1 else np.zeros(1)
    else:
        u = np.maximum((np.arange(n) + 0.5) * (F / n) - 0.5, 0.0)
    i0 = np.minimum(np.floor(u).astype(np.int64), F - 1)
    i1 = np.minimum(i0 + 1, F - 1)
    w = (u - i0).astype(x.dtype)[:, None]
    return x[i0] * (1 - w) + x[i1] * w


# --------------------------------------------------------------------------- matching


def _patches(x: np.ndarray, p: int) -> np.ndarray:
    """All stride-1 patches of ``(F, C)`` frames, flattened: ``(F - p + 1, p · C)``."""
    win = np.lib.stride_tricks.sliding_window_view(x, p, axis=0)  # (n, C, p)
    return np.ascontiguousarray(win.transpose(0, 2, 1)).reshape(win.shape[0], -1)


def _normalised_nn(X: np.ndarray, Y: np.ndarray, yy: np.ndarray, alpha: float, block: int):
    """Nearest input patch per output patch under GenMM's normalised distance."""
    d = X.shape[1]
    D = np.empty((X.shape[0], Y.shape[0]), dtype=np.float32)
    for a in range(0, X.shape[0], block):
        xb = X[a : a + block]
        Db = xb @ Y.T
        Db *= -2.0
        Db += (xb * xb).sum(1)[:, None]
        Db += yy[None, :]
        D[a : a + block] = Db
    D /= d
    D /= alpha + D.min(axis=0)[None, :]
    return D.argmin(axis=1)


def _blend(target: np.ndarray, nnf: np.ndarray, length: int, p: int) -> np.ndarray:
    """Average of the overlapping matched patches at every output frame."""
    out = np.zeros((length, target.shape[1]), dtype=np.float32)
    count = np.zeros((length, 1), dtype=np.float32)
    n = nnf.shape[0]
    for k in range(p):
        out[k : k + n] += target[nnf + k]
        count[k : k + n] += 1.0
    return out / count


def _source_index(nnf: np.ndarray, length: int, p: int) -> np.ndarray:
    """Input frame at the centre of the patch matched around each output frame."""
    c = p // 2
    t = np.clip(np.arange(length) - c, 0, nnf.shape[0] - 1)
    return nnf[t] + (np.arange(length) - t)


# ------------------------------------------------- the released code's computation


def unfold(x: np.ndarray, p: int) -> np.ndarray:
    """``unfoldNd`` of ``(C, L)`` channels: ``(C · p, L - p + 1)`` patch columns.

    As the released code's ``unfoldNd``: a convolution with ``C`` groups whose kernels
    are the ``(p, p)`` identity repeated per channel (built on every call, as there),
    ``out[c · p + k, t] = Σ_j δ_kj · x[c, t + j]``, summed directly (``np.einsum``) over
    the ``(C, p, L - p + 1)`` sliding windows: the convolution's ``C · p² · (L - p + 1)``
    multiply-adds, as oneDNN's grouped convolution computes them.
    """
    C, L = x.shape
    n = L - p + 1
    weight = np.tile(np.eye(p, dtype=x.dtype)[None], (C, 1, 1))  # (C, p, p) one-hot
    windows = np.lib.stride_tricks.sliding_window_view(x, n, axis=1)  # (C, p, n)
    return np.einsum("ckj,cjn->ckn", weight, windows).reshape(C * p, n)


def fold(cols: np.ndarray, length: int, p: int) -> np.ndarray:
    """``foldNd``: the transpose of :func:`unfold`, ``(C · p, n)`` columns → ``(C, length)``.

    As the released code: the target index of every column entry is the unfolded
    ``arange(length)``; the entries are scatter-added there, tap by tap (tap ``k``'s
    indices are the consecutive run starting at ``idx[k, 0]``, so the scatter is a
    slice add, in the released code's order).
    """
    n = cols.shape[1]
    C = cols.shape[0] // p
    idx = unfold(np.arange(length, dtype=np.float32)[None, :], p).astype(np.int64)  # (p, n)
    src = cols.reshape(C, p, n)  # the released reshape: a copy when cols is a transposed view
    out = np.zeros((C, length), dtype=cols.dtype)
    for k in range(p):
        out[:, idx[k, 0] : idx[k, 0] + n] += src[:, k]
    return out


def extract_patches(x: np.ndarray, p: int) -> np.ndarray:
    """``extract_patches``: ``(C, L)`` → ``(L - p + 1, C · p)`` rows, channel-major."""
    return np.ascontiguousarray(unfold(x, p).T)


def combine_patches(patches: np.ndarray, length: int, p: int) -> np.ndarray:
    """``combine_patches``: fold ``(n, C · p)`` patch rows into ``(C, length)`` frames and
    divide by the fold of the unfolded ones (recomputed on every call, as released)."""
    C = patches.shape[1] // p
    combined = fold(np.ascontiguousarray(patches.T).reshape(C * p, -1), length, p)
    divisor = fold(unfold(np.ones((C, length), dtype=patches.dtype), p), length, p)
    return combined / divisor


def efficient_cdist(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """``(n1, n2)`` squared distances over the dimension ``d``, norms recomputed per call."""
    dist = (X * X).sum(1)[:, None] + (Y * Y).sum(1)[None, :] - 2.0 * (X @ Y.T)
    dist /= X.shape[1]
    return dist


def nearest_released(X: np.ndarray, Y: np.ndarray, alpha: float, block: int):
    """``get_NNs_Dists``: column minima in ``block``-column passes, then the normalised
    nearest neighbour per row in ``block``-row passes; ``(n1,)`` indices and distances."""
    mins = np.empty(Y.shape[0], dtype=X.dtype)
    for b in range(0, Y.shape[0], block):
        mins[b : b + block] = efficient_cdist(X, Y[b : b + block]).min(0)
    normalizing_row = alpha + mins[None, :]
    nnf = np.empty(X.shape[0], dtype=np.int64)
    dists = np.empty(X.shape[0], dtype=X.dtype)
    for a in range(0, X.shape[0], block):
        d = efficient_cdist(X[a : a + block], Y) / normalizing_row
        nnf[a : a + block] = d.argmin(1)
        dists[a : a + block] = d.min(1)
    return nnf, dists


def _released_step(syn: np.ndarray, y_patches: np.ndarray, p: int, alpha: float,
                   block: int) -> tuple[np.ndarray, np.ndarray, float]:
    """One ``PatchCoherentLoss`` call on ``(C, L)`` frames: blended frames, matches, loss."""
    nnf, dists = nearest_released(extract_patches(syn, p), y_patches, alpha, block)
    return combine_patches(y_patches[nnf], syn.shape[1], p), nnf, float(dists.mean())


def _resample_channels(x: np.ndarray, n: int, align_corners: bool = False) -> np.ndarray:
    """:func:`resample_linear` of ``(C, L)`` channels (``F.interpolate``'s layout)."""
    return np.ascontiguousarray(resample_linear(x.T, n, align_corners=align_corners).T)


def genmm_synthesize(motion, length: int, seed: int, params: GenMMParams | None = None) -> dict:
    """Synthesise ``length`` frames from ``motion`` with the GenMM algorithm.

    Parameters
    ----------
    motion : Motion
        The example (at the synthesis rate; the benchmark uses 30 fps).
    length : int
        Output frames.
    seed : int
        Seeds ``np.random.default_rng`` (the initial noise: the only randomness).
    params : GenMMParams, optional

    Returns
    -------
    dict
        ``motion`` (the output on ``motion``'s skeleton and rate), ``source_index``
        (``(length,)`` input frame at the centre of the patch matched around each
        output frame at the finest level, an approximation: frames are blends),
        ``input_lengths`` and ``output_lengths`` (the pyramids), ``losses`` (the mean
        normalised match distance of every step, the released code's loss; empty with
        ``computation="lean"``).
    """
    prm = params or GenMMParams()
    p = prm.patch_size
    feat, info = genmm_features(motion)
    F = feat.shape[0]
    if F < p or length < p:
        raise ValueError(f"genmm_synthesize: input and output need ≥ {p} frames")
    ratio = p * prm.coarse_patches / F
    in_len = pyramid_lengths(F, ratio, prm.pyr_factor)
    out_len = pyramid_lengths(length, ratio, prm.pyr_factor)
    if len(out_len) != len(in_len):
        out_len = [max(p, int(np.round(n * length / F))) for n in in_len[:-1]] + [length]
    rng = np.random.default_rng(seed)

    nnf = np.zeros(0, dtype=np.int64)
    losses: list[float] = []
    if prm.computation == "released":  # (C, L) channels, as the released tensors
        feat_c = np.ascontiguousarray(feat.T)
        targets = [_resample_channels(feat_c, n) for n in in_len]
        syn = _resample_channels(targets[0], out_len[0], align_corners=True)
    else:
        targets = [resample_linear(feat, n) for n in in_len]
        syn = resample_linear(targets[0], out_len[0], align_corners=True)
    if prm.noise_sigma > 0:
        # drawn frame-major for both computations (the same noise for a seed)
        noise = rng.standard_normal((out_len[0], feat.shape[1])).astype(np.float32)
        noise *= np.float32(prm.noise_sigma)
        syn = np.fmod(syn + (noise.T if prm.computation == "released" else noise),
                      np.float32(1.0))
    for lvl, target in enumerate(targets):
        if prm.computation == "released":
            if lvl > 0:
                syn = _resample_channels(syn, out_len[lvl])
            y_patches = extract_patches(target, p)  # cached for the level's steps
            for _ in range(prm.num_steps):
                syn, nnf, loss = _released_step(syn, y_patches, p, prm.alpha, prm.block)
                losses.append(loss)
            continue
        if lvl > 0:
            syn = resample_linear(syn, out_len[lvl])
        Y = _patches(target, p)
        yy = (Y * Y).sum(1)
        for _ in range(prm.num_steps):
            nnf = _normalised_nn(_patches(syn, p), Y, yy, prm.alpha, prm.block)
            syn = _blend(target, nnf, syn.shape[0], p)
    if prm.computation == "released":
        syn = syn.T
    return {
        "losses": losses,
        "motion": features_to_motion(syn, motion, info),
        "source_index": _source_index(nnf, length, p),
        "input_lengths": in_len,
        "output_lengths": out_len,
    }
