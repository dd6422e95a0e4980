"""GenMM baseline for ``benchmarks/texture.py`` — a NumPy reimplementation, not GenMM's code.

GenMM (Li, Chen, Li, Sorkine-Hornung, Chen, "Example-based Motion Synthesis via
Generative Motion Matching", ACM TOG 42(4), SIGGRAPH 2023) is not on PyPI.  This
module reimplements its published algorithm from the paper's description, with the
defaults of the paper and of its released configuration, so that the benchmark can
run it in the same process, on the same inputs and seeds, as ours:

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

Departures from the released code (none changes the algorithm):

* frame 0's root velocity is set to frame 1's (the released code stores an absolute
  position there);
* when the output pyramid would have a different number of levels than the input's
  (the released code then stops short of the requested length), the output lengths
  are the input lengths scaled by ``length / F_in``, the last one exactly ``length``;
* the distance matrix of a step is computed once (the released code computes it
  twice, once for the column minima and once for the matches); NumPy float32 on the
  CPU, matrix products in row blocks;
* non-root joint translations, when the input has them, are not synthesised: the
  output keeps the rest offsets (GenMM's features have none either);
* the up axis is ``y`` (the released default, and the convention of every BVH in
  ``shared/data``).

Calibrated against GenMM itself (commit fae65cd, the authors' last before a
third-party key-frame patch that breaks ``GenMM.run``; PyTorch 2.13 CPU, one thread,
run outside this repository on the benchmark's 30 fps input as written by this
package's BVH writer, GenMM's ``configs/default.yaml``; its output BVHs read back with
the rate set to 30 fps) on ``cmu_131_02`` at 30 fps, 312 → 1024 frames, seeds 0–2,
both evaluated by ``benchmarks/texture.py --calibrate FILE`` (means, min–max over
seeds)::

    method                 CPU s             cover  global  local  jerk×  skate×
    GenMM (released code)  0.96 (0.84–1.03)  0.995  0.150   0.117  1.04   1.15
    this reimplementation  0.23 (0.22–0.24)  1.000  0.157   0.129  1.10   1.17
    ratio                  0.24              1.00   1.05    1.10   1.06   1.01

Every metric within 10 %; the time is not: this module takes a quarter of GenMM's CPU
time.  Profile of the released code on one thread: the two distance passes (matrix
products, 38 %), patch extraction and folding by ``unfoldNd`` convolutions (27 %),
tensor reshape copies (11 %); here patches are strided views and each distance
matrix is computed once — the same algorithm, less overhead, so a speed comparison
with this baseline is about 4× stricter than one with GenMM's code.

All inputs, in the same run as ours (``benchmarks/texture.py --seeds 5 --no-cases
--no-speed --genmm-command CMD``, ``CMD`` a script outside the repository calling
GenMM's code; seeds 0–4; both draw their own random numbers, so per-seed outputs
differ), reimplementation / released code, ratio of the means (CPU: the summary's
column *CPU s reimpl./GenMM released*)::

    input (frames)  output  CPU s  cover  global  local  jerk×  skate×
    salsa (512)     1024    0.25   1.00   1.10    1.00   0.83   1.05
    salsa (561)     1122    0.26   1.00   1.05    1.09   0.88   1.09
    walk (312)      1024    0.21   1.00   1.17    1.17   1.05   1.02
    walk (312)       624    0.21   0.94   1.13    1.14   1.00   1.01
    8-walk (266)    1024    0.19   1.00   1.03    1.06   1.05   1.00
    8-walk (266)     532    0.19   1.00   0.92    0.93   0.28   0.98

CPU time 0.18–0.26 of the released code's on every row (two runs); coverage,
diversity and skate within 17 % (the spread over 5 seeds is larger: walk global
0.12–0.20 for either); the reimplementation's coverage 0.94 on walk 624 is one seed at
0.72.  The released code's jerk× is higher on salsa (1.46–1.61 vs 1.28–1.33) and on
8-walk 532 (11.0, one seed 33×): it stores the absolute root position in the first
frame's velocity channel, a root pop wherever that patch is matched.
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
    block: int = 1024  # rows of the distance matrix per matrix product


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
        ``input_lengths`` and ``output_lengths`` (the pyramids).
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

    targets = [resample_linear(feat, n) for n in in_len]
    syn = resample_linear(targets[0], out_len[0], align_corners=True)
    if prm.noise_sigma > 0:
        noise = rng.standard_normal(syn.shape).astype(np.float32) * np.float32(prm.noise_sigma)
        syn = np.fmod(syn + noise, np.float32(1.0))
    nnf = np.zeros(0, dtype=np.int64)
    for lvl, target in enumerate(targets):
        if lvl > 0:
            syn = resample_linear(syn, out_len[lvl])
        Y = _patches(target, p)
        yy = (Y * Y).sum(1)
        for _ in range(prm.num_steps):
            nnf = _normalised_nn(_patches(syn, p), Y, yy, prm.alpha, prm.block)
            syn = _blend(target, nnf, syn.shape[0], p)
    return {
        "motion": features_to_motion(syn, motion, info),
        "source_index": _source_index(nnf, length, p),
        "input_lengths": in_len,
        "output_lengths": out_len,
    }
