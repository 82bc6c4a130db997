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

It runs block by block on the past and the block in hand (a block's first velocity is read from
its own first two frames, which the decoder emits together), so a stream decoded block by block
and the same latents decoded at once get the same frames.
"""

from __future__ import annotations

import numpy as np


class SeamInertia:
    """Causal filter of one stream's decoded motion; call it on whole blocks, in order."""

    def __init__(self, stride: int, decay: float) -> None:
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"seam inertia (decay per frame) must be in [0, 1), got {decay}")
        if decay > 0 and stride < 2:
            raise ValueError(f"seam inertia needs blocks of at least 2 frames, got stride {stride}")
        self.stride, self.decay = stride, decay
        k = np.arange(stride, dtype=np.float64)
        rate = -np.log(decay) if decay > 0 else 0.0
        # The spring's offset on the block's frames k: x0 * (1 + rate k) e^(-rate k) + v0 * k e^(-rate k).
        self._from_position = ((1.0 + rate * k) * np.exp(-rate * k))[:, None, None]
        self._from_velocity = (k * np.exp(-rate * k))[:, None, None]
        self.reset()

    def reset(self) -> None:
        self._last: np.ndarray | None = None  # the last two output frames, (2, P, 3)

    def __call__(self, motion: np.ndarray) -> np.ndarray:
        """(n, Dx) motion vectors in metres, the stream's next n frames (whole blocks) -> the
        same frames, continued across each seam."""
        if self.decay == 0:
            return motion
        if len(motion) % self.stride:
            raise ValueError(f"seam inertia takes whole blocks of {self.stride} frames, got "
                             f"{len(motion)} frames")
        points = np.asarray(motion, np.float64).reshape(len(motion), -1, 3)
        out = np.empty_like(points)
        for start in range(0, len(points), self.stride):
            block = points[start:start + self.stride]
            if self._last is None:
                out[start:start + self.stride] = block  # the stream's first block: no seam yet
            else:
                before, last = self._last
                x0 = last + (last - before) - block[0]
                v0 = (last - before) - (block[1] - block[0])
                out[start:start + self.stride] = (block + x0 * self._from_position
                                                  + v0 * self._from_velocity)
            self._last = out[start + self.stride - 2:start + self.stride].copy()
        return out.reshape(motion.shape).astype(motion.dtype)
