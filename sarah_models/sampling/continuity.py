"""Root continuity across latent blocks: inertialization of the decoder's block-boundary jumps.

Each latent token decodes to s frames. A flow sample's consecutive tokens disagree slightly on
where the body is, and the decoder turns each disagreement into a jump of the whole body at the
first frame of the next block: on the fixture benchmark (docs/results.md, sixteenth run) the
shipped model's streamed pelvis had 32x the acceleration variance of the ground truth, 82 % of
it on block-boundary frames, and that jump alone was most of its FGD_acc.

Game engines hide the same kind of seam between two animation clips by inertialization: at the
seam the new pose is shifted so that it continues the old motion, and the shift then decays to
nothing. ``RootInertia`` does this for the root: at the first frame of every block the offset is
set so that the pelvis continues at its last velocity, and on every other frame the offset keeps
``retention`` of itself. The offset moves every point of the frame alike (a translation), so the
pose is the decoder's own and a seam's correction is spread over ~1 / (1 - retention) frames.
``retention = 0`` returns the decoder's output as is (the paper).

It runs frame by frame on the past only, so a stream decoded block by block and the same latents
decoded at once get the same frames.
"""

from __future__ import annotations

import numpy as np

from sarah_data.skeleton import MotionLayout

ROOT_JOINT = "pelvis"


class RootInertia:
    """Causal filter of one stream's decoded motion; call it on the frames in order."""

    def __init__(self, layout: MotionLayout, stride: int, retention: float) -> None:
        if not 0.0 <= retention < 1.0:
            raise ValueError(f"boundary inertia (retention per frame) must be in [0, 1), got "
                             f"{retention}")
        if retention > 0 and stride < 2:
            raise ValueError(f"boundary inertia needs blocks of at least 2 frames, got stride "
                             f"{stride}")
        self.layout, self.stride, self.retention = layout, stride, retention
        channels = layout.joint_slice(ROOT_JOINT)
        self._root_points = slice(channels.start // 3, channels.stop // 3)
        self.reset()

    def reset(self) -> None:
        self._frame = 0
        self._offset = np.zeros(3)
        self._previous: list[np.ndarray] = []  # the last two output root positions

    def __call__(self, motion: np.ndarray) -> np.ndarray:
        """(n, Dx) motion vectors in metres, the stream's next n frames -> the same, shifted."""
        if self.retention == 0:
            self._frame += len(motion)
            return motion
        points = np.asarray(motion, np.float64).reshape(len(motion), -1, 3)
        roots = points[:, self._root_points].mean(axis=1)
        offsets = np.empty_like(roots)
        for i, root in enumerate(roots):
            if self._frame % self.stride == 0 and len(self._previous) == 2:
                before, last = self._previous
                self._offset = 2.0 * last - before - root  # continue at the last velocity
            else:
                self._offset = self._offset * self.retention
            offsets[i] = self._offset
            self._previous = [self._previous[-1], root + self._offset] if self._previous else [
                root + self._offset]
            self._frame += 1
        return (points + offsets[:, None]).reshape(motion.shape).astype(motion.dtype)
