"""Adaptive local smoothing of the transitions (Moradoff §3.8).

At every transition (a seam between output frames ``i`` and ``i+1`` whose
sources are not consecutive) an *acceleration test* compares the acceleration
at the two seam frames with the accelerations of frames ``i-3 … i-1`` and
``i+2 … i+4``; acceleration is the mean over joints of the FK joint
acceleration, on a trajectory integrated locally around the seam.  A seam
fails when its acceleration exceeds ``accel_tolerance`` × the mean reference
acceleration (and an absolute floor that lets still poses pass), or — an
addition to the thesis' test — when the jerk of the frames around it exceeds
``jerk_limit`` (the caller passes a multiple of the input's p99 jerk).  A failing
seam is smoothed by a pass of a Gaussian of width 5 (binomial taps
``[1, 4, 6, 4, 1] / 16``) over a window of ``±k`` frames (with a 5-frame cosine
taper, whose edges stay below the input's jerk), on quaternions (taps
sign-aligned, weighted sum, normalised) and on the root features; ``k`` widens
by one per failing test until no discontinuity remains (or ``max_widening`` is
reached).

Before the test, :func:`transition_blend` (an addition) cross-fades each seam between
the two input lines it joins; the jerk test then covers the whole fade
(``jerk_reach``).

Every frame count above is at 30 fps (:data:`SMOOTHING_RATE`, the thesis'
rate); at a higher synthesis rate each scales by ``rate / 30`` (the Gaussian
becomes a sampled one of the same width in seconds), so the smoothing and the
test cover the same time at any rate.

Constrained frames are pinned: after every pass the rotation and height offsets
that smoothing introduced at a constrained frame are removed by a displacement
that decays to zero (raised cosine) over the smoothing radius.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from math import comb

import numpy as np

from mocapflow.stages.motion.kinematics import forward_kinematics
from mocapflow.stages.motion.rotations import (
    quat_exp,
    quat_inverse,
    quat_log,
    quat_multiply,
    yaw_quaternion,
)

__all__ = [
    "SmoothingResult",
    "adaptive_smoothing",
    "filter_quaternions",
    "gaussian_taps",
    "rate_scale",
    "seam_test",
    "transition_blend",
]

#: Frame rate at which the frame counts of the smoothing are stated (the thesis' 30
#: fps): at another rate the Gaussian's width, the window and its taper, and the test's
#: reference frames scale by ``rate / SMOOTHING_RATE``, so a pass smooths the same span
#: of time (at 120 fps the 5 taps covered a quarter of it: 19 of 28 seams failed).
SMOOTHING_RATE = 30.0
#: Frames on each side of a seam used to evaluate the acceleration test (at 30 fps).
_HALF = 6
#: Taper (frames at 30 fps) of a smoothing window.
_TAPER = 5


def rate_scale(rate: float) -> float:
    """Frames at ``rate`` per frame at :data:`SMOOTHING_RATE` (1 at or below it)."""
    return max(float(rate) / SMOOTHING_RATE, 1.0)


def gaussian_taps(width: int = 5, scale: float = 1.0) -> np.ndarray:
    """Binomial approximation of a Gaussian with ``width`` taps (odd).

    Parameters
    ----------
    width : int
        Taps at :data:`SMOOTHING_RATE` (std ``√(width − 1) / 2`` frames).
    scale : float
        Frames per frame at :data:`SMOOTHING_RATE` (:func:`rate_scale`): above 1,
        a sampled Gaussian of ``scale`` × that std, cut at 3 std.

    Returns
    -------
    (T,) float ndarray
        ``T = width`` at ``scale = 1``.
    """
    if width < 3 or width % 2 == 0:
        raise ValueError(f"gaussian_width must be odd and >= 3, got {width}")
    if scale <= 1.0:
        w = np.array([comb(width - 1, k) for k in range(width)], dtype=np.float64)
        return w / w.sum()
    sd = scale * np.sqrt(width - 1) / 2.0
    x = np.arange(-int(np.ceil(3 * sd)), int(np.ceil(3 * sd)) + 1)
    w = np.exp(-0.5 * (x / sd) ** 2)
    return w / w.sum()


def _row_sum(p: np.ndarray) -> np.ndarray:
    """Sum over a short last axis (3 or 4: vectors, quaternions), kept as a length-1 axis.

    Left to right, the order in which ``np.sum(p, axis=-1)`` (and so ``np.linalg.norm``)
    adds fewer than 8 values (NumPy 2.4; tests/stages/texture/test_exact_shortcuts.py
    checks it), so the same values, without a reduction over rows of 3-4 (about six
    times slower on the ``(frames, joints, 4)`` arrays of a smoothing pass).
    """
    out = p[..., 0:1] + p[..., 1:2]
    for k in range(2, p.shape[-1]):
        out += p[..., k : k + 1]
    return out


def _shift_index(L: int, m: int, cyclic: bool, frames: np.ndarray | None = None) -> np.ndarray:
    idx = (np.arange(L) if frames is None else frames) + m
    return np.mod(idx, L) if cyclic else np.clip(idx, 0, L - 1)


def filter_quaternions(q: np.ndarray, taps: np.ndarray, *, cyclic: bool = False,
                       frames: np.ndarray | None = None) -> np.ndarray:
    """Gaussian filter of quaternion tracks along frames.

    Parameters
    ----------
    q : (L, ..., 4) float ndarray
    taps : (w,) float ndarray
        Odd number of weights centred on the frame.
    cyclic : bool
        Wrap at the ends (loops); else clamp.
    frames : (F,) int ndarray, optional
        Only these frames filtered (default all ``L``).

    Returns
    -------
    (L, ..., 4) or (F, ..., 4) float ndarray
    """
    L = q.shape[0]
    h = taps.size // 2
    q0 = q if frames is None else q[frames]
    acc = np.zeros_like(q0)
    for m, w in zip(range(-h, h + 1), taps):
        s = q[_shift_index(L, m, cyclic, frames)]
        sign = np.where(_row_sum(s * q0) < 0, -1.0, 1.0)
        acc += w * sign * s
    return acc / np.sqrt(_row_sum(acc * acc))


def _filter_linear(x: np.ndarray, taps: np.ndarray, *, cyclic: bool,
                   frames: np.ndarray | None = None) -> np.ndarray:
    L = x.shape[0]
    h = taps.size // 2
    acc = np.zeros_like(x if frames is None else x[frames])
    for m, w in zip(range(-h, h + 1), taps):
        acc += w * x[_shift_index(L, m, cyclic, frames)]
    return acc


def _blend_quaternions(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Normalised lerp from ``a`` to ``b`` by per-frame weight ``w`` (L,)."""
    sign = np.where(_row_sum(a * b) < 0, -1.0, 1.0)
    ww = w.reshape((-1,) + (1,) * (a.ndim - 1))
    out = (1 - ww) * a + ww * sign * b
    return out / np.sqrt(_row_sum(out * out))


