"""Import a sarah-export glTF into Blender: ``blender --python scripts/blender_import_glb.py -- FILE.glb``
(add ``-b`` for no window). Uses Blender's own importer (the io_scene_gltf2 add-on) with the scene
at the file's frame rate, so every frame of the motion is a whole frame of the scene. Works with
every Blender, including Debian's 3.4 package, whose add-on still calls ``numpy.bool`` (gone since
NumPy 1.24, which Debian ships beside it): the alias is put back here."""

import json
import struct
import sys

import bpy
import numpy

try:
    numpy.bool  # noqa: B018
except AttributeError:  # NumPy 1.24-1.26 (NumPy 2 has a numpy.bool of its own again)
    numpy.bool = bool

def file_fps(path: str) -> float:
    """The frame rate sarah-export records in the file's extras (30 when absent)."""
    with open(path, "rb") as handle:
        _, _, _, length, _ = struct.unpack("<IIIII", handle.read(20))
        document = json.loads(handle.read(length))
    return float(document.get("extras", {}).get("fps", 30.0))


def import_glb(path: str):
    scene = bpy.context.scene
    scene.render.fps = int(round(file_fps(path)))
    bpy.ops.import_scene.gltf(filepath=path)
    armature = next(o for o in scene.objects if o.type == "ARMATURE" and o.animation_data)
    first, last = (int(round(f)) for f in armature.animation_data.action.frame_range)
    scene.frame_start, scene.frame_end = first, last
    return armature


if __name__ == "__main__" and "--" in sys.argv:
    import_glb(sys.argv[sys.argv.index("--") + 1])
