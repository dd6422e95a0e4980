"""The blend's evidence against its members beyond the validation copies (beyond Park &
Hodgins 2006): what a gap itself shows, and what the take's measured samples never do.

:func:`~mocapflow.stages.skin.fill_blend.fill_by_validated_blend` weighs five estimates
of every run of holes by their errors on copies of the run.  The copies cannot see what
the marker does inside its own gap; this module reads it where it shows:

* :func:`_outlying_estimates`: a member far beyond its validated error from the others'
  estimates of the run (:data:`OUTLIER_FACTOR`, :data:`CONSENSUS_FACTOR`), sooner where
  it misses the measured trajectory at the run's ends (:func:`_boundary_misses`);
* :func:`_end_excess`: how much farther a member misses the trajectory at the run's ends
  than the trajectory misses its own nearest samples (:data:`END_REFERENCE_FACTOR`; the
  samples within :data:`END_REACH` frames, in a row or not), which the blend takes as a
  floor of the member's error;
* :func:`_take_bounds`: what the marker's measured samples never do over the take, the
  distances it keeps to its rigid partners (:data:`PARTNER_MAX_SPREAD`) and its fastest
  step;
* :func:`_jumps_in_runs`: a member's samples next to a step longer than that
  (:data:`PLAUSIBILITY_LIMIT`), all of its samples of a run where they are half of them
  (:data:`ERRATIC_SHARE`);
* :func:`_keep_plausible`: a member off the distances to the rigid partners;
* :func:`_isolated_spikes`: measured samples that stand alone off their trajectory (a
  reconstruction glitch, :data:`SPIKE_FACTOR`, :data:`SPIKE_CONTRAST`), which the spline
  member does not interpolate through.

The measurements behind each bound are in the comment above it, and the blend's results
on the shared real C3Ds in :mod:`~mocapflow.stages.skin.fill_blend`'s docstring.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "BOUNDARY_FACTOR",
    "BOUNDARY_GUARD",
    "CONSENSUS_FACTOR",
    "CONSENSUS_MARGIN",
    "END_REACH",
    "END_REFERENCE_FACTOR",
    "ERRATIC_SHARE",
    "JOINLESS_OUTLIER_FACTOR",
    "OUTLIER_FACTOR",
    "PARTNER_MAX_SPREAD",
    "PARTNER_MIN_FRAMES",
    "PLAUSIBILITY_LIMIT",
    "SPIKE_CONTRAST",
    "SPIKE_FACTOR",
]


#: A blend member whose estimate of a run lies farther from the other members' median
#: than this many times the validated RMS errors (its own plus the others' median) is
#: left out of that run (:func:`_outlying_estimates`).  At 3 it also dropped a spline that
#: was right: PiG calibration, the whole right arm gone for 0.5 s (the gap protocol's
#: 0.5 s / 10 % / clustered mask of seed 555), where the four spatial members share their
#: error (4-16 mm, donors gone with the arm) and the spline, 1-2 mm off, lay 4-5 mm from
#: them: 1.43 -> 3.31 mm; at 5 that stays 1.43 mm and the cases of
#: :func:`_outlying_estimates` keep their gains.
OUTLIER_FACTOR = 5.0


#: A blend member whose estimate of a run lies farther than this many standard deviations
#: from the other members' inverse-variance weighted mean is left out of that run too
#: (:func:`_consensus_distance`, the first test of :func:`_outlying_estimates`).  The
#: median test above scales by the members' errors added, as if every one were as far off
#: as its copies say; the weighted mean of four members validated at 1-3 mm is known
#: far better than any of them.  basket_sprint, BodyL:C7 knocked out over frames
#: 1435-1446 (0.1 s, the 0.1 s / 1 % / independent mask of seed 788): the spline,
#: validated at 0.79 mm, is 6.7 mm off and 6.5 mm from the others' median, 2.4 x its
#: scale there; the two rigid-body fills (0.9-1.1 mm validated) are 0.1-0.4 mm off and the
#: others' weighted mean lies 6.4 deviations from the spline: blend 3.5 -> 0.14 mm RMS.
#: Where the spatial members share one error the test is nearer its bound: in the PiG arm
#: case of :data:`OUTLIER_FACTOR` (copies 1.6-2.5 mm, in the gap 4-6 mm off together) the
#: right spline of RELB lies 3.9 deviations from them and stays; the arm's other
#: markers 2.0-2.1.
CONSENSUS_FACTOR = 5.0


#: The test of :data:`CONSENSUS_FACTOR` leaves a member out only where it stands apart: its
#: deviations at least this many times the next member's (:func:`_standing_apart`).  Two
#: well-validated members that disagree lie about as many deviations from the rest, each
#: the other's main counterweight, and nothing says which is off; a third that agrees
#: with one of them breaks the tie (the basket case above: 6.4 against 3.8).  pyomeca, the
#: box's 8 markers and 8 thorax markers gone for 2 s (the 2 s / 30 % / clustered mask of
#: seed 802): on the box the local fill (validated at 17-28 mm, 78-165 mm off) and the
#: spline (8-26 mm, 53-66 mm off) lie 5.0-9.8 deviations from the others, within 1.11 x
#: of each other; leaving out the farther handed the box to the local fill: 3,200 samples
#: at 49.0 mm mean (28.9 before the test, 26.4 with this margin).
CONSENSUS_MARGIN = 1.25


#: The same test at this factor for a member that also misses the measured trajectory at
#: the run's ends by more than :data:`BOUNDARY_FACTOR` × the others' median miss
#: (:func:`_boundary_misses`): the gap itself shows it off where the others join.  The arm
#: case above is not touched by it: the spline joins the trajectory at the ends.
JOINLESS_OUTLIER_FACTOR = 3.0


#: A member whose miss at the run's ends (:func:`_boundary_misses`) exceeds this many
#: times its validated RMS error plus the others' median miss is left out whatever its
#: distance from the others (:func:`_outlying_estimates`).
BOUNDARY_FACTOR = 2.0


#: The end-miss rules of :func:`_outlying_estimates` leave a member out only while a member
#: validated within this many times its RMS error remains: the misses tell apart members
#: the copies scored alike, and never hand a run to members they scored far worse.  ktk
#: racing, Head1 and Head2 over a 0.5 s hole (the 0.5 s / 10 % / clustered mask of seed
#: 610): the local fill, validated at 4.7-5.5 mm and 46-54 mm off, misses the ends by
#: 61-73 mm; the others, validated at 38-124 mm, are 62-326 mm off: without this bound it
#: was left out and the repetition's blend went 33 -> 180 mm.
BOUNDARY_GUARD = 3.0


def _measured_ends(x: np.ndarray, a: int, b: int, *, reach: int = 4,
                   in_a_row: bool = True) -> list[tuple[int, np.ndarray]]:
    """The ends of the run ``a..b-1`` of one marker's trajectory ``x (F, 3)`` (NaN where not
    measured): ``(at, frames)`` for the start (``at`` 0) and the end (``at`` -1), ``frames``
    the up to 4 measured frames nearest the run within ``reach`` frames of it (nearest
    first), in a row from the run's side (``in_a_row``) or not."""
    seen = np.isfinite(x).all(-1)
    ends = []
    for at, step in ((0, -1), (-1, 1)):  # start, end
        f = (a - 1 if step < 0 else b) + step * np.arange(reach)
        f = f[(f >= 0) & (f < len(x))]
        f = f[:int(np.cumprod(seen[f]).sum())] if in_a_row else f[seen[f]]
        ends.append((at, f[:4]))
    return ends


