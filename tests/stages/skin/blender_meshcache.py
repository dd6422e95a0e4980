"""Run by Blender (``blender -b --factory-startup --python THIS -- OBJ PC2 FRAME OUT``).

Imports the OBJ without axis conversion, adds Blender's built-in Mesh Cache modifier
reading the PC2, evaluates the scene at FRAME and writes the evaluated vertex positions
(and the object count and vertex count) to OUT as JSON.  Exits 1 on any error.
"""

import json
import sys

import bpy

obj_path, pc2_path, frame, out = sys.argv[sys.argv.index("--") + 1:]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.obj_import(filepath=obj_path, forward_axis="Y", up_axis="Z")
meshes = [o for o in bpy.context.scene.objects if o.type == "MESH"]
ob = meshes[0]
mod = ob.modifiers.new("cache", "MESH_CACHE")
mod.cache_format = "PC2"
mod.filepath = pc2_path
mod.frame_start = 0.0
mod.forward_axis = "POS_Y"
mod.up_axis = "POS_Z"
bpy.context.scene.frame_set(int(frame))
deps = bpy.context.evaluated_depsgraph_get()
ev = ob.evaluated_get(deps)
me = ev.to_mesh()
world = ob.matrix_world
verts = [list(world @ v.co) for v in me.vertices]
json.dump({"objects": len(meshes), "vertices": len(me.vertices), "positions": verts},
          open(out, "w"))
