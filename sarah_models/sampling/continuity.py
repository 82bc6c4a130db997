"""Continuity across latent blocks: inertialization of the seams between decoded tokens.

Each latent token decodes to s frames. A flow sample's consecutive tokens disagree slightly on
where the body is and how it moves, and the decoder turns each disagreement into a seam: on the
fixture benchmark (docs/results.md, sixteenth run) the shipped model's streamed motion put 82 %
of its acceleration on the last frame of a block, its whole body jumping from one block to the
next, and those seams were most of its FGD_acc.

Game engines hide the same kind of seam between two animation clips by inertialization: at the
seam the new motion is offset so that it continues the old one, position and velocity, and the
offset then decays to nothing. ``SeamInertia`` does this for every point of the motion vector
(icosahedron vertices and shell points alike): at the first frame of every block, the offset of
each point is the difference between where the output was heading (its last position plus its
last velocity) and where the new block starts, and between their velocities; the offset then
decays as a critically damped spring, x(k) = (x0 + (v0 + y x0) k) exp(-y k) with
exp(-y) = ``decay``, so position and velocity stay continuous at the seam and the correction is
spread over ~1 / (1 - decay) frames. ``decay = 0`` returns the decoder's output as is (the paper).

That continuation is a constant-velocity prediction, so on motion without any seam it still
offsets every block by the acceleration at its first frame and damps it: the fixtures' ground
truth through it alone scores FGD_acc 194 against Random's 138 (docs/results.md, fortieth run).
``mode="position"`` reads the seam's position jump against the mean of the velocities on both
sides, last position + (last velocity + the block's first velocity) / 2 - the block's first
frame, which is exact for motion of constant acceleration, and springs that jump out with the
block's own velocity kept (v0 = 0): the ground truth passes with 50, and the benchmark model's
samples, through the whole decoding chain, score lower too. ``mode="velocity"`` is the
sixteenth run's, which the models shipped so far decode with.

``still`` leaves some body parts (``JOINT_GROUPS``' names: their joints' icosahedra and the
shell points nearest them) as the decoder put them (``vae.seam_skips_hands``: the hands). The
rigid skeleton places each hand as a piece on its wrist and each finger along its decoded
direction, so a still hand goes where its sprung wrist goes and keeps its own motion; sprung
point by point, the fingers' own seams and their real beats are smoothed together, and on the
fixture benchmark's test windows the hands came further from the data while the arms and the
trunk came nearer (docs/results.md, hundred-and-fifth run).

It runs block by block on the past and the block in hand (a block's first velocity is read from
its own first two frames, which the decoder emits together), so a stream decoded block by block
and the same latents decoded at once get the same frames.
"""

from __future__ import annotations

import numpy as np

from sarah_data.skeleton import MotionLayout

from ..config import SEAM_MODES


class SeamInertia:
    """Causal filter of one stream's decoded motion; call it on whole blocks, in order.

    ``decay`` acts on the pose (each point relative to the root); ``root_decay`` on the root's
    translation, which every point shares (None: ``decay`` too). ``root_points`` are the
    points whose mean is the root (the pelvis icosahedron). ``still``: body parts the spring
    leaves as decoded, in ``layout``."""

    def __init__(self, stride: int, decay: float, root_decay: float | None = None,
                 root_points: slice | None = None, mode: str = "velocity",
                 layout: MotionLayout | None = None, still: tuple[str, ...] = ()) -> None:
        if mode not in SEAM_MODES:
            raise ValueError(f"seam inertia mode must be one of {SEAM_MODES}, got {mode!r}")
        self.mode = mode
        root_decay = decay if root_decay is None else root_decay
        for name, value in (("decay", decay), ("root decay", root_decay)):
            if not 0.0 <= value < 1.0:
                raise ValueError(f"seam inertia ({name} per frame) must be in [0, 1), got {value}")
        if max(decay, root_decay) > 0 and stride < 2:
            raise ValueError(f"seam inertia needs blocks of at least 2 frames, got stride {stride}")
        if root_decay != decay and root_points is None:
            raise ValueError("seam inertia with its own root decay needs the root's points")
        if still and layout is None:
            raise ValueError("seam inertia that leaves body parts still needs the motion's layout")
        self.layout, self.still = layout, tuple(still)
        self.stride, self.decay, self.root_decay = stride, decay, root_decay
        self._root = root_points if root_decay != decay else None
        self._pose_spring = self._spring(decay)
        self._root_spring = self._spring(root_decay)
        self.reset()

    def _spring(self, decay: float) -> tuple[np.ndarray, np.ndarray]:
        """The spring's offset on a block's frames k, per unit of the seam's position and
        velocity offsets: x0 (1 + rate k) e^(-rate k) + v0 k e^(-rate k); none at decay 0."""
        k = np.arange(self.stride, dtype=np.float64)[:, None, None]
        if decay == 0:
            return np.zeros_like(k), np.zeros_like(k)
        rate = -np.log(decay)
        return (1.0 + rate * k) * np.exp(-rate * k), k * np.exp(-rate * k)

    def reset(self) -> None:
        self._last: np.ndarray | None = None  # the last two output frames, (2, P, 3)
        self._still: np.ndarray | None = None  # the points of ``still``, from the first frame

    def __call__(self, motion: np.ndarray, stance: np.ndarray | None = None,
                 user: np.ndarray | None = None) -> np.ndarray:
        """(n, Dx) motion vectors in metres, the stream's next n frames (whole blocks) -> the
        same frames, continued across each seam."""
        if self.decay == 0 and self.root_decay == 0:
            return motion
        if len(motion) % self.stride:
            raise ValueError(f"seam inertia takes whole blocks of {self.stride} frames, got "
                             f"{len(motion)} frames")
        points = np.asarray(motion, np.float64).reshape(len(motion), -1, 3)
        if self.still and self._still is None and len(motion):
            self._still = self.layout.group_points(motion[0], self.still)
        out = np.empty_like(points)
        for start in range(0, len(points), self.stride):
            block = points[start:start + self.stride]
            if self._last is None:
                out[start:start + self.stride] = block  # the stream's first block: no seam yet
            else:
                before, last = self._last
                v_last, v_first = last - before, block[1] - block[0]
                if self.mode == "velocity":
                    x0, v0 = last + v_last - block[0], v_last - v_first
                else:
                    x0, v0 = last + 0.5 * (v_last + v_first) - block[0], np.zeros_like(v_last)
                offsets = self._offsets(x0, v0)
                if self._still is not None:
                    offsets[:, self._still] = 0.0
                out[start:start + self.stride] = block + offsets
            self._last = out[start + self.stride - 2:start + self.stride].copy()
        return out.reshape(motion.shape).astype(motion.dtype)

    def _offsets(self, x0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        """(s, P, 3): the block's offsets from the seam's position and velocity offsets (P, 3)."""
        position, velocity = self._pose_spring
        if self._root is None:
            return x0 * position + v0 * velocity
        x_root = x0[self._root].mean(axis=0)
        v_root = v0[self._root].mean(axis=0)
        root_position, root_velocity = self._root_spring
        return ((x0 - x_root) * position + (v0 - v_root) * velocity
                + x_root * root_position + v_root * root_velocity)

