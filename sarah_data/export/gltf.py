"""Binary glTF 2.0 (.glb) of the SMPL-X skeleton, animated, with a stick figure skinned to it.

glTF is what game engines and the web import without a plug-in (Godot, Unreal, Unity through
glTFast or UnityGLTF, three.js, Babylon.js, Blender); none of the first three reads BVH. The
file holds:

- 55 joint nodes in the SMPL-X tree, each translated from its parent by the rest skeleton's
  bone (the body's betas, or one fitted to the motion, as the BVH's), with identity rotations at
  rest: SMPL-X's rest pose, so each node's animated rotation is the joint's local rotation;
- a skin over those joints and a mesh that draws each bone as a thin four-sided prism from the
  parent joint to the child, rigidly skinned to the parent (so an importer builds an armature
  and shows a body without the SMPL-X model, which no file of ours may ship);
- one animation, "motion": every joint's rotation and the pelvis's translation per frame at the
  motion's frame rate, linear.

Axes are ours and glTF's alike: metres, y up, right-handed. Written atomically.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from sarah_data.atomic import atomic_path
from sarah_data.constants import JOINT_NAMES, JOINT_PARENTS

from .kinematics import SkeletonFit, children_of
from .motion import ExportMotion

BONE_WIDTH = 0.2  # of its length, the stick figure's prism side (at most ``MAX_WIDTH`` metres)
MAX_WIDTH = 0.04
# glTF's numbers: component types, buffer view targets, the GLB chunk types.
FLOAT, UNSIGNED_SHORT, UNSIGNED_INT = 5126, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942


def stick_figure(rest: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (V, 3) in the rest pose, triangles (F, 3), each vertex's joint (V,)): a prism
    per bone from its parent joint to its child, skinned to the parent."""
    vertices, triangles, joints = [], [], []
    for child, parent in enumerate(JOINT_PARENTS):
        if parent < 0:
            continue
        start, end = rest[parent], rest[child]
        axis = end - start
        length = float(np.linalg.norm(axis))
        if length < 1e-6:
            continue
        axis /= length
        across = np.cross(axis, [0.0, 1.0, 0.0] if abs(axis[1]) < 0.9 else [1.0, 0.0, 0.0])
        across /= np.linalg.norm(across)
        other = np.cross(axis, across)
        half = 0.5 * min(BONE_WIDTH * length, MAX_WIDTH)
        corners = [half * (s * across + t * other) for s, t in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
        first = len(vertices)
        vertices += [start + c for c in corners] + [end + c for c in corners]
        joints += [parent] * 8
        for i in range(4):  # the four sides, each two triangles facing out
            a, b = first + i, first + (i + 1) % 4
            triangles += [(a, b, b + 4), (a, b + 4, a + 4)]
        triangles += [(first, first + 2, first + 1), (first, first + 3, first + 2),  # the ends
                      (first + 4, first + 5, first + 6), (first + 4, first + 6, first + 7)]
    return (np.asarray(vertices, np.float32), np.asarray(triangles, np.uint32),
            np.asarray(joints, np.uint16))


def continuous(quaternions: np.ndarray) -> np.ndarray:
    """(T, J, 4) each quaternion's sign chosen to agree with the frame before: q and -q are the
    same rotation, and an engine that interpolates between frames (a 60 Hz game loop) must not
    turn the long way round between two keys. A frame flips where the raw pair disagrees, so its
    sign is the running product of those flips."""
    agree = np.sum(quaternions[1:] * quaternions[:-1], axis=-1) >= 0.0
    signs = np.cumprod(np.where(agree, 1.0, -1.0), axis=0)
    out = quaternions.copy()
    out[1:] *= signs[..., None].astype(out.dtype)
    return out


class _Buffer:
    """The binary chunk and its accessors, filled in order (each view 4-byte aligned)."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray, kind: str, component: int, target: int | None = None,
            bounds: bool = False) -> int:
        """Append ``array`` as one accessor of ``kind`` (SCALAR, VEC3, ...); its index."""
        array = np.ascontiguousarray(array)
        self.data += b"\0" * (-len(self.data) % 4)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": array.nbytes}
        if target is not None:
            view["target"] = target
        self.data += array.tobytes()
        self.views.append(view)
        accessor = {"bufferView": len(self.views) - 1, "componentType": component,
                    "count": int(array.shape[0]), "type": kind}
        if bounds:  # required for positions and animation times
            flat = array.reshape(array.shape[0], -1)
            accessor["min"], accessor["max"] = flat.min(0).tolist(), flat.max(0).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def gltf_document(motion: ExportMotion, fit: SkeletonFit) -> tuple[dict, bytes]:
    """The glTF JSON and its binary chunk for ``fit`` (``motion.fit()``)."""
    rest = fit.rest_joints
    frames, joints = fit.local.shape[:2]
    buffer = _Buffer()

    vertices, triangles, owners = stick_figure(rest)
    weights = np.zeros((len(vertices), 4), np.float32)
    weights[:, 0] = 1.0
    influences = np.zeros((len(vertices), 4), np.uint16)
    influences[:, 0] = owners
    primitive = {"attributes": {
        "POSITION": buffer.add(vertices, "VEC3", FLOAT, ARRAY_BUFFER, bounds=True),
        "JOINTS_0": buffer.add(influences, "VEC4", UNSIGNED_SHORT, ARRAY_BUFFER),
        "WEIGHTS_0": buffer.add(weights, "VEC4", FLOAT, ARRAY_BUFFER)},
        "indices": buffer.add(triangles.reshape(-1), "SCALAR", UNSIGNED_INT, ELEMENT_ARRAY_BUFFER)}
    # A joint's bind pose is the rest skeleton's, unturned: its inverse moves it back to the origin.
    inverse_bind = np.tile(np.eye(4, dtype=np.float32), (joints, 1, 1))
    inverse_bind[:, :3, 3] = -rest
    # glTF matrices are column-major: the transpose of numpy's row-major layout.
    binds = buffer.add(np.swapaxes(inverse_bind, 1, 2).reshape(joints, 16), "MAT4", FLOAT)

    times = buffer.add((np.arange(frames) / motion.fps).astype(np.float32), "SCALAR", FLOAT, bounds=True)
    quaternions = Rotation.from_matrix(fit.local.reshape(-1, 3, 3)).as_quat().astype(np.float32)
    quaternions = continuous(quaternions.reshape(frames, joints, 4))
    samplers = [{"input": times, "interpolation": "LINEAR",
                 "output": buffer.add(fit.root_position.astype(np.float32), "VEC3", FLOAT)}]
    channels = [{"sampler": 0, "target": {"node": 0, "path": "translation"}}]
    for joint in range(joints):
        samplers.append({"input": times, "interpolation": "LINEAR",
                         "output": buffer.add(quaternions[:, joint], "VEC4", FLOAT)})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": joint, "path": "rotation"}})

    nodes, children = [], children_of()
    for joint, name in enumerate(JOINT_NAMES):
        parent = JOINT_PARENTS[joint]
        node = {"name": name,
                "translation": (rest[joint] - (rest[parent] if parent >= 0 else 0.0)).tolist()}
        if children[joint]:
            node["children"] = children[joint]
        nodes.append(node)
    nodes.append({"name": "body", "mesh": 0, "skin": 0})
    document = {
        "asset": {"version": "2.0", "generator": "sarah-export"},
        "extras": {"source": motion.source, "body_shape_source": motion.shape.source,
                   "pose_from": fit.pose_from, "fps": float(motion.fps)},
        "scene": 0,
        "scenes": [{"name": motion.name, "nodes": [0, joints]}],
        "nodes": nodes,
        "meshes": [{"name": "stick figure", "primitives": [primitive]}],
        "skins": [{"name": "SMPL-X skeleton", "joints": list(range(joints)), "skeleton": 0,
                   "inverseBindMatrices": binds}],
        "animations": [{"name": "motion", "samplers": samplers, "channels": channels}],
        "accessors": buffer.accessors,
        "bufferViews": buffer.views,
        "buffers": [{"byteLength": len(buffer.data)}],
    }
    return document, bytes(buffer.data)


def glb_bytes(document: dict, binary: bytes) -> bytes:
    """The GLB container: a 12-byte header, the JSON chunk (space-padded), the binary chunk."""
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return (struct.pack("<III", GLB_MAGIC, 2, total) + struct.pack("<II", len(text), JSON_CHUNK) + text
            + struct.pack("<II", len(binary), BIN_CHUNK) + binary)


def save_glb(path: str | Path, payload: bytes) -> None:
    with atomic_path(Path(path)) as tmp:
        Path(tmp).write_bytes(payload)


def write_glb(path: str | Path, motion: ExportMotion, pose_from: str = "joints") -> SkeletonFit:
    """Write ``path`` (.glb) atomically; returns the fit (for its residual)."""
    fit = motion.fit(pose_from)
    save_glb(path, glb_bytes(*gltf_document(motion, fit)))
    return fit
