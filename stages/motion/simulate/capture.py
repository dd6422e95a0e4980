"""Dense-marker capture simulator with ground truth (for Park & Hodgins 2006).

The ``simulate_capture`` stage drives a body with a motion by linear-blend
skinning **plus known non-rigid skin motion**, sticks ~350 markers on its skin
and simulates a Vicon-like capture of them.  The steps and where they live:

1. **motion** — :func:`capture_motion` (here): ``calibration`` seconds in the
   skeleton's rest pose (T-pose, legs abducted), blended into a treadmill run,
   a treadmill walk (:mod:`~mocapflow.stages.motion.simulate.gait`), a range of
   motion (:mod:`~mocapflow.stages.motion.simulate.range_of_motion`) or a BVH;
2. **body** — :func:`capture_body` (here): a procedural capsule body around the
   motion's skeleton (:mod:`~mocapflow.stages.motion.simulate.capsules`) or the
   MakeHuman mesh (:mod:`~mocapflow.stages.motion.simulate.makehuman`), posed
   by :mod:`~mocapflow.stages.motion.simulate.body`;
3. **markers** — :func:`_marker_sites` (here) places them with
   :func:`~mocapflow.stages.motion.simulate.markers.place_markers` where the
   calibration pose shows them to the cameras; marker centres sit
   ``marker_radius`` above the skin;
4. **skin motion** — :func:`_moving_skin` (here) moves skin and markers with
   :class:`~mocapflow.stages.motion.simulate.skin_dynamics.SkinDynamics`;
5. **occlusion, merging, fragmentation** —
   :mod:`~mocapflow.stages.motion.simulate.optical` (camera ring, ray casting
   against the body capsules, markers merged in skin folds, Vicon-style
   fragments with labels only at the label frame);
6. **measurement noise** — isotropic Gaussian, ``noise`` metres (here).

Ground truth (``truth`` record, :func:`_capture_truth`): true marker positions,
visibility, part (dominant skin-weight joint) and body region per marker, the
true fragment -> marker map, the bind-pose marker layout, and the true mesh per
frame (``mesh`` output).  :mod:`mocapflow.stages.metrics.cleaning` scores a
cleaned capture against it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np

from mocapflow.pipeline import Context, FilePath, stage
from mocapflow.stages.motion.datatypes import Markers, Mesh, Motion
from mocapflow.stages.motion.formats.bvh import read_bvh
from mocapflow.stages.motion.geometry import vertex_normals
from mocapflow.stages.motion.kinematics import resample_motion
from mocapflow.stages.motion.rotations import quat_from_axis_angle, quat_identity, quat_slerp
from mocapflow.stages.motion.simulate.body import Body, skin, skinning_transforms
from mocapflow.stages.motion.simulate.capsules import procedural_body
from mocapflow.stages.motion.simulate.gait import procedural_walk
from mocapflow.stages.motion.simulate.makehuman import load_makehuman_body
from mocapflow.stages.motion.simulate.markers import (
    REGIONS,
    SurfacePoints,
    find_joint,
    marker_regions,
    place_markers,
)
from mocapflow.stages.motion.simulate.optical import (
    calibration_cameras,
    camera_ring,
    crowded,
    fragment_capture,
    marker_visibility,
)
from mocapflow.stages.motion.simulate.range_of_motion import procedural_range_of_motion
from mocapflow.stages.motion.simulate.skin_dynamics import SkinDynamics

__all__ = ["capture_body", "capture_motion", "simulate_capture"]


# --------------------------------------------------------------------------- motion


def capture_motion(
    kind: str, n_frames: int, *, rate: float, rng: np.random.Generator,
    calibration: float = 0.5, calibration_abduction: float = 12.0, bvh: str | None = None,
) -> Motion:
    """The motion of a simulated capture, starting with a rest-pose calibration.

    Parameters
    ----------
    kind : {"dynamic", "walk", "range_of_motion"}
        ``dynamic``: a run on a treadmill (forward progression removed);
        ``walk``: a treadmill walk; ``range_of_motion``: joint groups flexed in
        turn.  Ignored when ``bvh`` is given.
    n_frames : int
        Total frames, calibration included.
    rate : float
    rng : numpy.random.Generator
    calibration : float
        Seconds of calibration pose at the start (the rest pose, arms out, with
        the legs abducted by ``calibration_abduction`` degrees so the inner
        thighs are visible), then 0.25 s of blending into the motion.
    calibration_abduction : float
        Hip abduction of the calibration pose (degrees).
    bvh : str, optional
        A BVH file to drive the body instead (resampled to ``rate``).

    Returns
    -------
    Motion
    """
    n_cal = int(round(calibration * rate))
    n_blend = int(round(0.25 * rate)) if n_cal else 0
    m = _driving_motion(kind, max(n_frames - n_cal, 1), rate=rate, rng=rng, bvh=bvh)
    if n_cal == 0:
        return m
    return _with_calibration(m, n_frames, n_cal, n_blend, calibration_abduction)


def _driving_motion(kind: str, n_mot: int, *, rate: float, rng: np.random.Generator,
                    bvh: str | None) -> Motion:
    """``n_mot`` frames of the motion that follows the calibration (see :func:`capture_motion`)."""
    if bvh is not None:
        m = read_bvh(bvh)
        if abs(m.rate - rate) > 1e-6:
            m = resample_motion(m, rate)
        if m.n_frames < n_mot:
            raise ValueError(f"{bvh}: {m.n_frames} frames at {rate} Hz, {n_mot} needed")
        return m.replace(root_position=m.root_position[:n_mot], rotations=m.rotations[:n_mot],
                         translations=None if m.translations is None else m.translations[:n_mot])
    if kind in ("dynamic", "walk"):
        m = procedural_walk(n_mot, rate=rate, gait="run" if kind == "dynamic" else "walk",
                            seed=rng)
        root = m.root_position.copy()
        root[:, [0, 2]] -= np.linspace(root[0, [0, 2]], root[-1, [0, 2]], n_mot)  # treadmill
        return m.replace(root_position=root)
    if kind == "range_of_motion":
        return procedural_range_of_motion(n_mot, rate=rate, seed=rng)
    raise ValueError(f"unknown capture motion {kind!r} (dynamic, walk, range_of_motion)")


def _with_calibration(m: Motion, n_frames: int, n_cal: int, n_blend: int,
                      abduction: float) -> Motion:
    """``m`` after ``n_cal`` frames of the calibration pose, cut to ``n_frames``.

    The calibration "star" pose is the rest pose with the legs abducted by
    ``abduction`` degrees (so the inner thighs are seen too); its last
    ``n_blend`` frames blend (smoothstep slerp) into the first frame of ``m``.
    """
    J = m.skeleton.n_joints
    rest = quat_identity((n_cal, J))
    for side, sign in (("Left", 1.0), ("Right", -1.0)):
        j = find_joint(m.skeleton.names, f"{side}UpLeg")
        if j is not None:
            rest[:, j] = quat_from_axis_angle(np.array([0.0, 0.0, 1.0]),
                                              np.radians(sign * abduction))
    u = np.clip((np.arange(n_cal) - (n_cal - n_blend)) / max(n_blend, 1), 0, 1)
    u = u * u * (3 - 2 * u)
    rot = quat_slerp(rest, np.broadcast_to(m.rotations[0], rest.shape), u[:, None])
    root = np.broadcast_to(m.root_position[0], (n_cal, 3))
    tr = None
    if m.translations is not None:
        first = np.broadcast_to(m.translations[0], (n_cal,) + m.translations.shape[1:])
        tr = np.concatenate([first, m.translations])
    out = m.replace(rotations=np.concatenate([rot, m.rotations])[:n_frames],
                    root_position=np.concatenate([root, m.root_position])[:n_frames],
                    translations=None if tr is None else tr[:n_frames])
    out.attrs["calibration_frames"] = n_cal
    return out


# --------------------------------------------------------------------------- body


def capture_body(motion: Motion, *, body_mesh: str | None = None,
                 body_vertices: int = 3000) -> Body:
    """The body a capture is simulated on.

    Parameters
    ----------
    motion : Motion
        The driving motion (its skeleton shapes a procedural body).
    body_mesh : str, optional
        The MakeHuman ``makehuman_base.obj`` (rig and weights JSON beside it).
    body_vertices : int
        Vertex count of the procedural body.

    Returns
    -------
    Body
    """
    if body_mesh is not None:
        return load_makehuman_body(body_mesh)
    return procedural_body(motion.skeleton, n_vertices=body_vertices)


# --------------------------------------------------------------------------- simulation


def _layout_rng(rng: np.random.Generator) -> np.random.Generator:
    """A generator for the marker layout, derived from ``rng``'s seed, not its state.

    The layout stream is a fixed child of ``rng``'s seed sequence, so it neither
    depends on what the motion draws before it nor changes the main stream (a
    generator without a seed sequence gives up 4 draws instead, before the motion).
    """
    seq = getattr(rng.bit_generator, "seed_seq", None)
    if not isinstance(seq, np.random.SeedSequence):
        return np.random.default_rng(rng.bit_generator.random_raw(4))
    child = np.random.SeedSequence(seq.entropy, spawn_key=(*seq.spawn_key, 0x5EED1A))
    return np.random.default_rng(child)


def _marker_sites(body: Body, motion: Motion, R: np.ndarray, p: np.ndarray, n_markers: int, *,
                  n_cameras: int, min_cameras: int, marker_radius: float,
                  rng: np.random.Generator) -> SurfacePoints:
    """Marker sites where the calibration pose (frame 0) shows them, so all can be labelled.

    The layout depends on the body and ``rng`` (the layout stream) only, never on
    the motion: a range-of-motion trial and a dynamic trial of one seed share it.
    """
    v0 = skin(body, R[:1], p[:1])
    n0 = vertex_normals(v0, body.faces)
    cams0 = calibration_cameras(v0[0], motion.root_position[0], n_cameras=n_cameras)
    seen0 = marker_visibility(v0 + marker_radius * n0, n0, body, R[:1], p[:1], cams0)[0]
    return place_markers(body, n_markers, rng=rng, eligible=seen0 >= min_cameras + 1)


def _moving_skin(body: Body, motion: Motion, R: np.ndarray, p: np.ndarray,
                 sites: SurfacePoints, dynamics: SkinDynamics, *, marker_radius: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True skin ``(F, V, 3)``, true marker centres ``(F, M, 3)`` and their normals.

    Markers are bind-pose points ``marker_radius`` above the skin, carried by the
    skin's weights and the same non-rigid fields as the vertices.
    """
    skin_n, skin_w = sites.normals(body), sites.weights(body)
    mpts = sites.points(body) + marker_radius * skin_n
    pts = np.concatenate([body.vertices, mpts])
    nrm = np.concatenate([body.normals, skin_n])
    W = np.concatenate([body.weights, skin_w])
    part = np.concatenate([body.part, np.argmax(skin_w, axis=1)])
    allpos = dynamics.apply(body, motion, R, p, pts, nrm, W, part, rng=rng)
    V = body.n_vertices
    mesh_seq, true = allpos[:, :V], allpos[:, V:]
    corners = np.unique(body.faces[sites.face])
    vn = np.zeros(mesh_seq.shape[:1] + (body.n_vertices, 3))
    vn[:, corners] = _vertex_normals_at(mesh_seq, body.faces, corners)
    normals = sites.interpolate(body, vn)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return mesh_seq, true, normals


