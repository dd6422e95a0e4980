"""Data types of mocapflow and their exact Zarr (de)serialisation.

All lengths are metres; the unit of the source file is kept in ``attrs``
(``source_unit``) so writers can give it back.  Arrays are frame-major: the
store chunks them along ``frame`` and keeps the marker / joint / xyz axes whole.

Types
-----
Markers
    Optical markers from C3D: ``positions (F, M, 3)``, NaN where missing.
Skeleton, Motion
    Joint hierarchy and its animation (BVH, ASF/AMC): rotations as unit
    quaternions ``(w, x, y, z)``.
Mesh
    Triangle mesh, optionally animated: ``vertices (V, 3)`` or ``(F, V, 3)``.
Strokes, StrokesSet
    2-D pen trajectories with pen-up breaks; several of them as one output.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mocapflow.pipeline.codecs import (
    Encoded,
    codec,
    component_coords,
    frame_coords,
    label_coord,
)

__all__ = ["Markers", "Mesh", "Motion", "Skeleton", "Strokes", "StrokesSet", "UNIT_SCALE"]

#: Metres per unit for the unit strings found in C3D POINT:UNITS, BVH/ASF conventions.
UNIT_SCALE: dict[str, float] = {
    "m": 1.0,
    "dm": 0.1,
    "cm": 0.01,
    "mm": 0.001,
    "in": 0.0254,
    "inch": 0.0254,
    "ft": 0.3048,
    "cmu": 0.0254 / 0.45,  # CMU BVH/ASF length unit: inches / 0.45
}


def _f64(a: Any, shape_tail: tuple[int, ...] | None = None, name: str = "array") -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if shape_tail is not None and arr.shape[arr.ndim - len(shape_tail) :] != shape_tail:
        raise ValueError(f"{name}: expected shape (..., {shape_tail}), got {arr.shape}")
    return arr


def _hz(rate: float | None) -> str:
    """``"120 Hz"`` (``"? Hz"`` when unknown)."""
    return "? Hz" if rate is None else f"{float(rate):.4g} Hz"


def _axes(attrs: dict[str, Any]) -> str:
    """``", up +z"`` when ``attrs`` names the up axis, else ``""``."""
    up = attrs.get("up") if isinstance(attrs, dict) else None
    return f", up {str(up)[:8]}" if up else ""


def _names(names: Sequence[str], most: int = 3) -> str:
    """The first ``most`` names, then ``…`` (a repr stays one line)."""
    shown = ", ".join(str(n)[:24] for n in list(names)[:most])
    return shown + (", …" if len(names) > most else "")


# --------------------------------------------------------------------------- markers


@dataclass(eq=False)
class Markers:
    """Marker trajectories of one capture trial.

    Parameters
    ----------
    positions : (F, M, 3) float ndarray
        Labelled marker positions in metres; NaN where the marker is missing.
    labels : list of str
        ``M`` labels.
    rate : float
        Frames per second.
    first_frame : int
        Index of the first frame in the source (C3D ``first_frame``).
    residuals : (F, M) float ndarray, optional
        Reconstruction residuals (metres) where the source has them; NaN where missing.
    fragments : (F, U, 3) float ndarray, optional
        Unlabelled trajectories (C3D ``*12`` style), NaN outside each fragment.
    fragment_labels : list of str
        ``U`` names of the unlabelled trajectories.
    attrs : dict
        Source file, ``source_unit``, points excluded as model outputs, etc.; for
        C3D sources ``c3d_parameters``, the file's whole parameter section as a JSON
        tree (see :func:`mocapflow.stages.motion.formats.c3d.parameter_tree`).
    analogs : (S, C) float ndarray, optional
        Analog samples of the source (C3D ``ANALOG`` data, ``S = F x`` subframes,
        ``C`` channels) in the source's units (``ANALOG:SCALE``, ``GEN_SCALE`` and
        ``OFFSET`` applied); their labels, units and rate are in
        ``attrs["c3d_parameters"]["ANALOG"]``.
    status : (F, M) int8 ndarray, optional
        Per-sample state after cleaning: -1 missing, 0 measured, 1 merged from a
        fragment, 2 filled (the ``clean`` stage's codes); ``None`` for raw captures.
    """

    positions: np.ndarray
    labels: list[str]
    rate: float
    first_frame: int = 0
    residuals: np.ndarray | None = None
    fragments: np.ndarray | None = None
    fragment_labels: list[str] = field(default_factory=list)
    attrs: dict[str, Any] = field(default_factory=dict)
    analogs: np.ndarray | None = None
    status: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.positions = _f64(self.positions, (3,), "positions")
        if self.positions.ndim != 3:
            raise ValueError(f"positions: expected (F, M, 3), got {self.positions.shape}")
        self.labels = [str(x) for x in self.labels]
        if len(self.labels) != self.positions.shape[1]:
            raise ValueError(
                f"{len(self.labels)} labels for {self.positions.shape[1]} markers"
            )
        if self.residuals is not None:
            self.residuals = _f64(self.residuals)
            if self.residuals.shape != self.positions.shape[:2]:
                raise ValueError(f"residuals: expected {self.positions.shape[:2]}")
        if self.fragments is None:
            self.fragments = np.full((self.n_frames, 0, 3), np.nan)
        self.fragments = _f64(self.fragments, (3,), "fragments")
        self.fragment_labels = [str(x) for x in self.fragment_labels]
        if len(self.fragment_labels) != self.fragments.shape[1]:
            raise ValueError("fragment_labels and fragments disagree")
        self.rate = float(self.rate)
        self.first_frame = int(self.first_frame)
        if self.analogs is not None:
            self.analogs = _f64(self.analogs)
            S = self.analogs.shape[0]
            if self.analogs.ndim != 2 or (self.n_frames and S % self.n_frames):
                raise ValueError(
                    f"analogs: expected (S, C) with S a multiple of {self.n_frames} frames, "
                    f"got {self.analogs.shape}"
                )
        if self.status is not None:
            self.status = np.asarray(self.status, dtype=np.int8)
            if self.status.shape != self.positions.shape[:2]:
                raise ValueError(f"status: expected {self.positions.shape[:2]}")

    def __repr__(self) -> str:
        """One line: frames × markers, rate, up axis, missing share (never array contents)."""
        F, M = self.positions.shape[:2]
        missing = 100.0 * (1.0 - self.visible.mean()) if F * M else 0.0
        extra = f", {self.fragments.shape[1]} fragments" if self.fragments.shape[1] else ""
        if self.analogs is not None:
            extra += f", {self.analogs.shape[1]} analog channels"
        if self.status is not None:
            extra += f", {100.0 * (self.status == 2).mean():.1f}% filled"
        return (f"Markers({F} frames × {M} markers @ {_hz(self.rate)}{_axes(self.attrs)}, "
                f"{missing:.1f}% missing{extra})")

    @property
    def n_frames(self) -> int:
        """Number of frames ``F``."""
        return self.positions.shape[0]

    @property
    def analog_subframes(self) -> int:
        """Analog samples per frame (0 without analogs)."""
        if self.analogs is None or not self.n_frames:
            return 0
        return self.analogs.shape[0] // self.n_frames

    @property
    def n_markers(self) -> int:
        """Number of labelled markers ``M``."""
        return self.positions.shape[1]

    @property
    def visible(self) -> np.ndarray:
        """``(F, M)`` bool: marker present in frame."""
        return np.isfinite(self.positions).all(axis=-1)

    def replace(self, **changes: Any) -> Markers:
        """A copy with some fields replaced.

        ``status`` is carried over only while the labels and frame count stay (it
        belongs to those samples) and ``analogs`` only while the frame count stays,
        unless given.
        """
        kw = dict(
            positions=self.positions,
            labels=self.labels,
            rate=self.rate,
            first_frame=self.first_frame,
            residuals=self.residuals,
            fragments=self.fragments,
            fragment_labels=self.fragment_labels,
            attrs=dict(self.attrs),
            analogs=self.analogs,
            status=self.status,
        )
        kw.update(changes)
        new_f = np.shape(kw["positions"])[0]
        if "status" not in changes and self.status is not None and (
            new_f != self.n_frames or [str(x) for x in kw["labels"]] != self.labels
        ):
            kw["status"] = None
        if "analogs" not in changes and new_f != self.n_frames:
            kw["analogs"] = None
        return Markers(**kw)

    def take_frames(self, frames: np.ndarray | slice) -> Markers:
        """A copy with only these frames (positions, residuals and fragments alike).

        Parameters
        ----------
        frames : (K,) int ndarray or slice
            The analog samples of those frames are kept with them.
        """
        analogs = None
        if self.analogs is not None:
            n = self.analog_subframes
            rows = np.arange(self.n_frames * n).reshape(self.n_frames, n)[frames].ravel()
            analogs = self.analogs[rows]
        return self.replace(
            positions=self.positions[frames],
            residuals=None if self.residuals is None else self.residuals[frames],
            fragments=self.fragments[frames],
            analogs=analogs,
            status=None if self.status is None else self.status[frames],
        )


def _analog_labels(m: Markers) -> list[str] | None:
    """``ANALOG:LABELS`` of a C3D source when there is one per analog channel."""
    try:
        labels = m.attrs["c3d_parameters"]["ANALOG"]["parameters"]["LABELS"]["value"]
    except (KeyError, TypeError):
        return None
    if m.analogs is None or not isinstance(labels, list) or len(labels) != m.analogs.shape[1]:
        return None
    return [str(x).strip() for x in labels]


def _markers_coords(m: Markers) -> dict[str, tuple[np.ndarray, tuple[str, ...]]]:
    """``frame`` (source numbers from ``first_frame``), ``time`` (s), labels, ``xyz``."""
    coords = {
        **frame_coords(m.n_frames, m.rate, m.first_frame),
        "marker": label_coord(m.labels, "marker"),
        "fragment": label_coord(m.fragment_labels, "fragment"),
        **component_coords("xyz"),
    }
    if m.analogs is not None:
        n = m.analog_subframes
        sample = m.first_frame * n + np.arange(m.analogs.shape[0], dtype=np.int64)
        if n and m.rate > 0:
            coords["analog_time"] = (sample / (m.rate * n), ("analog_sample",))
        labels = _analog_labels(m)
        if labels is not None:
            coords["channel"] = label_coord(labels, "channel")
    return coords


def _encode_markers(m: Markers) -> Encoded:
    arrays = {
        "positions": (m.positions, ("frame", "marker", "xyz")),
        "fragments": (m.fragments, ("frame", "fragment", "xyz")),
    }
    if m.residuals is not None:
        arrays["residuals"] = (m.residuals, ("frame", "marker"))
    if m.analogs is not None:
        arrays["analogs"] = (m.analogs, ("analog_sample", "channel"))
    if m.status is not None:
        arrays["status"] = (m.status, ("frame", "marker"))
    return Encoded(
        "markers",
        arrays,
        {
            "labels": m.labels,
            "rate": m.rate,
            "first_frame": m.first_frame,
            "fragment_labels": m.fragment_labels,
            "attrs": m.attrs,
        },
        _markers_coords(m),
    )


def _decode_markers(e: Encoded) -> Markers:
    a = e.attrs
    return Markers(
        positions=e.arrays["positions"][0],
        labels=a["labels"],
        rate=a["rate"],
        first_frame=a["first_frame"],
        residuals=e.arrays["residuals"][0] if "residuals" in e.arrays else None,
        fragments=e.arrays["fragments"][0],
        fragment_labels=a["fragment_labels"],
        attrs=a.get("attrs", {}),
        analogs=e.arrays["analogs"][0] if "analogs" in e.arrays else None,
        status=e.arrays["status"][0] if "status" in e.arrays else None,
    )


codec("markers", encode=_encode_markers, decode=_decode_markers)(Markers)


# --------------------------------------------------------------------------- skeleton / motion


@dataclass(eq=False)
class Skeleton:
    """A joint hierarchy.

    Parameters
    ----------
    names : list of str
        ``J`` joint names, parents before children (index 0 is the root).
    parents : (J,) int ndarray
        Parent index per joint, -1 for the root.
    offsets : (J, 3) float ndarray
        Rest offset of each joint from its parent, metres (root: its offset).
    channels : list of list of str
        Per joint, the BVH-style channel names in file order, e.g.
        ``["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"]``.
        The rotation order of a joint is the order of its rotation channels.
    end_parents : (E,) int ndarray
        Joint index owning each End Site.
    end_offsets : (E, 3) float ndarray
        End Site offsets, metres.
    attrs : dict
        Format details needed to write the file back (e.g. ASF axes, dof limits).
    """

    names: list[str]
    parents: np.ndarray
    offsets: np.ndarray
    channels: list[list[str]]
    end_parents: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    end_offsets: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.names = [str(n) for n in self.names]
        self.parents = np.asarray(self.parents, dtype=np.int64)
        self.offsets = _f64(self.offsets, (3,), "offsets").reshape(-1, 3)
        self.channels = [[str(c) for c in ch] for ch in self.channels]
        self.end_parents = np.asarray(self.end_parents, dtype=np.int64).reshape(-1)
        self.end_offsets = _f64(self.end_offsets).reshape(-1, 3)
        J = len(self.names)
        if self.parents.shape != (J,) or self.offsets.shape != (J, 3) or len(self.channels) != J:
            raise ValueError("skeleton: names, parents, offsets and channels disagree in length")
        if J and self.parents[0] != -1:
            raise ValueError("skeleton: joint 0 must be the root (parent -1)")
        if np.any(self.parents[1:] >= np.arange(1, J)) or np.any(self.parents[1:] < 0):
            raise ValueError("skeleton: every parent must come before its child")

    def __repr__(self) -> str:
        """One line: joint count, root, end sites."""
        root = f", root {self.names[0][:24]!r}" if self.names else ""
        return f"Skeleton({self.n_joints} joints{root}, {len(self.end_parents)} end sites)"

    @property
    def n_joints(self) -> int:
        """Number of joints ``J``."""
        return len(self.names)

    def index(self, name: str) -> int:
        """Index of the joint called ``name`` (``KeyError`` naming it if absent)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint named {name!r} in skeleton") from None

    def children(self, j: int) -> list[int]:
        """Indices of the children of joint ``j``."""
        return [int(i) for i in np.flatnonzero(self.parents == j)]

    def rotation_order(self, j: int) -> str:
        """Rotation order of joint ``j`` as letters in channel order, e.g. ``"ZXY"``."""
        return "".join(c[0].upper() for c in self.channels[j] if c.lower().endswith("rotation"))


@dataclass(eq=False)
class Motion:
    """Animation of a skeleton.

    Parameters
    ----------
    skeleton : Skeleton
    root_position : (F, 3) float ndarray
        Root translation per frame, metres.
    rotations : (F, J, 4) float ndarray
        Local joint rotations as unit quaternions ``(w, x, y, z)``.
    rate : float
        Frames per second (BVH ``Frame Time`` is ``1 / rate``).
    translations : (F, J, 3) float ndarray, optional
        Per-frame local translations for joints with position channels
        (non-root); where given they replace the joint's offset.  ``None`` when
        only the root translates.
    attrs : dict
        ``source_unit``, source file, etc.
    """

    skeleton: Skeleton
    root_position: np.ndarray
    rotations: np.ndarray
    rate: float
    translations: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.root_position = _f64(self.root_position, (3,), "root_position").reshape(-1, 3)
        self.rotations = _f64(self.rotations, (4,), "rotations")
        F, J = self.rotations.shape[:2] if self.rotations.ndim == 3 else (-1, -1)
        if self.rotations.ndim != 3 or J != self.skeleton.n_joints:
            raise ValueError(
                f"rotations: expected (F, {self.skeleton.n_joints}, 4), got {self.rotations.shape}"
            )
        if self.root_position.shape[0] != F:
            raise ValueError("root_position and rotations disagree in frame count")
        if self.translations is not None:
            self.translations = _f64(self.translations, (3,), "translations")
            if self.translations.shape != (F, J, 3):
                raise ValueError(f"translations: expected {(F, J, 3)}")
        self.rate = float(self.rate)

    def __repr__(self) -> str:
        """One line: frames × joints, rate, duration, root, up axis."""
        F, J = self.rotations.shape[:2]
        secs = f", {F / self.rate:.3g} s" if self.rate > 0 else ""
        root = f", root {self.skeleton.names[0][:24]!r}" if J else ""
        extra = ", joint translations" if self.translations is not None else ""
        return (f"Motion({F} frames × {J} joints @ {_hz(self.rate)}{secs}{root}"
                f"{_axes(self.attrs)}{extra})")

    @property
    def n_frames(self) -> int:
        """Number of frames ``F``."""
        return self.rotations.shape[0]

    def replace(self, **changes: Any) -> Motion:
        """A copy with some fields replaced."""
        kw = dict(
            skeleton=self.skeleton,
            root_position=self.root_position,
            rotations=self.rotations,
            rate=self.rate,
            translations=self.translations,
            attrs=dict(self.attrs),
        )
        kw.update(changes)
        return Motion(**kw)


def _skeleton_attrs(s: Skeleton) -> dict[str, Any]:
    return {
        "names": s.names,
        "parents": s.parents.tolist(),
        "channels": s.channels,
        "end_parents": s.end_parents.tolist(),
        "attrs": s.attrs,
    }


def _skeleton_arrays(s: Skeleton) -> dict[str, tuple[np.ndarray, tuple[str, ...]]]:
    return {
        "offsets": (s.offsets, ("joint", "xyz")),
        "end_offsets": (s.end_offsets, ("end_site", "xyz")),
    }


def _skeleton_from(arrays: dict, a: dict) -> Skeleton:
    return Skeleton(
        names=a["names"],
        parents=np.asarray(a["parents"], dtype=np.int64),
        offsets=arrays["offsets"][0],
        channels=a["channels"],
        end_parents=np.asarray(a["end_parents"], dtype=np.int64),
        end_offsets=arrays["end_offsets"][0],
        attrs=a.get("attrs", {}),
    )


def _skeleton_coords(s: Skeleton) -> dict[str, tuple[np.ndarray, tuple[str, ...]]]:
    """Joint names along ``joint``, ``<parent>_end<i>`` along ``end_site``, ``xyz``."""
    ends = [f"{s.names[p]}_end{i}" for i, p in enumerate(s.end_parents.tolist())]
    return {
        "joint": label_coord(s.names, "joint"),
        "end_site": label_coord(ends, "end_site"),
        "end_parent": label_coord([s.names[p] for p in s.end_parents.tolist()], "end_site"),
        **component_coords("xyz"),
    }


def _encode_skeleton(s: Skeleton) -> Encoded:
    return Encoded("skeleton", _skeleton_arrays(s), _skeleton_attrs(s), _skeleton_coords(s))


def _decode_skeleton(e: Encoded) -> Skeleton:
    return _skeleton_from(e.arrays, e.attrs)


codec("skeleton", encode=_encode_skeleton, decode=_decode_skeleton)(Skeleton)


def _encode_motion(m: Motion) -> Encoded:
    arrays = _skeleton_arrays(m.skeleton)
    arrays["root_position"] = (m.root_position, ("frame", "xyz"))
    arrays["rotations"] = (m.rotations, ("frame", "joint", "wxyz"))
    if m.translations is not None:
        arrays["translations"] = (m.translations, ("frame", "joint", "xyz"))
    attrs = {"skeleton": _skeleton_attrs(m.skeleton), "rate": m.rate, "attrs": m.attrs}
    coords = {**_skeleton_coords(m.skeleton), **component_coords("wxyz"),
              **frame_coords(m.n_frames, m.rate)}  # BVH / AMC frames: 0-based
    return Encoded("motion", arrays, attrs, coords)


def _decode_motion(e: Encoded) -> Motion:
    return Motion(
        skeleton=_skeleton_from(e.arrays, e.attrs["skeleton"]),
        root_position=e.arrays["root_position"][0],
        rotations=e.arrays["rotations"][0],
        rate=e.attrs["rate"],
        translations=e.arrays["translations"][0] if "translations" in e.arrays else None,
        attrs=e.attrs.get("attrs", {}),
    )


codec("motion", encode=_encode_motion, decode=_decode_motion)(Motion)


# --------------------------------------------------------------------------- mesh


@dataclass(eq=False)
class Mesh:
    """A triangle mesh, static or animated.

    Parameters
    ----------
    vertices : (V, 3) or (F, V, 3) float ndarray
        Vertex positions in metres (one pose, or one per frame).
    faces : (T, 3) int ndarray
        Triangles as vertex indices.
    rate : float, optional
        Frames per second of an animated mesh.
    attrs : dict
        E.g. ``vertex_labels``, source.
    point_data : dict, optional
        Numeric per-vertex data the exporters write as VTK point data and USD
        primvars: ``name -> (V,) or (V, k)`` array (e.g. ``part_weights (V, P)``),
        or, for an animated mesh, ``(F, V)`` / ``(F, V, k)`` with one value per
        frame (e.g. ``error_mm``).
    """

    vertices: np.ndarray
    faces: np.ndarray
    rate: float | None = None
    attrs: dict[str, Any] = field(default_factory=dict)
    point_data: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = _f64(self.vertices, (3,), "vertices")
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        V = self.vertices.shape[-2]
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= V):
            raise ValueError("faces index vertices out of range")
        pd = {}
        for name, a in dict(self.point_data or {}).items():
            a = np.asarray(a)
            if not (isinstance(name, str) and name.isidentifier()) or a.dtype.kind not in "biuf":
                raise ValueError(f"point_data {name!r}: a numeric array under an identifier name")
            if not (a.ndim in (1, 2) and a.shape[0] == V) and not self.frame_varying(a):
                raise ValueError(
                    f"point_data {name!r}: expected (V,) or (V, k) with V = {V}"
                    + (f", or (F, V) / (F, V, k) with F = {self.vertices.shape[0]}"
                       if self.animated else "") + f"; got {a.shape}")
            pd[name] = a
        self.point_data = pd

    def __repr__(self) -> str:
        """One line: (frames ×) vertices, faces, rate, up axis, point-data names."""
        V, T = self.vertices.shape[-2], self.faces.shape[0]
        head = (f"{self.vertices.shape[0]} frames × {V} vertices @ {_hz(self.rate)}"
                if self.animated else f"{V} vertices")
        pd = f", point data: {_names(sorted(self.point_data))}" if self.point_data else ""
        return f"Mesh({head}, {T} faces{_axes(self.attrs)}{pd})"

    @property
    def animated(self) -> bool:
        """Whether ``vertices`` holds one pose per frame."""
        return self.vertices.ndim == 3

    def frame_varying(self, a: np.ndarray) -> bool:
        """Whether a point-data array holds one value per frame: ``(F, V)`` / ``(F, V, k)``
        of an animated mesh."""
        return (self.animated and a.ndim in (2, 3)
                and a.shape[:2] == self.vertices.shape[:2])


