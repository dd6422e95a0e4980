"""One near-rigid part's deformation model (Park & Hodgins 2006, §5.3).

:func:`prepare_part` builds what does not depend on the frame (:class:`PartModel`:
local coordinates, basis normalisation, marker kernel, the bound vertices' rows);
:func:`fit_part` fits it in every frame (:class:`PartFit`): the rigid transform
(:func:`_rigid_fits`), the quadratic (P&H Eq. 6, :func:`_quadratic_fits`, damped
toward rigid by ``damping``), the RBF residual (P&H Eq. 7, :func:`_residual_fits`),
with frames that could not be fitted interpolated in time; :func:`evaluate_part`
moves points by the fitted model (P&H Eq. 8).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from mocapflow.stages.motion.absolute_orientation import absolute_orientation_batch
from mocapflow.stages.motion.rotations import (
    quat_continuity,
    quat_from_matrix,
    quat_normalize,
    quat_to_matrix,
)
from mocapflow.stages.skin.binding import DeformError
from mocapflow.stages.skin.kernels import (
    _solve_kernel,
    _solve_thin_plate,
    _well_conditioned_kernel,
    dilation,
    quadratic_basis,
    rbf_matrix,
    thin_plate_matrix,
)
from mocapflow.stages.skin.segmentation import Segmentation

__all__ = [
    "MODES",
    "RESIDUAL_KERNELS",
    "PartFit",
    "PartModel",
    "evaluate_part",
    "fit_part",
    "prepare_part",
    "soft_clamp",
]


Mode = Literal["rigid", "quadratic", "rigid_residual", "quadratic_residual"]


MODES: tuple[str, ...] = ("rigid", "quadratic", "rigid_residual", "quadratic_residual")


ResidualKernel = Literal["cubic_bspline", "thin_plate"]


RESIDUAL_KERNELS: tuple[str, ...] = ("cubic_bspline", "thin_plate")


@dataclass
class PartModel:
    """Everything about one part that does not depend on the frame.

    Attributes
    ----------
    name : str
    members : (n,) int ndarray
        Marker indices of the part (``α > 0``).
    alpha : (n,) float ndarray
        Their weights, used in the fits.
    local : (n, 3) float ndarray
        Reference marker positions in the part's local frame (``p̄``).
    origin : (3,) float ndarray
    axes : (3, 3) float ndarray
    scale : float
        RMS radius of ``local`` (basis normalisation).
    q_mean : (9,) float ndarray
        Weighted mean of the scaled monomials (basis centring).
    sigma : float
        RBF dilation.
    kernel : (n, n) scipy.sparse.csc_matrix
        ``Φ`` among the markers.
    quadratic : bool
        Whether the part has enough markers for the quadratic transform.
    vertices : (Vp, ) int ndarray
        Mesh vertices with ``β > 0`` for this part.
    beta : (Vp,) float ndarray
    vertex_basis : (Vp, 9) float ndarray
        Centred scaled monomials of the vertices.
    vertex_local : (Vp, 3) float ndarray
    vertex_kernel : (Vp, n) scipy.sparse.csr_matrix
    messages : list of str
        Adjustments made (e.g. a reduced dilation).
    residual_kernel : {"cubic_bspline", "thin_plate"}
        Radial kernel of the residual (P&H Eq. 7 uses the cubic B-spline).
    support : (2, 3) float ndarray or None
        Lower and upper corners (local frame) of the box where the quadratic is
        evaluated as fitted: the markers' bounding box grown by a margin; beyond
        it the monomials continue to first order (:meth:`basis`).  ``None``: the
        quadratic everywhere (the paper).
    clamp_margin : float or None
        Soft clamp of the non-rigid displacement at the part's largest marker
        deviation ``b`` (:func:`soft_clamp`: unchanged up to ``b``, never beyond
        ``(1 + clamp_margin) b``).  ``None``: no clamp (the paper).
    """

    name: str
    members: np.ndarray
    alpha: np.ndarray
    local: np.ndarray
    origin: np.ndarray
    axes: np.ndarray
    scale: float
    q_mean: np.ndarray
    sigma: float
    kernel: sp.csc_matrix
    quadratic: bool
    vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    beta: np.ndarray = field(default_factory=lambda: np.zeros(0))
    vertex_basis: np.ndarray = field(default_factory=lambda: np.zeros((0, 9)))
    vertex_local: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    vertex_kernel: sp.csr_matrix | None = None
    messages: list[str] = field(default_factory=list)
    residual_kernel: str = "cubic_bspline"
    support: np.ndarray | None = None
    clamp_margin: float | None = None

    def basis(self, local: np.ndarray) -> np.ndarray:
        """Centred scaled monomials of local points ``(..., 3) -> (..., 9)``.

        Inside the :attr:`support` box the paper's ``q``; outside, ``q`` of the
        nearest point of the box: the quadratic's displacement is held at its
        value on the box instead of growing where no marker constrains it.
        """
        p = local / self.scale
        if self.support is not None:
            p = np.clip(p, self.support[0] / self.scale, self.support[1] / self.scale)
        return quadratic_basis(p) - self.q_mean

    def kernel_rows(self, local: np.ndarray) -> sp.csr_matrix:
        """Residual kernel values ``(N, n)`` of local points ``(N, 3)`` at the part's markers."""
        if self.residual_kernel == "thin_plate":
            return thin_plate_matrix(local, self.local, self.scale)
        return rbf_matrix(local, self.local, self.sigma)


