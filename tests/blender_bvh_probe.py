"""Run inside Blender (``blender -b --factory-startup --python THIS -- file.bvh out.json``):
import a BVH with Blender's own importer and write the frame range and every bone's head in
world space at the first, middle and last frame."""

import builtins
import json
import sys

import bpy

# Debian's Blender 3.4 BVH importer opens files with mode "rU", which Python 3.11 removed; newer
# Blender releases open with "r". Dropping the "U" changes nothing else about the import.
_open = builtins.open


def _open_without_u(file, mode="r", *args, **kwargs):
    return _open(file, mode.replace("U", ""), *args, **kwargs)


builtins.open = _open_without_u

path, out = sys.argv[sys.argv.index("--") + 1:][:2]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_anim.bvh(filepath=path, global_scale=1.0, frame_start=1, use_fps_scale=False,
                        rotate_mode="NATIVE", axis_forward="-Z", axis_up="Y")
armature = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
first, last = (int(round(f)) for f in armature.animation_data.action.frame_range)
frames = sorted({first, (first + last) // 2, last})
heads = {}
for frame in frames:
    bpy.context.scene.frame_set(frame)
    heads[frame] = {bone.name: list(armature.matrix_world @ bone.head) for bone in armature.pose.bones}
with _open(out, "w") as handle:
    json.dump({"frame_range": [first, last], "fps": bpy.context.scene.render.fps, "heads": heads}, handle)
