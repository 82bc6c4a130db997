"""Run inside Blender (``blender -b --factory-startup --python THIS -- file.glb out.json``):
import a glTF with Blender's own importer and write the animation's frame range, the scene's
frame rate, the meshes and every bone's head in world space at the first, middle and last frame."""

import json
import runpy
import sys
from pathlib import Path

import bpy

# The README's import script: one owner of how our glTF goes into Blender.
import_glb = runpy.run_path(str(Path(__file__).resolve().parents[1] / "scripts" / "blender_import_glb.py"))["import_glb"]

path, out = sys.argv[sys.argv.index("--") + 1:][:2]
bpy.ops.wm.read_factory_settings(use_empty=True)
armature = import_glb(path)
first, last = bpy.context.scene.frame_start, bpy.context.scene.frame_end
frames = sorted({first, (first + last) // 2, last})
heads = {}
for frame in frames:
    bpy.context.scene.frame_set(frame)
    heads[frame] = {bone.name: list(armature.matrix_world @ bone.head) for bone in armature.pose.bones}
meshes = [o.name for o in bpy.context.scene.objects if o.type == "MESH"]
with open(out, "w") as handle:
    json.dump({"frame_range": [first, last], "fps": bpy.context.scene.render.fps, "heads": heads,
               "meshes": meshes, "bones": len(armature.pose.bones)}, handle)