def prepare_part(
    segmentation: Segmentation,
    p: int,
    *,
    vertices: np.ndarray | None = None,
    beta: np.ndarray | None = None,
    min_quadratic_markers: int = 10,
    dilation_factor: float = 2.0,
    residual_kernel: str = "cubic_bspline",
    support_margin: float | None = 0.5,
    clamp_margin: float | None = 0.1,
) -> PartModel:
    """Frame-independent model of part ``p`` (local coordinates, bases, kernels).

    Parameters
    ----------
    segmentation : Segmentation
    p : int
        Part index.
    vertices : (V, 3) float ndarray, optional
        Rest vertices of the detailed mesh (omit to fit markers only).
    beta : (V, P) float ndarray, optional
        Vertex weights from :func:`~mocapflow.stages.skin.binding.bind_mesh`.
    min_quadratic_markers : int
    dilation_factor : float
        B-spline support = this × the part's largest nearest-neighbour distance.
    residual_kernel : {"cubic_bspline", "thin_plate"}
        ``"cubic_bspline"``: the paper's compactly supported kernel (sparse);
        ``"thin_plate"``: ``r² log r`` with a linear polynomial (dense, per part).
    support_margin : float or None
        The quadratic is evaluated as fitted within the markers' bounding box (in
        the part's frame) grown by this × the part's largest nearest-neighbour
        marker distance, and continued to first order beyond it
        (:meth:`PartModel.basis`); ``None``: everywhere (the paper).
    clamp_margin : float or None
        Non-rigid displacements beyond the part's largest marker deviation are
        softly clamped to at most ``1 + clamp_margin`` times it
        (:func:`soft_clamp`); ``None``: no clamp (the paper).

    Returns
    -------
    PartModel
    """
    if residual_kernel not in RESIDUAL_KERNELS:
        raise DeformError(
            f"unknown residual kernel {residual_kernel!r}; choose one of {list(RESIDUAL_KERNELS)}"
        )
    members = segmentation.members(p)
    alpha = segmentation.weights[members, p]
    origin, axes = segmentation.origins[p], segmentation.axes[p]
    local = (segmentation.reference[members] - origin) @ axes
    w = alpha / alpha.sum()
    scale = float(np.sqrt(np.sum(w * np.sum(local**2, 1)))) or 1.0
    q_mean = w @ quadratic_basis(local / scale)  # markers are inside the support box
    sigma = dilation(local, factor=dilation_factor)
    note = ""
    if residual_kernel == "thin_plate":
        kernel = thin_plate_matrix(local, local, scale).tocsc()
    else:
        kernel, sigma, note = _well_conditioned_kernel(local, sigma, segmentation.part_names[p])
    model = PartModel(
        name=segmentation.part_names[p],
        members=members,
        alpha=alpha,
        local=local,
        origin=origin,
        axes=axes,
        scale=scale,
        q_mean=q_mean,
        sigma=sigma,
        kernel=kernel,
        quadratic=len(members) >= min_quadratic_markers,
        residual_kernel=residual_kernel,
        support=None if support_margin is None
        else np.stack([local.min(0), local.max(0)])
        + np.array([[-1.0], [1.0]]) * float(support_margin) * _largest_nearest_neighbour(local),
        clamp_margin=None if clamp_margin is None else float(clamp_margin),
    )
    if note:
        model.messages.append(note)
    if vertices is not None and beta is not None:
        vidx = np.flatnonzero(beta[:, p] > 0)
        vl = (vertices[vidx] - origin) @ axes
        model.vertices = vidx
        model.beta = beta[vidx, p]
        model.vertex_local = vl
        model.vertex_basis = model.basis(vl)
        model.vertex_kernel = model.kernel_rows(vl)
    return model


