"""Root trajectory of a synthesized motion (Moradoff §3.10).

The synthesis copies the root as velocities in the heading frame (yaw rate,
horizontal velocity) and an absolute height; the trajectory is their
integral.  To follow a user path (polyline or spline on the ground plane,
e.g. a figure-8) the velocities are rotated into the path's local frame: the
motion's smoothed travel direction is turned onto the path tangent at the
distance travelled so far, the high-frequency sway is kept in the path frame.
``y`` is up; ground-plane points are ``(x, z)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "PathCurve",
    "PathError",
    "figure_eight",
    "follow_path",
    "heading_direction",
    "integrate_root",
]


class PathError(ValueError):
    """A path param that cannot be followed."""


def heading_direction(heading: np.ndarray) -> np.ndarray:
    """Ground-plane unit vector ``(x, z)`` of a heading (``R_y(h) (0, 0, 1)``).

    Parameters
    ----------
    heading : (...) float ndarray

    Returns
    -------
    (..., 2) float ndarray
    """
    h = np.asarray(heading, dtype=np.float64)
    return np.stack([np.sin(h), np.cos(h)], axis=-1)


def _rotate_xz(v: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """``R_y(angle)`` applied to ground-plane vectors ``(x, z)``."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([v[..., 0] * c + v[..., 1] * s, -v[..., 0] * s + v[..., 1] * c], axis=-1)