def _carried(x: np.ndarray, f0: int, f1: int, to: int) -> np.ndarray:
    """``(3,)``: the trajectory ``x (F, 3)`` carried on in a straight line from its measured
    frames ``f1`` and ``f0`` to frame ``to`` (``2 x[f0] - x[f1]`` a frame on)."""
    s = (to - f0) / (f0 - f1)
    return (1 + s) * x[f0] - s * x[f1]


def _carried_miss(est: np.ndarray, x: np.ndarray, at: int, f: np.ndarray, a: int,
                  b: int) -> np.ndarray:
    """``(K,)``: how far the members' estimates ``est (K, b - a, 3)`` of the run ``a..b-1`` lie
    at its end ``at`` (0: frame ``a``, -1: frame ``b - 1``) from the trajectory ``x`` carried
    on from its measured ``f[0]``, ``f[1]`` (:func:`_carried`)."""
    return np.linalg.norm(est[:, at] - _carried(x, f[0], f[1], a if at == 0 else b - 1),
                          axis=-1)


def _boundary_misses(est: np.ndarray, positions: np.ndarray, m: int, a: int,
                     b: int) -> np.ndarray:
    """``(K,)``: how far each member's estimate ``est (K, b - a, 3)`` of marker ``m``'s run
    ``a..b-1`` lies, at the run's first and last frame, from the measured trajectory carried
    one frame on (``2 x[a-1] - x[a-2]``, ``2 x[b] - x[b+1]``; ``positions (F, M, 3)``, NaN
    where not measured): the larger miss of the two ends, an end without two measured
    samples left out; NaN when neither has them.  A sample of each member's error inside the
    gap that no validation copy gives; carrying the trajectory on errs by about its change
    of velocity over a frame (at 50 Hz on the Eb015pr walk, 0.2-2.4 mm where the markers
    move 1-3 mm a frame)."""
    x = positions[:, m]
    miss = [_carried_miss(est, x, at, f, a, b) for at, f in _measured_ends(x, a, b)
            if len(f) >= 2]
    return np.max(miss, axis=0) if miss else np.full(est.shape[0], np.nan)


