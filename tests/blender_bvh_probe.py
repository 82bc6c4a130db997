"""Run inside Blender (``blender -b --factory-startup --python THIS -- file.bvh out.json``):
import a BVH with Blender's own importer and write the frame range and every bone's head in
world space at the first, middle and last frame."""

import json
import runpy
import sys
from pathlib import Path

import bpy

# The README's import script: one owner of how our BVH goes into Blender.
import_bvh = runpy.run_path(str(Path(__file__).resolve().parents[1] / "scripts" / "blender_import_bvh.py"))["import_bvh"]

path, out = sys.argv[sys.argv.index("--") + 1:][:2]
bpy.ops.wm.read_factory_settings(use_empty=True)
armature = import_bvh(path)
first, last = (int(round(f)) for f in armature.animation_data.action.frame_range)
frames = sorted({first, (first + last) // 2, last})
heads = {}
for frame in frames:
    bpy.context.scene.frame_set(frame)
    heads[frame] = {bone.name: list(armature.matrix_world @ bone.head) for bone in armature.pose.bones}
with open(out, "w") as handle:
    json.dump({"frame_range": [first, last], "fps": bpy.context.scene.render.fps, "heads": heads}, handle)
