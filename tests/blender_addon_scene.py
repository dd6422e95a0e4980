"""Run by Blender for ``tests/test_blender_addon.py``: install the add-on, use it as a user
would, and write what the scene holds to JSON.

``blender -b --factory-startup --python THIS -- ZIP MOCAPFLOW_CMD STORE OUT MODE ARGS...``

* ``texture BVH LENGTH IN1:OUT1,IN2:OUT2 RADIUS [VARIANTS [PNG]]``: import the take,
  author the constraints as ``c:<in>`` markers at frame ``frame_start + out``, a closed
  Bezier circle as the path and the frame range as the length, run the Synthesize
  operator; measure the result (length, constraint errors, loop closure); then, when
  given, import VARIANTS (as ``motions``) and render PNG.
* ``markers C3D FRAME``: import the C3D; labels, positions and states at FRAME.
* ``mesh OBJ FRAME``: import the OBJ + PC2; vertex count and positions at FRAME.
* ``motions BVH1,BVH2,...`` (files of one folder): import them on a grid; their files,
  locations, scales, frame ranges and the scene's rate.

Exits 1 on any error (``--python-exit-code 1``), its traceback in OUT's ``error``.
Blender's modules only (Debian's Blender runs on the system Python, which may have
no NumPy).
"""

import json
import math
import sys

import bpy
import mathutils

zip_path, command, store, out, mode, *args = sys.argv[sys.argv.index("--") + 1:]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.preferences.addon_install(filepath=zip_path, overwrite=True)
bpy.ops.preferences.addon_enable(module="mocapflow_blender")
prefs = bpy.context.preferences.addons["mocapflow_blender"].preferences
prefs.executable = command
prefs.store = store
scene = bpy.context.scene
scene.frame_start = 1
result: dict = {}


def finished(res) -> None:
    assert res == {"FINISHED"}, res


def pose(ob, frame: int) -> dict:
    """World matrices of the armature's pose bones at a scene frame."""
    scene.frame_set(frame)
    mw = ob.matrix_world
    return {pb.name: (mw @ pb.matrix).copy() for pb in ob.pose.bones}


def relative(mats: dict, root: str) -> dict:
    """Each bone's matrix in the root bone's frame (heading and travel removed)."""
    inv = mats[root].inverted()
    return {k: inv @ m for k, m in mats.items() if k != root}


def angle_deg(a, b) -> float:
    """Angle of the rotation between two matrices' rotations."""
    d = a.to_quaternion().rotation_difference(b.to_quaternion())
    return math.degrees(abs(d.angle) if abs(d.angle) <= math.pi else 2 * math.pi - d.angle)