def _encode_mesh(m: Mesh) -> Encoded:
    dims = ("frame", "vertex", "xyz") if m.animated else ("vertex", "xyz")
    coords = component_coords("xyz")
    if m.animated:
        coords.update(frame_coords(m.vertices.shape[0], m.rate))
    labels = m.attrs.get("vertex_labels")
    if isinstance(labels, list) and len(labels) == m.vertices.shape[-2]:
        coords["vertex"] = label_coord(labels, "vertex")
    arrays = {"vertices": (m.vertices, dims), "faces": (m.faces, ("face", "corner"))}
    for name, a in m.point_data.items():
        lead = ("frame", "vertex") if m.frame_varying(a) else ("vertex",)
        arrays[f"point_data.{name}"] = (a, lead + (f"{name}_component",) * (a.ndim - len(lead)))
    attrs = {"rate": m.rate, "attrs": m.attrs}
    if m.point_data:  # only then, so meshes without it keep their digests
        attrs["point_data"] = sorted(m.point_data)
    return Encoded("mesh", arrays, attrs, coords)


def _decode_mesh(e: Encoded) -> Mesh:
    return Mesh(
        vertices=e.arrays["vertices"][0],
        faces=e.arrays["faces"][0],
        rate=e.attrs.get("rate"),
        attrs=e.attrs.get("attrs", {}),
        point_data={n: e.arrays[f"point_data.{n}"][0] for n in e.attrs.get("point_data", [])},
    )