def _largest_nearest_neighbour(local: np.ndarray) -> float:
    """The largest distance ``(m)`` from a marker to its nearest neighbour (marker spacing)."""
    if len(local) < 2:
        return 0.0
    dist, _ = cKDTree(local).query(local, k=2)
    return float(dist[:, 1].max())


def soft_clamp(u: np.ndarray, bound: np.ndarray, margin: float | np.ndarray) -> np.ndarray:
    """Shorten displacements ``u (..., 3)`` longer than ``bound (...)``, smoothly (``margin``:
    one, or one per displacement ``(...)``).

    A length ``r ≤ b`` is kept; beyond it becomes ``b + m tanh((r - b) / m)``
    with ``m = margin · b`` (continuous slope at ``b``, never ``≥ b + m``).
    """
    r = np.linalg.norm(u, axis=-1)
    b = np.broadcast_to(bound, r.shape)
    over = r > b
    if not over.any():
        return u
    r, b = r[over], b[over]  # the lengths beyond the bound only (the others are kept)
    m = np.broadcast_to(margin, over.shape)[over] * b
    with np.errstate(divide="ignore", invalid="ignore"):
        new = b + np.where(m > 0, m * np.tanh((r - b) / np.where(m > 0, m, 1.0)), 0.0)
    out = u.copy()
    out[over] = u[over] * (new / r)[:, None]
    return out


@dataclass
class PartFit:
    """Per-frame parameters of one part.

    Attributes
    ----------
    R : (F, 3, 3) float ndarray
    d : (F, 3) float ndarray
        Rigid transform ``x ≈ R p̄ + d`` (translation after the quadratic offset).
    A : (F, 3, 9) float ndarray
        Quadratic transform in the centred scaled basis, as a deviation from
        the identity (``p̂ = p̄ + A q``); zero in rigid modes.
    W : (F, n, 3) float ndarray
        RBF coefficients of the residual; zero in modes without residual.
    rigid_frames : (F,) bool ndarray
        Frames whose rigid transform was fitted (others interpolated).
    quadratic_frames : (F,) bool ndarray
        Frames whose quadratic was fitted (others interpolated or rigid).
    messages : list of str
        Fallbacks taken (the stage turns them into warnings).
    rigid_d : (F, 3) float ndarray or None
        Translation of the rigid (Horn) fit alone, ``x ≈ R p̄ + rigid_d``; ``d``
        also carries the quadratic's constant (``None``: the same as ``d``).
    marker_deviation : (F,) float ndarray or None
        Largest distance of the part's visible markers from their rigid
        prediction (interpolated in time where not fitted): the bound of
        :func:`soft_clamp`.
    """

    R: np.ndarray
    d: np.ndarray
    A: np.ndarray
    W: np.ndarray
    rigid_frames: np.ndarray
    quadratic_frames: np.ndarray
    messages: list[str] = field(default_factory=list)
    rigid_d: np.ndarray | None = None
    marker_deviation: np.ndarray | None = None


