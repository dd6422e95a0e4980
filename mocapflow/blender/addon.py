"""mocapflow for Blender: author texture-synthesis constraints and paths, import every result.

This file is the add-on's ``__init__.py`` (``mocapflow blender-addon --out
mocapflow_blender.zip`` packs it with ``c3d.py``).  It runs inside Blender with
Blender's own Python and its modules only (``bpy``, ``mathutils``; not even NumPy,
which Debian's Blender, running on the system Python, may lack).  mocapflow is never imported here;
it runs through its command line (the ``mocapflow`` executable, a preference of
the add-on), one subprocess per step:

* ``mocapflow run texture --target ingest --json`` then ``mocapflow show
  ingest/KEY --json``: the length unit mocapflow reads a BVH file in, so every
  BVH is imported in metres (:func:`bvh_scales`);
* ``mocapflow run texture --set ...`` / ``export`` / ``show``: the texture graph
  (:func:`synthesize_texture`).

Authoring (Moradoff 2002, the texture graph), in the 3D view's sidebar tab
"mocapflow":

1. **Import take** (:func:`import_take`): a BVH as an armature that remembers
   its file (``obj["mocapflow_source"]``); its frame ``k`` (the file's 0-based
   frame) is at scene frame ``frame_start + k``.
2. Timeline markers named ``c:<input_frame>`` are constraints: the take's frame
   ``input_frame`` is required at the marker's frame (output frame ``marker -
   frame_start``).  The scene's frame range is the output length.  An optional
   curve object is the ground path; a closed (cyclic) curve makes a loop.
3. **Synthesize**: runs the graph at the scene's frame rate (so the length and
   constraint frames are kept exactly) and puts the result on a copy of the
   armature as a new action, with timeline markers ``seam`` and ``held c:<i>``.

Import (every graph): motions (BVH files in metres at their frame rate; several
are placed on a grid, e.g. the variation graph's variants), markers (C3D: one
empty per point, labelled, with an animated ``mocapflow_state`` property: 0
measured, 1 merged, 2 filled, 3 missing), and the animated mesh (rest OBJ + PC2
point cache through Blender's Mesh Cache modifier).  Markers and meshes keep the
files' coordinates (metres) on their objects; the parent / object rotation turns
the file's up axis to Blender's Z.  The commands run in the foreground: Blender
waits for them.
"""

from __future__ import annotations

import json
import math
import os
import shlex
import shutil
import struct
import subprocess
import tempfile

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)
from bpy_extras.io_utils import ImportHelper
from mathutils.geometry import interpolate_bezier

from . import c3d

bl_info = {
    "name": "mocapflow",
    "author": "mocapflow",
    "version": (0, 1, 0),
    "blender": (3, 4, 0),
    "location": "View3D > Sidebar > mocapflow",
    "description": "Texture synthesis authored on the timeline (constraints, path) and "
                   "import of mocapflow results: motions, cleaned markers, animated meshes",
    "category": "Animation",
}

#: Prefix of a timeline marker that is a constraint (``c:<input_frame>``).
CONSTRAINT_PREFIX = "c:"
#: Names of the markers a synthesis puts on the timeline (replaced by the next one).
SEAM_MARKER, HELD_PREFIX = "seam", "held c:"


class MocapflowError(RuntimeError):
    """A mocapflow command that failed, or a scene that cannot be synthesized (one line)."""


# --------------------------------------------------------------------------- preferences


class MocapflowPreferences(bpy.types.AddonPreferences):
    bl_idname = __name__

    executable: StringProperty(
        name="mocapflow command",
        description="The mocapflow executable (or a command line such as "
                    "'/path/python -m mocapflow'); empty: 'mocapflow' found on PATH",
        default="")
    store: StringProperty(
        name="Store", subtype="DIR_PATH",
        description="mocapflow store (--store) and exports folder; empty: "
                    "<temp>/mocapflow-blender")
    executor: StringProperty(
        name="Executor", default="sync",
        description="--executor of the runs (sync: in the mocapflow process; local: Dask "
                    "workers)")

    def draw(self, context):
        for name in ("executable", "store", "executor"):
            self.layout.prop(self, name)


def _prefs(context=None):
    context = context or bpy.context
    addon = context.preferences.addons.get(__name__)
    return addon.preferences if addon else None