def _window(L: int, centre: float, inner: float, cyclic: bool, taper: float = _TAPER,
            frames: np.ndarray | None = None) -> np.ndarray:
    """Weight 1 within ``inner`` of ``centre``, cosine taper over ``taper`` frames (exactly
    0 beyond), at every frame or at ``frames`` only."""
    f = np.arange(L, dtype=np.float64) if frames is None else frames.astype(np.float64)
    d = np.abs(f - centre)
    if cyclic:
        d = np.minimum(d, L - d)
    x = np.clip((d - inner) / taper, 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * x))


def _cycloidal_ramp(x: np.ndarray) -> np.ndarray:
    """C² ramp from 0 (x ≤ 0) to 1 (x ≥ 1): ``x − sin(2πx) / 2π`` (the cycloidal cam
    profile: zero rate and acceleration at both ends, and the lowest peak jerk of the
    usual C² ramps, 4π² ≈ 39.5 against the quintic smoothstep's 60)."""
    x = np.clip(x, 0.0, 1.0)
    return x - np.sin(2.0 * np.pi * x) / (2.0 * np.pi)


def transition_blend(
    rotations_in: np.ndarray,
    features_in: np.ndarray,
    source_index: np.ndarray,
    seams: np.ndarray,
    rate: float,
    *,
    duration: float,
    constrained: list[int] | np.ndarray = (),
    cyclic: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cross-fade each seam between the two input lines it joins (an addition to §3.8).

    At a seam between output frames ``t - 1`` and ``t`` (sources ``a = s[t-1]`` and
    ``b = s[t]``) the output before the seam is faded towards the frames that lead
    into ``b`` in the input (``b - 1, b - 2, …``) and the output after it starts from
    the frames that follow ``a`` in the input (``a + 1, a + 2, …``), with the C² weight
    :func:`_cycloidal_ramp` rising from 0 to 1 across the window.  Every blended frame is a
    mix of two input frames at the same offset from the seam, so the motion keeps the
    input's detail (a Gaussian pass low-passes it) and its windows stay close to the
    input's own (GANimator's local diversity); the adaptive smoothing then treats only
    the seams that still fail its test.

    Parameters
    ----------
    rotations_in : (F, J, 4) float ndarray
        Input local rotations (root heading removed).
    features_in : (F, D) float ndarray
        Input root features ``[yaw_rate, vx, vz, height, translations…]``.
    source_index : (L,) int ndarray
        Input frame copied into each output frame.
    seams : (S,) int ndarray
        Seams between ``t - 1`` and ``t`` (``t = 0``: the loop wrap), ascending.
    rate : float
        Frames per second of ``source_index``.
    duration : float
        Seconds of a whole cross-fade (half before the seam, half after); shortened
        where the input has no frames to continue a line, to half the distance to the
        next seam, and so that no constrained frame is blended.  0 disables.
    constrained : sequence of int
        Output frames left as copied.
    cyclic : bool
        Loop mode (windows wrap around the output).

    Returns
    -------
    rotations : (L, J, 4) float ndarray
    features : (L, D) float ndarray
    lines : (L, 2) int ndarray
        The two input frames mixed at each output frame (both ``s[t]`` where no
        cross-fade reaches).
    weight : (L,) float ndarray
        Weight of ``lines[:, 1]`` (0 where no cross-fade reaches).
    """
    src = np.asarray(source_index, dtype=np.int64)
    L, F = src.size, rotations_in.shape[0]
    rot = rotations_in[src].copy()
    feat = features_in[src].copy()
    lines = np.stack([src, src], axis=1)
    weight = np.zeros(L)
    seams = np.sort(np.asarray(seams, dtype=np.int64))
    half = int(round(0.5 * duration * rate))
    if half < 1 or seams.size == 0:
        return rot, feat, lines, weight
    cons = np.sort(np.asarray(constrained, dtype=np.int64))
    S = seams.size
    for n, t in enumerate(seams):
        if cyclic:
            gap_prev = (t - seams[n - 1]) % L or L
            gap_next = (seams[(n + 1) % S] - t) % L or L
        else:
            gap_prev = t - seams[n - 1] if n else t
            gap_next = seams[n + 1] - t if n + 1 < S else L - t
        a, b = src[t - 1], src[t]
        before = min(half, int(b), gap_prev // 2 if (cyclic or n) else gap_prev)
        after = min(half, int(F - 1 - a), gap_next // 2 if (cyclic or n + 1 < S) else gap_next)
        if cons.size:  # constrained frames keep their copies: the window stops short of them
            d = (t - cons) % L if cyclic else t - cons
            d_before = d[d >= 1] if not cyclic else d[(d >= 1) & (d <= L // 2)]
            if d_before.size:
                before = min(before, int(d_before.min()) - 1)
            d = (cons - t) % L if cyclic else cons - t
            d_after = d[d >= 0] if not cyclic else d[d <= L // 2]
            if d_after.size:
                after = min(after, int(d_after.min()))
        if before + after < 2:
            continue
        u = np.arange(-before, after)  # offsets from the seam: frames t + u
        w = _cycloidal_ramp((u + before + 0.5) / (before + after))
        f = t + u
        f = np.mod(f, L) if cyclic else f
        line_a = np.where(u < 0, src[f], a + 1 + u)  # the line before the seam, continued
        line_b = np.where(u < 0, b + u, src[f])  # the line after it, led into
        rot[f] = _blend_quaternions(rotations_in[line_a], rotations_in[line_b], w)
        feat[f] = (1.0 - w[:, None]) * features_in[line_a] + w[:, None] * features_in[line_b]
        lines[f, 0], lines[f, 1], weight[f] = line_a, line_b, w
    return rot, feat, lines, weight


def seam_test(
    skeleton,
    rotations: np.ndarray,
    features: np.ndarray,
    seams: np.ndarray,
    rate: float,
    *,
    cyclic: bool,
    accel_tolerance: float = 1.0,
    accel_floor: float = 0.0,
    reference: np.ndarray | None = None,
    jerk_limit: float | None = None,
    jerk_reach: int = 1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Acceleration test at each seam.

    Parameters
    ----------
    skeleton : Skeleton
    rotations : (L, J, 4) float ndarray
        Local rotations, root heading removed.
    features : (L, D) float ndarray
        Root features ``[yaw_rate, vx, vz, height, (translations…)]``.
    seams : (S,) int ndarray
        Seams between frames ``t - 1`` and ``t`` (``t = 0``: the loop wrap).
    rate : float
    cyclic : bool
    accel_tolerance : float
    accel_floor : float
        Seam accelerations (m/s²) below this always pass (still poses).
    reference : (S,) float ndarray, optional
        Reference accelerations to test against (default: measured here).  The
        smoothing passes the ones of the unsmoothed track, whose reference
        frames do not yet feel the smoothing window.
    jerk_limit : float, optional
        Largest mean joint jerk (m/s³) allowed at the three frames (at 30 fps)
        whose jerk stencil spans the seam; a seam above it fails as well.
    jerk_reach : int
        Frames (at 30 fps) on each side of the seam whose jerk is tested: 1, the
        three frames above; more when the seam was cross-faded
        (:func:`transition_blend`), to cover the fade (at most the test window's
        ``_HALF - 2``); scaled with the rate as every frame count here.

    Returns
    -------
    passed : (S,) bool ndarray
    seam_acc : (S,) float ndarray
        Largest acceleration of the two seam frames (m/s²).
    ref_acc : (S,) float ndarray
        Largest acceleration of the reference frames.
    """
    S = seams.size
    if S == 0:
        return np.ones(0, bool), np.zeros(0), np.zeros(0)
    L = rotations.shape[0]
    J = rotations.shape[1]
    r = rate_scale(rate)
    half, nref = int(round(_HALF * r)), int(round(3 * r))  # frames at this rate
    idx, ok = _test_window(seams, L, rate, cyclic)
    yaw = features[idx, 0]
    vel = features[idx, 1:3]
    heading = np.concatenate([np.zeros((S, 1)), np.cumsum(yaw[:, :-1], axis=1)], axis=1)
    c, s = np.cos(heading), np.sin(heading)
    dx = vel[..., 0] * c + vel[..., 1] * s
    dz = -vel[..., 0] * s + vel[..., 1] * c
    root = np.zeros(idx.shape + (3,))
    root[..., 1:, 0] = np.cumsum(dx[:, :-1], axis=1)
    root[..., 1:, 2] = np.cumsum(dz[:, :-1], axis=1)
    root[..., 1] = features[idx, 3]
    rot = rotations[idx].copy()
    rot[..., 0, :] = quat_multiply(yaw_quaternion(heading), rot[..., 0, :])
    trans = None
    if features.shape[1] > 4:
        trans = features[idx, 4:].reshape(idx.shape + (J, 3))
    pos, _ = forward_kinematics(skeleton, rot, root, translations=trans)
    acc3 = pos[:, 2:] - 2 * pos[:, 1:-1] + pos[:, :-2]
    a = np.sqrt(_row_sum(acc3 * acc3)[..., 0]).mean(-1) * rate**2  # (np.linalg.norm's values)
    a_ok = ok[:, 2:] & ok[:, 1:-1] & ok[:, :-2]
    acc = np.full(idx.shape, np.nan)
    acc[:, 1:-1] = np.where(a_ok, a, np.nan)
    i = half - 1  # frame before the seam, local index
    seam_acc = np.nanmax(acc[:, i : i + 2], axis=1)
    ref = np.concatenate([acc[:, i - nref : i], acc[:, i + 2 : i + 2 + nref]], axis=1)
    with np.errstate(invalid="ignore"):
        ref_acc = np.where(np.isfinite(ref).any(1), np.nanmean(ref, 1), 0)
    if reference is not None:
        ref_acc = np.asarray(reference, dtype=np.float64)
    passed = ~(seam_acc > np.maximum(accel_tolerance * ref_acc, accel_floor))
    passed |= ~np.isfinite(ref).any(1)
    if jerk_limit is not None:
        j = pos[:, 3:] - 3 * pos[:, 2:-1] + 3 * pos[:, 1:-2] - pos[:, :-3]
        j = np.sqrt(_row_sum(j * j)[..., 0]).mean(-1) * rate**3  # local frame f = index + 1
        j_ok = ok[:, 3:] & ok[:, :-3]
        # frames i-R … i+R: R = 1 at 30 fps (i-1, i, i+1), widened with the rate and reach
        R = min(max(int(jerk_reach), 1) * int(round(r)), half - 2)
        jerk = np.where(j_ok, j, np.nan)[:, i - 1 - R : i + R]
        with np.errstate(invalid="ignore"):
            passed &= ~(np.nanmax(np.nan_to_num(jerk, nan=0.0), axis=1) > jerk_limit)
    return passed, seam_acc, ref_acc