def _end_excess(est: np.ndarray, positions: np.ndarray, m: int, a: int, b: int) -> np.ndarray:
    """``(K,)``: how much farther each member's estimate ``est (K, b - a, 3)`` of marker
    ``m``'s run ``a..b-1`` lies, at the run's first and last frame, from the measured
    trajectory carried on in a straight line from its two nearest samples (:func:`_carried`;
    ``positions (F, M, 3)``, NaN where not measured) than :data:`END_REFERENCE_FACTOR` ×
    carrying it on misses the trajectory's own nearest samples (the larger over the one or
    two nearest that have two measured samples behind them): the larger excess of the two
    ends, 0 where within; NaN where neither end has three measured samples within
    :data:`END_REACH` frames (:func:`_measured_ends`: on a marker seen now and then, the
    samples need not be in a row)."""
    x = positions[:, m]
    out = []
    for at, f in _measured_ends(x, a, b, reach=END_REACH, in_a_row=False):
        if len(f) < 3:
            continue
        ref = max(np.linalg.norm(x[f[i]] - _carried(x, f[i + 1], f[i + 2], f[i]))
                  for i in range(len(f) - 2))
        out.append(np.maximum(_carried_miss(est, x, at, f, a, b)
                              - END_REFERENCE_FACTOR * ref, 0.0))
    return np.max(out, axis=0) if out else np.full(est.shape[0], np.nan)


#: How far (frames) from a run's end :func:`_end_excess` looks for the measured samples it
#: carries the trajectory on from.  In a row (the three frames next to the run) on most
#: runs; a marker seen now and then leaves gaps between them: basket_sprint's
#: ``ForearmL:Marker4`` (120 Hz), measured over frames 2439-2446 between holes of 56 and 2
#: frames, then at 2449, 2451, 2454 and 2456 (the gap protocol's 0.1 s / 1 % / independent
#: mask of seed 907 knocks out the eight, joining them into a 66-frame run): the
#: whole-body PCA, validated best (12 mm RMS against the spline's 17 mm and the local
#: fill's 149), is 154 mm off there and misses the trajectory carried back to frame 2448 by
#: 87 mm, where carrying it on misses its own sample at 2449 by 18 mm; the spline, 48 mm
#: off, misses by 1 mm.  With the three samples in a row required, that end was not read
#: and the blend was 102 mm off.
END_REACH = 8


#: How many times the measured trajectory's own miss of its last samples, carried on, a
#: member's miss at a run's end may be before the rest counts as its error
#: (:func:`_end_excess`): the trajectory's acceleration changes from frame to frame.
#: Measured against the least miss of the run's members instead, the spline (which
#: carries the trajectory on by construction, missing it by about nothing) set the
#: reference: ktk racing, OlecraneR knocked out for 70 frames while moving 36 mm a frame (the
#: 1 s / 1 % / clustered mask of seed 898), every spatial member missed by 25-28 mm where
#: the trajectory misses its own last samples by 15-32 mm, and the exact rigid-body fill
#: lost the run: 0.004 -> 6.3 mm; with this reference it keeps it (excess 0).
END_REFERENCE_FACTOR = 2.0