def mocapflow_command(context=None) -> list[str]:
    """argv of the mocapflow command (the preference, else ``mocapflow`` on PATH)."""
    prefs = _prefs(context)
    text = (prefs.executable if prefs else "").strip()
    if text:
        return shlex.split(text)
    found = shutil.which("mocapflow")
    if not found:
        raise MocapflowError("mocapflow is not on PATH: set its path in the add-on's "
                             "preferences (Edit > Preferences > Add-ons > mocapflow)")
    return [found]


def work_folder(context=None) -> str:
    """The store / exports folder (the preference, else ``<temp>/mocapflow-blender``)."""
    prefs = _prefs(context)
    root = bpy.path.abspath(prefs.store) if prefs and prefs.store else os.path.join(
        tempfile.gettempdir(), "mocapflow-blender")
    os.makedirs(root, exist_ok=True)
    return root


def run_mocapflow(args: list[str], context=None, *, timeout: float = 3600) -> str:
    """Run ``mocapflow ARGS``; its stdout, or MocapflowError with its last error line."""
    argv = [*mocapflow_command(context), *args]
    try:
        p = subprocess.run(argv, capture_output=True, text=True, timeout=timeout)
    except OSError as e:  # not found, not executable
        raise MocapflowError(f"cannot run {argv[0]!r} ({e.strerror}): set the mocapflow "
                             "command in the add-on's preferences") from None
    except subprocess.TimeoutExpired:
        raise MocapflowError(f"mocapflow {args[0]} took over {timeout:.0f} s; "
                             "stopped") from None
    if p.returncode != 0:
        lines = [ln for ln in p.stderr.strip().splitlines() if ln.strip()]
        raise MocapflowError(f"mocapflow {args[0]} failed: "
                             + (lines[-1] if lines else f"exit code {p.returncode}"))
    return p.stdout


def _store_args(context=None) -> list[str]:
    prefs = _prefs(context)
    return ["--store", os.path.join(work_folder(context), "store"),
            "--executor", (prefs.executor if prefs else "") or "sync", "-q"]


def _show(node_key: str, context=None) -> dict:
    """``mocapflow show NODE/KEY --json`` (the entry's manifest and output attrs)."""
    store = os.path.join(work_folder(context), "store")
    return json.loads(run_mocapflow(["show", node_key, "--store", store, "--json"], context))


def bvh_scales(paths: list[str], context=None) -> dict[str, dict]:
    """How mocapflow reads each BVH file: ``{path: {"scale": metres per unit, "rate": fps}}``.

    Runs the texture graph's ``ingest`` node on the files (``--target ingest``) and
    reads each entry's motion attrs (``source_scale``, ``resampled_from_rate``).
    """
    args = ["run", "texture", "--target", "ingest", "--json", *_store_args(context)]
    for p in paths:
        args += ["--parts", os.path.abspath(p)]
    tasks = json.loads(run_mocapflow(args, context))["tasks"]
    out: dict[str, dict] = {}
    for t in tasks:
        if t["node"] != "ingest":
            continue
        entry = _show(f"{t['stage']}/{t['key']}", context)
        attrs = entry["outputs"]["motion"]["attrs"]["attrs"]
        rate = attrs.get("resampled_from_rate") or 1.0 / float(attrs["frame_time"])
        out[t["part"]] = {"scale": float(attrs["source_scale"]), "rate": float(rate)}
    missing = [p for p in paths if os.path.abspath(p) not in out]
    if missing:
        raise MocapflowError(f"mocapflow did not read {missing[0]} (a glob character in "
                             "its name?)")
    return {p: out[os.path.abspath(p)] for p in paths}


# --------------------------------------------------------------------------- import


def _link(context, ob) -> None:
    if ob.name not in context.scene.collection.objects:
        context.scene.collection.objects.link(ob)


def _bvh_importer_shim() -> None:
    """Blender 3.4's BVH importer opens files in mode ``"rU"``, which Python 3.11 (the
    system Python of Debian's Blender) refuses: give its module an ``open`` that drops
    the ``U``.  Nothing else changes; a fixed importer is left alone."""
    try:
        from io_anim_bvh import import_bvh as module  # noqa: PLC0415 (Blender's add-on)
    except ImportError:
        return
    if "open" not in vars(module):
        module.open = lambda file, mode="r", *a, **k: open(file, mode.replace("U", ""), *a,
                                                           **k)


