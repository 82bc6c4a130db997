"""Import a sarah-export BVH into Blender: ``blender --python scripts/blender_import_bvh.py -- FILE.bvh``
(add ``-b`` for no window). Uses Blender's own importer, sets the scene to the clip's 30 fps and
frame range. Works with every Blender, including Debian's 3.4 package, whose BVH importer opens
files with mode "rU" (removed in Python 3.11): that mode is read as "r" here."""

import builtins
import sys

import bpy

_open = builtins.open


def _open_without_u(file, mode="r", *args, **kwargs):
    return _open(file, mode.replace("U", ""), *args, **kwargs)


def import_bvh(path: str):
    builtins.open = _open_without_u
    try:
        bpy.ops.import_anim.bvh(filepath=path, global_scale=1.0, frame_start=1, use_fps_scale=False,
                                update_scene_fps=True, update_scene_duration=True,
                                rotate_mode="NATIVE", axis_forward="-Z", axis_up="Y")
    finally:
        builtins.open = _open
    return next(o for o in bpy.context.scene.objects if o.type == "ARMATURE" and o.select_get())


if __name__ == "__main__" and "--" in sys.argv:
    import_bvh(sys.argv[sys.argv.index("--") + 1])
