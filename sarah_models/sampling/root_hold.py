"""Root hold: a body that stands where it stands until the decoder really moves it.

People in conversation mostly stand: they shift their weight and turn, and walk now and then.
The decoded body does not stand still. On the fixture benchmark the shipped model's streamed
pelvis moved at 0.3 m/s at the median frame where the ground truth's stood (0 m/s), travelling
2.6x the ground truth's path per window: the decoder's floor position wanders slowly and
widely, back and forth over tens of centimetres (docs/results.md, seventeenth and eighteenth
runs). Drawn on the feet, that wander is what the foot lock turns into steps that the ground
truth never takes.

``RootHold`` moves the whole body on the floor (x and z of every point; heights stay the
decoder's) so that its pelvis holds still while the decoded pelvis (or, reading the feet, the
body's glide) stays within ``radius`` of it, and follows it beyond that: each frame the held
position closes ``FOLLOW`` of the decoded pelvis's distance beyond ``radius`` -- a dead zone and
a first-order lag, so the body starts and stops walking without a jump in velocity and walks
``radius`` plus ``v (1 - FOLLOW) / (fps FOLLOW)`` behind the decoded pelvis (33 cm at 1 m/s with
the shipped model's 20 cm radius), never faster than ``MAX_SPEED``, the fastest the data's
people walk: where the decoded pelvis jumps, the body walks after it. Causal, frame by frame, so
a stream decoded in chunks and the same frames decoded at once are the same.

What the hold reads (``reads``, ``vae.root_hold_reads``). "pelvis": where the decoded pelvis
goes. A walking person's pelvis goes there too, and the hold cannot tell the two apart: it holds
a real body's sways and the first ``radius`` of its walks, its feet then slide with the shift,
and the foot lock turns that into steps the data did not take (the ground truth through the
benchmark's chain: FGD_acc 1,167 with the hold, 34 without; docs/results.md, forty-fourth run).
"feet": only how far the whole body glides. A walking person moves over a standing foot; a
wandering decoder moves the whole body, feet included. Each frame the standing foot is the lower
one where the other is lifted (a real step's swinging foot can move less than a glided standing
one early in its swing), else the one that moved less; the hold holds the sum of its floor
moves, and the body's moves over its standing foot pass as decoded. Real motion, whose standing
feet do not move, passes unchanged.

What the hold turns (``turn``, ``vae.root_hold_turn``). Holding the body back moves it, and
moving it changes its bearing to the user: the decoded body walked somewhere and faces its user
from there, and the held one, kept where it stood with the decoded orientation, faces its user
more than the data's people do (head angle +0.11 over the data's on the fixture benchmark's test
windows, look-away 0.04 against 0.22; docs/results.md, seventy-sixth run). With ``turn`` the
held body turns about its pelvis by that share of the change in bearing, from where the decoded
pelvis is to where the held one is, so that it faces its user as the decoded body does. The turn
follows the bearing at ``TURN_FOLLOW`` per frame, never faster than ``TURN_RATE``: a user who
walks past the body swings its bearing by up to half a turn in a few frames. It reads the
user's floor-projected head in the frame the motion is in, frame by frame (``user``).

The held position starts at the origin. Decoding runs in the generation frame, which puts the
agent's pelvis at the origin at the stream's first frame (``sarah_data.frames``, paper 3.1): where
the body starts is known, not generated. The decoder alone starts it 15 cm away on average
(frame-0 offset, docs/results.md, nineteenth run); starting the hold at the decoded position
kept that error for as long as the body stood.
"""

from __future__ import annotations

import numpy as np

from sarah_data.constants import FPS
from sarah_data.frames import rotation_about_y, wrap_angle
from sarah_data.skeleton import FEET, ROOT, MotionLayout

from ..config import HOLD_READS
from .foot_lock import RELEASE

FOLLOW = 0.2  # of the distance beyond the radius, per frame: a 1 / 0.2 = 5-frame lag
# m/s: the fastest the body walks, the fastest pelvis of the seed-0 fixture training corpus
# (2.01 m/s; 99th percentile 1.67). The decoded pelvis runs at up to 7 (streamed) and 15 m/s
# (offline), and no step the data takes keeps feet under a body that fast (docs/results.md,
# twenty-sixth run).
MAX_SPEED = 2.0
# The turn's lag and speed limit, chosen on the fixture benchmark's tuning windows (followed
# at once and unlimited, the turn swung bodies whose user came near: FGD_acc 421 against 334 so;
# docs/results.md, seventy-seventh run).
TURN_FOLLOW = 0.2  # of the remaining angle, per frame
TURN_RATE = 1.0  # rad/s