#: Object rotation (XYZ Euler, radians) turning a file's up axis to Blender's +Z.
UP_ROTATION = {"x": (0.0, -math.pi / 2, 0.0), "y": (math.pi / 2, 0.0, 0.0),
               "z": (0.0, 0.0, 0.0)}


def _up_axis(up: str, c3d_file=None) -> str:
    """``"x"``, ``"y"`` or ``"z"``: ``up`` as given, or for ``"auto"`` the axis of the
    C3D's ``POINT:Y_SCREEN`` (sign ignored: files get it wrong; else z)."""
    up = up.lower().lstrip("+-")
    if up == "auto":
        screen = (c3d_file.parameters.get("POINT:Y_SCREEN") or [""])[0] if c3d_file else ""
        up = screen.strip().lower().lstrip("+-")[:1]
        up = up if up in UP_ROTATION else "z"
    if up not in UP_ROTATION:
        raise MocapflowError(f"up axis {up!r}: expected x, y, z or auto")
    return up


def import_bvh(context, path: str, *, scale: float, name: str | None = None,
               update_fps: bool = False):
    """Import a BVH as an armature (metres: ``scale`` metres per file unit), its frame 0
    at the scene's ``frame_start``, one file frame per scene frame; returns the object."""
    _bvh_importer_shim()
    before = set(bpy.data.objects)
    res = bpy.ops.import_anim.bvh(
        filepath=path, global_scale=scale, frame_start=context.scene.frame_start,
        use_fps_scale=False, update_scene_fps=update_fps, update_scene_duration=False,
        rotate_mode="NATIVE", axis_forward="-Z", axis_up="Y")
    new = [o for o in bpy.data.objects if o not in before and o.type == "ARMATURE"]
    if res != {"FINISHED"} or not new:
        raise MocapflowError(f"Blender could not import {path}")
    ob = new[0]
    if name:
        ob.name = name
    ob["mocapflow_file"] = os.path.abspath(path)
    ob["mocapflow_scale"] = scale
    return ob


def import_take(context, path: str):
    """The source take of a synthesis: the BVH in metres, the scene at its frame rate."""
    info = bvh_scales([path], context)[path]
    ob = import_bvh(context, path, scale=info["scale"], update_fps=False)
    ob["mocapflow_source"] = os.path.abspath(path)
    ob["mocapflow_rate"] = info["rate"]
    _set_scene_rate(context.scene, info["rate"])
    return ob


def _set_scene_rate(scene, rate: float) -> None:
    fps = max(int(round(rate)), 1)
    scene.render.fps = fps
    scene.render.fps_base = fps / rate