codec("mesh", encode=_encode_mesh, decode=_decode_mesh)(Mesh)


# --------------------------------------------------------------------------- strokes


@dataclass(eq=False)
class Strokes:
    """2-D pen trajectories of one written example.

    Parameters
    ----------
    points : (N, 2) float ndarray
        Pen positions, all strokes concatenated in drawing order.
    stroke_starts : (S,) int ndarray
        Index in ``points`` where each stroke (pen-down run) starts; the first is 0.
    rate : float
        Samples per second.
    times : (N,) float ndarray, optional
        Sample times in seconds where the source has them.
    attrs : dict
        ``letter``, ``example``, source, unit.
    """

    points: np.ndarray
    stroke_starts: np.ndarray
    rate: float
    times: np.ndarray | None = None
    attrs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.points = _f64(self.points, (2,), "points").reshape(-1, 2)
        self.stroke_starts = np.asarray(self.stroke_starts, dtype=np.int64).reshape(-1)
        if self.stroke_starts.size == 0 or self.stroke_starts[0] != 0:
            raise ValueError("stroke_starts must start with 0")
        if np.any(np.diff(self.stroke_starts) <= 0) or self.stroke_starts[-1] >= max(
            len(self.points), 1
        ):
            raise ValueError("stroke_starts must be increasing and inside points")
        if self.times is not None:
            self.times = _f64(self.times).reshape(-1)
            if self.times.shape[0] != self.points.shape[0]:
                raise ValueError("times and points disagree in length")
        self.rate = float(self.rate)

    def __repr__(self) -> str:
        """One line: samples, strokes, rate, letter."""
        letter = self.attrs.get("letter") if isinstance(self.attrs, dict) else None
        tail = f", letter {str(letter)[:8]!r}" if letter is not None else ""
        return (f"Strokes({len(self.points)} samples in {len(self.stroke_starts)} strokes "
                f"@ {_hz(self.rate)}{tail})")

    def strokes(self) -> list[np.ndarray]:
        """The pen-down runs as a list of ``(n_i, 2)`` arrays."""
        return np.split(self.points, self.stroke_starts[1:])