def _consensus_distance(e: np.ndarray, mse: np.ndarray, k: int, o: np.ndarray) -> float:
    """RMS distance of member ``k``'s estimate ``e[k]`` ``(L, 3)`` from the others' (``o``)
    inverse-variance weighted mean, in units of the standard deviation of that difference
    (``√(mse_k + 1 / Σ_o mse_o⁻¹)``)."""
    w = 1.0 / np.maximum(mse[o], 1e-300)
    c = np.tensordot(w, e[o], axes=1) / w.sum()
    d = np.sqrt(np.mean(np.sum((e[k] - c) ** 2, -1)))
    return float(d / np.sqrt(mse[k] + 1.0 / w.sum()))


def _standing_apart(e: np.ndarray, mse: np.ndarray, live: np.ndarray) -> np.ndarray:
    """``(K,)``: :func:`_consensus_distance` of the member of ``live`` farthest from the
    others, where it is at least :data:`CONSENSUS_MARGIN` times the next member's; 0 for
    every other member (``e (K, L, 3)``, ``mse (K,)``)."""
    z = np.zeros(len(mse))
    for k in live:
        z[k] = _consensus_distance(e, mse, k, live[live != k])
    first, second = np.sort(z)[::-1][:2]
    keep = np.zeros(len(mse))
    if first >= CONSENSUS_MARGIN * second:
        keep[np.argmax(z)] = first
    return keep


def _outlying_estimates(est: np.ndarray, runs: list[tuple[int, int, int]], mse: np.ndarray,
                        weights: np.ndarray, positions: np.ndarray | None = None) -> np.ndarray:
    """``(K, R)`` bool: the members of each run whose estimate the gap itself shows far off,
    beyond what the validation copies predicted.

    For each run with at least 3 weighted members (``weights (K, R)``,
    :func:`fill_blend._blend_weights` with repeats already at 0; ``mse (K, R)``,
    :func:`fill_blend._validation_mse`; ``est (K, F, M, 3)``,
    :func:`fill_blend._blend_members`), member ``k`` with validated scale ``s_k = √mse_k`` + the
    median of the others' ``√mse`` and RMS distance ``d_k`` over the run from the others'
    per-sample median is off when

    * ``d_k > OUTLIER_FACTOR s_k`` (:data:`OUTLIER_FACTOR`) or its distance from the
      others' inverse-variance weighted mean exceeds :data:`CONSENSUS_FACTOR` standard
      deviations (:func:`_consensus_distance`) and :data:`CONSENSUS_MARGIN` times the
      next member's (:func:`_standing_apart`), or
    * ``d_k > JOINLESS_OUTLIER_FACTOR s_k`` and its miss at the run's ends
      (:func:`_boundary_misses`, from ``positions (F, M, 3)``) exceeds
      :data:`BOUNDARY_FACTOR` × the others' median miss, or
    * that miss exceeds :data:`BOUNDARY_FACTOR` × (``√mse_k`` + the others' median miss).

    The last two apply only while another member's ``√mse`` is within
    :data:`BOUNDARY_GUARD` × ``√mse_k``.  The member off by the largest ratio is left
    out, and the last two tests are repeated on the rest while 3 remain.  The first alone
    leaves out at most one member: of the three left after it, two wrong ones that agree
    outvote a right one (pyomeca's box marker ``boite:droite_ext``, the 1 s / 1 % /
    independent mask of seed 594: after the spline, 61 mm off, the local fill and the
    whole-body PCA, 8 mm off together, left out the rigid-body fill, 0.6 mm off: blend
    0.6 -> 8.2 mm).  Without ``positions``, the first
    rule alone.  The median, unweighted: the others' weighted mean is the outlier itself
    when it holds the weight, and then every other member looks as far off as it does.

    The copies cannot see what a marker does inside its own gap; the other members'
    estimates there can, and so can the measured samples at its ends.  PiG calibration
    (100 Hz, 300 frames): LFHD knocked out over frames 184-283 (1 s, the head turning near
    the take's end): the copies scored the spline lowest (0.56 mm), but in the gap it is
    18 mm off where the four spatial members agree within 2 mm (the nearest-donor rigid fill
    0.7 mm off): blend 7.7 mm mean, 1.1 mm without the spline.  LPSI knocked out over
    frames 2-11 (its first frames jump 30 mm): the spline, scored 0.03-0.07 mm on copies
    later in the take, is 33 mm off, the others 5-7 mm: blend 32.8 -> 4.9 mm.  Eb015pr
    (50 Hz walk, 26 markers), the right foot and shank and LSK4 gone for 0.5 s over frames
    152-176 (the 0.5 s / 30 % / clustered mask of seed 531): the local fill and the
    whole-body PCA, scored 7-11 mm on the copies, are 64-132 mm off on RSK2-4 and miss
    the trajectory at the ends by 10-71 mm, where the spline and the rigid-body fills
    (3-13 mm off) miss it by 0.2-4 mm.  The distance alone left out one of the two (1.05-1.33
    × its bound) and the other held the weight: blend 42-48 mm; it also lies beyond 3 × its
    scale and misses the ends by more than twice the others do, so it goes too: 4-11 mm."""
    K = est.shape[0]
    out = np.zeros((K, len(runs)), dtype=bool)
    for r, (m, a, b) in enumerate(runs):
        e = est[:, a:b, m]  # (K, L, 3)
        live = np.flatnonzero(np.isfinite(e).all((1, 2)) & (weights[:, r] > 0)
                              & np.isfinite(mse[:, r]))  # fmt: skip
        miss = (np.full(K, np.nan) if positions is None else
                _boundary_misses(e, positions, m, a, b))  # fmt: skip
        rms = np.sqrt(mse[:, r])
        while len(live) >= 3:
            worst, flagged = 1.0, -1
            first = not out[:, r].any()  # the distance tests leave out one member at most
            apart = _standing_apart(e, mse[:, r], live) / CONSENSUS_FACTOR if first else None
            for k in live:
                o = live[live != k]
                d = np.sqrt(np.mean(np.sum((e[k] - np.median(e[o], axis=0)) ** 2, -1)))
                scale = rms[k] + np.median(rms[o])
                ratio = max(d / (OUTLIER_FACTOR * scale), apart[k]) if first else 0.0
                others_miss = np.median(miss[o])
                if (miss[k] > BOUNDARY_FACTOR * others_miss  # False where NaN
                        and rms[o].min() <= BOUNDARY_GUARD * rms[k]):  # fmt: skip
                    ratio = max(ratio, d / (JOINLESS_OUTLIER_FACTOR * scale),
                                miss[k] / (BOUNDARY_FACTOR * (rms[k] + others_miss)))
                if ratio > worst:
                    worst, flagged = ratio, k
            if flagged < 0:
                break
            out[flagged, r] = True
            live = live[live != flagged]
    return out