def import_motions(context, paths: list[str], *, spacing: float = 1.5):
    """Import BVH files (e.g. the variation graph's variants) as armatures in metres, on
    a square grid ``spacing`` metres apart (x, then -y), the scene at the first file's
    frame rate; returns the objects."""
    scales = bvh_scales(paths, context)
    _set_scene_rate(context.scene, scales[paths[0]]["rate"])
    cols = max(int(math.ceil(math.sqrt(len(paths)))), 1)
    obs = []
    for i, p in enumerate(paths):
        ob = import_bvh(context, p, scale=scales[p]["scale"])
        ob.location.x += (i % cols) * spacing
        ob.location.y -= (i // cols) * spacing
        obs.append(ob)
    return obs


def _keyframes(action, path: str, index: int, frames: list[float], values: list[float],
               group: str, interpolation: str = "LINEAR") -> None:
    """One F-curve with a key per frame, set in one go (foreach_set)."""
    fc = action.fcurves.new(path, index=index, action_group=group)
    fc.keyframe_points.add(len(frames))
    co = [0.0] * (2 * len(frames))
    co[0::2], co[1::2] = frames, values
    fc.keyframe_points.foreach_set("co", co)
    code = bpy.types.Keyframe.bl_rna.properties["interpolation"].enum_items[interpolation].value
    fc.keyframe_points.foreach_set("interpolation", [code] * len(frames))
    fc.update()


def import_markers(context, path: str, *, size: float = 0.01, set_rate: bool = True,
                   up: str = "auto"):
    """A C3D file's points as animated empties.

    One empty per point, named by its label, under an empty named after the file;
    unlabelled fragments (``*N``) under a second one.  The points' locations are the
    file's coordinates in metres; the root empty turns the file's ``up`` axis
    (:func:`_up_axis`) to Blender's +Z.  Each empty has the int
    property ``mocapflow_state`` keyed per frame (0 measured, 1 merged, 2 filled,
    3 missing, :func:`c3d.sample_state`) and location keys at its valid frames.
    File frame ``k`` (0-based) is at scene frame ``frame_start + k``.
    """
    data = c3d.read_c3d_points(path)
    state = c3d.sample_state(data)
    scene = context.scene
    if set_rate:
        _set_scene_rate(scene, data.rate)
    n_frames = len(data.positions)
    frames = [float(scene.frame_start + f) for f in range(n_frames)]
    stem = os.path.splitext(os.path.basename(path))[0]
    root = bpy.data.objects.new(stem, None)
    root.rotation_euler = UP_ROTATION[_up_axis(up, data)]
    frag_root = None
    _link(context, root)
    root["mocapflow_file"] = os.path.abspath(path)
    root["mocapflow_states"] = ",".join(c3d.STATE_NAMES)
    made = []
    for p, label in enumerate(data.labels):
        ob = bpy.data.objects.new(label or f"point{p + 1}", None)
        ob.empty_display_type = "SPHERE"
        ob.empty_display_size = size
        ob["mocapflow_label"] = label
        ob["mocapflow_state"] = state[0][p] if n_frames else c3d.MISSING
        if label.startswith("*"):
            if frag_root is None:
                frag_root = bpy.data.objects.new(f"{stem}.fragments", None)
                _link(context, frag_root)
                frag_root.parent = root
            ob.parent = frag_root
        else:
            ob.parent = root
        _link(context, ob)
        ob.animation_data_create()
        action = bpy.data.actions.new(f"{stem}.{label}")
        ob.animation_data.action = action
        ok = [f for f in range(n_frames) if state[f][p] != c3d.MISSING]
        if ok:
            for i in range(3):
                _keyframes(action, "location", i, [frames[f] for f in ok],
                           [data.positions[f][p][i] for f in ok], "location")
            ob.location = data.positions[ok[0]][p]
        _keyframes(action, '["mocapflow_state"]', 0, frames,
                   [float(state[f][p]) for f in range(n_frames)], "state", "CONSTANT")
        made.append(ob)
    if n_frames:
        scene.frame_end = int(frames[-1])
    return root, made


def import_mesh(context, obj_path: str, pc2_path: str, *, up: str = "y"):
    """An animated mesh exported by mocapflow (rest OBJ + PC2) as one object whose Mesh
    Cache modifier plays the PC2, cache frame ``k`` at scene frame ``frame_start + k``.

    Vertices are the files' coordinates (metres); the object turns the mesh's ``up``
    axis (mocapflow meshes: y unless their ``attrs["up"]`` says otherwise) to +Z."""
    before = set(bpy.data.objects)
    bpy.ops.wm.obj_import(filepath=obj_path, forward_axis="Y", up_axis="Z")
    new = [o for o in bpy.data.objects if o not in before and o.type == "MESH"]
    if len(new) != 1:
        raise MocapflowError(f"{obj_path}: expected one mesh, Blender imported {len(new)}")
    ob = new[0]
    ob.rotation_euler = UP_ROTATION[_up_axis(up)]
    mod = ob.modifiers.new("mocapflow cache", "MESH_CACHE")
    mod.cache_format = "PC2"
    mod.filepath = os.path.abspath(pc2_path)
    mod.frame_start = float(context.scene.frame_start)
    mod.forward_axis = "POS_Y"
    mod.up_axis = "POS_Z"
    with open(pc2_path, "rb") as fh:
        n = struct.unpack("<i", fh.read(32)[28:32])[0]  # the header's numSamples
    context.scene.frame_end = context.scene.frame_start + n - 1
    ob["mocapflow_file"] = os.path.abspath(pc2_path)
    return ob


# --------------------------------------------------------------------------- authoring


def constraints_from_markers(scene) -> list[list[int]]:
    """``[input_frame, output_frame]`` of every ``c:<input_frame>`` timeline marker."""
    out = []
    for m in scene.timeline_markers:
        if not m.name.startswith(CONSTRAINT_PREFIX):
            continue
        text = m.name[len(CONSTRAINT_PREFIX):].strip()
        if not text.lstrip("-").isdigit():
            raise MocapflowError(f"marker {m.name!r}: expected c:<input frame>, e.g. c:120")
        out.append([int(text), m.frame - scene.frame_start])
    return sorted(out, key=lambda c: c[1])


def path_from_curve(curve_ob, armature) -> tuple[list[list[float]], bool]:
    """A curve object as mocapflow's ground path ``[[x, z], ...]`` (metres, the take's
    Y-up frame: Blender x, -y in the armature's space) and whether it is closed.

    Bezier splines are sampled at the curve's resolution; poly and NURBS splines
    by their points.  A closed path repeats its first point at the end.
    """
    if curve_ob.type != "CURVE" or not curve_ob.data.splines:
        raise MocapflowError(f"{curve_ob.name}: the path must be a curve object")
    spline = curve_ob.data.splines[0]
    m = armature.matrix_world.inverted() @ curve_ob.matrix_world
    closed = bool(spline.use_cyclic_u)
    if spline.type == "BEZIER":
        pts = list(spline.bezier_points)
        n = len(pts) if closed else len(pts) - 1
        res = max(curve_ob.data.resolution_u, 2)
        local = []
        for i in range(n):
            a, b = pts[i], pts[(i + 1) % len(pts)]
            seg = interpolate_bezier(a.co, a.handle_right, b.handle_left, b.co, res + 1)
            local += seg[:-1]
        if not closed:
            local.append(pts[-1].co)
    else:
        local = [p.co.xyz for p in spline.points]
    xy = [m @ v for v in local]
    path = [[float(v.x), float(-v.y)] for v in xy]
    if closed:
        path.append(list(path[0]))
    return path, closed


def synthesize_texture(context, armature, *, seed: int = 0, path_object=None,
                       levels: int = 0, extra: list[str] | None = None):
    """Run the texture graph on the armature's source take as authored on the timeline
    and put the result on a copy of the armature; returns ``(copy, report)`` (the
    run's warnings in ``copy["mocapflow_warnings"]``).

    The synthesis runs at the scene's frame rate (the take's own when they agree
    to 0.1 %), so ``length`` is the scene's frame count and every constraint lands
    on its marker's frame.  ``extra``: further ``--set NODE.PARAM=VALUE`` items.
    """
    scene = context.scene
    source = armature.get("mocapflow_source")
    if not source or not os.path.exists(source):
        raise MocapflowError(f"{armature.name}: no source take (import it with 'Import "
                             "take', or set its 'mocapflow_source' property to the BVH path)")
    fps = scene.render.fps / scene.render.fps_base
    src_rate = float(armature.get("mocapflow_rate", fps))
    rate = src_rate if abs(fps - src_rate) <= 1e-3 * src_rate else fps
    length = scene.frame_end - scene.frame_start + 1
    cons = constraints_from_markers(scene)
    path, loop = (path_from_curve(path_object, armature) if path_object is not None
                  else (None, False))
    sets = {
        "params.rate": rate, "params.output_rate": rate, "params.length": length,
        "params.levels": levels or None, "synth.seeds": [int(seed)],
        "synth.constraints": cons, "synth.loop": loop, "synth.path": path,
    }
    args = ["texture", "--parts", source, "--target", "synth"]
    for k, v in sets.items():
        args += ["--set", f"{k}={json.dumps(v)}"]
    for item in extra or []:
        args += ["--set", item]
    tasks = json.loads(run_mocapflow(["run", *args, "--json", *_store_args(context)], context))
    task = next(t for t in tasks["tasks"] if t["node"] == "synth")
    key = task["key"]
    out = os.path.join(work_folder(context), "exports", f"synth-{key}")
    files = json.loads(run_mocapflow(["export", *args, "--to", out, "--json",
                                      *_store_args(context)], context))["files"]
    bvh = next(f for f in files if f.endswith(".bvh"))
    with open(next(f for f in files if f.endswith("report.json"))) as fh:
        report = json.load(fh)
    scale = float(armature.get("mocapflow_scale", 1.0))
    copy = _motion_on_copy(context, armature, bvh, scale, f"{armature.name}.texture.seed{seed}")
    copy["mocapflow_report"] = json.dumps({k: report.get(k) for k in (
        "length", "output_frames", "constraints", "constraint_output_frames",
        "constraint_max_angle_deg", "n_seams", "loop", "seed")})
    copy["mocapflow_warnings"] = [str(w) for w in task.get("warnings") or []]
    _result_markers(scene, report)
    return copy, report


def _motion_on_copy(context, armature, bvh: str, scale: float, name: str):
    """The BVH's animation as a new action on a copy of ``armature``."""
    tmp = import_bvh(context, bvh, scale=scale)
    action = tmp.animation_data.action
    action.name = name
    copy = armature.copy()
    copy.data = armature.data.copy()
    copy.name = name
    copy.animation_data_clear()
    copy.animation_data_create()
    copy.animation_data.action = action
    for k in ("mocapflow_source",):
        if k in copy:
            del copy[k]
    copy["mocapflow_file"] = bvh
    _link(context, copy)
    data = tmp.data
    bpy.data.objects.remove(tmp)
    bpy.data.armatures.remove(data)
    return copy


def _result_markers(scene, report: dict) -> None:
    """Timeline markers ``seam`` and ``held c:<i>`` of a synthesis (replacing older ones)."""
    for m in list(scene.timeline_markers):
        if m.name == SEAM_MARKER or m.name.startswith(HELD_PREFIX):
            scene.timeline_markers.remove(m)
    k = report["output_rate"] / report["rate"]
    for s in report.get("seams", []):
        scene.timeline_markers.new(SEAM_MARKER, frame=scene.frame_start + int(round(s * k)))
    for (i, _), j in zip(sorted(report["constraints"], key=lambda c: c[1]),
                         report["constraint_output_frames"]):
        scene.timeline_markers.new(f"{HELD_PREFIX}{i}", frame=scene.frame_start + int(j))


# --------------------------------------------------------------------------- operators


UP_ITEMS = [("AUTO", "Auto", "POINT:Y_SCREEN's axis, else Z"), ("X", "X", ""),
            ("Y", "Y", ""), ("Z", "Z", "")]


class _Reporting:
    """execute() → run(); a MocapflowError becomes an error report and CANCELLED."""

    def execute(self, context):
        try:
            self.run(context)
        except MocapflowError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        return {"FINISHED"}


class MOCAPFLOW_OT_import_take(_Reporting, bpy.types.Operator, ImportHelper):
    """Import a BVH take (in metres) as the source of a texture synthesis"""

    bl_idname = "mocapflow.import_take"
    bl_label = "Import take (BVH)"
    bl_options = {"REGISTER", "UNDO"}
    filename_ext = ".bvh"
    filter_glob: StringProperty(default="*.bvh", options={"HIDDEN"})

    def run(self, context):
        ob = import_take(context, self.filepath)
        context.view_layer.objects.active = ob


class MOCAPFLOW_OT_synthesize(_Reporting, bpy.types.Operator):
    """Run mocapflow's texture graph on the active armature's take (constraints: timeline
    markers c:<input frame>; path: the scene's mocapflow path curve; length: the frame
    range) and import the result on a copy of the armature"""

    bl_idname = "mocapflow.synthesize"
    bl_label = "Synthesize texture"
    bl_options = {"REGISTER", "UNDO"}
    seed: IntProperty(name="Seed", default=0, min=0, description="variant (synth seed)")
    levels: IntProperty(name="Levels", default=0, min=0,
                        description="pyramid levels (0: 4 at 30 fps, one more per doubling)")
    foot_ik: BoolProperty(name="Foot IK", default=True,
                          description="pin stance toes with leg IK (synth.foot_ik)")

    def run(self, context):
        arm = context.active_object
        if arm is None or arm.type != "ARMATURE":
            raise MocapflowError("select the armature of the source take")
        copy, _ = synthesize_texture(context, arm, seed=self.seed,
                                     path_object=context.scene.mocapflow_path,
                                     levels=self.levels,
                                     extra=[f"synth.foot_ik={json.dumps(self.foot_ik)}"])
        context.view_layer.objects.active = copy
        for w in copy["mocapflow_warnings"]:
            self.report({"WARNING"}, str(w))


class MOCAPFLOW_OT_import_motions(_Reporting, bpy.types.Operator, ImportHelper):
    """Import mocapflow BVH results (e.g. variation variants) as armatures on a grid"""

    bl_idname = "mocapflow.import_motions"
    bl_label = "Import motions (BVH)"
    bl_options = {"REGISTER", "UNDO"}
    filename_ext = ".bvh"
    filter_glob: StringProperty(default="*.bvh", options={"HIDDEN"})
    files: CollectionProperty(type=bpy.types.OperatorFileListElement)
    directory: StringProperty(subtype="DIR_PATH")
    spacing: FloatProperty(name="Spacing", default=1.5, min=0.0, unit="LENGTH",
                           description="distance between the armatures of several files")

    def run(self, context):
        names = [f.name for f in self.files if f.name] or [os.path.basename(self.filepath)]
        folder = self.directory or os.path.dirname(self.filepath)
        import_motions(context, [os.path.join(folder, n) for n in names],
                       spacing=self.spacing)


class MOCAPFLOW_OT_import_markers(_Reporting, bpy.types.Operator, ImportHelper):
    """Import a C3D file (e.g. mocapflow's cleaned markers) as labelled animated empties"""

    bl_idname = "mocapflow.import_markers"
    bl_label = "Import markers (C3D)"
    bl_options = {"REGISTER", "UNDO"}
    filename_ext = ".c3d"
    filter_glob: StringProperty(default="*.c3d", options={"HIDDEN"})
    size: FloatProperty(name="Size", default=0.01, min=0.0, unit="LENGTH")
    set_rate: BoolProperty(name="Scene rate", default=True,
                           description="set the scene's frame rate to the file's")
    up: EnumProperty(name="Up axis", default="AUTO", items=UP_ITEMS,
                     description="the file's up axis, turned to Blender's Z")

    def run(self, context):
        try:
            import_markers(context, self.filepath, size=self.size, set_rate=self.set_rate,
                           up=self.up)
        except c3d.C3DReadError as e:
            raise MocapflowError(str(e)) from None


class MOCAPFLOW_OT_import_mesh(_Reporting, bpy.types.Operator, ImportHelper):
    """Import mocapflow's animated mesh (rest OBJ with its PC2 point cache beside it)"""

    bl_idname = "mocapflow.import_mesh"
    bl_label = "Import animated mesh (OBJ + PC2)"
    bl_options = {"REGISTER", "UNDO"}
    filename_ext = ".obj"
    filter_glob: StringProperty(default="*.obj", options={"HIDDEN"})
    up: EnumProperty(name="Up axis", default="Y", items=UP_ITEMS[1:],
                     description="the mesh's up axis, turned to Blender's Z")

    def run(self, context):
        pc2 = os.path.splitext(self.filepath)[0] + ".pc2"
        if not os.path.exists(pc2):
            raise MocapflowError(f"{pc2}: no point cache next to the OBJ")
        import_mesh(context, self.filepath, pc2, up=self.up)


class MOCAPFLOW_PT_panel(bpy.types.Panel):
    bl_label = "mocapflow"
    bl_idname = "MOCAPFLOW_PT_panel"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "mocapflow"

    def draw(self, context):
        col = self.layout.column()
        col.label(text="Texture synthesis")
        col.operator(MOCAPFLOW_OT_import_take.bl_idname)
        col.prop(context.scene, "mocapflow_path")
        col.label(text="Constraints: markers c:<input frame>")
        col.operator(MOCAPFLOW_OT_synthesize.bl_idname)
        col.separator()
        col.label(text="Import results")
        col.operator(MOCAPFLOW_OT_import_motions.bl_idname)
        col.operator(MOCAPFLOW_OT_import_markers.bl_idname)
        col.operator(MOCAPFLOW_OT_import_mesh.bl_idname)


CLASSES = (MocapflowPreferences, MOCAPFLOW_OT_import_take, MOCAPFLOW_OT_synthesize,
           MOCAPFLOW_OT_import_motions, MOCAPFLOW_OT_import_markers, MOCAPFLOW_OT_import_mesh,
           MOCAPFLOW_PT_panel)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.mocapflow_path = PointerProperty(
        type=bpy.types.Object, name="Path",
        description="ground path of the synthesis (a curve; closed: a loop)",
        poll=lambda self, ob: ob.type == "CURVE")


def unregister():
    del bpy.types.Scene.mocapflow_path
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
