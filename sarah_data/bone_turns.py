"""Rotations that turn bone directions onto others: the shortest one for one direction, the best
one for several at once.

Shared by the decoding chain (``sarah_models.sampling.rigid_skeleton``: shell points turned with
their corrected bones) and the exporters (``sarah_data.export.kinematics``: each joint's rotation
turned until its bones point at the motion's joints).
"""

from __future__ import annotations

import numpy as np

OPPOSITE = -1.0 + 1e-6  # a cosine at or below it: the directions are opposite


def unit(vectors: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
    """``vectors`` (..., 3) made unit; where one has no length, ``fallback`` (else zero)."""
    norm = np.linalg.norm(vectors, axis=-1, keepdims=True)
    out = np.divide(vectors, norm, out=np.zeros_like(vectors, dtype=np.float64), where=norm > 1e-9)
    return out if fallback is None else np.where(norm > 1e-9, out, fallback)


def shortest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations turning directions (..., 3) ``a`` onto ``b`` about their common
    normal (Rodrigues): the smallest that do. The identity where either has no length; where they
    are opposite, half a circle about an axis across ``a`` (any such axis turns ``a`` onto ``b``)."""
    a, b = unit(a), unit(b)
    v, cos = np.cross(a, b), np.sum(a * b, axis=-1)
    cross = np.zeros(a.shape[:-1] + (3, 3))
    cross[..., 0, 1], cross[..., 0, 2], cross[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    cross[..., 1, 0], cross[..., 2, 0], cross[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    turn = np.divide(1.0, 1.0 + cos, out=np.zeros_like(cos), where=cos > OPPOSITE)
    rotation = np.eye(3) + cross + cross @ cross * turn[..., None, None]
    opposite = cos <= OPPOSITE
    if opposite.any():
        across = np.cross(a[opposite], [1.0, 0.0, 0.0])
        weak = np.linalg.norm(across, axis=-1) < 1e-6  # a along x: cross with y instead
        across[weak] = np.cross(a[opposite][weak], [0.0, 1.0, 0.0])
        axis = unit(across)
        rotation[opposite] = 2.0 * axis[..., :, None] * axis[..., None, :] - np.eye(3)
    return rotation


def best_rotation(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(..., 3, 3) the rotations that best turn the directions ``source`` onto ``target``
    (..., K, 3), K >= 2 (Kabsch on unit vectors; of equally good ones, the smallest). A target of
    no length, a child on its parent, asks for no turn."""
    u = unit(source)
    t = unit(target, fallback=u)
    cross = np.einsum("...ki,...kj->...ij", t, u) + 1e-9 * np.eye(3)  # the eye: the smallest turn
    left, _, right = np.linalg.svd(cross)
    flip = np.ones(cross.shape[:-1])
    flip[..., -1] = np.sign(np.linalg.det(left @ right))
    return (left * flip[..., None, :]) @ right


def rotation_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(...) degrees of the rotation between rotations ``a`` and ``b`` (..., 3, 3)."""
    cos = (np.trace(np.swapaxes(a, -1, -2) @ b, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