def _fill_in_time(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Linear interpolation along axis 0 from ``valid`` frames (held at the ends)."""
    if valid.all():
        return values
    F = len(values)
    good = np.flatnonzero(valid)
    flat = values.reshape(F, -1)
    out = np.empty_like(flat)
    t = np.arange(F)
    for k in range(flat.shape[1]):
        out[:, k] = np.interp(t, good, flat[good, k])
    return out.reshape(values.shape)


def _fill_rotations(R: np.ndarray, valid: np.ndarray) -> np.ndarray:
    if valid.all():
        return R
    q = quat_from_matrix(np.where(valid[:, None, None], R, np.eye(3)))
    q[valid] = quat_continuity(q[valid], axis=0)
    q = quat_normalize(_fill_in_time(q, valid))
    return quat_to_matrix(q)


def _frame_ranges(mask: np.ndarray) -> str:
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return ""
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.r_[idx[0], idx[breaks + 1]]
    ends = np.r_[idx[breaks], idx[-1]]
    parts = [f"{a}" if a == b else f"{a}-{b}" for a, b in zip(starts, ends)]
    return ", ".join(parts[:5]) + (", ..." if len(parts) > 5 else "")


def fit_part(
    model: PartModel,
    x: np.ndarray,
    *,
    mode: str,
    min_quadratic_markers: int = 10,
    damping: float = 0.0,
) -> PartFit:
    """Fit one part's rigid, quadratic and residual model in every frame.

    Parameters
    ----------
    model : PartModel
    x : (F, n, 3) float ndarray
        Observed positions of the part's markers, NaN where missing.
    mode : {"rigid", "quadratic", "rigid_residual", "quadratic_residual"}
    min_quadratic_markers : int
        Fewer visible markers than this in a frame: the quadratic is not fitted
        there (interpolated from neighbouring frames).
    damping : float
        Ridge on the 9 quadratic coefficients (toward the rigid transform),
        relative to the summed marker weights; 0 is the paper's plain
        pseudo-inverse (P&H Eq. 6).

    Returns
    -------
    PartFit

    Raises
    ------
    DeformError
        The part has < 3 visible non-collinear markers in every frame.
    """
    if mode not in MODES:
        raise DeformError(f"unknown deformation mode {mode!r}; choose one of {list(MODES)}")
    F, n = x.shape[:2]
    messages: list[str] = []
    vis = np.isfinite(x).all(-1)
    R, d, rigid_ok = _rigid_fits(model, x, vis, messages)
    with np.errstate(invalid="ignore"):
        dev = np.linalg.norm(x - model.local[None] @ R.transpose(0, 2, 1) - d[:, None], axis=-1)
    deviation = _fill_in_time(np.max(np.where(vis, dev, 0.0), axis=1), rigid_ok)
    rigid_d = _fill_in_time(d, rigid_ok)
    use_quadratic = mode.startswith("quadratic")
    if use_quadratic and not model.quadratic:
        messages.append(
            f"part {model.name!r} has {n} markers (< {min_quadratic_markers}): the quadratic "
            f"transform is under-determined, using rigid"
            f"{' + residual' if mode.endswith('residual') else ''} for this part"
        )
        use_quadratic = False
    A = np.zeros((F, 3, 9))
    c = np.zeros((F, 3))
    quad_ok = np.zeros(F, bool)
    if use_quadratic:
        A, c, quad_ok = _quadratic_fits(model, x, vis, R, d, rigid_ok, messages,
                                        min_quadratic_markers=min_quadratic_markers,
                                        damping=damping)
    # fold the offset into the translation: x = R (p̄ + A q + c) + d = R (p̄ + A q) + d'
    d = d + (R @ c[:, :, None])[..., 0]
    W = np.zeros((F, n, 3))
    poly = np.zeros((F, 4, 3))  # thin plate: [1, p̄/scale] coefficients per frame
    if mode.endswith("residual"):
        W, poly = _residual_fits(model, x, vis, R, d, A, rigid_ok)
    R = _fill_rotations(R, rigid_ok)
    d = _fill_in_time(d, rigid_ok)
    if mode.endswith("residual") and model.residual_kernel == "thin_plate":
        A, d = _fold_linear_polynomial(model, R, A, d, poly)
    return PartFit(R, d, A, W, rigid_ok, quad_ok, messages, rigid_d, deviation)


def _rigid_fits(model: PartModel, x: np.ndarray, vis: np.ndarray,
                messages: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 1: Horn's fit of the part's ``p̄`` onto the visible ``x`` per frame, ``α``-weighted.

    Returns ``R (F, 3, 3)``, ``d (F, 3)`` (NaN where not fitted) and the fitted
    frames ``(F,)``; frames left unfitted are reported in ``messages``.

    Raises
    ------
    DeformError
        No frame has 3 visible non-collinear markers.
    """
    F, n = x.shape[:2]
    w = np.where(vis, model.alpha[None, :], 0.0)
    src = np.broadcast_to(model.local, (F, n, 3))
    R, d = absolute_orientation_batch(src, x, weights=w)
    rigid_ok = np.isfinite(R).all((1, 2))
    if not rigid_ok.any():
        raise DeformError(
            f"part {model.name!r} has fewer than 3 visible non-collinear markers in every "
            f"frame ({n} markers): it cannot be placed"
        )
    if not rigid_ok.all():
        messages.append(
            f"part {model.name!r}: fewer than 3 usable markers in {int((~rigid_ok).sum())} of "
            f"{F} frames ({_frame_ranges(~rigid_ok)}); its model there is interpolated from "
            "the nearest fitted frames"
        )
    return R, d, rigid_ok


def _quadratic_fits(
    model: PartModel, x: np.ndarray, vis: np.ndarray, R: np.ndarray, d: np.ndarray,
    rigid_ok: np.ndarray, messages: list[str], *, min_quadratic_markers: int, damping: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 2 (P&H Eq. 6): ``p̂ - p̄ ≈ A q(p̄) + c`` per frame, one (damped) pseudo-inverse
    per visibility pattern.

    Returns ``A (F, 3, 9)`` (interpolated in time where not fitted), ``c (F, 3)``
    (0 there) and the fitted frames ``(F,)``; fallbacks go to ``messages``.
    """
    F, n = x.shape[:2]
    with np.errstate(invalid="ignore"):
        local_obs = (x - d[:, None, :]) @ R  # p̂ = R^T (x - d), NaN where missing
    dev = local_obs - model.local[None]  # p̂ - p̄
    A = np.zeros((F, 3, 9))
    c = np.zeros((F, 3))
    quad_ok = rigid_ok & (vis.sum(1) >= min_quadratic_markers)
    if not quad_ok.any():
        messages.append(
            f"part {model.name!r}: never {min_quadratic_markers} visible markers in one "
            "frame, using rigid for this part"
        )
        return A, c, quad_ok
    D = np.concatenate([model.basis(model.local), np.ones((n, 1))], axis=1)  # (n, 10)
    for pattern, frames in _patterns(vis, quad_ok):
        sw = np.sqrt(model.alpha * pattern)
        G = _damped_pinv(sw[:, None] * D, damping * float(np.sum(model.alpha * pattern)))
        rhs = np.where(pattern[None, :, None], dev[frames], 0.0) * sw[None, :, None]
        coef = (G @ rhs).transpose(0, 2, 1)  # (f, 3, 10)
        A[frames] = coef[..., :9]
        c[frames] = coef[..., 9]
    if not quad_ok[rigid_ok].all():
        messages.append(
            f"part {model.name!r}: fewer than {min_quadratic_markers} visible markers in "
            f"{int((rigid_ok & ~quad_ok).sum())} frames "
            f"({_frame_ranges(rigid_ok & ~quad_ok)}); quadratic terms interpolated there"
        )
    A = _fill_in_time(A, quad_ok)
    c = np.where(quad_ok[:, None], c, 0.0)
    return A, c, quad_ok


def _residual_fits(model: PartModel, x: np.ndarray, vis: np.ndarray, R: np.ndarray,
                   d: np.ndarray, A: np.ndarray,
                   rigid_ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Step 3 (P&H Eq. 7): the RBF interpolation of what the rigid + quadratic model leaves,
    one solve per visibility pattern.

    Returns the kernel weights ``W (F, n, 3)`` and, for the thin plate, its linear
    polynomial ``(F, 4, 3)`` (``[1, p̄/scale]``; zero otherwise), both
    interpolated in time where the part was not fitted.
    """
    F, n = x.shape[:2]
    W = np.zeros((F, n, 3))
    with np.errstate(invalid="ignore"):
        model_pos = model.local[None] + model.basis(model.local) @ A.transpose(0, 2, 1)
        resid = (x - d[:, None, :]) @ R - model_pos
    poly = np.zeros((F, 4, 3))  # thin plate: [1, p̄/scale] coefficients per frame
    for pattern, frames in _patterns(vis, rigid_ok):
        idx = np.flatnonzero(pattern)
        rhs = resid[frames][:, idx, :].transpose(1, 0, 2).reshape(len(idx), -1)
        K = model.kernel[idx][:, idx]
        if model.residual_kernel == "thin_plate":
            sol, pc = _solve_thin_plate(K, model.local[idx] / model.scale, rhs)
            poly[frames] = pc.reshape(4, len(frames), 3).transpose(1, 0, 2)
        else:
            sol = _solve_kernel(K, rhs)
        W[np.ix_(frames, idx)] = sol.reshape(len(idx), len(frames), 3).transpose(1, 0, 2)
    W = _fill_in_time(W, rigid_ok)
    if model.residual_kernel == "thin_plate":
        poly = _fill_in_time(poly, rigid_ok)
    return W, poly


def _fold_linear_polynomial(model: PartModel, R: np.ndarray, A: np.ndarray, d: np.ndarray,
                            poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fold the thin-plate residual's linear polynomial ``a0 + a1 p̄/scale`` into ``A``
    and ``d`` (``p̄_k/scale = q_k + q_mean_k`` for the three linear monomials)."""
    lin = poly[:, 1:].transpose(0, 2, 1)  # (F, 3, 3): [i, k]
    A = A.copy()
    A[:, :, :3] += lin
    const = poly[:, 0] + lin @ model.q_mean[:3]
    d = d + (R @ const[:, :, None])[..., 0]
    return A, d



def _damped_pinv(D: np.ndarray, lam: float) -> np.ndarray:
    """``(10, n)`` solution operator of ``min |D a - y|^2 + lam |a[:9]|^2`` (P&H Eq. 6 when 0)."""
    if lam <= 0:
        return np.linalg.pinv(D, rcond=1e-8)
    reg = np.zeros((9, D.shape[1]))
    reg[:, :9] = np.sqrt(lam) * np.eye(9)
    return np.linalg.pinv(np.concatenate([D, reg]), rcond=1e-8)[:, : D.shape[0]]


def _patterns(vis: np.ndarray, frames_ok: np.ndarray):
    """Yield ``(pattern (n,) bool, frame indices)`` for each visibility pattern."""
    ok = np.flatnonzero(frames_ok)
    if ok.size == 0:
        return
    if vis[ok].all():  # the common case after cleaning: one pattern, no sort
        yield np.ones(vis.shape[1], bool), ok
        return
    pats, inv = np.unique(vis[ok], axis=0, return_inverse=True)
    inv = np.asarray(inv).ravel()
    for k, pat in enumerate(pats):
        yield pat, ok[inv == k]


def evaluate_part(model: PartModel, fit: PartFit, local: np.ndarray | None = None,
                  basis: np.ndarray | None = None,
                  kernel: sp.csr_matrix | None = None) -> np.ndarray:
    """Global positions of points moved by one part's model (P&H Eq. 8).

    ``R (p̄ + u) + d_rigid`` with ``u = A q(p̄) + c + Wᵀ φ(p̄)`` the non-rigid
    terms (``q`` continued linearly outside the part's support box,
    :meth:`PartModel.basis`), ``R u`` soft-clamped at the part's marker deviation
    (:func:`soft_clamp`) when the model has a ``clamp_margin``; with neither,
    exactly P&H Eq. 8.

    Parameters
    ----------
    model : PartModel
    fit : PartFit
        Parameters of ``F`` frames.
    local, basis, kernel : optional
        Local coordinates ``(N, 3)``, centred monomials ``(N, 9)`` and kernel rows
        ``(N, n)`` of the points; default: the model's mesh vertices.

    Returns
    -------
    (F, N, 3) float ndarray
    """
    local = model.vertex_local if local is None else local
    basis = model.vertex_basis if basis is None else basis
    kernel = model.vertex_kernel if kernel is None else kernel
    F = fit.R.shape[0]
    N = len(local)
    rigid_d = fit.d if fit.rigid_d is None else fit.rigid_d
    c = ((fit.d - rigid_d)[:, None, :] @ fit.R)[:, 0]  # (F, 3): R^T (d - d_rigid)
    u = basis @ fit.A.transpose(0, 2, 1) + c[:, None, :]
    if np.any(fit.W):
        n = fit.W.shape[1]
        r = kernel @ fit.W.transpose(1, 0, 2).reshape(n, F * 3)  # (N, F*3)
        u += r.reshape(N, F, 3).transpose(1, 0, 2)
    if model.clamp_margin is not None and fit.marker_deviation is not None:
        u = soft_clamp(u, fit.marker_deviation[:, None], model.clamp_margin)
    return (local[None] + u) @ fit.R.transpose(0, 2, 1) + rigid_d[:, None, :]
