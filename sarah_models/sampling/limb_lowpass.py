"""Limb low-pass: the arms' and hands' motion relative to the pelvis, without the jitter above
the frequencies people's arms move at.

The benchmark's VAE decodes the arms with 1.9-48x the data's acceleration power above 6 Hz,
where the data's arms have a tenth of theirs, and the hands likewise (docs/results.md,
fifty-sixth run): latent tokens come at 7.5 Hz (s = 4), and each block's arms disagree a little
with the last. The seam spring (``continuity.py``) damps every acceleration at a seam, the beats'
too; a low-pass passes the beats (the fixtures' syllable-rate gestures at ~4.5 Hz) and stops
what lies above them.

``LimbLowpass`` filters the joint icosahedra of ``JOINT_GROUPS``' arms and hands, and the shell
points nearest them in the stream's first frame (``sarah_data.skeleton.shell_parts``), with a
second-order Butterworth low-pass of ``cutoff`` Hz per coordinate, relative to the pelvis: the
pelvis's translation is taken out before and put back after, so a walking body's arms do not
lag behind it. Causal, frame by frame (one biquad state per coordinate, started at the first
frame's value so a still body passes unchanged): a stream decoded in chunks and the same frames
decoded at once are the same. The price is a delay of about 1 / (2 pi cutoff) s * sqrt(2) at low
frequencies (37 ms at 6 Hz).
"""

from __future__ import annotations

import math

import numpy as np

from sarah_data.constants import FPS
from sarah_data.skeleton import ICOSAHEDRON_POINTS, JOINT_GROUPS, ROOT, MotionLayout, shell_parts

LIMBS = ("arms", "hands")  # the JOINT_GROUPS filtered


def butterworth(cutoff: float, fps: float = FPS) -> tuple[np.ndarray, np.ndarray]:
    """A second-order Butterworth low-pass's (b, a), a[0] = 1 (the bilinear transform, as the RBJ
    cookbook gives it)."""
    if not 0 < cutoff < fps / 2:
        raise ValueError(f"limb low-pass cutoff must be in (0, {fps / 2:g}) Hz, got {cutoff}")
    w0 = 2 * math.pi * cutoff / fps
    alpha = math.sin(w0) / math.sqrt(2)  # Q = 1 / sqrt(2)
    b = np.array([(1 - math.cos(w0)) / 2, 1 - math.cos(w0), (1 - math.cos(w0)) / 2])
    a = np.array([1 + alpha, -2 * math.cos(w0), 1 - alpha])
    return b / a[0], a / a[0]


class LimbLowpass:
    """Causal filter of one stream's motion, in metres; call it on the stream's frames in
    order."""

    def __init__(self, layout: MotionLayout, cutoff: float, fps: float = FPS) -> None:
        self.layout = layout
        self.b, self.a = butterworth(cutoff, fps)
        joints = [layout.joint(n) for group in LIMBS for n in JOINT_GROUPS[group]
                  if n in layout.joint_names]
        self.joint_points = (np.asarray(joints)[:, None] * ICOSAHEDRON_POINTS
                             + np.arange(ICOSAHEDRON_POINTS)).ravel()
        self.root = layout.joint_slice(ROOT)
        self.reset()

    def reset(self) -> None:
        self.points: np.ndarray | None = None  # point indices filtered, set at the first frame
        self.state: np.ndarray | None = None  # (2, points, 3): the biquad's two delays

    def _start(self, frame: np.ndarray) -> None:
        icosahedra, shell = self.layout.split(frame)
        parts = shell_parts(icosahedra, shell, self.layout.joint_names)
        shell_points = [p for group in LIMBS for p in parts.get(group, ())]
        offset = self.layout.num_joints * ICOSAHEDRON_POINTS
        self.points = np.concatenate([self.joint_points, offset + np.asarray(shell_points, int)])

    def __call__(self, motion: np.ndarray) -> np.ndarray:
        out = np.array(motion, dtype=np.float64)
        if not len(out):
            return out
        if self.points is None:
            self._start(out[0])
        points = out.reshape(len(out), -1, 3)  # a view into ``out``
        pelvis = out[:, self.root].reshape(len(out), ICOSAHEDRON_POINTS, 3).mean(axis=1)
        (b0, b1, b2), (_, a1, a2) = self.b, self.a
        for t in range(len(out)):
            x = points[t, self.points] - pelvis[t]
            if self.state is None:  # a still limb passes unchanged: the steady state of x
                second = (b2 - a2) * x
                self.state = np.stack([(1 - b0) * x, second])
            y = b0 * x + self.state[0]
            self.state = np.stack([b1 * x - a1 * y + self.state[1], b2 * x - a2 * y])
            points[t, self.points] = y + pelvis[t]
        return out