@dataclass
class SmoothingResult:
    """Smoothed output and what the smoothing did.

    Attributes
    ----------
    rotations : (L, J, 4) float ndarray
    features : (L, D) float ndarray
    widening : (S,) int ndarray
        Final ``k`` of each seam (0: passed untouched).
    passed : (S,) bool ndarray
        Seams that pass the acceleration test after smoothing.
    seam_acc, ref_acc : (S,) float ndarray
        Test values after smoothing.
    """

    rotations: np.ndarray
    features: np.ndarray
    widening: np.ndarray
    passed: np.ndarray
    seam_acc: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ref_acc: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _pin(rot, feat, rot0, feat0, frames, radius, cyclic):
    """Remove the offsets smoothing left at the constrained frames (in place)."""
    L = rot.shape[0]
    frames = sorted(int(f) for f in frames)
    for n, c in enumerate(frames):
        others = [abs(c - o) for k, o in enumerate(frames) if k != n]
        if cyclic:
            others = [min(d, L - d) for d in others]
        r = min([radius] + [d - 1 for d in others])
        if r < 1:
            rot[c], feat[c, 3:] = rot0[c], feat0[c, 3:]
            continue
        d = np.abs(np.arange(L) - c)
        if cyclic:
            d = np.minimum(d, L - d)
        w = np.where(d <= r, 0.5 * (1 + np.cos(np.pi * d / (r + 1))), 0.0)
        delta = quat_multiply(quat_inverse(rot[c]), rot0[c])
        delta = np.where(delta[..., :1] < 0, -delta, delta)
        lg = quat_log(delta)  # (J, 3)
        rot[:] = quat_multiply(rot, quat_exp(w[:, None, None] * lg[None]))
        feat[:, 3:] += w[:, None] * (feat0[c, 3:] - feat[c, 3:])[None, :]
        rot[c], feat[c, 3:] = rot0[c], feat0[c, 3:]