def heading(target: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """The heading (rad about +y, as ``sarah_data.frames.yaw_of``: 0 = toward +z) from
    ``origin`` to ``target``, both (..., 2) floor points (x, z)."""
    d = target - origin
    return np.arctan2(d[..., 0], d[..., 1])


class RootHold:
    """Causal filter of one stream's motion, in metres with y up; call it on the stream's
    frames in order."""

    def __init__(self, layout: MotionLayout, radius: float, follow: float = FOLLOW,
                 max_speed: float = MAX_SPEED, reads: str = "pelvis", turn: float = 0.0) -> None:
        if not radius > 0:
            raise ValueError(f"root hold radius must be positive, got {radius}")
        if not 0 < follow <= 1:
            raise ValueError(f"root hold follow must be in (0, 1], got {follow}")
        if not max_speed > 0:
            raise ValueError(f"root hold max_speed must be positive, got {max_speed}")
        if reads not in HOLD_READS:
            raise ValueError(f"root hold reads one of {HOLD_READS}, got {reads!r}")
        if reads == "feet" and not all(name in layout.joint_names for name in FEET):
            raise ValueError(f"root hold: the motion's layout has no {' and '.join(FEET)}")
        if not 0 <= turn <= 1:
            raise ValueError(f"root hold turn must be in [0, 1], got {turn}")
        self.layout, self.radius, self.follow, self.reads = layout, radius, follow, reads
        self.turn = turn
        self.max_move = max_speed / FPS
        self.reset()

    def reset(self) -> None:
        self._held = np.zeros(2)  # the body's pelvis on the floor (x, z): the frame's origin
        self._glide: np.ndarray | None = None  # "feet": the pelvis's start plus the feet's glide
        self._feet: np.ndarray | None = None  # "feet": the previous frame's decoded feet (x, z)
        self._angle = 0.0  # the held body's turn (rad, about y), with ``turn``

    @property
    def reads_user(self) -> bool:
        """Whether each call needs the user's floor path (``turn``)."""
        return self.turn > 0

    def __call__(self, motion: np.ndarray, stance: np.ndarray | None = None,
                 user: np.ndarray | None = None) -> np.ndarray:
        """``user`` (n, 2): the user's floor-projected head (x, z) at these frames, in the
        motion's frame; needed with ``turn``."""
        x = np.asarray(motion, dtype=np.float64)
        if self.turn and (user is None or np.shape(user) != (len(x), 2)):
            raise ValueError(f"a root hold that turns (vae.root_hold_turn) reads the user's floor "
                             f"path at every frame: ({len(x)}, 2) wanted, got "
                             f"{None if user is None else np.shape(user)}")
        joints = self.layout.joint_positions(x, [ROOT, *FEET] if self.reads == "feet" else [ROOT])
        pelvis = joints[:, 0, [0, 2]]
        path = pelvis if self.reads == "pelvis" else self._glide_path(joints)
        shift = np.zeros((len(x), 3))
        for t in range(len(x)):
            away = path[t] - self._held
            distance = float(np.hypot(*away))
            if distance > self.radius:
                move = min(self.follow * (distance - self.radius), self.max_move)
                self._held += away * (move / distance)
            shift[t, [0, 2]] = self._held - path[t]
        points = x.reshape(len(x), -1, 3) + shift[:, None]
        if self.turn:
            held = pelvis + shift[:, [0, 2]]
            change = wrap_angle(heading(user, held) - heading(user, pelvis))
            points = turned(points, held, self._follow_turn(self.turn * change))
        return points.reshape(x.shape).astype(motion.dtype)

    def _follow_turn(self, targets: np.ndarray) -> np.ndarray:
        """The body's turn at each frame (rad), following ``targets`` at ``TURN_FOLLOW`` of the
        rest per frame, at most ``TURN_RATE``."""
        limit, angles = TURN_RATE / FPS, np.empty(len(targets))
        for t, target in enumerate(targets):
            step = TURN_FOLLOW * wrap_angle(float(target) - self._angle)
            self._angle += min(max(step, -limit), limit)
            angles[t] = self._angle
        return angles

    def _glide_path(self, joints: np.ndarray) -> np.ndarray:
        """(n, 3 [pelvis, feet], 3) -> (n, 2): where the whole body has glided, the stream's first
        pelvis plus the sum of each frame's floor move of the standing foot: the lower one where
        the other is lifted (a real step's swinging foot may move less, early in its swing), else
        the one that moved less (decoded feet glide without lifting)."""
        feet = joints[:, 1:, [0, 2]]
        if self._glide is None:  # the stream's first frame: nothing has glided yet
            self._glide, self._feet = joints[0, 0, [0, 2]], feet[0]
        moved = feet - np.concatenate([self._feet[None], feet[:-1]])
        heights = joints[:, 1:, 1]
        least = np.argmin(np.hypot(moved[..., 0], moved[..., 1]), axis=1)
        standing = np.where(np.abs(heights[:, 0] - heights[:, 1]) > RELEASE,
                            np.argmin(heights, axis=1), least)
        glide = moved[np.arange(len(moved)), standing]
        # summed from the last frame's position on, frame by frame: chunks add up as the whole
        path = np.cumsum(np.concatenate([self._glide[None], glide]), axis=0)[1:]
        self._glide, self._feet = path[-1], feet[-1]
        return path


def turned(points: np.ndarray, centres: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(n, P, 3) points turned about the vertical through ``centres`` (n, 2: x, z) by ``angles``
    (n,) rad, each frame's: every heading (``heading``) grows by it; heights stay."""
    centre = np.stack([centres[:, 0], np.zeros(len(centres)), centres[:, 1]], axis=-1)[:, None]
    return centre + np.einsum("tij,tpj->tpi", rotation_about_y(angles), points - centre)
