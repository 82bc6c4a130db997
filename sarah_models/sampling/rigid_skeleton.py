"""Rigid bones: decoded joints put back on a skeleton whose bones keep their length.

The decoder emits every joint's icosahedron on its own, so nothing holds a bone to one length:
on the fixture benchmark the shipped model's streamed bones stretched and shrank by 30 % (p95
over frames and body bones; its VAE reconstructing the ground truth: 25 %), led by the head,
the wrists, the feet and the hips, and a limb that changes length is the first thing a viewer
sees (docs/results.md, seventeenth run). ``RigidSkeleton`` keeps what the decoder says about
the pose, each bone's direction, and takes each bone's length from the training data's skeleton
(``stats.h5``'s ``bone_length``): walking the skeleton from the root, every joint is placed at
its parent's corrected position plus the bone's length along its decoded direction, and its
icosahedron moves with it (its rotation is the decoder's). Shell points follow the joints near
them (``ShellFollow``): each moves by a blend of the joints' corrections, weighted by a Gaussian
of its distance to each (``shell_radius``) in the stream's first frame, the way skinning weights
fall off.

Causal: a stream decoded block by block and the same frames at once agree exactly.
"""

from __future__ import annotations

import numpy as np

from sarah_data.skeleton import MotionLayout

SHELL_RADIUS = 0.05  # m: a shell point follows the joints within a few centimetres of it


class RigidSkeleton:
    """(n, Dx) motion vectors in metres -> the same frames on a skeleton with ``lengths``
    (metres, one per ``layout.bones``). Call it on a stream's frames in order (``reset`` starts
    another stream): the shell's weights on the joints are its first frame's."""

    def __init__(self, layout: MotionLayout, lengths, shell_radius: float = SHELL_RADIUS) -> None:
        lengths = np.asarray(lengths, dtype=np.float64).reshape(-1)
        if len(lengths) != len(layout.bones):
            raise ValueError(f"rigid skeleton: {len(lengths)} bone lengths for a layout of "
                             f"{len(layout.bones)} bones")
        if not (np.all(np.isfinite(lengths)) and np.all(lengths > 0)):
            raise ValueError("rigid skeleton: bone lengths must be finite and positive")
        self.layout, self.lengths = layout, lengths
        # Bones a level at a time (parents placed before their children), as index arrays.
        depth: dict[int, int] = {}
        for child, parent in layout.bones:
            depth[child] = depth.get(parent, 0) + 1
        self._levels = []
        for level in sorted(set(depth.values())):
            rows = [i for i, (child, _) in enumerate(layout.bones) if depth[child] == level]
            bones = np.array([layout.bones[i] for i in rows])
            self._levels.append((bones[:, 0], bones[:, 1], lengths[rows, None]))
        self.shell = ShellFollow(shell_radius)

    def reset(self) -> None:
        self.shell.reset()

    def __call__(self, motion: np.ndarray) -> np.ndarray:
        x = np.asarray(motion, dtype=np.float64)
        icosahedra, shell = self.layout.split(x)
        joints = icosahedra.mean(axis=-2)
        placed = joints.copy()
        for child, parent, length in self._levels:
            direction = joints[:, child] - joints[:, parent]
            norm = np.linalg.norm(direction, axis=-1, keepdims=True)
            # A bone the decoder collapsed to a point has no direction to keep: leave it.
            scale = np.divide(length, norm, out=np.ones_like(norm), where=norm > 1e-9)
            placed[:, child] = placed[:, parent] + direction * scale
        correction = placed - joints
        return finish(motion, icosahedra, shell, correction, self.shell(shell, joints, correction))


def finish(motion, icosahedra, shell, correction, shell_correction) -> np.ndarray:
    """The motion vector with every icosahedron moved by its joint's correction and the shell
    points by theirs, in the input's dtype."""
    n = len(icosahedra)
    out = np.concatenate([(icosahedra + correction[:, :, None]).reshape(n, -1),
                          (shell + shell_correction).reshape(n, -1)], axis=1)
    return out.astype(np.asarray(motion).dtype)


class ShellFollow:
    """How shell points follow corrections of the joints: each moves by a blend of the joints',
    weighted by exp(-d^2 / 2 radius^2) of its distance d to each (relative to its nearest, so a
    point far from every joint still follows the nearest). Like skinning weights the blend is
    fixed for a body: it is taken from the first frame it sees (``reset`` forgets it)."""

    def __init__(self, radius: float = SHELL_RADIUS) -> None:
        if not radius > 0:
            raise ValueError(f"shell radius must be positive, got {radius}")
        self.radius = radius
        self.reset()

    def reset(self) -> None:
        self.weights: np.ndarray | None = None

    def __call__(self, shell: np.ndarray, joints: np.ndarray, correction: np.ndarray) -> np.ndarray:
        """(T, P, 3) shell points, (T, J, 3) joints and their corrections -> (T, P, 3)."""
        if self.weights is None:
            d2 = np.sum((shell[0, :, None, :] - joints[0, None, :, :]) ** 2, axis=-1)
            weights = np.exp(-(d2 - d2.min(axis=-1, keepdims=True)) / (2.0 * self.radius ** 2))
            self.weights = weights / weights.sum(axis=-1, keepdims=True)
        return np.einsum("pj,tjc->tpc", self.weights, correction)
