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
    speed varies as its poses do; there is no separate time-warp model.
    Streams have any length;
    for cyclic inputs they continue through cycle after cycle.  Several
    variants are sampled together (vectorised over variants and DOFs; the
    nearest-instance search is a batched matrix product + ``argpartition``).
    ``noise_time`` (an addition; ``None`` is the paper): the standard-normal
    draws of successive frames form an AR(1) process with that correlation
    time, so every frame keeps its conditional Gaussian as marginal but the
    velocity noise is no longer white (white noise on the delta is what makes
    variants of captured takes ~10x jerkier than the inputs).
Noise baselines (Lau §8, the ``sample_noise`` stage)
    ``strawman``: an input clip, time-warped by a random smooth monotone warp,
    plus Gaussian-smoothed white noise.  ``perlin``: an input clip plus 1-D
    Perlin gradient noise per DOF.  Amplitudes are in units of each DOF's
    standard deviation; :func:`matched_amplitude` finds the amplitude at which
    a baseline's DTW distance to the inputs equals that of our variants
    (the paper's amplitude matching).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from scipy.ndimage import gaussian_filter1d

from mocapflow.pipeline import Context, stage
from mocapflow.stages.variation.clips import Clips, flatten_clips
from mocapflow.stages.variation.kernel import kernel_regression
from mocapflow.stages.variation.model import VariationModel
from mocapflow.stages.variation.search import DAG
from mocapflow.stages.variation.training import PHASE, prior_data, standardization, transition_data

__all__ = [
    "SampleError",
    "Sampler",
    "matched_amplitude",
    "perlin_noise",
    "sample",
    "sample_noise",
    "strawman_noise",
]


class SampleError(ValueError):
    """Bad sampling request (length, count, sigma)."""


class Sampler:
    """Precomputed tables for sampling a :class:`VariationModel`.

    Parameters
    ----------
    model : VariationModel
    """

    def __init__(self, model: VariationModel):
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
        self.wmask = np.zeros((D, pmax))
        for i, c in enumerate(cols):
            self.cols[i, : len(c)] = c
            self.wmask[i, : len(c)] = 1.0
        U = bank[:, self.cols] * self.wmask  # (N, D, pmax)
        self.U_t = np.ascontiguousarray(U.transpose(1, 2, 0))  # (D, pmax, N)
        self.A = (U * U).sum(axis=-1).T.copy()  # (D, N)
        self.Y = np.ascontiguousarray(td.Y.T)  # (D, N)
        self.h2t = (model.transition_bandwidth**2)[:, None]  # (D, 1)
        self.Zc = np.ascontiguousarray(td.F[:, D:].T)  # (D, N) standardised x[t+1]
        self.retention = float(p.get("retention", 1.0))
        self.YYZ = np.ascontiguousarray(np.stack([self.Y, self.Y**2, self.Zc], axis=-1))  # (D,N,3)
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

    def sample_prior(self, rng: np.random.Generator, count: int, sigma: float) -> np.ndarray:
        """Frames 0 and 1, standardised: ``(count, 2D)``."""
        Z = self.Zp
        N = Z.shape[0]
        z = np.zeros((count, 2 * self.D))
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
            z[:, v] = mu + sigma * np.sqrt(var) * rng.standard_normal(count)
        return z

    def run(
        self,
        rng: np.random.Generator,
        *,
        count: int,
        length: int,
        sigma: float = 1.0,
        stop_at_end: bool = False,
        noise_time: float | None = None,
    ) -> np.ndarray | list[np.ndarray]:
        """Sample ``count`` variants of ``length`` frames.

        Parameters
        ----------
        rng : numpy.random.Generator
        count : int
        length : int
            Frames (≥ 2).
        sigma : float
            Scale of every standard deviation (0: mean motion).
        stop_at_end : bool
            End each variant at the first frame where its ``_phase`` DOF
            reaches ``1 − 0.5 / median length``; ``length`` is then the maximum.
        noise_time : float, optional
            Correlation time (seconds) of the standard-normal draws of the
            transition network: AR(1) with ``ρ = exp(−1 / (noise_time · rate))``,
            so each frame's delta keeps its conditional Gaussian (Lau Eq. 5–6) as
            marginal but successive draws are correlated.  ``None``: independent
            draws per frame (the paper; white velocity noise, jerky positions).

        Returns
        -------
        (count, length, D) float ndarray, or list of (T_b, D) with ``stop_at_end``
            DOF values (varying DOFs, original units).
        """
        end = np.full(count, length)
        names = self.model.clips.labels
        if stop_at_end and PHASE not in names:
            raise SampleError("stop_at_end needs a model with the _phase DOF")
        ip = names.index(PHASE) if stop_at_end else 0
        done_at = 1.0 - 0.5 / max(float(np.median(self.model.clips.lengths)), 2.0)
        D, B = self.D, count
        z = np.zeros((B, length, D))
        z01 = self.sample_prior(rng, B, sigma)
        z[:, 0], z[:, 1] = z01[:, :D], z01[:, D:]
        k = self.k
        N = self.Y.shape[1]
        vscale = self.vw / self.ratio
        half_inv_h2 = (0.5 / np.maximum(self.h2t, 1e-300))[:, :, None]  # (D, 1, 1)
        lam = self.retention
        rho = 0.0 if not noise_time else math.exp(-1.0 / (noise_time * self.model.clips.rate))
        eps = rng.standard_normal((D, B)) if rho > 0.0 else None
        for t in range(2, length):
            zp, zc = z[:, t - 2], z[:, t - 1]
            g = np.concatenate([zp, zc, (zc - zp) * vscale], axis=1)  # (B, 3D)
            qd = (g[:, self.cols] * self.wmask).transpose(1, 0, 2)  # (D, B, pmax)
            d2 = qd @ self.U_t  # (D, B, N)
            d2 *= -2.0
            d2 += self.A[:, None, :]
            d2 += (qd * qd).sum(axis=-1)[..., None]
            # the k nearest instances (ties included): threshold from a partition
            if k < N:
                part = np.partition(d2, k - 1, axis=-1)
                thr = part[..., k - 1 : k]
                dmin = part[..., :k].min(axis=-1, keepdims=True)
            else:
                thr = d2.max(axis=-1, keepdims=True)
                dmin = d2.min(axis=-1, keepdims=True)
            w = np.exp(-(d2 - dmin) * half_inv_h2)
            w *= d2 <= thr
            s = w @ self.YYZ  # (D, B, 3): Σw·Δ, Σw·Δ², Σw·z[t+1]
            sw = w.sum(axis=-1)
            mu = s[..., 0] / sw
            var = np.maximum(s[..., 1] / sw - mu * mu, 0.0) + self.ms * self.ms
            if rho > 0.0:
                eps = rho * eps + math.sqrt(1.0 - rho * rho) * rng.standard_normal((D, B))
            else:
                eps = rng.standard_normal((D, B))
            delta = mu + sigma * np.sqrt(var) * eps
            znext = zc + delta.T * self.ratio
            if lam < 1.0:
                znext += (lam - 1.0) * (zc - (s[..., 2] / sw).T)
            z[:, t] = znext
            if stop_at_end:
                ph = znext[:, ip] * self.stats["std"][ip] + self.stats["mean"][ip]
                end = np.where((end == length) & (ph >= done_at), t + 1, end)
                if np.all(end < length):
                    break
        x = z * self.stats["std"] + self.stats["mean"]
        if stop_at_end:
            return [x[b, : end[b]] for b in range(count)]
        return x


@stage("sample", outputs=("variants",))
def sample(
    model: VariationModel,
    *,
    count: int = 1,
    length: int | None = None,
    sigma: float = 1.0,
    noise_time: float | None = None,
    seed: int = 0,
    ctx: Context,
) -> dict:
    """Sample motion variants from a learned model (Lau §6).

    Parameters
    ----------
    model : VariationModel
    count : int
        Variants per task (fan out with ``seeds:`` for more tasks).
    length : int, optional
        Frames per variant.  Default: cyclic inputs the median input clip
        length; other inputs (with the ``_phase`` DOF) each variant ends where
        its phase reaches 1 (at most 1.5 × the longest input).  Any length for
        cyclic inputs.
    sigma : float
        Standard-deviation scale; 0 gives the mean motion.
    noise_time : float, optional
        Correlation time of the sampling noise, seconds (:meth:`Sampler.run`;
        null: independent per frame, as the paper).
    seed : int
        Seeds ``ctx.rng`` (with the part id).
    ctx : Context
        ``ctx.rng`` draws the variants.

    Returns
    -------
    dict
        ``variants``: :class:`~mocapflow.stages.variation.clips.Clips` of ``count``
        trajectories of the model's layout; origins copied from the first input clip.
    """
    clips = model.clips
    if length is not None and not clips.cyclic and length > 1.5 * clips.lengths.max():
        ctx.warn(
            f"length {length} exceeds the longest (non-cyclic) input clip "
            f"({clips.lengths.max()} frames): the end continues past the data"
        )
    length, stop = _variant_length(clips, count=count, length=length, sigma=sigma,
                                   noise_time=noise_time)
    x = Sampler(model).run(ctx.rng, count=count, length=length, sigma=sigma, stop_at_end=stop,
                           noise_time=noise_time)
    return {"variants": _variant_clips(clips, x, sigma=sigma, noise_time=noise_time)}


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


def _variant_clips(
    clips: Clips, x: np.ndarray | list[np.ndarray], *, sigma: float, noise_time: float | None
) -> Clips:
    """Sampled DOF values as :class:`Clips` of the training clips' layout (``_phase`` dropped).

    Parameters
    ----------
    clips : Clips
        The model's training clips.
    x : (B, T, D) float ndarray or list of (T_b, D) float ndarray
        From :meth:`Sampler.run`.
    sigma, noise_time : float
        Recorded in ``attrs``.

    Returns
    -------
    Clips
    """
    count = len(x)
    layout: dict[str, Any] = {}
    if PHASE in clips.dof_names:  # internal DOF (the last one): not part of the output
        x = [t[:, :-1] for t in x]
        layout = dict(dof_names=clips.dof_names[:-1], varying=clips.varying[:-1],
                      constant_values=clips.constant_values[:-1])
    return clips.replace(
        **layout,
        trajectories=list(x),
        origins=np.repeat(clips.origins[:1], count, axis=0),
        names=[f"variant{i}" for i in range(count)],
        attrs={**clips.attrs, "sigma": sigma, "noise_time": noise_time},
    )


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
