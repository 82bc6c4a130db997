"""Stance anchor: the body moves on the floor only as far as its feet carry it.

A walking person moves forward over a foot that stands: in every frame one foot (at least) is
planted, and the pelvis travels relative to it. A wandering decoder moves the whole body
instead, feet included: its feet glide with the pelvis. ``RootHold`` cannot tell the two apart
by the pelvis alone (a dead zone and a lag on where the pelvis goes), so it delays and smooths
real walking too: on the fixture benchmark the decoding chain took the ground truth's FGD_acc
from 34 without the hold to 1,167 with it (docs/results.md, forty-fourth run).

``StanceAnchor`` reads the feet. Each frame the foot that moved less since the previous frame
stands (for a walking body it does not move; for a gliding one it moves with the body), and the
whole body is moved back on the floor (x and z of every point; heights stay the decoder's) by
that foot's horizontal displacement, up to ``max_speed``: a glide faster than that (the decoder
walking the body without stepping) is slowed by ``max_speed`` and goes on, and the foot lock
steps under it. A body whose feet stand, the ground truth's, passes unchanged; a body gliding on
both feet slower than ``max_speed`` stays where it is; a body stepping, one foot standing while
the other swings, walks over the standing foot as far as the decoder walks it.

The body starts with its pelvis at the origin, where the generation frame puts the agent at the
stream's first frame (``sarah_data.frames``), as ``RootHold``'s does. Causal, frame by frame, so
a stream decoded in chunks and the same frames decoded at once are the same.
"""

from __future__ import annotations

import numpy as np

from sarah_data.constants import FPS
from sarah_data.skeleton import FEET, ROOT, MotionLayout


class StanceAnchor:
    """Causal filter of one stream's motion, in metres with y up; call it on the stream's
    frames in order."""

    def __init__(self, layout: MotionLayout, max_speed: float) -> None:
        if not max_speed > 0:
            raise ValueError(f"stance anchor max_speed must be positive, got {max_speed}")
        if not all(name in layout.joint_names for name in FEET):
            raise ValueError(f"stance anchor: the motion's layout has no {' and '.join(FEET)}")
        self.layout, self.max_move = layout, max_speed / FPS
        self.reset()

    def reset(self) -> None:
        self._shift: np.ndarray | None = None  # (x, z) the body is moved by
        self._previous: np.ndarray | None = None  # the decoded feet on the floor, (2, 2)

    def __call__(self, motion: np.ndarray) -> np.ndarray:
        x = np.asarray(motion, dtype=np.float64)
        floor = self.layout.joint_positions(x, [ROOT, *FEET])[..., [0, 2]]  # (n, 3, 2)
        shift = np.zeros((len(x), 3))
        for t in range(len(x)):
            feet = floor[t, 1:]
            if self._shift is None:
                self._shift = -floor[t, 0]
            else:
                moved = feet - self._previous
                distance = np.hypot(*moved.T)
                stance = int(np.argmin(distance))
                taken = min(1.0, self.max_move / distance[stance]) if distance[stance] > 0 else 0.0
                self._shift = self._shift - moved[stance] * taken
            self._previous = feet
            shift[t, [0, 2]] = self._shift
        points = x.reshape(len(x), -1, 3) + shift[:, None]
        return points.reshape(x.shape).astype(motion.dtype)