#: Two markers are rigid partners (:func:`_take_bounds`) where their measured distance
#: varies by at most this (m) over the frames both are measured, and those are at least
#: :data:`PARTNER_MIN_FRAMES`: markers on one segment or object.
PARTNER_MAX_SPREAD = 0.02

#: See :data:`PARTNER_MAX_SPREAD`.
PARTNER_MIN_FRAMES = 100

#: A blend member is left out of a run where its estimate lies farther than this (m, RMS
#: over the run) outside the distance ranges the marker keeps to its rigid partners over
#: the take (:func:`_partner_excess`), and out of the samples either side of a step this
#: much longer than the marker's fastest measured step (:func:`_jumps`); where no member
#: is left, the samples stay holes (:func:`_keep_plausible`).  On the six shared real
#: C3Ds, mask seeds 810-819 (every configuration of the gap protocol), the knocked-out
#: samples themselves lie at most 88.7 mm outside their markers' ranges to rigid partners
#: (Eb015pr; PiG calibration 86.5 mm: a static take whose subject moves inside some gaps;
#: 99 % within 0-14 mm), and their steps (from the sample before a run to the one after
#: it) exceed the marker's fastest measured step by at most 48 mm (Eb015pr; 13 mm on
#: basket_sprint).
PLAUSIBILITY_LIMIT = 0.1