def _vertex_normals_at(vertices: np.ndarray, faces: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Vertex normals ``(F, len(at), 3)`` of only the vertices ``at``."""
    touch = np.isin(faces, at).any(1)
    sub = faces[touch]
    used, inv = np.unique(sub, return_inverse=True)
    n = vertex_normals(vertices[:, used], inv.reshape(-1, 3))
    return n[:, np.searchsorted(used, at)]


#: Axis names of the ``truth`` record's arrays (its ``_dims``: codecs.RECORD_DIMS).
_TRUTH_DIMS = {
    "positions": ["frame", "marker", "xyz"], "visible": ["frame", "marker"],
    "n_cameras_seeing": ["frame", "marker"], "part": ["marker"],
    "marker_weights": ["marker", "joint"], "region": ["marker"], "marker_face": ["marker"],
    "marker_barycentric": ["marker", "corner"], "bind_pose": ["marker", "xyz"],
    "reference_pose": ["marker", "xyz"], "fragment_marker": ["fragment"],
    "cameras": ["camera", "xyz"],
}


def _capture_truth(body: Body, sites: SurfacePoints, true: np.ndarray, *, visible, seen,
                   frag_marker, label_frame, labels, cams, noise, marker_radius, rate,
                   motion_name) -> dict[str, Any]:
    """The ``truth`` record of :func:`simulate_capture`."""
    skin_pts, skin_n, skin_w = sites.points(body), sites.normals(body), sites.weights(body)
    skin_part = np.argmax(skin_w, axis=1)
    return {
        "positions": true,
        "visible": visible,
        "n_cameras_seeing": seen.astype(np.int16),
        "part": skin_part.astype(np.int64),
        "part_names": list(body.skeleton.names),
        "marker_weights": skin_w,
        "region": marker_regions(body, skin_pts, skin_n, skin_part),
        "region_names": list(REGIONS),
        "marker_face": sites.face.astype(np.int64),
        "marker_barycentric": sites.barycentric,
        "bind_pose": skin_pts + marker_radius * skin_n,
        "reference_pose": true[label_frame],
        "fragment_marker": frag_marker,
        "label_frame": label_frame,
        "labels": labels,
        "cameras": cams,
        "noise": noise,
        "marker_radius": marker_radius,
        "rate": rate,
        "motion": motion_name,
        "_dims": {k: list(v) for k, v in _TRUTH_DIMS.items()},
    }


@stage("simulate_capture", outputs=("markers", "truth", "mesh", "motion"))
def simulate_capture(
    *,
    n_markers: int = 350,
    n_frames: int = 900,
    rate: float = 120.0,
    motion: Literal["dynamic", "walk", "range_of_motion"] = "dynamic",
    seed: int = 0,
    bvh: FilePath | None = None,
    body_mesh: FilePath | None = None,
    body_vertices: int = 3000,
    noise: float = 0.0003,
    n_cameras: int = 12,
    min_cameras: int = 2,
    calibration: float = 0.5,
    bulge: float = 1.0,
    jiggle: float = 1.0,
    breathing: float = 1.0,
    break_rate: float = 0.2,
    ghost_rate: float = 1.0,
    marker_radius: float = 0.007,
    min_separation: float = 0.02,
    ctx: Context,
) -> dict[str, Any]:
    """Simulate a dense-marker capture (Park & Hodgins style) with ground truth.

    Parameters
    ----------
    n_markers : int
        Markers on the skin (~350 gives 5-7 cm spacing, denser at elbows/shoulders).
    n_frames : int
        Frames, the rest-pose calibration included.
    rate : float
        Frames per second.
    motion : {"dynamic", "walk", "range_of_motion"}
        Treadmill run, treadmill walk, or joint groups flexed in turn.
    seed : int
        Seeds ``ctx.rng`` (motion variation, layout, noise, fragmentation).  The
        marker layout comes from its own stream of that seed and from the
        calibration pose only, so trials of one seed and part id with different
        ``motion`` (a range-of-motion trial and a dynamic one) share the body,
        the marker labels and their placement.
    bvh : FilePath, optional
        Drive the body with this BVH instead of a procedural motion.
    body_mesh : FilePath, optional
        The MakeHuman ``makehuman_base.obj`` (rig and weights JSON beside it);
        default: a procedural body built around the motion's skeleton.
    body_vertices : int
        Vertex count of the procedural body (and of the ``mesh`` output).
    noise : float
        Measurement noise, standard deviation per axis (metres).
    n_cameras, min_cameras : int
        Cameras on the ring; cameras needed to reconstruct a marker.
    calibration : float
        Seconds of T-pose at the start.
    bulge, jiggle, breathing : float
        Scales of the non-rigid skin motion (0 disables).
    break_rate : float
        Extra trajectory breaks per marker per second.
    ghost_rate : float
        Ghost trajectories per second.
    marker_radius : float
        Metres from the skin to a marker's centre.
    min_separation : float
        Markers closer than this to another (skin folds) merge in the images and
        are lost, metres.
    ctx : Context
        ``ctx.rng`` drives everything random; ``ctx.map`` the visibility tests.

    Returns
    -------
    dict
        ``markers`` (:class:`Markers`: labelled runs through the label frame,
        unlabelled fragments ``*N``), ``truth`` (record: ``positions (F, M, 3)``
        true marker centres, ``visible (F, M)``, ``part (M,)`` dominant joint
        with ``part_names``, ``marker_weights (M, J)``, ``region (M,)`` with
        ``region_names``, ``marker_face (M,)`` / ``marker_barycentric (M, 3)``:
        the skin point under each marker on ``mesh`` (the marker sits
        ``marker_radius`` above it along the normal),
        ``bind_pose (M, 3)``, ``reference_pose (M, 3)`` true positions at the
        label frame, ``fragment_marker (U,)`` true marker per fragment (-1 ghost),
        ``label_frame``, ``cameras (C, 3)``, ``noise``), ``mesh`` (:class:`Mesh`,
        true skin ``(F, V, 3)``), ``motion`` (the driving :class:`Motion`).
    """
    rng = ctx.rng
    layout_rng = _layout_rng(rng)
    if n_markers < 4:
        raise ValueError(f"simulate_capture: n_markers must be >= 4, got {n_markers}")
    if n_frames < 2 or rate <= 0:
        raise ValueError("simulate_capture: need n_frames >= 2 and rate > 0")
    mot = capture_motion(motion, n_frames, rate=rate, rng=rng, calibration=calibration, bvh=bvh)
    body = capture_body(mot, body_mesh=body_mesh, body_vertices=body_vertices)
    R, p = skinning_transforms(body, mot)
    cams = camera_ring(mot.root_position, n_cameras=n_cameras)
    sites = _marker_sites(body, mot, R, p, n_markers, n_cameras=n_cameras,
                          min_cameras=min_cameras, marker_radius=marker_radius, rng=layout_rng)
    dynamics = SkinDynamics(bulge=bulge, jiggle=jiggle, breathing=breathing)
    mesh_seq, true, normals = _moving_skin(body, mot, R, p, sites, dynamics,
                                           marker_radius=marker_radius, rng=rng)
    seen = marker_visibility(true, normals, body, R, p, cams, ctx=ctx)
    visible = (seen >= min_cameras) & ~crowded(true, min_separation)
    observed = true + rng.normal(0.0, noise, true.shape)
    labelled, frags, frag_marker, label_frame = fragment_capture(
        observed, visible, rate=rate, rng=rng, break_rate=break_rate, ghost_rate=ghost_rate,
        ghost_source=true, ghost_normals=normals)
    labels = [f"M{i + 1:03d}" for i in range(n_markers)]
    truth = _capture_truth(
        body, sites, true, visible=visible, seen=seen, frag_marker=frag_marker,
        label_frame=label_frame, labels=labels, cams=cams, noise=noise,
        marker_radius=marker_radius, rate=rate,
        motion_name=motion if bvh is None else Path(bvh).name)
    truth["seed"] = int(seed)
    return {"markers": _captured_markers(labelled, frags, labels, rate=rate, motion=motion,
                                         label_frame=label_frame),
            "truth": truth, "mesh": _true_mesh(mesh_seq, body, sites, rate=rate), "motion": mot}


def _captured_markers(labelled: np.ndarray, frags: np.ndarray, labels: list[str], *,
                      rate: float, motion: str, label_frame: int) -> Markers:
    """The ``markers`` output: labelled runs ``(F, M, 3)`` and fragments ``*1 … *U``."""
    return Markers(
        positions=labelled, labels=labels, rate=rate, first_frame=0,
        fragments=frags, fragment_labels=[f"*{u + 1}" for u in range(frags.shape[1])],
        attrs={"source": "simulate_capture", "source_unit": "m", "motion": motion,
               "label_frame": label_frame, "up": "+y", "forward": "+z",
               "axes_source": {"up": "simulator", "up_confidence": "high",
                               "forward": "simulator"}})


def _true_mesh(mesh_seq: np.ndarray, body: Body, sites: SurfacePoints, *, rate: float) -> Mesh:
    """The ``mesh`` output: the true skin ``(F, V, 3)`` with its joints, parts, marker faces."""
    return Mesh(mesh_seq, body.faces, rate=rate, attrs={
        "source": body.attrs.get("source", "procedural"),
        "joint_names": list(body.skeleton.names),
        "vertex_part": body.part.tolist(),
        "marker_face": sites.face.tolist(),
    })