def integrate_root(
    yaw_rate: np.ndarray,
    velocity: np.ndarray,
    *,
    heading0: float = 0.0,
    origin: np.ndarray | tuple[float, float] = (0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Integrate heading-frame root velocities.

    Parameters
    ----------
    yaw_rate : (L,) float ndarray
        Heading change from frame ``t`` to ``t + 1`` (radians).
    velocity : (L, 2) float ndarray
        Displacement ``(x, z)`` from ``t`` to ``t + 1`` in the heading frame of ``t``.
    heading0 : float
        Heading of frame 0.
    origin : (2,) float
        Ground position ``(x, z)`` of frame 0.

    Returns
    -------
    heading : (L,) float ndarray
    ground : (L, 2) float ndarray
        ``(x, z)`` per frame.
    """
    yaw = np.asarray(yaw_rate, dtype=np.float64)
    heading = heading0 + np.concatenate([[0.0], np.cumsum(yaw[:-1])])
    disp = _rotate_xz(np.asarray(velocity, dtype=np.float64), heading)
    ground = np.asarray(origin, dtype=np.float64) + np.vstack(
        [np.zeros((1, 2)), np.cumsum(disp[:-1], axis=0)]
    )
    return heading, ground


def figure_eight(radius: float = 2.0, n_points: int = 65) -> np.ndarray:
    """A closed figure-8 on the ground plane (two loops crossing at the origin).

    Parameters
    ----------
    radius : float
        Half width of each loop, metres (loops ``2 radius`` wide, ``4 radius`` long overall).
    n_points : int

    Returns
    -------
    (n_points, 2) float ndarray
        ``(x, z)``; first point equals the last.
    """
    u = np.linspace(0.0, 2.0 * np.pi, n_points)
    pts = np.stack([radius * np.sin(2 * u), 2.0 * radius * np.sin(u)], axis=-1)
    pts[-1] = pts[0]
    return pts


@dataclass
class PathCurve:
    """An arc-length parametrised ground-plane curve.

    Attributes
    ----------
    samples : (M, 2) float ndarray
        Dense points ``(x, z)``.
    s : (M,) float ndarray
        Arc length at each sample.
    closed : bool
        First and last control points coincide (the path wraps).
    """

    samples: np.ndarray
    s: np.ndarray
    closed: bool

    @classmethod
    def from_points(cls, points, *, mode: str = "polyline") -> PathCurve:
        """Build from control points.

        Parameters
        ----------
        points : (N, 2) or (N, 3) array_like
            ``(x, z)`` or ``(x, y, z)`` (``y`` ignored).
        mode : {"polyline", "spline"}
            Straight segments, or a C² cubic spline through the points (periodic when closed).
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] not in (2, 3) or p.shape[0] < 2:
            raise PathError(
                f"path: expected a list of >= 2 points [x, z] or [x, y, z], got {p.shape}"
            )
        if not np.isfinite(p).all():
            raise PathError("path: points must be finite")
        if p.shape[1] == 3:
            p = p[:, [0, 2]]
        keep = np.concatenate([[True], np.linalg.norm(np.diff(p, axis=0), axis=1) > 1e-9])
        p = p[keep]
        if p.shape[0] < 2:
            raise PathError("path: all points coincide")
        span = np.ptp(p, axis=0).max()
        closed = p.shape[0] > 3 and np.linalg.norm(p[0] - p[-1]) < 1e-6 * max(span, 1.0)
        if mode == "spline":
            from scipy.interpolate import CubicSpline

            u = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
            if closed:
                p[-1] = p[0]
            cs = CubicSpline(u, p, bc_type="periodic" if closed else "natural", axis=0)
            dense = cs(np.linspace(0.0, u[-1], max(400, 40 * p.shape[0])))
        elif mode == "polyline":
            seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
            n_each = np.maximum(2, np.ceil(seg / 0.02).astype(int))
            dense = np.vstack(
                [np.linspace(a, b, k, endpoint=False) for a, b, k in zip(p[:-1], p[1:], n_each)]
                + [p[-1:]]
            )
        else:
            raise PathError(f"path_mode must be 'polyline' or 'spline', got {mode!r}")
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
        return cls(dense, s, bool(closed))

    @property
    def length(self) -> float:
        """Total arc length, metres."""
        return float(self.s[-1])

    def _wrap(self, s: np.ndarray) -> np.ndarray:
        return np.mod(s, self.length) if self.closed else s

    def point(self, s: np.ndarray) -> np.ndarray:
        """Points at arc lengths ``s`` (extrapolated along the end tangent when open).

        Parameters
        ----------
        s : (...) float ndarray

        Returns
        -------
        (..., 2) float ndarray
        """
        s = self._wrap(np.asarray(s, dtype=np.float64))
        x = np.interp(s, self.s, self.samples[:, 0])
        z = np.interp(s, self.s, self.samples[:, 1])
        out = np.stack([x, z], axis=-1)
        if not self.closed:
            over = np.clip(s - self.length, 0.0, None)[..., None]
            out = out + over * heading_direction(self.tangent_angle(np.array(self.length)))
        return out

    def tangent_angle(self, s: np.ndarray) -> np.ndarray:
        """Heading (``atan2(dx, dz)``) of the tangent at arc lengths ``s``.

        Parameters
        ----------
        s : (...) float ndarray

        Returns
        -------
        (...) float ndarray
            Radians, continuous along the curve samples.
        """
        d = np.gradient(self.samples, self.s, axis=0)
        ang = np.unwrap(np.arctan2(d[:, 0], d[:, 1]))
        s = self._wrap(np.asarray(s, dtype=np.float64))
        return np.interp(np.clip(s, 0.0, self.length), self.s, ang)

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance from points to the curve and the arc length of the closest sample.

        Parameters
        ----------
        points : (N, 2) float ndarray

        Returns
        -------
        distance : (N,) float ndarray
        s : (N,) float ndarray
        """
        from scipy.spatial import cKDTree

        d, i = cKDTree(self.samples).query(np.asarray(points, dtype=np.float64))
        return d, self.s[i]


def _gauss(x: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter1d

    if sigma <= 0:
        return x
    return gaussian_filter1d(x, sigma, axis=0, mode="nearest")


def follow_path(
    yaw_rate: np.ndarray,
    velocity: np.ndarray,
    curve: PathCurve,
    rate: float,
    *,
    travel_window: float = 0.5,
    min_speed: float = 0.1,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Root trajectory following a path by rotating velocities into its local frame.

    Parameters
    ----------
    yaw_rate : (L,) float ndarray
    velocity : (L, 2) float ndarray
        Heading-frame velocities of the synthesized motion (per frame).
    curve : PathCurve
    rate : float
        Frames per second.
    travel_window : float
        Gaussian sigma (seconds) separating travel from sway.
    min_speed : float
        Travel speed (m/s) below which the travel direction is taken from the neighbours.

    Returns
    -------
    heading : (L,) float ndarray
    ground : (L, 2) float ndarray
    info : dict
        ``distance`` travelled, ``path_length``, ``beyond_end`` (frames past an open path's end).
    """
    heading, ground = integrate_root(yaw_rate, velocity)
    L = heading.shape[0]
    disp = _rotate_xz(np.asarray(velocity, dtype=np.float64), heading)
    sigma = travel_window * rate
    travel = _gauss(disp, sigma)
    speed = np.linalg.norm(travel, axis=1)
    smooth_ground = np.vstack([np.zeros((1, 2)), np.cumsum(travel[:-1], axis=0)])
    sway = ground - smooth_ground
    s = np.concatenate([[0.0], np.cumsum(speed[:-1])])
    alpha = np.arctan2(travel[:, 0], travel[:, 1])
    moving = speed * rate >= min_speed
    phi = curve.tangent_angle(s)
    if moving.any():
        psi_raw = np.angle(np.exp(1j * (phi - alpha)))
        idx = np.arange(L)
        z = np.exp(1j * psi_raw)
        zr = np.interp(idx, idx[moving], z.real[moving])
        zi = np.interp(idx, idx[moving], z.imag[moving])
        zs = _gauss(zr, 0.5 * sigma) + 1j * _gauss(zi, 0.5 * sigma)
        psi = np.unwrap(np.angle(zs))
    else:
        psi = np.full(L, phi[0] - heading[0])
    new_heading = heading + psi
    new_ground = curve.point(s) + _rotate_xz(sway, psi)
    beyond = 0 if curve.closed else int(np.sum(s > curve.length))
    return new_heading, new_ground, {
        "distance": float(s[-1]),
        "path_length": curve.length,
        "beyond_end": beyond,
    }


def toe_displacements(
    yaw_rate: np.ndarray, velocity: np.ndarray, toe_local: np.ndarray
) -> np.ndarray:
    """Per-frame toe displacement in the heading frame of each frame.

    Parameters
    ----------
    yaw_rate : (L,) float ndarray
    velocity : (L, 2) float ndarray
        Root displacement ``t → t+1`` in the heading frame of ``t``.
    toe_local : (L, T, 2) float ndarray
        Toe ground position relative to the root in each frame's heading frame.

    Returns
    -------
    (L, T, 2) float ndarray
        ``velocity[t] + R_y(yaw[t]) toe[t+1] - toe[t]`` (the last frame repeats).
    """
    nxt = np.concatenate([toe_local[1:], toe_local[-1:]], axis=0)
    d = _rotate_xz(nxt, yaw_rate[:, None]) - toe_local + velocity[:, None, :]
    d[-1] = d[-2] if d.shape[0] > 1 else d[-1]
    return d


def plant_feet(
    yaw_rate: np.ndarray,
    velocity: np.ndarray,
    toe_local: np.ndarray,
    source_index: np.ndarray,
    source_displacement: np.ndarray,
    source_contact: np.ndarray,
    *,
    cyclic: bool = False,
    smooth: float = 2.0,
) -> np.ndarray:
    """Root velocities that keep the stance toes moving as in the input.

    Smoothing a seam changes the pose; with the copied root velocity a toe in
    contact would slide.  On every frame whose source frame (and the next
    frame's source) has a toe in contact, the root velocity is chosen so that
    the toe moves as it moved in the input at that source frame (the mean
    correction when both toes are down).  Frames copied verbatim are left
    unchanged.

    Parameters
    ----------
    yaw_rate : (L,) float ndarray
    velocity : (L, 2) float ndarray
        Root velocities (heading frame) of the output.
    toe_local : (L, T, 2) float ndarray
        Output toe positions relative to the root, heading frame.
    source_index : (L,) int ndarray
    source_displacement : (F, T, 2) float ndarray
        :func:`toe_displacements` of the input.
    source_contact : (F, T) bool ndarray
        Toe contacts of the input.
    cyclic : bool
    smooth : float
        Gaussian sigma (frames) applied to the accumulated root offset.

    Returns
    -------
    (L, 2) float ndarray
    """
    src = np.asarray(source_index, dtype=np.int64)
    nxt = np.roll(src, -1)
    contact = source_contact[src] & source_contact[nxt]
    if not cyclic:
        contact[-1] = False
    current = toe_displacements(yaw_rate, velocity, toe_local)
    corr = source_displacement[src] - current  # (L, T, 2)
    n = contact.sum(axis=1)
    mean = np.where(
        n[:, None] > 0,
        np.sum(np.where(contact[..., None], corr, 0.0), axis=1) / np.maximum(n, 1)[:, None],
        0.0,
    )
    # the root offset the corrections add up to, smoothed so the root stays smooth
    offset = np.vstack([np.zeros((1, 2)), np.cumsum(mean, axis=0)])
    if smooth > 0:
        from scipy.ndimage import gaussian_filter1d

        offset = gaussian_filter1d(offset, smooth, axis=0, mode="nearest")
    return velocity + np.diff(offset, axis=0)