def _take_bounds(positions: np.ndarray, markers: np.ndarray
                 ) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, float]]:  # fmt: skip
    """Per marker of ``markers``, what its measured samples never do (``positions (F, M,
    3)``, NaN where not measured): its rigid partners (:data:`PARTNER_MAX_SPREAD`) with
    the least and greatest distance to each over the frames both are measured, and its
    fastest step between two measured consecutive frames (inf where it has none):
    ``{marker: (partners (P,) int, lo (P,), hi (P,), step)}``."""
    out = {}
    for m in markers:
        d = np.linalg.norm(positions - positions[:, m:m + 1], axis=-1)  # (F, M)
        seen = np.isfinite(d)
        lo = np.where(seen, d, np.inf).min(0)
        hi = np.where(seen, d, -np.inf).max(0)
        ok = (seen.sum(0) >= PARTNER_MIN_FRAMES) & (hi - lo <= PARTNER_MAX_SPREAD)
        ok[m] = False
        p = np.flatnonzero(ok)
        steps = np.linalg.norm(np.diff(positions[:, m], axis=0), axis=-1)
        fast = np.max(steps, where=np.isfinite(steps), initial=-np.inf)
        out[int(m)] = (p, lo[p], hi[p], float(fast) if np.isfinite(fast) else np.inf)
    return out


def _partner_excess(e: np.ndarray, partners: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                    measured: np.ndarray) -> np.ndarray:
    """``(K,)``: how far each member's estimate ``e (K, L, 3)`` of a run (NaN where it has
    none) lies outside the marker's distance ranges ``lo``, ``hi`` ``(P,)`` to its rigid
    ``partners`` (:func:`_take_bounds`) measured in the run's frames (``measured (L, M,
    3)``, NaN where not): per frame the largest over the partners, RMS over the frames it
    estimates with any; 0 where it has none."""
    d = np.linalg.norm(e[:, :, None] - measured[None, :, partners], axis=-1)  # (K, L, P)
    x = np.fmax.reduce(np.maximum(d - hi, lo - d), axis=-1, initial=-np.inf)  # (K, L)
    at = x > -np.inf  # NaN (no estimate, partner unmeasured) never wins fmax
    return np.sqrt(np.sum(np.where(at, np.maximum(x, 0.0), 0.0) ** 2, -1)
                   / np.maximum(at.sum(-1), 1))  # fmt: skip