def adaptive_smoothing(
    skeleton,
    rotations: np.ndarray,
    features: np.ndarray,
    seams: np.ndarray,
    rate: float,
    *,
    constrained: list[int] | np.ndarray = (),
    cyclic: bool = False,
    gaussian_width: int = 5,
    accel_tolerance: float = 1.0,
    accel_floor: float = 0.0,
    max_widening: int = 12,
    jerk_limit: float | None = None,
    jerk_reach: int = 1,
) -> SmoothingResult:
    """Smooth every seam that fails the acceleration test, widening until it passes.

    Parameters
    ----------
    skeleton : Skeleton
    rotations : (L, J, 4) float ndarray
        Local rotations (root heading removed).
    features : (L, D) float ndarray
        ``[yaw_rate, vx, vz, height, translations…]``.
    seams : (S,) int ndarray
        Seams between ``t - 1`` and ``t``.
    rate : float
    constrained : sequence of int
        Output frames pinned to their values.
    cyclic : bool
        Loop mode (windows wrap).
    gaussian_width : int
        Taps of the Gaussian (5) at :data:`SMOOTHING_RATE`.
    accel_tolerance : float
        Seam acceleration allowed, relative to the mean reference acceleration.
    accel_floor : float
        Seam accelerations below this (m/s²) pass whatever the references.
    max_widening : int
        Largest ``k`` (passes; pass ``k`` smooths ``±k`` frames at 30 fps).
    jerk_limit : float, optional
        Seams whose jerk exceeds this (m/s³) fail too (see :func:`seam_test`).
    jerk_reach : int
        Frames (at 30 fps) each side of a seam whose jerk is tested (:func:`seam_test`).

    Returns
    -------
    SmoothingResult
    """
    rot = np.array(rotations, dtype=np.float64)
    feat = np.array(features, dtype=np.float64)
    pinned = len(constrained) > 0  # _pin may change any frame; else only a pass's frames
    rot0, feat0 = (rot.copy(), feat.copy()) if pinned else (rot, feat)  # (read by _pin)
    seams = np.asarray(seams, dtype=np.int64)
    r = rate_scale(rate)
    taps = gaussian_taps(gaussian_width, r)
    taper = _TAPER * r
    k = np.zeros(seams.size, dtype=np.int64)
    L = rot.shape[0]
    passed, sa, ref = seam_test(
        skeleton,
        rot,
        feat,
        seams,
        rate,
        cyclic=cyclic,
        accel_tolerance=accel_tolerance,
        accel_floor=accel_floor,
        jerk_limit=jerk_limit,
        jerk_reach=jerk_reach,
    )
    if pinned:  # the whole track before a pass (else only the frames it smooths)
        before_rot, before_feat = rot.copy(), feat.copy()
    while not passed.all():
        fail = ~passed & (k < max_widening)
        if not fail.any():
            break
        k[fail] += 1
        w = np.zeros(L)
        for t, kk in zip(seams[fail], k[fail]):
            # the window's frames (it is exactly 0 beyond inner + taper)
            reach = kk * r + taper + 1
            f = np.arange(int(np.floor(t - 0.5 - reach)), int(np.ceil(t - 0.5 + reach)) + 1)
            f = np.mod(f, L) if cyclic else f[(f >= 0) & (f < L)]
            if f.size >= L:
                w = np.maximum(w, _window(L, t - 0.5, kk * r, cyclic, taper))
            else:
                w[f] = np.maximum(w[f], _window(L, t - 0.5, kk * r, cyclic, taper, frames=f))
        act = np.flatnonzero(w > 0)  # frames inside a smoothing window (the rest keep theirs)
        if not pinned:
            before_rot, before_feat = rot[act], feat[act]
        rot[act] = _blend_quaternions(
            rot[act], filter_quaternions(rot, taps, cyclic=cyclic, frames=act), w[act])
        feat[act] += w[act, None] * (
            _filter_linear(feat, taps, cyclic=cyclic, frames=act) - feat[act])
        # a seam's test reads only the frames of its window: only the seams whose window
        # holds a frame this pass changed are tested again (the others keep their result)
        if pinned:
            _pin(rot, feat, rot0, feat0, constrained, int(k.max() * r + taper) + 2, cyclic)
            changed = (rot != before_rot).any(axis=(1, 2)) | (feat != before_feat).any(axis=1)
        else:
            changed = np.zeros(L, dtype=bool)
            changed[act] = ((rot[act] != before_rot).any(axis=(1, 2))
                            | (feat[act] != before_feat).any(axis=1))
        again = changed[_test_window(seams, L, rate, cyclic)[0]].any(axis=1)
        if again.any():
            p2, s2, _ = seam_test(
                skeleton,
                rot,
                feat,
                seams[again],
                rate,
                cyclic=cyclic,
                accel_tolerance=accel_tolerance,
                accel_floor=accel_floor,
                reference=ref[again],
                jerk_limit=jerk_limit,
        jerk_reach=jerk_reach,
            )
            passed, sa = passed.copy(), sa.copy()
            passed[again], sa[again] = p2, s2
        if pinned:
            before_rot, before_feat = rot.copy(), feat.copy()
    return SmoothingResult(rot, feat, k, passed, sa, ref)


def _test_window(
    seams: np.ndarray, L: int, rate: float, cyclic: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Frames ``(S, w)`` the acceleration test of each seam reads (:func:`seam_test`), and
    which of them lie inside the motion (all, when ``cyclic``)."""
    half = int(round(_HALF * rate_scale(rate)))
    raw = seams[:, None] + np.arange(-half, half)[None, :]
    if cyclic:
        return np.mod(raw, L), np.ones(raw.shape, bool)
    return np.clip(raw, 0, L - 1), (raw >= 0) & (raw < L)