def median(xs: list[float]) -> float:
    xs = sorted(xs)
    return xs[len(xs) // 2]


def texture(bvh: str, length: str, pairs: str, radius: str, variants: str = "",
            png: str = "") -> None:
    finished(bpy.ops.mocapflow.import_take(filepath=bvh))
    src = bpy.context.view_layer.objects.active
    n = int(length)
    scene.frame_end = scene.frame_start + n - 1
    cons = [tuple(map(int, p.split(":"))) for p in pairs.split(",")]
    for i, j in cons:
        scene.timeline_markers.new(f"c:{i}", frame=scene.frame_start + j)
    bpy.ops.curve.primitive_bezier_circle_add(radius=float(radius), location=(0, 0, 0))
    curve = bpy.context.view_layer.objects.active
    scene.mocapflow_path = curve
    bpy.context.view_layer.objects.active = src
    result["errors"] = _failures(src)
    finished(bpy.ops.mocapflow.synthesize(seed=0))
    copy = bpy.context.view_layer.objects.active
    action = copy.animation_data.action
    keys = {len(fc.keyframe_points) for fc in action.fcurves}
    root = src.pose.bones[0].name
    errs = []
    for i, j in cons:
        a = relative(pose(src, scene.frame_start + i), root)
        b = relative(pose(copy, scene.frame_start + j), root)
        c = relative(pose(copy, scene.frame_start + j + 12), root)  # 0.1 s later
        errs.append({
            "input": i, "output": j,
            "max_mm": max(1000 * (a[k].translation - b[k].translation).length for k in a),
            "max_deg": max(angle_deg(a[k], b[k]) for k in a),
            "later_deg": max(angle_deg(a[k], c[k]) for k in a),
        })
    # loop closure: the last -> first step against the ordinary steps
    frames = [pose(copy, scene.frame_start + f) for f in range(n)]
    body = [[m.translation for m in relative(p, root).values()] for p in frames]
    rootp = [p[root].translation for p in frames]

    def body_step(a, b) -> float:
        return max((u - v).length for u, v in zip(a, b))

    step_body = [body_step(body[f], body[f + 1]) for f in range(n - 1)]
    step_root = [(rootp[f + 1] - rootp[f]).length for f in range(n - 1)]
    result.update(
        source=src.name, copy=copy.name, action=action.name,
        frame_range=list(action.frame_range), keys=sorted(keys),
        fps=scene.render.fps / scene.render.fps_base, constraints=errs,
        markers=sorted((m.name, m.frame) for m in scene.timeline_markers),
        report=json.loads(copy["mocapflow_report"]),
        body_step_max=max(step_body), body_step_median=median(step_body),
        body_wrap=body_step(body[-1], body[0]),
        root_step_max=max(step_root), root_step_median=median(step_root),
        root_wrap=(rootp[0] - rootp[-1]).length, root_travel=sum(step_root),
        root_to_curve_max=max(abs(p.xy.length - float(radius)) for p in rootp),
    )
    if variants:  # the import of several results, in the same session
        motions(variants)
    if png:
        _render(copy, src, curve, n, png)


def _error(op, **kw) -> str:
    """The error an operator reports (Blender raises it as RuntimeError in -b)."""
    try:
        res = op(**kw)
    except RuntimeError as e:
        return str(e).strip().splitlines()[0]
    return f"no error: {res}"


def _failures(src) -> dict[str, str]:
    """What the Synthesize operator says on a bad scene (nothing runs)."""
    out = {}
    bpy.context.view_layer.objects.active = None
    out["no_armature"] = _error(bpy.ops.mocapflow.synthesize)
    bpy.context.view_layer.objects.active = src
    bad = scene.timeline_markers.new("c:abc", frame=5)
    out["bad_marker"] = _error(bpy.ops.mocapflow.synthesize)
    scene.timeline_markers.remove(bad)
    cmd = prefs.executable
    prefs.executable = "/nonexistent/mocapflow"
    out["no_command"] = _error(bpy.ops.mocapflow.synthesize)
    prefs.executable = cmd
    return out


def _stick(ob, frame: int, name: str, color, radius: float = 0.02) -> None:
    """A renderable stick figure of an armature's pose: a square tube per bone."""
    scene.frame_set(frame)
    mw = ob.matrix_world
    verts, faces = [], []
    for pb in ob.pose.bones:
        a, b = mw @ pb.head, mw @ pb.tail
        d = b - a
        if d.length < 1e-6:
            continue
        u = d.orthogonal().normalized() * radius
        v = d.cross(u).normalized() * radius
        k = len(verts)
        for c in (a, b):
            verts += [c + u + v, c - u + v, c - u - v, c + u - v]
        faces += [(k + i, k + (i + 1) % 4, k + 4 + (i + 1) % 4, k + 4 + i) for i in range(4)]
        faces += [(k, k + 1, k + 2, k + 3), (k + 7, k + 6, k + 5, k + 4)]
    me = bpy.data.meshes.new(name)
    me.from_pydata([tuple(x) for x in verts], [], faces)
    st = bpy.data.objects.new(name, me)
    scene.collection.objects.link(st)
    mat = bpy.data.materials.new(name)
    mat.diffuse_color = color
    me.materials.append(mat)


def _render(copy, src, curve, n: int, png: str) -> None:
    """Workbench render: the result at several frames along the path (orange), the held
    constraint poses (green) and the path (a bevelled curve) on a ground plane."""
    curve.data.bevel_depth = 0.01
    for k, f in enumerate(range(0, n, max(n // 6, 1))):
        _stick(copy, scene.frame_start + f, f"out{k}", (1.0, 0.45, 0.1, 1))
    for i, (_name, frame) in enumerate(sorted((m.name, m.frame) for m in scene.timeline_markers
                                             if m.name.startswith("held"))):
        _stick(copy, frame, f"held{i}", (0.1, 0.8, 0.2, 1))
    bpy.ops.mesh.primitive_plane_add(size=6.0, location=(0, 0, 0))
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    cam.location = (0.0, -6.0, 3.2)
    cam.rotation_euler = (math.radians(68), 0.0, 0.0)
    scene.camera = cam
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.color_type = "MATERIAL"
    scene.render.resolution_x, scene.render.resolution_y = 960, 640
    scene.render.filepath = png
    bpy.ops.render.render(write_still=True)


def markers(c3d_path: str, frame: str) -> None:
    finished(bpy.ops.mocapflow.import_markers(filepath=c3d_path))
    scene.frame_set(scene.frame_start + int(frame))
    empties = [o for o in scene.objects if "mocapflow_label" in o]
    labelled = [o for o in empties if not o["mocapflow_label"].startswith("*")]
    root = labelled[0].parent
    result.update(
        labels=[o["mocapflow_label"] for o in labelled],
        fragments=[o["mocapflow_label"] for o in empties if o not in labelled],
        positions=[list(root.matrix_world.inverted() @ o.matrix_world.translation)
                   for o in labelled],  # in the file's frame
        up=list(root.matrix_world.to_3x3() @ mathutils.Vector((0, 1, 0))),
        states=[int(o["mocapflow_state"]) for o in labelled],
        fps=scene.render.fps / scene.render.fps_base,
    )


def mesh(obj_path: str, frame: str) -> None:
    finished(bpy.ops.mocapflow.import_mesh(filepath=obj_path))
    meshes = [o for o in scene.objects if o.type == "MESH"]
    scene.frame_set(scene.frame_start + int(frame))
    ob = meshes[0]
    me = ob.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
    result.update(objects=len(meshes), vertices=len(me.vertices),
                  positions=[list(v.co) for v in me.vertices],  # in the file's frame
                  up=list(ob.matrix_world.to_3x3() @ mathutils.Vector((0, 1, 0))),
                  frame_end=scene.frame_end)


def motions(paths: str) -> None:
    files = paths.split(",")
    folder = files[0].rsplit("/", 1)[0]
    before = set(scene.objects)
    finished(bpy.ops.mocapflow.import_motions(
        directory=folder, files=[{"name": f.rsplit("/", 1)[1]} for f in files], spacing=2.0))
    arms = [o for o in scene.objects if o.type == "ARMATURE" and o not in before]
    result["motions"] = {
        "files": [o["mocapflow_file"] for o in arms], "locations": [list(o.location) for o in arms],
        "scales": [float(o["mocapflow_scale"]) for o in arms],
        "frames": [list(o.animation_data.action.frame_range) for o in arms],
        "fps": scene.render.fps / scene.render.fps_base}


try:
    {"texture": texture, "markers": markers, "mesh": mesh, "motions": motions}[mode](*args)
except Exception:  # the traceback in the JSON too: the test shows it in short lines
    import traceback
    result["error"] = traceback.format_exc()
    raise
finally:
    with open(out, "w") as fh:
        json.dump(result, fh)