def _jumps(e: np.ndarray, fast: float, before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """``(K, L)`` bool: the samples of each member's estimate ``e (K, L, 3)`` of a run next
    to a step longer than the marker's fastest measured step ``fast`` +
    :data:`PLAUSIBILITY_LIMIT`, its steps taken between consecutive estimates and from and
    to the measured sample before and after the run where there is one (``before``,
    ``after`` ``(3,)``, NaN where not)."""
    K = e.shape[0]
    path = np.concatenate([np.broadcast_to(before, (K, 1, 3)), e,
                           np.broadcast_to(after, (K, 1, 3))], axis=1)
    steps = np.linalg.norm(np.diff(path, axis=1), axis=-1)  # (K, L + 1), NaN at a missing end
    bad = steps > fast + PLAUSIBILITY_LIMIT  # False where NaN
    return bad[:, :-1] | bad[:, 1:]  # the step into a sample, the step out of it


#: A blend member whose samples next to a jump (:func:`_jumps`) are at least this share of
#: the samples it estimates in a run is erratic there and leaves all of the run
#: (:func:`_jumps_in_runs`): its few samples between jumps are no better than the ones
#: beside them.  basket_sprint, WheelchairL:Marker4 flickering over frames 2873-2913 and
#: knocked out over 2877-2887 (the 0.1 s / 10 % / independent mask of seed 882): the local
#: fill and the whole-body PCA jump beside 20 of the run's 34 samples (0.59) and are
#: 17-509 mm and 550-1,134 mm off at the knocked-out ones; the spline, 0.3-3.9 mm off,
#: shared the samples between jumps with the local fill: the repetition's blend 27.3 mm
#: (18 samples filled), with them out 2.7 mm (22).  At 0.25 this also took the run of the
#: 143-frame case of :func:`_jumps_in_runs` from them (shares 0.20-0.35, 65-110 mm off
#: where the spline is 250-304 mm): that repetition 136 -> 213 mm; at 0.5 it stays 136.
ERRATIC_SHARE = 0.5


def _jumps_in_runs(est: np.ndarray, runs: list[tuple[int, int, int]], positions: np.ndarray,
                   bounds: dict, *, erratic: bool = True) -> np.ndarray:
    """``(K, F, M)`` bool: the samples of each member's estimate (``est (K, F, M, 3)``,
    :func:`fill_blend._blend_members`) next to a step longer than its marker ever makes
    (:func:`_jumps`; ``bounds``, :func:`_take_bounds`; ``positions (F, M, 3)``, NaN where
    not measured).  A jump is local: the same member is often the best one a few frames
    away (basket_sprint, the 1 s / 10 % / clustered mask of seed 820: ForearmL:Marker1, 2
    and 4 over frames 2383-2526, where the local fill and the whole-body PCA jump 1.3-2.3 m
    in a frame somewhere in the run and are 84-117 mm off at the knocked-out samples, the
    spline 263-315 mm; leaving them out of the whole run took that repetition from 95 to
    276 mm, out of those samples alone 101 mm).  Applied to the blend too
    (:func:`fill_blend.fill_by_validated_blend`, ``est`` ``(1, F, M, 3)``): where its members part
    by metres the blend jumps between them (basket_sprint as captured, 5.4 m in a frame), and
    the samples either side stay holes.  With ``erratic``, a member jumping beside at least
    :data:`ERRATIC_SHARE` of the samples it estimates in a run is flagged on all of them
    (not for the blend: its samples between jumps are the members' that stayed)."""
    F = positions.shape[0]
    jumps = np.zeros(est.shape[:3], dtype=bool)
    nowhere = np.full(3, np.nan)
    for m, a, b in runs:
        e = est[:, a:b, m]
        j = _jumps(e, bounds[m][3], positions[a - 1, m] if a > 0 else nowhere,
                   positions[b, m] if b < F else nowhere)
        has = np.isfinite(e).all(-1)  # (K, L)
        off = erratic & (j.sum(1) >= ERRATIC_SHARE * np.maximum(has.sum(1), 1))  # (K,)
        jumps[:, a:b, m] = j | (off[:, None] & has)
    return jumps


def _keep_plausible(weights: np.ndarray, est: np.ndarray, runs: list[tuple[int, int, int]],
                    positions: np.ndarray, bounds: dict) -> np.ndarray:
    """``(K, R)`` bool: the members of each run whose estimate lies more than
    :data:`PLAUSIBILITY_LIMIT` outside the distances the marker keeps to its rigid partners
    over the take (:func:`_partner_excess`; ``bounds``, :func:`_take_bounds`), their
    ``weights (K, R)`` set to 0 in place.  Where that leaves a run no weighted member, it
    goes to the member estimating all of it that stays within that bound, the least
    outside it; where there is none, to nobody (``est (K, F, M, 3)``,
    :func:`fill_blend._blend_members`, NaN where a member has no estimate; ``positions (F, M, 3)``,
    NaN where not measured).  The copies score a model where its donors and inputs were
    measured; over a long gap of a marker whose segment is hidden with it a model may
    extrapolate anywhere, and the take's own measured samples show where.

    basket_sprint (120 Hz, the 0.1 s / 10 % / clustered mask of seed 814):
    WheelchairL:Marker2, missing over frames 2333-2581 with one more sample knocked out
    inside, keeps 206.7-214.5 mm from WheelchairL:Marker1 over the take; the local fill and
    the whole-body PCA put it 2.4-2.7 m from where it was, the spline 0.28 m: blend 1.61 m.
    In the same repetition SWL:Marker2 (a push-rim marker, at most 33 mm a frame), frames
    2467-2506, three samples knocked out: the local fill jumps metres within the run, which
    put the spline (9 mm off, validated best) far from the median of two and out of the
    run (:func:`_outlying_estimates`), the whole-body PCA (150 mm off) holding the weight:
    blend 135 mm; with the jumps out of the tests (:func:`_jumps_in_runs`) the spline
    stays.  As captured, the take loses the head, trunk and hand markers from about frame
    2100 to its end (1,500-1,600 frames): the local fill and the whole-body PCA, the only
    members reaching all of it, jump up to 8-10 m a frame there."""
    K, R = weights.shape
    out = np.zeros((K, R), dtype=bool)
    for r, (m, a, b) in enumerate(runs):
        partners, lo, hi, _ = bounds[m]
        if not len(partners):
            continue
        e = est[:, a:b, m]
        x = _partner_excess(e, partners, lo, hi, positions[a:b])
        out[:, r] = x > PLAUSIBILITY_LIMIT
        if not out[:, r].any():
            continue
        weights[out[:, r], r] = 0.0
        if not weights[:, r].any():
            full = np.isfinite(e).all((1, 2)) & ~out[:, r]
            if full.any():
                weights[np.argmin(np.where(full, x, np.inf)), r] = 1.0
    return out


#: A measured sample is an isolated spike (:func:`_isolated_spikes`) when it lies more than
#: this many times its marker's median off the midpoint of its two neighbours (the median
#: over the take: the marker's noise and curvature at its own rate).  The spline member's
#: cubic through a spike rings across the gap beside it: basket_sprint (120 Hz), ``BodyL:C7``
#: knocked out over frames 1250-1261 (gap protocol 0.1 s / 1 % / independent, mask seed
#: 911): frame 1248, two samples before the gap, stands 4.1 mm off the midpoint of its
#: neighbours, 32 times the marker's median (0.13 mm; C7 has such one-frame spikes every
#: few frames there), and the spline through it is 7.7 mm off in the gap (5-15 mm at every
#: sample), without it 0.5 mm.  Its copies were scored 0.38 mm, so it held the blend: 7.7 mm
#: against the rigid-body fill's 1.65.  Flagged (with :data:`SPIKE_CONTRAST`) of the measured
#: samples at 10 / 20 / 40: basket_sprint 657 / 422 / 169 of 58,560 (C7's two at 10 and 20
#: only), Qualisys 38 / 17 / 1 of 18,700, pyomeca 61 / 12 / 0, PiG 7 / 1 / 0, Eb015pr 4 / 1 /
#: 1, racing and the simulator's dense captures none.
SPIKE_FACTOR = 20.0

#: See :data:`SPIKE_FACTOR`: a spike also lies this many times farther off that midpoint than
#: either neighbour lies off its own neighbours' once the spike is put on the midpoint.  A
#: single sample displaced by ``d`` leaves its neighbours where they were (they lie ``d / 2``
#: off their own midpoints only because of it); a kink of the trajectory (a sudden change of
#: velocity, which is motion) puts the neighbours half as far off as the corner: contrast 2.
SPIKE_CONTRAST = 4.0


def _isolated_spikes(positions: np.ndarray) -> np.ndarray:
    """``(F, M)`` bool: measured samples that stand alone off their marker's trajectory.

    Sample ``i`` of marker ``m`` (``positions (F, M, 3)``, NaN where not measured), with
    ``i - 1 … i + 1`` and at least one of ``i - 2``, ``i + 2`` measured, is a spike when
    its distance ``d`` from the midpoint ``p`` of samples ``i - 1`` and ``i + 1`` exceeds
    :data:`SPIKE_FACTOR` × the marker's median such distance and :data:`SPIKE_CONTRAST` ×
    the larger of the distances of samples ``i - 1`` and ``i + 1`` from the midpoints of
    their own neighbours with ``p`` in place of sample ``i`` (the one measured, where the
    other's outer neighbour is not).  The first and last two frames are never spikes.
    """
    P = np.asarray(positions, dtype=float)
    F, M = P.shape[:2]
    out = np.zeros((F, M), dtype=bool)
    if F < 5:
        return out
    mid = 0.5 * (P[:-2] + P[2:])  # frames 1 .. F-2: midpoint of the two neighbours
    dev = np.linalg.norm(P[1:-1] - mid, axis=-1)  # (F-2, M), NaN where any is missing
    seen = np.isfinite(dev)
    scale = np.full(M, np.nan)
    some = seen.any(0)
    scale[some] = np.nanmedian(dev[:, some], axis=0)
    p = mid[1:-1]  # frames 2 .. F-3
    left = np.linalg.norm(P[1:-3] - 0.5 * (P[:-4] + p), axis=-1)
    right = np.linalg.norm(P[3:-1] - 0.5 * (p + P[4:]), axis=-1)
    d = dev[1:-1]
    with np.errstate(invalid="ignore"):
        out[2:-2] = (d > SPIKE_FACTOR * scale) & (d > SPIKE_CONTRAST * np.fmax(left, right))
    return out
