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
lag behind it. Causal (``scipy.signal.lfilter`` carrying its state from chunk to chunk, started
at the first frame's steady state so a still body passes unchanged): a stream decoded in chunks and the same frames
decoded at once are the same. The price is a delay of about 1 / (2 pi cutoff) s * sqrt(2) at low
frequencies (37 ms at 6 Hz).
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from sarah_data.constants import FPS
from sarah_data.skeleton import ROOT, MotionLayout

LIMBS = ("arms", "hands")  # the JOINT_GROUPS filtered


def butterworth(cutoff: float, fps: float = FPS) -> tuple[np.ndarray, np.ndarray]:
    """A second-order Butterworth low-pass's (b, a), a[0] = 1."""
    if not 0 < cutoff < fps / 2:
        raise ValueError(f"limb low-pass cutoff must be in (0, {fps / 2:g}) Hz, got {cutoff}")
    return signal.butter(2, cutoff, fs=fps)


class LimbLowpass:
    """Causal filter of one stream's motion, in metres; call it on the stream's frames in
    order."""

    def __init__(self, layout: MotionLayout, cutoff: float, fps: float = FPS) -> None:
        self.layout = layout
        self.b, self.a = butterworth(cutoff, fps)
        self.reset()

    def reset(self) -> None:
        self.points: np.ndarray | None = None  # point indices filtered, set at the first frame
        self.state: np.ndarray | None = None  # (2, points * 3): the filter's two delays

    def __call__(self, motion: np.ndarray, stance: np.ndarray | None = None,
                 user: np.ndarray | None = None) -> np.ndarray:
        out = np.array(motion, dtype=np.float64)
        if not len(out):
            return out
        if self.points is None:
            self.points = self.layout.group_points(out[0], LIMBS)
        points = out.reshape(len(out), -1, 3)  # a view into ``out``
        pelvis = self.layout.joint_positions(out, [ROOT])[:, 0]
        x = (points[:, self.points] - pelvis[:, None]).reshape(len(out), -1)
        if self.state is None:  # a still limb passes unchanged: the steady state of frame 0
            self.state = signal.lfilter_zi(self.b, self.a)[:, None] * x[0]
        y, self.state = signal.lfilter(self.b, self.a, x, axis=0, zi=self.state)
        points[:, self.points] = y.reshape(len(out), -1, 3) + pelvis[:, None]
        return out
