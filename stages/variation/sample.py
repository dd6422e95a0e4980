"""Sampling variants from the learned DBN and noise baselines (Lau et al. 2009, §6 and §8).

Sampling (the ``sample`` stage, :class:`Sampler`)
    The prior network is sampled in topological order (each node Gaussian
    with the kernel-regression mean and variance given its sampled parents),
    giving frames 0 and 1; then the transition network is unrolled: every DOF
    of frame ``t+2`` gets ``x[t+1] + Δ`` with ``Δ`` drawn from its kernel
    regression on frames ``t`` and ``t+1``.  ``sigma`` scales every standard
    deviation: ``sigma = 0`` gives the mean motion.  Spatial and temporal
    variation come out of the same draws: the transition network is second
    order (it regresses the delta on position and velocity), so a variant's
    speed varies as its poses do; the ``sample`` stage also plays each variant
    at a time warp drawn from the inputs' warps (:mod:`~.warp`, learned by
    ``learn(time_warp=True)``), and cyclic variants are whole cycles by default
    (lengths varying as the inputs').  Streams have any length;
    for cyclic inputs they continue through cycle after cycle.  Several
    variants are sampled together (vectorised over variants and DOFs; the
    nearest-instance search is a batched matrix product + ``argpartition``).
    ``noise_time`` (an addition; ``None`` is the paper): the standard-normal
    draws of successive frames form an AR(1) process with that correlation
    time, scaled so that the variance accumulated over many frames equals
    white noise's: the velocity noise is no longer white (white noise on the
    delta is what makes variants of captured takes ~10x jerkier than the
    inputs) and ``sigma`` keeps its meaning.
    Cycle phase (cyclic models, :func:`~.training.with_phase`): cyclic
    variants start where the cycle phase passes 0, as every input cycle
    does; ``loop`` cuts one stream into consecutive cycles
    (:meth:`Sampler.cycles`).  The ``predicted`` output is the network's
    mean of every frame given the sampled ones before it.
    Crowds: :meth:`Sampler.stream` yields frame by frame for any number of
    agents; ``Sampler(model, window=W)`` restricts each agent's neighbour
    search to the ``W`` instances nearest in cycle phase and selects the ``k``
    nearest on exponents rounded to 1/512 (an approximation, ~4x faster on the
    walk at ``W = 64``: one-step mean within 0.04 of the exact std at the
    median; ``None`` is the exact search).
Noise baselines (Lau §8, the ``sample_noise`` stage)
    ``strawman``: an input clip, time-warped by a random smooth monotone warp,
    plus Gaussian-smoothed white noise.  ``perlin``: an input clip plus 1-D
    Perlin gradient noise per DOF.  Amplitudes are in units of each DOF's
    standard deviation; :func:`matched_amplitude` finds the amplitude at which
    a baseline's DTW distance to the inputs equals that of our variants
    (the paper's amplitude matching).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator
from typing import Any, Literal

import numpy as np
from scipy.ndimage import gaussian_filter1d

from mocapflow.pipeline import Context, stage
from mocapflow.stages.variation.clips import Clips, clips_to_motions, flatten_clips
from mocapflow.stages.variation.kernel import kernel_regression
from mocapflow.stages.variation.model import VariationModel
from mocapflow.stages.variation.search import DAG
from mocapflow.stages.variation.training import (
    CYCLE_PHASE,
    INTERNAL_DOFS,
    PHASE,
    phase_columns,
    prior_data,
    standardization,
    transition_data,
)
from mocapflow.stages.variation.warp import apply_time_warp, sample_time_warp

__all__ = [
    "SampleError",
    "Sampler",
    "chain_origins",
    "input_range",
    "matched_amplitude",
    "perlin_noise",
    "sample",
    "sample_noise",
    "strawman_noise",
]


AGENT_BLOCK = 32
"""Agents per transition block: the ``(D, block, N)`` kernel tables of one block stay in
cache (1,000 agents of the 54-DOF walk in one block: 3x slower per agent-frame)."""

EXPONENT_STEPS = 512.0
"""Crowd mode: the kernel exponents are rounded to 1 / 512 for the nearest-instance
selection (weights within 0.2 % of the ``k``-th count as ties)."""

_QMIN = -32768  # the int16 floor of the rounded exponents


class SampleError(ValueError):
    """Bad sampling request (length, count, sigma)."""


class Sampler:
    """Precomputed tables for sampling a :class:`VariationModel`, and its samplers.

    The neighbour search of the transition network runs in single precision
    (the kernel exponents ``c (|q|² − 2 q·u + |u|²)`` as one batched matrix
    product over DOFs, the ``k`` nearest by a partition, :meth:`nearest`, the
    kernel sums as a second product, :meth:`kernel_sums`); the sampled state is
    kept in double precision.

    Parameters
    ----------
    model : VariationModel
    window : int, optional
        Cyclic models (with the cycle phase DOFs): each agent searches its
        ``k`` nearest instances among the ``window`` training instances nearest
        to it in cycle phase (rounded out to a bin of agents sharing one slice
        of the phase-sorted bank), instead of among all of them, selected on
        rounded exponents (:meth:`nearest` ``quantized``) — the crowd mode,
        several times faster; ``None`` (default): all instances (exact).
    """

    def __init__(self, model: VariationModel, *, window: int | None = None):
        self.model = model
        clips = model.clips
        p = model.params
        self.D = D = clips.n_dofs
        trajs = clips.trajectories
        self.stats = standardization(trajs)
        td = transition_data(
            trajs,
            self.stats,
            cyclic=bool(p["cyclic"]),
            k=2,
            kernel_width=p["kernel_width"],
            min_std=p["min_std"],
            velocity_weight=p["velocity_weight"],
            exclusion=0,
        )
        pd = prior_data(
            trajs,
            self.stats,
            k=2,
            kernel_width=p["kernel_width"],
            min_std=p["min_std"],
            window=p["prior_window"],
            exclusion=0,
        )
        self.ms = float(p["min_std"])
        self.vw = float(p["velocity_weight"])
        self.ratio = td.ratio
        N = td.F.shape[0]
        self.k = min(int(p["k"]), N)
        # transition tables: per DOF the padded feature columns of the bank [F | V]
        bank = np.concatenate([td.F, td.V], axis=1)  # (N, 3D)
        cols = [[D + i, 2 * D + i, *model.transition_parents[i]] for i in range(D)]
        pmax = max(len(c) for c in cols)
        self.cols = np.zeros((D, pmax), dtype=np.int64)
        self.wmask = np.zeros((D, pmax), dtype=np.float32)
        for i, c in enumerate(cols):
            self.cols[i, : len(c)] = c
            self.wmask[i, : len(c)] = 1.0
        U = (bank[:, self.cols] * self.wmask).astype(np.float32)  # (N, D, pmax)
        # the kernel exponent e = −d² / 2h² = c (|q|² − 2 q·u + |u|²) with c = −1 / 2h²,
        # per DOF, as one product: the query [q, 1, c|q|²] times the table
        # [−2c u; c|u|²; 1] (pmax + 2 rows per instance)
        self.c = (-0.5 / np.maximum(model.transition_bandwidth**2, 1e-30)).astype(np.float32)
        Ut = U.transpose(1, 2, 0) * (-2.0 * self.c)[:, None, None]  # (D, pmax, N)
        Ac = (U * U).sum(axis=-1).T * self.c[:, None]  # (D, N)
        self.Ue = np.ascontiguousarray(np.concatenate(
            [Ut, Ac[:, None, :], np.ones_like(Ac)[:, None, :]], axis=1), dtype=np.float32)
        Y = td.Y.T  # (D, N)
        Zc = td.F[:, D:].T  # (D, N) standardised x[t+1]
        #: (D,) offset retention per DOF: the calibrated ``retention_dof`` of the model
        #: (:func:`~.scores.transition_node_retention`), else the ``half_life`` one
        self.retention = np.broadcast_to(
            np.asarray(p.get("retention_dof", p.get("retention", 1.0)), dtype=np.float64),
            (D,)).copy()
        # Σw·Δ, Σw·Δ², Σw·z[t+1], Σw in one product
        self.YYZ = np.ascontiguousarray(
            np.stack([Y, Y**2, Zc, np.ones_like(Y)], axis=-1).astype(np.float32))  # (D, N, 4)
        # prior
        self.Zp = pd.Z
        self.kp = min(int(p["k"]), pd.Z.shape[0])
        dag = DAG(2 * D)
        for v, ps in enumerate(model.prior_parents):
            for u in ps:
                dag.add(u, v)
        self.order = dag.order()
        if len(self.order) != 2 * D:
            raise SampleError("prior network of the model has a cycle")
        names = clips.labels
        self.phase_cols = phase_columns(names)
        #: the model has the cycle phase (cos, sin) of cyclic clips
        self.cycle_phase = all(n in names for n in CYCLE_PHASE)
        self.ends_at_phase = PHASE in names
        self.window = None
        if self.cycle_phase:  # cycle phase of every instance's frame t+1
            self.inst_phase = self.cycle_phase_of(td.F[:, D:] * self.stats["std"]
                                                  + self.stats["mean"])
        if window is not None:
            if not window >= 1:
                raise SampleError(f"window must be a number of instances >= 1, got {window}")
            if self.cycle_phase and int(window) < N:
                self._phase_bank(int(window))

    def _phase_bank(self, window: int) -> None:
        """Tables of the crowd mode: the bank sorted by cycle phase, wrapped by a window."""
        N = self.inst_phase.shape[0]
        order = np.argsort(self.inst_phase, kind="stable")
        self.window = window
        self.win_phase = self.inst_phase[order]
        self.stride = max(1, window // 4)
        self.L = L = min(window + self.stride, N)
        # per bin of agents the contiguous tables of its slice (matmul needs them contiguous)
        starts = np.arange(0, N, self.stride)
        sl = order[(starts[:, None] + np.arange(L)[None, :]) % N]  # (bins, L)
        self.Uw = [np.ascontiguousarray(self.Ue[:, :, i]) for i in sl]
        self.YYZw = [np.ascontiguousarray(self.YYZ[:, i]) for i in sl]

    # ------------------------------------------------------------------ the networks
    def sample_prior(
        self, rng: np.random.Generator, count: int, sigma: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Frames 0 and 1 from the prior network, standardised.

        Returns
        -------
        z, mean : (count, 2D) float ndarray
            The draws, and each node's conditional mean given its sampled parents.
        """
        Z = self.Zp
        N = Z.shape[0]
        z = np.zeros((count, 2 * self.D))
        mean = np.zeros((count, 2 * self.D))
        for v in self.order:
            ps = self.model.prior_parents[v]
            y = Z[:, v]
            if not ps:
                mu = np.full(count, y.mean())
                var = np.full(count, y.var() * N / max(N - 1, 1) + self.ms**2)
            else:
                d2 = ((z[:, None, ps] - Z[None, :, ps]) ** 2).sum(axis=-1)  # (B, N)
                kk = self.kp
                if kk < N:
                    idx = np.argpartition(d2, kk - 1, axis=-1)[:, :kk]
                else:
                    idx = np.broadcast_to(np.arange(N), d2.shape)
                mu, var = kernel_regression(
                    np.take_along_axis(d2, idx, axis=-1),
                    y[idx],
                    h2=self.model.prior_bandwidth[v] ** 2,
                    min_std=self.ms,
                )
            mean[:, v] = mu
            z[:, v] = mu + sigma * np.sqrt(var) * rng.standard_normal(count)
        return z, mean

    def transition(self, zp: np.ndarray, zc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The transition network's conditional Gaussian of the next frame (Lau Eq. 5–6).

        Agents are taken :data:`AGENT_BLOCK` at a time, so that the
        ``(D, block, N)`` kernel tables stay in cache (:meth:`kernel_sums`); in
        the crowd mode (``window``) the agents are first grouped by the phase
        slice of the bank they search.

        Parameters
        ----------
        zp, zc : (B, D) float ndarray
            Frames ``t`` and ``t+1``, standardised.

        Returns
        -------
        mean : (B, D) float ndarray
            Mean of frame ``t+2`` (standardised): ``x[t+1]`` plus the kernel mean
            of the delta, with the offset retention ``λ``.
        std : (B, D) float ndarray
            Standard deviation of frame ``t+2`` (standardised units).
        """
        B = zp.shape[0]
        if self.window is not None:  # crowd mode: agents sorted by the start of their window
            N = self.win_phase.shape[0]
            ph = self.cycle_phase_of(zc * self.stats["std"] + self.stats["mean"])
            first = (np.searchsorted(self.win_phase, ph) - self.window // 2) % N
            bins = first // self.stride
            agents = np.argsort(bins, kind="stable")
            bins = bins[agents]
            cut = np.flatnonzero(np.diff(bins)) + 1
            groups = [(int(bins[lo]), lo, hi) for lo, hi in zip(np.r_[0, cut], np.r_[cut, B])]
            zp, zc = zp[agents], zc[agents]
        else:
            groups = [(None, 0, B)]
        vscale = self.vw / self.ratio
        g = np.concatenate([zp, zc, (zc - zp) * vscale], axis=1).astype(np.float32)  # (B, 3D)
        q = (g[:, self.cols] * self.wmask).transpose(1, 0, 2)  # (D, B, pmax)
        qq = np.einsum("dbp,dbp->db", q, q) * self.c[:, None]
        qa = np.concatenate([q, np.ones_like(qq)[..., None], qq[..., None]], axis=-1)
        s = np.empty((self.D, B, 4))
        step = AGENT_BLOCK
        for b, lo, hi in groups:
            U, YYZ = (self.Ue, self.YYZ) if b is None else (self.Uw[b], self.YYZw[b])
            for c0 in range(lo, hi, step):
                c1 = min(c0 + step, hi)
                s[:, c0:c1] = self.kernel_sums(qa[:, c0:c1], U, YYZ, quantized=b is not None)
        sw = s[..., 3]
        mu = s[..., 0] / sw
        var = np.maximum(s[..., 1] / sw - mu * mu, 0.0) + self.ms * self.ms
        mean = zc + mu.T * self.ratio
        lam = self.retention
        if np.any(lam < 1.0):
            mean += (lam - 1.0) * (zc - (s[..., 2] / sw).T)
        std = np.sqrt(var).T * self.ratio
        if self.window is not None:  # back to the callers' order
            back = np.empty_like(agents)
            back[agents] = np.arange(B)
            mean, std = mean[back], std[back]
        return mean, std

    def kernel_sums(
        self, qa: np.ndarray, U: np.ndarray, YYZ: np.ndarray, *, quantized: bool = False
    ) -> np.ndarray:
        """Kernel-weighted sums over each query's ``k`` nearest instances (Lau Eq. 6).

        Parameters
        ----------
        qa : (D, b, pmax + 2) float32 ndarray
            Per DOF the agents' padded query features, then ``1`` and ``c|q|²``.
        U : (D, pmax + 2, n) float32 ndarray
            The matching slice of the instance table (:attr:`Ue`, :attr:`Uw`).
        YYZ : (D, n, 4) float32 ndarray
            The instances' ``Δ``, ``Δ²``, ``z[t+1]`` and ``1``.
        quantized : bool
            The selection of :meth:`nearest` (the crowd mode).

        Returns
        -------
        (D, b, 4) float ndarray
            ``Σw·Δ, Σw·Δ², Σw·z[t+1], Σw`` with ``w = exp(−d² / 2h²)`` over the
            ``k`` nearest instances (ties included).
        """
        e = qa @ U  # (D, b, n): the kernel exponents, <= 0
        n = e.shape[-1]
        k = min(self.k, n)
        mask = self.nearest(e, k, quantized=quantized)
        w = np.exp(e)  # (a masked exp is several times slower than exp and product)
        w *= mask
        sums = w @ YYZ
        # rows whose weights underflowed (every selected instance far): again with the
        # exponents shifted by their largest, which cancels in the ratios
        far = sums[..., 3] < 1e-25
        if far.any():
            ef = e[far]
            wf = np.exp(ef - ef.max(axis=-1, keepdims=True)) * mask[far]
            sums[far] = np.einsum("rn,rnc->rc", wf, YYZ[np.nonzero(far)[0]])
        return sums

    @staticmethod
    def nearest(e: np.ndarray, k: int, *, quantized: bool = False) -> np.ndarray:
        """Mask of the ``k`` largest kernel exponents along the last axis (ties included).

        Parameters
        ----------
        e : (..., n) float32 ndarray
            Kernel exponents ``−d² / 2h²`` (≤ 0).
        k : int
            ``1 ≤ k ≤ n``.
        quantized : bool
            Select on the exponents rounded up to multiples of
            ``1 /`` :data:`EXPONENT_STEPS` (an int16 partition): the mask is the
            exact one plus the exponents within one step below the ``k``-th.
            Rows whose ``k``-th exponent is below ``−32767 / EXPONENT_STEPS``
            are selected exactly.

        Returns
        -------
        (..., n) bool ndarray
        """
        n = e.shape[-1]
        if not quantized:
            return e >= np.partition(e, n - k, axis=-1)[..., n - k : n - k + 1]
        qe = np.empty(e.shape, dtype=np.int16)  # clamped, then rounded towards 0 (up)
        np.multiply(np.maximum(e, _QMIN / EXPONENT_STEPS), EXPONENT_STEPS, out=qe,
                    casting="unsafe")
        thr = np.partition(qe, n - k, axis=-1)[..., n - k : n - k + 1]
        mask = qe >= thr
        far = thr[..., 0] <= _QMIN + 1
        if far.any():
            mask[far] = Sampler.nearest(e[far], k)
        return mask

    # ------------------------------------------------------------------ samplers
    def stream(
        self,
        rng: np.random.Generator,
        *,
        count: int = 1,
        sigma: float = 1.0,
        noise_time: float | None = None,
        predicted: bool = False,
    ) -> Iterator[np.ndarray] | Iterator[tuple[np.ndarray, np.ndarray]]:
        """Endless frame-by-frame streams of ``count`` agents (the unrolled network, Lau §6).

        Frames 0 and 1 come from the prior network, every later frame from the
        transition network given the two before it, for as long as the
        caller asks (``next()``, ``itertools.islice``).  All agents advance
        together (vectorised over agents and DOFs); each agent's frames depend
        only on the generator's draws, not on how many frames are taken.

        Parameters
        ----------
        rng : numpy.random.Generator
        count : int
            Agents sampled together.
        sigma : float
            Scale of every standard deviation (0: the mean motion).
        noise_time : float, optional
            Correlation time (seconds) of the standard-normal draws of the
            transition network: AR(1) with ``ρ = exp(−1 / (noise_time · rate))``,
            scaled by ``√((1 − ρ) / (1 + ρ))`` so that a sum of many successive
            draws has the variance of as many independent ones: the noise
            spectrum moves to low frequencies (smooth velocities) while the
            variation it accumulates over a cycle stays what ``sigma`` says (at
            full marginal variance, ``sigma = 1`` with 0.2 s made streams drift
            off the cycle: cadence 0.65 × the inputs').  ``None``: independent
            draws per frame (the paper).
        predicted : bool
            Also yield the network's conditional mean of each frame given the
            sampled frames before it (the prior network's for frames 0–1).

        Yields
        ------
        (count, D) float ndarray
            One frame of every agent (varying DOFs incl. phase DOFs, original
            units); with ``predicted`` a pair ``(frame, mean)``.
        """
        m, sd = self.stats["mean"], self.stats["std"]
        z01, mu01 = self.sample_prior(rng, count, sigma)
        D = self.D
        zp, zc = z01[:, :D], z01[:, D:]
        for z, mu in ((zp, mu01[:, :D]), (zc, mu01[:, D:])):
            yield (z * sd + m, mu * sd + m) if predicted else z * sd + m
        rho = 0.0 if not noise_time else math.exp(-1.0 / (noise_time * self.model.clips.rate))
        eps = rng.standard_normal((count, D)) if rho > 0.0 else None
        # correlated draws scaled so that their sum over many frames has the variance
        # of white draws: the noise spectrum changes, the long-run variation does not
        kappa = math.sqrt((1.0 - rho) / (1.0 + rho))
        while True:
            mean, std = self.transition(zp, zc)
            if rho > 0.0:
                eps = rho * eps + math.sqrt(1.0 - rho * rho) * rng.standard_normal((count, D))
            else:
                eps = rng.standard_normal((count, D))
            zp, zc = zc, mean + (sigma * kappa) * std * eps
            yield (zc * sd + m, mean * sd + m) if predicted else zc * sd + m

    def _cycle_hint(self) -> str:
        """What the input clips were, for a model that does not cycle."""
        clips = self.model.clips
        n = clips.lengths
        return (f" (it learnt from {len(n)} clip(s) of {int(n.min())}-{int(n.max())} frames, "
                f"{n.min() / clips.rate:.2f}-{n.max() / clips.rate:.2f} s: a cycle cut from a "
                "short take may be a single step; give takes of several cycles, or "
                "clips.cut: none)")

    @property
    def cycle_limit(self) -> int:
        """Frames a stream may run without its cycle phase passing 0 (3 of the longest input)."""
        return 3 * int(self.model.clips.lengths.max()) + 2

    @staticmethod
    def passes_zero(prev: np.ndarray, ph: np.ndarray) -> np.ndarray:
        """Frames whose cycle phase ``ph`` passes 0 upwards from the previous ``prev``."""
        return (prev < 0) & (ph >= 0) & (ph - prev < np.pi)

    def cycle_phase_of(self, x: np.ndarray) -> np.ndarray:
        """Cycle phase ``φ ∈ (−π, π]`` of frames ``x (..., D)`` (models with the cycle phase)."""
        c, s = self.phase_cols
        return np.arctan2(x[..., s], x[..., c])

    def run(
        self,
        rng: np.random.Generator,
        *,
        count: int,
        length: int,
        sigma: float = 1.0,
        stop_at_end: bool = False,
        noise_time: float | None = None,
        predicted: bool = False,
        start_at_phase: bool = False,
        one_cycle: bool = False,
    ) -> Any:
        """Sample ``count`` variants of ``length`` frames (:meth:`stream`, cut).

        Parameters
        ----------
        rng : numpy.random.Generator
        count : int
        length : int
            Frames (≥ 2).
        sigma, noise_time, predicted
            As in :meth:`stream`.
        stop_at_end : bool
            End each variant at the first frame where its ``_phase`` DOF
            reaches ``1 − 0.5 / median length``; ``length`` is then the maximum.
        start_at_phase : bool
            Cyclic models: each variant starts at the first frame where its cycle
            phase passes 0, the phase every input cycle starts at (the stream's
            frames before it are dropped).
        one_cycle : bool
            With ``start_at_phase``: each variant is one whole cycle, ending at
            the frame before its cycle phase passes 0 again (its length is its
            own, as the input cycles' are; ``length`` is ignored).

        Returns
        -------
        (count, length, D) float ndarray, or list of (T_b, D) with ``stop_at_end``
        or ``one_cycle``
            DOF values (varying DOFs incl. phase DOFs, original units); with
            ``predicted`` a pair ``(variants, means)`` of the same form.
        """
        if stop_at_end and not self.ends_at_phase:
            raise SampleError("stop_at_end needs a model with the _phase DOF")
        if start_at_phase and not self.cycle_phase:
            raise SampleError("start_at_phase needs a model with the cycle phase DOFs")
        if one_cycle and not start_at_phase:
            raise SampleError("one_cycle needs start_at_phase")
        gen = self.stream(rng, count=count, sigma=sigma, noise_time=noise_time, predicted=True)
        xs, ms = [], []
        start = np.zeros(count, dtype=np.int64)
        end = np.full(count, length)
        if start_at_phase:
            start[:] = -1
            limit = self.cycle_limit
            prev = None
            for t in range(limit):
                x, mu = next(gen)
                xs.append(x)
                ms.append(mu)
                ph = self.cycle_phase_of(x)
                if prev is not None:
                    hit = (start < 0) & self.passes_zero(prev, ph)
                    start[hit] = t
                prev = ph
                if np.all(start >= 0):
                    break
            if np.any(start < 0):
                raise SampleError(
                    f"the cycle phase of {int((start < 0).sum())} stream(s) did not pass 0 "
                    f"within {limit} frames: the model does not cycle{self._cycle_hint()}")
            end = start + length
            if one_cycle:
                end = self._cycle_ends(gen, xs, ms, start, limit)
        ip = self.model.clips.labels.index(PHASE) if stop_at_end else 0
        done_at = 1.0 - 0.5 / max(float(np.median(self.model.clips.lengths)), 2.0)
        while len(xs) < int(end.max()):
            x, mu = next(gen)
            t = len(xs)
            xs.append(x)
            ms.append(mu)
            if stop_at_end and t >= 2:
                end = np.where((end == length) & (x[:, ip] >= done_at), t + 1, end)
                if np.all(end < length):
                    break
        X, M = np.stack(xs, axis=1), np.stack(ms, axis=1)  # (count, T, D)
        if stop_at_end:
            out = [X[b, : end[b]] for b in range(count)], [M[b, : end[b]] for b in range(count)]
        elif one_cycle:
            out = ([X[b, start[b] : end[b]] for b in range(count)],
                   [M[b, start[b] : end[b]] for b in range(count)])
        elif start_at_phase:
            out = (np.stack([X[b, start[b] : end[b]] for b in range(count)]),
                   np.stack([M[b, start[b] : end[b]] for b in range(count)]))
        else:
            out = X[:, :length], M[:, :length]
        return out if predicted else out[0]

    def _cycle_ends(
        self, gen: Iterator, xs: list, ms: list, start: np.ndarray, limit: int
    ) -> np.ndarray:
        """The frame where each agent's cycle phase passes 0 again after its ``start``,
        advancing ``gen`` (appending to ``xs``, ``ms``) as long as needed."""
        ph = self.cycle_phase_of(np.stack(xs, axis=1))  # (count, T) frames so far
        end = np.full(len(start), -1)
        for b, p in enumerate(ph):
            hits = np.flatnonzero(self.passes_zero(p[:-1], p[1:])) + 1
            hits = hits[hits > start[b] + 1]
            if hits.size:
                end[b] = hits[0]
        prev = ph[:, -1]
        while np.any(end < 0):
            x, mu = next(gen)
            t = len(xs)
            xs.append(x)
            ms.append(mu)
            ph = self.cycle_phase_of(x)
            hit = (end < 0) & (t > start + 1) & self.passes_zero(prev, ph)
            end[hit] = t
            prev = ph
            late = (end < 0) & (t - start > limit)
            if late.any():
                raise SampleError(
                    f"the cycle phase of {int(late.sum())} stream(s) did not pass 0 again "
                    f"within {limit} frames: the model does not cycle{self._cycle_hint()}")
        return end

    def cycles(
        self,
        rng: np.random.Generator,
        *,
        count: int,
        sigma: float = 1.0,
        noise_time: float | None = None,
    ) -> tuple[list[np.ndarray], list[np.ndarray], int]:
        """``count`` consecutive cycles of one stream (loopable variants).

        The stream is cut where its cycle phase passes 0, the phase every
        input cycle starts at; the frames before the first such frame are
        dropped.  Played in order the cycles are the stream itself: the last
        two frames of a cycle condition the first frame of the next, as the
        unrolled network does.

        Returns
        -------
        cycles : list of (T_c, D) float ndarray
        means : list of (T_c, D) float ndarray
            The network's predicted means of the same frames.
        skipped : int
            Stream frames before the first cycle.
        """
        if not self.cycle_phase:
            raise SampleError("loop needs a cyclic model with the cycle phase DOFs "
                              "(learn cyclic clips with phase: true)")
        gen = self.stream(rng, count=1, sigma=sigma, noise_time=noise_time, predicted=True)
        limit = self.cycle_limit
        xs, ms, cuts = [], [], []
        prev = None
        while len(cuts) < count + 1:
            x, mu = next(gen)
            ph = float(self.cycle_phase_of(x[0]))
            if prev is not None and self.passes_zero(prev, ph):
                cuts.append(len(xs))
            prev = ph
            xs.append(x[0])
            ms.append(mu[0])
            if len(xs) - (cuts[-1] if cuts else 0) > limit:
                raise SampleError(f"the stream's cycle phase did not pass 0 within {limit} "
                                  f"frames: the model does not cycle{self._cycle_hint()}")
        X, M = np.stack(xs), np.stack(ms)
        return ([X[a:b] for a, b in itertools.pairwise(cuts)],
                [M[a:b] for a, b in itertools.pairwise(cuts)], cuts[0])


@stage("sample", outputs=("variants", "predicted"))
def sample(
    model: VariationModel,
    *,
    count: int = 1,
    length: int | None = None,
    sigma: float = 1.0,
    noise_time: float | None = None,
    loop: bool = False,
    time_warp: bool = True,
    seed: int = 0,
    ctx: Context,
) -> dict:
    """Sample motion variants from a learned model (Lau §6).

    Parameters
    ----------
    model : VariationModel
    count : int
        Variants per task (fan out with ``seeds:`` for more tasks); with
        ``loop``, consecutive cycles of one stream.
    length : int, optional
        Frames per variant.  Default: cyclic inputs (with the cycle phase) one
        whole cycle each, from where the cycle phase passes 0 to the frame
        before it passes 0 again, so lengths vary as the input cycles' do
        (:meth:`Sampler.run` ``one_cycle``; at the median length every variant
        of the walks aligned to its nearest input on the diagonal: warp-slope std
        0.3 x the inputs'), cyclic inputs without it the median input clip
        length; other inputs (with the ``_phase`` DOF) each variant ends where
        its phase reaches 1 (at most 1.5 × the longest input).  Any length for
        cyclic inputs.  Not with ``loop`` (each cycle ends where it ends).
    sigma : float
        Standard-deviation scale; 0 gives the mean motion (paper: 1).
    noise_time : float, optional
        Correlation time of the sampling noise, seconds (:meth:`Sampler.stream`;
        null: independent per frame, as the paper).
    loop : bool
        Loopable variants of a cyclic model: the ``count`` variants are
        consecutive cycles of one stream, each from the frame where the cycle
        phase passes 0 (where every input cycle starts) to the frame before
        the next; played in order they are seamless (they are the stream), and
        each variant's origin is where the previous one ends.
    time_warp : bool
        Play each variant at a time warp drawn from the model's learned warps
        (``params["time_warp"]`` of the ``learn`` stage, scaled by ``sigma``;
        :func:`~mocapflow.stages.variation.warp.sample_time_warp`), the same
        warp for its ``predicted`` means: a whole-cycle variant (the default
        ``length``) gets the drawn overall pace too (its length changes), a
        variant of a given ``length`` keeps its length; not with ``loop`` (the
        cycles keep the stream's timing, seamless at the joins); ``False``, or a
        model without warps: the network's own timing.
    seed : int
        Seeds ``ctx.rng`` (with the part id).
    ctx : Context
        ``ctx.rng`` draws the variants.

    Returns
    -------
    dict
        ``variants``: :class:`~mocapflow.stages.variation.clips.Clips` of ``count``
        trajectories of the model's layout (phase DOFs dropped; origins copied
        from the first input clip, or chained with ``loop``); ``attrs``
        ``input_range`` holds the inputs' per-DOF ``low`` / ``high`` of the
        ``dofs`` (varying DOF names).  Cyclic models start every variant at the
        inputs' phase.
        ``predicted``: the same layout holding the network's conditional mean
        of every frame given the sampled frames before it (the ``q̄`` of Lau
        Eq. 7 for the ``ik`` stage), played at the variant's time warp.
    """
    clips = model.clips
    if length is not None and not clips.cyclic and length > 1.5 * clips.lengths.max():
        ctx.warn(
            f"length {length} exceeds the longest (non-cyclic) input clip "
            f"({clips.lengths.max()} frames): the end continues past the data"
        )
    if loop and length is not None:
        raise SampleError("loop: each variant is one cycle, length cannot be given")
    whole = length is None
    length, stop = _variant_length(clips, count=count, length=length, sigma=sigma,
                                   noise_time=noise_time)
    sampler = Sampler(model)
    origins = None
    if loop:
        x, mu, _ = sampler.cycles(ctx.rng, count=count, sigma=sigma, noise_time=noise_time)
        origins = chain_origins(clips, x)
    else:
        x, mu = sampler.run(ctx.rng, count=count, length=length, sigma=sigma, stop_at_end=stop,
                            noise_time=noise_time, predicted=True,
                            start_at_phase=sampler.cycle_phase,
                            one_cycle=sampler.cycle_phase and whole)
    warps = model.params.get("time_warp")
    warped = bool(time_warp and warps is not None and sigma > 0 and not loop)
    if warped:
        x, mu = _warped(np.asarray(warps, dtype=np.float64), x, mu, rng=ctx.rng, sigma=sigma,
                        keep_length=not whole)
    attrs = {"sigma": sigma, "noise_time": noise_time, "loop": bool(loop), "time_warp": warped}
    variants = _variant_clips(clips, x, attrs=attrs, origins=origins)
    _key_figures(_strip_internal(clips), variants, ctx)
    return {"variants": variants,
            "predicted": _variant_clips(clips, mu, attrs={**attrs, "predicted_mean": True},
                                        origins=origins)}


def _warped(
    warps: np.ndarray, x: Any, mu: Any, *, rng: np.random.Generator, sigma: float,
    keep_length: bool,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Variants ``x`` and their means ``mu`` (each ``(T_b, D)``) at one sampled warp each
    (:func:`~.warp.sample_time_warp`)."""
    xs, ms = [], []
    for a, b in zip(x, mu):
        tau = sample_time_warp(warps, rng, length=len(a), sigma=sigma, keep_length=keep_length)
        xs.append(apply_time_warp(a, tau))
        ms.append(apply_time_warp(b, tau))
    return xs, ms


def _key_figures(inputs: Clips, variants: Clips, ctx: Context) -> None:
    """The run summary's figures of a sampling (``ctx.figure``; never in an output).

    ``jerk ratio``: mean absolute third difference of the standardised DOFs, variants
    over inputs; ``out of range %``: samples outside the inputs' per-DOF range.
    """
    std = np.concatenate(inputs.trajectories, axis=0).std(axis=0)
    std = np.where(std > 0, std, 1.0)

    def jerk(clips: Clips) -> float:
        d3 = [np.abs(np.diff(t / std, 3, axis=0)) for t in clips.trajectories if len(t) > 3]
        return float(np.mean(np.concatenate(d3))) if d3 else math.nan

    X = np.concatenate(variants.trajectories, axis=0)
    rng = variants.attrs["input_range"]
    low, high = np.asarray(rng["low"]), np.asarray(rng["high"])
    ctx.figure("variants", variants.n_clips)
    ctx.figure("frames", int(np.mean(variants.lengths)))
    j_in, j_out = jerk(inputs), jerk(variants)
    if j_in > 0 and math.isfinite(j_out):
        ctx.figure("jerk ratio", round(j_out / j_in, 3))
    if X.size:
        ctx.figure("out of range %", round(100.0 * float(np.mean((X < low) | (X > high))), 2))


def _variant_length(
    clips: Clips, *, count: int, length: int | None, sigma: float, noise_time: float | None
) -> tuple[int, bool]:
    """Check a sampling request; frames per variant and whether variants stop at phase 1."""
    if count < 1:
        raise SampleError(f"count must be at least 1, got {count}")
    stop = length is None and PHASE in clips.dof_names
    if length is None:
        length = int(1.5 * clips.lengths.max()) if stop else int(np.median(clips.lengths))
    if length < 2:
        raise SampleError(f"length must be at least 2 frames, got {length}")
    if sigma < 0 or not math.isfinite(sigma):
        raise SampleError(f"sigma must be a finite number >= 0, got {sigma}")
    if noise_time is not None and not (noise_time > 0 and math.isfinite(noise_time)):
        raise SampleError(f"noise_time must be a finite number of seconds > 0 or null, "
                          f"got {noise_time}")
    return length, stop


def chain_origins(clips: Clips, cycles: list[np.ndarray]) -> np.ndarray | None:
    """Origins ``(C, 4)`` that chain consecutive cycles: each starts where the last ends.

    With the root as heading rate and heading-frame velocity (``root="heading"``)
    the heading ψ and the horizontal root position are integrated over the
    cycles as :func:`~mocapflow.stages.variation.dofs.dofs_to_motion` does;
    otherwise (absolute root, strokes) ``None`` (the origins are unused).
    """
    if clips.attrs.get("root") != "heading" or clips.kind != "motion" or clips.skeleton is None:
        return None
    chained = clips.replace(trajectories=[np.concatenate(cycles, axis=0)],
                            origins=clips.origins[:1], names=["chain"])
    motion = clips_to_motions(_strip_internal(chained))[0]
    rname = clips.skeleton.names[0]
    names = chained.labels
    dpsi = np.concatenate(cycles, axis=0)[:, names.index(f"{rname}:heading_rate")] \
        if f"{rname}:heading_rate" in names else np.zeros(sum(len(c) for c in cycles))
    psi = clips.origins[0, 0] + np.concatenate([[0.0], np.cumsum(dpsi[1:])])
    starts = np.cumsum([0] + [len(c) for c in cycles[:-1]])
    return np.concatenate([psi[starts, None], motion.root_position[starts]], axis=1)


def _strip_internal(clips: Clips) -> Clips:
    """Clips without the phase DOFs (:data:`~.training.INTERNAL_DOFS`, the last columns)."""
    names = clips.labels
    keep = [i for i, n in enumerate(names) if n not in INTERNAL_DOFS]
    if len(keep) == len(names):
        return clips
    drop = [i for i, n in enumerate(clips.dof_names) if n in INTERNAL_DOFS]
    mask = np.ones(len(clips.dof_names), dtype=bool)
    mask[drop] = False
    return clips.replace(
        trajectories=[t[:, keep] for t in clips.trajectories],
        dof_names=[n for n, k in zip(clips.dof_names, mask) if k],
        varying=clips.varying[mask],
        constant_values=clips.constant_values[mask],
    )


def input_range(clips: Clips) -> dict[str, list]:
    """The inputs' per-DOF range: ``{"dofs": names, "low": [...], "high": [...]}``.

    Over every frame of every training clip, for the varying DOFs other than
    the phase DOFs (trajectory column order; radians for Euler channels).
    """
    plain = _strip_internal(clips)
    X = np.concatenate(plain.trajectories, axis=0)
    return {"dofs": plain.labels, "low": X.min(axis=0).tolist(), "high": X.max(axis=0).tolist()}


def _variant_clips(
    clips: Clips,
    x: np.ndarray | list[np.ndarray],
    *,
    attrs: dict[str, Any],
    origins: np.ndarray | None = None,
) -> Clips:
    """Sampled DOF values as :class:`Clips` of the training clips' layout (phase DOFs dropped).

    Parameters
    ----------
    clips : Clips
        The model's training clips.
    x : (B, T, D) float ndarray or list of (T_b, D) float ndarray
        From :meth:`Sampler.run` or :meth:`Sampler.cycles`.
    attrs : dict
        Added to ``attrs`` (with ``input_range``).
    origins : (B, 4) float ndarray, optional
        Default: the first input clip's, for every variant.

    Returns
    -------
    Clips
    """
    count = len(x)
    out = _strip_internal(clips.replace(
        trajectories=list(x),
        origins=np.repeat(clips.origins[:1], count, axis=0) if origins is None else origins,
        names=[f"variant{i}" for i in range(count)],
        attrs={**clips.attrs, **attrs, "input_range": input_range(clips)},
    ))
    return out


# --------------------------------------------------------------------------- noise baselines


def _gaussian_smooth(x: np.ndarray, width: float) -> np.ndarray:
    """``x`` smoothed along axis 0 by a Gaussian of std ``width`` samples (reflected ends)."""
    if width <= 0:
        return x
    return gaussian_filter1d(x, width, axis=0, mode="reflect")


def _base_track(
    clip: np.ndarray, length: int, cyclic: bool, warp: np.ndarray | None = None
) -> np.ndarray:
    """Clip resampled at (possibly warped) times ``0..length-1`` (tiled if cyclic)."""
    T = len(clip)
    tt = np.arange(length, dtype=np.float64) if warp is None else warp
    if cyclic:
        ext = np.concatenate([clip, clip[:1]], axis=0)
        u = np.mod(tt, T)
        grid = np.arange(T + 1)
    else:
        u = np.clip(tt * (T - 1) / max(length - 1, 1), 0, T - 1)
        ext = clip
        grid = np.arange(T)
    return np.stack([np.interp(u, grid, ext[:, d]) for d in range(clip.shape[1])], axis=1)


def strawman_noise(
    clips: Clips,
    rng: np.random.Generator,
    *,
    count: int,
    length: int,
    amplitude: float,
    warp: float = 0.1,
    smoothing: float = 0.1,
) -> np.ndarray:
    """Strawman baseline: time-warped input clips plus smoothed Gaussian noise.

    Parameters
    ----------
    clips : Clips
    rng : numpy.random.Generator
    count, length : int
    amplitude : float
        Noise std in units of each DOF's std.
    warp : float
        Time-warp strength (relative speed change, < 1).
    smoothing : float
        Gaussian smoothing width of the noise, seconds.

    Returns
    -------
    (count, length, D) float ndarray
    """
    std = standardization(clips.trajectories)["std"]
    out = np.zeros((count, length, clips.n_dofs))
    sw = smoothing * clips.rate
    for b in range(count):
        c = int(rng.integers(clips.n_clips))
        T = clips.lengths[c]
        # smooth monotone warp: speed 1 + warp * smooth noise (kept > 0.2)
        speed = 1.0 + warp * _unit(_gaussian_smooth(rng.standard_normal(length), 0.25 * T))
        speed = np.maximum(speed, 0.2)
        tau = np.concatenate([[0.0], np.cumsum(speed[1:])])
        tau += rng.uniform(0, T) if clips.cyclic else 0.0
        if not clips.cyclic:
            tau *= (length - 1) / max(tau[-1], 1e-12)
        base = _base_track(clips.trajectories[c], length, clips.cyclic, tau)
        noise = _unit(_gaussian_smooth(rng.standard_normal((length, clips.n_dofs)), sw))
        out[b] = base + amplitude * std * noise
    return out


def _unit(x: np.ndarray) -> np.ndarray:
    """``x`` scaled to unit std per column (constant columns unchanged)."""
    s = x.std(axis=0)
    return x / np.where(s > 0, s, 1.0)


def perlin_noise(
    length: int, channels: int, rng: np.random.Generator, *, frequency: float, octaves: int = 2
) -> np.ndarray:
    """1-D Perlin gradient noise, unit std per channel.

    Parameters
    ----------
    length : int
        Samples.
    channels : int
    rng : numpy.random.Generator
    frequency : float
        Lattice points per sample of the first octave.
    octaves : int
        Octaves, each at twice the frequency and half the amplitude.

    Returns
    -------
    (length, channels) float ndarray
    """
    out = np.zeros((length, channels))
    for o in range(octaves):
        f = frequency * 2**o
        x = np.arange(length)[:, None] * f + rng.uniform(0, 1, channels)
        i0 = np.floor(x).astype(np.int64)
        fx = x - i0
        g = rng.uniform(-1, 1, (int(i0.max()) + 2, channels))
        ch = np.arange(channels)[None, :]
        n0 = g[i0, ch] * fx
        n1 = g[i0 + 1, ch] * (fx - 1.0)
        s = fx * fx * fx * (fx * (fx * 6 - 15) + 10)  # Perlin's quintic fade
        out += (n0 + s * (n1 - n0)) / 2**o
    return _unit(out)


def _perlin_variants(
    clips: Clips, rng: np.random.Generator, *, count: int, length: int, amplitude: float,
    frequency: float = 2.0,
) -> np.ndarray:
    """Perlin baseline: input clips (random start if cyclic) plus Perlin noise.

    Returns ``(count, length, D)`` DOF values; ``frequency`` is in lattice
    points per second.
    """
    std = standardization(clips.trajectories)["std"]
    out = np.zeros((count, length, clips.n_dofs))
    for b in range(count):
        c = int(rng.integers(clips.n_clips))
        start = rng.uniform(0, clips.lengths[c]) if clips.cyclic else 0.0
        tt = start + np.arange(length) if clips.cyclic else None
        base = _base_track(clips.trajectories[c], length, clips.cyclic, tt)
        out[b] = base + amplitude * std * perlin_noise(
            length, clips.n_dofs, rng, frequency=frequency / clips.rate
        )
    return out


def matched_amplitude(
    make: Callable[[float], Clips],
    distance: Callable[[Clips], float],
    target: float,
    *,
    low: float = 0.0,
    high: float = 2.0,
    iterations: int = 12,
) -> float:
    """Noise amplitude at which ``distance(make(a))`` equals ``target`` (bisection).

    Parameters
    ----------
    make : callable
        ``amplitude -> Clips`` with a *fixed* random stream (same seed).
    distance : callable
        ``Clips -> float`` (e.g. mean DTW distance to the inputs).
    target : float
        Our variants' distance.
    low, high : float
        Bracket; ``high`` is doubled until it overshoots (at most 6 times).
    iterations : int

    Returns
    -------
    float
    """
    for _ in range(6):
        if distance(make(high)) >= target:
            break
        high *= 2.0
    for _ in range(iterations):
        mid = 0.5 * (low + high)
        if distance(make(mid)) < target:
            low = mid
        else:
            high = mid
    return 0.5 * (low + high)


@stage("sample_noise", outputs=("variants",))
def sample_noise(
    clips: Any,
    *,
    method: Literal["strawman", "perlin"] = "perlin",
    amplitude: float = 0.2,
    count: int = 1,
    length: int | None = None,
    seed: int = 0,
    ctx: Context,
) -> dict:
    """Noise-baseline variants of the input clips (Lau §8).

    Parameters
    ----------
    clips : Clips or list of Clips
    method : {"strawman", "perlin"}
        :func:`strawman_noise` (time-warped inputs plus smoothed noise) or
        Perlin noise added to the inputs (:func:`perlin_noise`).
    amplitude : float
        Noise std in units of each DOF's std (match it to the model's variants
        with :func:`matched_amplitude`).
    count : int
        Baseline trajectories per task.
    length : int, optional
        Default the median input length.
    seed : int
        Seeds ``ctx.rng`` (with the part id).
    ctx : Context
        ``ctx.rng`` draws the baselines.

    Returns
    -------
    dict
        ``variants``: Clips of ``count`` trajectories named ``<method><i>``,
        origins copied from the first input clip.
    """
    data = flatten_clips(clips)
    length = int(np.median(data.lengths)) if length is None else int(length)
    if method == "strawman":
        x = strawman_noise(data, ctx.rng, count=count, length=length, amplitude=amplitude)
    elif method == "perlin":
        x = _perlin_variants(data, ctx.rng, count=count, length=length, amplitude=amplitude)
    else:
        raise SampleError(f"unknown noise baseline {method!r}")
    variants = data.replace(
        trajectories=list(x),
        origins=np.repeat(data.origins[:1], count, axis=0),
        names=[f"{method}{i}" for i in range(count)],
    )
    return {"variants": variants}