def _encode_strokes(s: Strokes) -> Encoded:
    arrays = {
        "points": (s.points, ("sample", "xy")),
        "stroke_starts": (s.stroke_starts, ("stroke",)),
    }
    if s.times is not None:
        arrays["times"] = (s.times, ("sample",))
    return Encoded("strokes", arrays, {"rate": s.rate, "attrs": s.attrs}, component_coords("xy"))


def _decode_strokes(e: Encoded) -> Strokes:
    return Strokes(
        points=e.arrays["points"][0],
        stroke_starts=e.arrays["stroke_starts"][0],
        rate=e.attrs["rate"],
        times=e.arrays["times"][0] if "times" in e.arrays else None,
        attrs=e.attrs.get("attrs", {}),
    )


codec("strokes", encode=_encode_strokes, decode=_decode_strokes)(Strokes)


# --------------------------------------------------------------------------- strokes set


class StrokesSet(list):
    """Several :class:`Strokes` (e.g. the 5 examples of one UCI letter) as one output.

    A plain ``list`` subclass with a registered codec, so a stage can return it as a
    single output (``ingest_strokes_set``) and ``mocapflow export`` writes it as one CSV.
    """

    def __init__(self, items: Sequence[Strokes] = ()) -> None:
        items = list(items)
        for s in items:
            if not isinstance(s, Strokes):
                raise TypeError(f"StrokesSet holds Strokes, got {type(s).__name__}")
        super().__init__(items)

    def __repr__(self) -> str:
        """One line: how many examples and samples (not each one)."""
        n = sum(len(s.points) for s in self)
        return f"StrokesSet({len(self)} examples, {n} samples)"


