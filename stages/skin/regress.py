"""Wide local regression of marker gaps (the default hole filling of the clean stage).

Per gap, the marker's coordinates in the local frame of its most rigid nearby
markers that stay visible through the gap are regressed (ridge) on theirs,
trained on the frames nearest the gap where the marker and those predictors
are measured: no complete frame of the capture is needed.  What it cannot
reach goes to the paper's local PCA passes (:mod:`mocapflow.stages.skin.fill`,
which also gives the measurements).

Every frame's rigid fit (Horn) is its own, so the fits of all the gaps of a chunk of
markers are made together, about :data:`_FRAMES_PER_FIT` frames per call
(:func:`_solve_gaps`): the same numbers as one call per gap, with ~40x fewer calls
(``ktk_kinematics_basket_sprint.c3d``, 3,678 frames with ~6,500 runs of holes, regressed
again in each of the gap filler's 6 local fills: 39,724 calls -> 966, a gap-protocol
case 44 -> 30 CPU-s whole process).  A frame's fit depends only on the marker, its
predictors and the frame, so it is made once and kept (:class:`_RigidFits`): the gaps
of one marker regressed frame by frame (runs halved while they lack predictors) share
most training frames (the same basket case: 13.3 M fits, 1.96 M distinct).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocapflow.stages.motion.absolute_orientation import absolute_orientation_batch
from mocapflow.stages.motion.contacts import true_runs
from mocapflow.stages.skin.predict import finite_rows, gather_samples

#: Predictors of the wide-neighbourhood regression: the marker's most rigid
#: nearby markers (smallest spread of their distance to it) visible through a gap.
REGRESSION_PREDICTORS = 32

#: A gap (or piece of one) is regressed only on at least this many predictors.
REGRESSION_MIN_PREDICTORS = 4

#: Nearest markers (reference pose) ranked by rigidity for the regression.
REGRESSION_POOL = 120

#: Ridge penalty of the regression (m², per training frame): about the
#: measurement noise variance, so directions the predictors hardly move in are
#: not fitted to noise.
REGRESSION_RIDGE = 1e-7

#: Training frames of one regression: those nearest the gap in time.
REGRESSION_TRAIN = 250

#: A run of holes with fewer usable predictors than this fraction of
#: ``n_predictors`` is split in halves (each half sees more predictors).
REGRESSION_SPLIT_FRACTION = 0.25

#: A regression needs at least half as many training frames as the holes it
#: fills, and never more than this: a marker measured in few frames (the inner
#: arm, the armpit) has long holes, over which a regression trained on a narrow
#: range of poses extrapolates badly; those go to the PCA passes.
REGRESSION_MIN_TRAIN = 100

#: Predictors are chosen so that at least this many training frames per
#: predictor remain (see :func:`choose_predictors`).
REGRESSION_FRAMES_PER_PREDICTOR = 4


def predictor_ranking(
    X: np.ndarray,
    reference: np.ndarray,
    markers: np.ndarray,
    *,
    pool: int = REGRESSION_POOL,
    min_frames: int = 30,
    max_frames: int = 300,
) -> list[np.ndarray]:
    """Candidate predictors of each marker, most rigid first.

    Parameters
    ----------
    X : (F, M, 3) float ndarray
        Measured positions, NaN where missing.
    reference : (M, 3) float ndarray
    markers : (n,) int ndarray
        Markers to rank candidates for.
    pool : int
        The ``pool`` markers nearest in the reference pose are ranked.
    min_frames : int
        Candidates measured together with the marker in fewer frames are dropped.
    max_frames : int
        The spread is measured on at most this many frames (evenly spaced).

    Returns
    -------
    list of (c,) int ndarray
        Per marker, candidates by increasing standard deviation of their
        distance to it over the frames where both are measured.
    """
    F = X.shape[0]
    sub = X[np.unique(np.linspace(0, F - 1, min(F, max_frames)).round().astype(int))]
    vis = finite_rows(sub)
    good = np.flatnonzero(np.isfinite(reference).all(1) & vis.any(0))
    need = max(3, int(min_frames * len(sub) / F))
    out = []
    for m in markers:
        d = np.linalg.norm(reference[good] - reference[m], axis=1)
        near = good[np.argsort(d, kind="stable")]
        near = near[near != m][:pool]
        dist = np.linalg.norm(sub[:, near] - sub[:, m:m + 1], axis=-1)  # (f, P)
        ok = np.isfinite(dist)
        cnt = ok.sum(0)
        d0 = np.where(ok, dist, 0.0)
        mean = d0.sum(0) / np.maximum(cnt, 1)
        sd = np.sqrt((np.where(ok, dist - mean, 0.0) ** 2).sum(0) / np.maximum(cnt, 1))
        sd[cnt < need] = np.inf
        order = np.argsort(sd, kind="stable")
        out.append(near[order[np.isfinite(sd[order])]])
    return out


def regress_gap(
    X: np.ndarray,
    visible: np.ndarray,
    marker: int,
    predictors: np.ndarray,
    runs: list[tuple[int, int]],
    reference: np.ndarray,
    *,
    ridge: float = REGRESSION_RIDGE,
    max_train: int = REGRESSION_TRAIN,
    offset_correction: bool = False,
    edge: int = 6,
) -> np.ndarray | None:
    """Estimate gaps of a marker by ridge regression on predictors visible through them.

    Every frame is brought into the predictors' local frame (rigid fit of their
    reference positions, origin at the marker's reference position); the
    marker's local coordinates are regressed on the predictors' (centred, ridge
    penalty ``ridge × n``) over the ``max_train`` frames nearest the gaps where
    the marker and every predictor are measured.

    Parameters
    ----------
    X : (F, M, 3) float ndarray
        Measured positions, NaN where missing.
    visible : (F, M) bool ndarray
        ``isfinite(X).all(-1)``.
    marker : int
    predictors : (k,) int ndarray
        Visible through every gap.
    runs : list of (int, int)
        The gaps (half-open frame ranges, in time order).
    reference : (M, 3) float ndarray
    ridge : float
        Ridge penalty per training frame (m²).
    max_train : int
        Training frames (nearest in time to the gaps).
    offset_correction : bool
        Add the model's mean residual over the ``edge`` measured frames at each
        end of a gap, blended linearly across it (one end: constant).
    edge : int

    Returns
    -------
    (N, 3) float ndarray
        The gaps' frames in order; None with too few training frames or a
        predictor missing in a gap.
    """
    problem = _gap_problem(X, visible, marker, predictors, runs, reference,
                           max_train=max_train)  # fmt: skip
    if problem is None:
        return None
    return _solve_gaps(X, [problem], ridge=ridge, offset_correction=offset_correction,
                       edge=edge)[0]


@dataclass
class _GapProblem:
    """One regression of :func:`regress_gap` up to its rigid fits: the marker, its
    predictors ``S (k,)``, the gaps, the training frames ``train (n,)`` followed by the
    gaps' frames in ``frames``, and the predictors' positions there ``P (len(frames), k,
    3)``, to be fitted by ``local`` (their reference positions about the marker's)."""

    marker: int
    S: np.ndarray
    runs: list[tuple[int, int]]
    train: np.ndarray
    frames: np.ndarray
    P: np.ndarray
    local: np.ndarray


def _gap_problem(X: np.ndarray, visible: np.ndarray, marker: int, predictors: np.ndarray,
                 runs: list[tuple[int, int]], reference: np.ndarray, *, max_train: int,
                 trainable: dict | None = None) -> _GapProblem | None:  # fmt: skip
    """The frames and predictor positions of :func:`regress_gap` (None: too few training
    frames, or a predictor missing in a gap).  ``trainable``: the frames where the marker
    and its predictors are all measured, kept per predictor set by a caller regressing
    many gaps of one marker."""
    S = np.asarray(predictors)
    gap = np.concatenate([np.arange(a, b) for a, b in runs])
    key = _set_key(marker, S)
    train = None if trainable is None else trainable.get(key)
    if train is None:
        train = np.flatnonzero(visible[:, marker] & visible[:, S].all(1))
        if trainable is not None:
            trainable[key] = train
    if len(train) < max(10, 3 * len(S) // 2) or not visible[gap][:, S].all():
        return None
    if len(train) > max_train:
        # the max_train nearest the centre (ties: the earlier frame) lie within
        # max_train places of it in ascending train: sort only those
        centre = 0.5 * (runs[0][0] + runs[-1][1] - 1)
        at = int(np.searchsorted(train, centre))
        near = train[max(0, at - max_train):at + max_train]
        near = near[np.argsort(np.abs(near - centre), kind="stable")[:max_train]]
        train = np.sort(near)
    frames = np.concatenate([train, gap])
    P = gather_samples(X, frames[:, None], S[None])
    local = np.broadcast_to(reference[S] - reference[marker], P.shape)
    return _GapProblem(int(marker), S, runs, train, frames, P, local)


#: Frames of :func:`_solve_gaps`' rigid fits per call of
#: :func:`~mocapflow.stages.motion.absolute_orientation.absolute_orientation_batch`: a few MB.
_FRAMES_PER_FIT = 20_000


def _set_key(marker: int, predictors: np.ndarray) -> tuple[int, bytes]:
    """A marker and its predictor set as a dictionary key (what a frame's rigid fit and
    training frames depend on besides the frame)."""
    return int(marker), np.asarray(predictors, dtype=np.int64).tobytes()


#: Most rigid fits a :class:`_RigidFits` keeps (12 floats each: about 40 MB).
_MOST_KEPT_FITS = 400_000


class _RigidFits:
    """The rigid fits :func:`_solve_gaps` has made, per marker and predictor set: a
    frame's fit depends only on them (its local positions are the predictors' reference
    positions about the marker's), so gaps sharing training frames (a marker's runs
    halved to single frames, the gap filler's validation copies shifted by a frame or
    two) fit each frame once.  ``store[(marker, S)]``: its fitted frames ``(n,)``
    ascending, ``R (n, 3, 3)`` and ``t (n, 3)``.  Past :data:`_MOST_KEPT_FITS` the sets
    the current gaps do not use are dropped (the same numbers: each fit is its own)."""

    def __init__(self, most: int = _MOST_KEPT_FITS) -> None:
        self.store: dict[tuple[int, bytes], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.most = most
        self.size = 0
        self.made = 0  # fits computed (the rest were looked up)

    @staticmethod
    def key(pr: _GapProblem) -> tuple[int, bytes]:
        return _set_key(pr.marker, pr.S)

    def missing(self, key: tuple[int, bytes], frames: np.ndarray) -> np.ndarray:
        """The ``frames`` (ascending, unique) not fitted yet for ``key``."""
        have = self.store.get(key)
        if have is None:
            return frames
        return frames[~np.isin(frames, have[0], assume_unique=True)]

    def make_room(self, n: int, keep: set) -> None:
        """Drop the sets not in ``keep`` when ``n`` more fits would pass :attr:`most`."""
        if self.size + n <= self.most:
            return
        for key in [k for k in self.store if k not in keep]:
            self.size -= len(self.store.pop(key)[0])

    def add(self, key: tuple[int, bytes], frames: np.ndarray, R: np.ndarray,
            t: np.ndarray) -> None:  # fmt: skip
        """Keep the fits ``R (n, 3, 3)``, ``t (n, 3)`` of ``frames (n,)`` (new to ``key``)."""
        self.made += len(frames)
        self.size += len(frames)
        have = self.store.get(key)
        if have is not None:
            frames = np.concatenate([have[0], frames])
            order = np.argsort(frames, kind="stable")
            frames = frames[order]
            R = np.concatenate([have[1], R])[order]
            t = np.concatenate([have[2], t])[order]
        self.store[key] = frames, R, t

    def get(self, key: tuple[int, bytes], frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        have, R, t = self.store[key]
        at = np.searchsorted(have, frames)
        return R[at], t[at]


def _solve_gaps(X: np.ndarray, problems: list[_GapProblem], *, ridge: float,
                offset_correction: bool, edge: int = 6,
                fits: _RigidFits | None = None) -> list[np.ndarray | None]:  # fmt: skip
    """The estimates of :func:`regress_gap` for many ``problems`` (:func:`_gap_problem`):
    the rigid fits each frame needs that ``fits`` (:class:`_RigidFits`, kept by the
    caller between calls) does not hold yet, those with as many predictors in one call
    (each frame's fit is its own: the same numbers as one call per problem), then each
    ridge regression.  None where a frame's predictors are degenerate (collinear)."""
    fits = _RigidFits() if fits is None else fits
    need: dict[tuple[int, bytes], list] = {}
    for pr in problems:
        key = fits.key(pr)
        if key in need:
            need[key][1].append(pr.frames)
        else:
            need[key] = [pr, [pr.frames]]
    todo = []
    for key, (pr, frames) in need.items():
        new = fits.missing(key, np.unique(np.concatenate(frames)))
        if len(new):
            todo.append((key, pr, new))
    fits.make_room(sum(len(new) for _, _, new in todo), set(need))
    by_k: dict[int, list[int]] = {}
    for j, (_, pr, _) in enumerate(todo):
        by_k.setdefault(len(pr.S), []).append(j)
    for idx in by_k.values():
        batch: list[int] = []
        n = 0
        for jj, j in enumerate(idx):
            batch.append(j)
            n += len(todo[j][2])
            if n < _FRAMES_PER_FIT and jj + 1 < len(idx):
                continue
            local, P = [], []
            for b in batch:
                _, pr, new = todo[b]
                P.append(gather_samples(X, new[:, None], pr.S[None]))
                local.append(np.broadcast_to(pr.local[0], P[-1].shape))
            R, t = absolute_orientation_batch(np.concatenate(local), np.concatenate(P))
            cut = np.cumsum([0, *[len(todo[b][2]) for b in batch]])
            for b, lo, hi in zip(batch, cut, cut[1:]):
                fits.add(todo[b][0], todo[b][2], R[lo:hi], t[lo:hi])
            batch, n = [], 0
    return [_ridge_estimate(X, pr, *fits.get(fits.key(pr), pr.frames), ridge=ridge,
                            offset_correction=offset_correction, edge=edge)
            for pr in problems]  # fmt: skip


def _ridge_estimate(X: np.ndarray, pr: _GapProblem, R: np.ndarray, t: np.ndarray, *,
                    ridge: float, offset_correction: bool, edge: int) -> np.ndarray | None:
    """The ridge regression of :func:`regress_gap` given the frames' rigid fits ``R (N, 3,
    3)``, ``t (N, 3)`` (None where one is degenerate)."""
    if not np.isfinite(R).all():
        return None  # degenerate (collinear) predictor set in some frame
    train, runs, n = pr.train, pr.runs, len(pr.train)
    Z = np.matmul(pr.P - t[:, None], R).reshape(len(pr.frames), -1)  # R^T (x - t), row-wise
    y = np.matmul((X[train, pr.marker] - t[:n])[:, None], R[:n])[:, 0]
    mz, my = Z[:n].mean(0), y.mean(0)
    Zc = Z - mz
    A = Zc[:n].T @ Zc[:n]
    A.flat[::len(A) + 1] += ridge * n  # the diagonal
    W = np.linalg.solve(A, Zc[:n].T @ (y - my))
    pred = Zc[n:] @ W + my
    if offset_correction:
        res = y - (Zc[:n] @ W + my)
        i = 0
        for a, b in runs:
            left = (train >= a - edge) & (train < a)
            right = (train >= b) & (train < b + edge)
            s = ((np.arange(a, b) - a + 1) / (b - a + 1))[:, None]
            if left.any() and right.any():
                pred[i:i + b - a] += res[left].mean(0) * (1 - s) + res[right].mean(0) * s
            elif left.any() or right.any():
                pred[i:i + b - a] += res[left | right].mean(0)
            i += b - a
    return np.matmul(R[n:], pred[..., None])[..., 0] + t[n:]


def _min_train(n_gap: int) -> int:
    """Fewest training frames for a regression over ``n_gap`` frames of holes:
    half the gap, between 20 and :data:`REGRESSION_MIN_TRAIN`."""
    return int(max(20, min(REGRESSION_MIN_TRAIN, n_gap // 2)))


def choose_predictors(
    visible: np.ndarray,
    marker: int,
    candidates: np.ndarray,
    *,
    n_predictors: int = REGRESSION_PREDICTORS,
    frames_per_predictor: int = REGRESSION_FRAMES_PER_PREDICTOR,
    min_frames: int = 20,
) -> np.ndarray:
    """Predictors for one regression, so that it keeps enough training frames.

    Candidates are taken in order; one that would leave fewer than
    ``max(min_frames, frames_per_predictor × k)`` frames where the marker and
    all ``k`` chosen predictors are measured is skipped.  Without this, many
    predictors each missing now and then leave no training frame (the local
    version of the whole-body PCA's need for complete frames).

    Parameters
    ----------
    visible : (F, M) bool ndarray
    marker : int
    candidates : (c,) int ndarray
        Visible through the gap, in order of preference.
    n_predictors, frames_per_predictor, min_frames : int

    Returns
    -------
    (k,) int ndarray, k <= n_predictors
    """
    cur = visible[:, marker].copy()
    chosen: list[int] = []
    for j in candidates:
        new = cur & visible[:, j]
        if np.count_nonzero(new) >= max(min_frames, frames_per_predictor * (len(chosen) + 1)):
            chosen.append(int(j))
            cur = new
            if len(chosen) == n_predictors:
                break
    return np.asarray(chosen, dtype=np.int64)


def regression_estimates(
    X: np.ndarray,
    marker: int,
    candidates: np.ndarray,
    holes: np.ndarray,
    reference: np.ndarray,
    *,
    visible: np.ndarray | None = None,
    n_predictors: int = REGRESSION_PREDICTORS,
    min_predictors: int = REGRESSION_MIN_PREDICTORS,
    ridge: float = REGRESSION_RIDGE,
    max_train: int = REGRESSION_TRAIN,
    max_span: int | None = None,
    offset_correction: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Regression estimates of one marker's holes (see :func:`regress_gap`).

    Each run of holes is regressed on the first ``n_predictors`` candidates
    visible through it (skipping those that would leave too few training
    frames, :func:`choose_predictors`).  Consecutive runs within ``max_span`` frames share one
    regression while at least ``n_predictors`` of the first ``2 n_predictors``
    candidates stay visible through all of them.  A run with fewer than
    ``REGRESSION_SPLIT_FRACTION × n_predictors`` usable candidates is halved
    until it has them; a single frame needs ``min_predictors`` (frames that
    still lack them are left out).  A regression needs training frames for
    at least half its holes (at most :data:`REGRESSION_MIN_TRAIN`).

    Parameters
    ----------
    X : (F, M, 3) float ndarray
        Measured positions, NaN where missing.
    marker : int
    candidates : (c,) int ndarray
        Predictors in order of preference (:func:`predictor_ranking`).
    holes : (F,) bool ndarray
        Frames to estimate.
    reference : (M, 3) float ndarray
    visible : (F, M) bool ndarray, optional
        ``isfinite(X).all(-1)`` if given (saves recomputing it).
    n_predictors, min_predictors : int
    ridge : float
    max_train : int
    max_span : int, optional
        Longest stretch of frames sharing one regression (default ``max_train // 2``).
    offset_correction : bool

    Returns
    -------
    frames : (N,) int ndarray
    estimates : (N, 3) float ndarray
    """
    vis = finite_rows(X) if visible is None else visible
    kw = {"n_predictors": n_predictors, "min_predictors": min_predictors, "ridge": ridge,
          "max_train": max_train, "max_span": max_span, "offset_correction": offset_correction}
    return _markers_estimates(X, vis, [marker], [candidates], [holes], reference, **kw)[0]


def _groups(vis: np.ndarray, holes: np.ndarray, top: np.ndarray, *, n_predictors: int,
            span: int) -> list[list[tuple[int, int]]]:
    """The runs of ``holes (F,)`` grouped as :func:`regression_estimates` regresses them
    together (within ``span`` frames, ``n_predictors`` of ``top`` visible through all)."""
    groups: list[list[tuple[int, int]]] = []
    cur: list[tuple[int, int]] = []
    cur_v = np.ones(len(top), bool)
    for a, b in true_runs(holes):
        v = vis[a:b][:, top].all(0)
        if cur and b - cur[0][0] <= span and (cur_v & v).sum() >= n_predictors:
            cur.append((a, b))
            cur_v &= v
            continue
        if cur:
            groups.append(cur)
        cur, cur_v = [(a, b)], v
    if cur:
        groups.append(cur)
    return groups


def _markers_estimates(
    X: np.ndarray, vis: np.ndarray, markers: list[int], rankings: list[np.ndarray],
    holes: list[np.ndarray], reference: np.ndarray, *, n_predictors: int, min_predictors: int,
    ridge: float, max_train: int, max_span: int | None, offset_correction: bool,
) -> list[tuple[np.ndarray, np.ndarray]]:  # fmt: skip
    """:func:`regression_estimates` of several markers (``holes``: each one's ``(F,)``),
    their rigid fits batched (:func:`_solve_gaps`, about :data:`_FRAMES_PER_FIT` frames
    at a time): first every group of runs, then the runs of the groups that could not be
    regressed together, one by one (halved while they lack predictors), as
    :func:`regression_estimates` describes."""
    span = max_train // 2 if max_span is None else max_span
    frames: list[list[np.ndarray]] = [[] for _ in markers]
    ests: list[list[np.ndarray]] = [[] for _ in markers]
    stacks: list[list[tuple[int, int]]] = [[] for _ in markers]
    jobs: list[tuple[int, list[tuple[int, int]]]] = []
    problems: list[_GapProblem] = []
    pending = 0  # frames of the pending problems
    fits = _RigidFits()

    def solve(flush: bool) -> None:
        """Solve the pending problems (when they hold enough frames, or ``flush``): an
        estimate goes to its marker, a failed group's runs to its stack."""
        nonlocal pending
        if not problems or (not flush and pending < _FRAMES_PER_FIT):
            return
        for (i, g), e in zip(jobs, _solve_gaps(X, problems, ridge=ridge, fits=fits,
                                               offset_correction=offset_correction)):
            if e is not None:
                frames[i].append(np.concatenate([np.arange(a, b) for a, b in g]))
                ests[i].append(e)
            elif len(g) > 1:
                stacks[i] += g
        jobs.clear()
        problems.clear()
        pending = 0

    def add(i: int, g: list[tuple[int, int]], pr: _GapProblem) -> None:
        nonlocal pending
        jobs.append((i, g))
        problems.append(pr)
        pending += len(pr.frames)
        solve(False)

    for i, (marker, cand, h) in enumerate(zip(markers, rankings, holes)):
        c = np.asarray(cand, dtype=np.int64)
        for g in _groups(vis, h, c[:2 * n_predictors], n_predictors=n_predictors, span=span):
            pr = None
            if len(g) > 1:
                ok = np.ones(len(c), bool)
                for a, b in g:
                    ok &= vis[a:b][:, c].all(0)
                n_gap = sum(b - a for a, b in g)
                S = choose_predictors(vis, marker, c[ok], n_predictors=n_predictors,
                                      min_frames=_min_train(n_gap))
                if len(S) >= min_predictors:
                    pr = _gap_problem(X, vis, marker, S, g, reference, max_train=max_train)
            if pr is None:
                stacks[i] += g
            else:
                add(i, g, pr)
    solve(True)
    want = max(min_predictors, int(REGRESSION_SPLIT_FRACTION * n_predictors))
    for i, (marker, cand) in enumerate(zip(markers, rankings)):
        c = np.asarray(cand, dtype=np.int64)
        stack = stacks[i]
        chosen: dict[tuple[bytes, int], np.ndarray] = {}  # the same runs' candidates
        trainable: dict = {}
        while stack:
            a, b = stack.pop()
            through = vis[a:b][:, c].all(0)
            key = through.tobytes(), _min_train(b - a)
            S = chosen.get(key)
            if S is None:
                S = chosen[key] = choose_predictors(vis, marker, c[through],
                                                    n_predictors=n_predictors,
                                                    min_frames=key[1])  # fmt: skip
            if len(S) < (min_predictors if b - a == 1 else want):
                if b - a > 1:
                    h = (a + b) // 2
                    stack += [(a, h), (h, b)]
                continue
            pr = _gap_problem(X, vis, marker, S, [(a, b)], reference, max_train=max_train,
                              trainable=trainable)  # fmt: skip
            if pr is not None:
                add(i, [(a, b)], pr)
    solve(True)
    return [(np.concatenate(f), np.concatenate(e)) if f else
            (np.zeros(0, np.int64), np.zeros((0, 3))) for f, e in zip(frames, ests)]


def _regress_chunk(item: tuple) -> tuple[np.ndarray, ...]:
    X, markers, holes, reference, kw = item
    X = np.ascontiguousarray(X)  # regress_gap gathers from it as (F * M, 3) rows
    vis = np.asfortranarray(finite_rows(X))  # one marker's frames contiguous
    ranking = predictor_ranking(X, reference, markers, pool=kw.pop("pool"))
    kw.setdefault("max_span", None)
    out = _markers_estimates(X, vis, [int(m) for m in markers], ranking,
                             [holes[:, m] for m in markers], reference, **kw)
    fs = [f for f, _ in out]
    ms = [np.full(len(f), m, dtype=np.int64) for m, (f, _) in zip(markers, out)]
    es = [e for _, e in out]
    if not fs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(fs), np.concatenate(ms), np.concatenate(es)