def _encode_set(ss: StrokesSet) -> Encoded:
    n = np.array([len(s.points) for s in ss], dtype=np.int64)
    k = np.array([len(s.stroke_starts) for s in ss], dtype=np.int64)
    points = np.concatenate([s.points for s in ss]) if ss else np.zeros((0, 2))
    starts = np.concatenate([s.stroke_starts for s in ss]) if ss else np.zeros(0, np.int64)
    has_t = [s.times is not None for s in ss]
    times = (
        np.concatenate([s.times if s.times is not None else np.zeros(len(s.points)) for s in ss])
        if ss
        else np.zeros(0)
    )
    return Encoded(
        "strokes_set",
        {
            "points": (points, ("sample", "xy")),
            "stroke_starts": (starts, ("stroke",)),
            "times": (times, ("sample",)),
            "n_samples": (n, ("example",)),
            "n_strokes": (k, ("example",)),
        },
        {"rates": [s.rate for s in ss], "has_times": has_t, "attrs": [s.attrs for s in ss]},
        component_coords("xy"),
    )


def _decode_set(e: Encoded) -> StrokesSet:
    a = e.attrs
    pts, starts, times = (e.arrays[k][0] for k in ("points", "stroke_starts", "times"))
    n, k = e.arrays["n_samples"][0], e.arrays["n_strokes"][0]
    po, so = np.concatenate([[0], np.cumsum(n)]), np.concatenate([[0], np.cumsum(k)])
    out = []
    for i in range(len(n)):
        out.append(
            Strokes(
                points=pts[po[i] : po[i + 1]],
                stroke_starts=starts[so[i] : so[i + 1]],
                rate=a["rates"][i],
                times=times[po[i] : po[i + 1]] if a["has_times"][i] else None,
                attrs=a["attrs"][i],
            )
        )
    return StrokesSet(out)


codec("strokes_set", encode=_encode_set, decode=_decode_set)(StrokesSet)
