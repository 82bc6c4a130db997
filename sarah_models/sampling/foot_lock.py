"""Foot lock: feet that stay where they were put, and step when the body has moved on.

Decoded feet do not stand still. On the fixture benchmark the shipped model's feet moved more than
3 cm/s while on the floor in 97 % of frame steps (the ground truth: none), and so did its VAE's
reconstruction of the ground truth: the decoded feet jitter by millimetres per frame, glide with
the body, and never lift off the floor (docs/results.md, seventeenth run). Game engines fix the
same artefact of blended animation by locking planted feet with inverse kinematics; this module
does that, causally, per foot:

- **planted**: the foot keeps its horizontal position from the frame it was planted; its height
  is the decoder's, but never below the floor (y = 0);
- **step** (``step="data"``, ``vae.foot_step``): when the decoded foot has moved ``radius`` away
  from where the foot is planted, the foot steps as the data's people step (the **stance** step
  below, landing after its ``STANCE_SWING_FRAMES`` frames). On the fixture benchmark's 96 tuning
  windows this took the shipped model's streamed FGD_acc from 1,121 by the arc to 823, and the
  benchmark recipe's model's (stepping by drift alone) from 611 to 466 at 0.1 m and 394 at 0.2 m
  (docs/results.md, seventy-first run);
- **arc step** (``step="arc"``, the lock's only step before): when the decoded foot has moved
  ``radius`` away from where the foot is planted, the
  foot swings over ``SWING_FRAMES`` frames along an arc ``LIFT`` above the decoded foot, or above
  the floor where the decoded foot is under it (lifted in the first frame, set down in the last
  two) to where the decoded foot will be when it lands (at the velocity it had when the step
  began), plus as far again in that direction, at most half of ``radius`` (the body walks into
  the step instead of dragging the foot behind), and is planted there;
- **lifted**: a planted foot that the decoder lifts more than ``RELEASE`` above where it was
  planted is taking a step of its own: it follows the decoded foot (the planted spot's horizontal
  offset fading out over ``RELEASE_FADE`` frames, so it does not jump) until the decoded foot is
  back within half of ``RELEASE`` of that height, or for as long as the arc's swing at most, and
  is planted where it is then. Real feet lift before they travel (the fixtures' 3.5 cm in a
  step's first frame, with 0 % of its travel), so real motion passes the lock as it came: on the
  fixture benchmark the rigid skeleton and the lock took the ground truth's FGD_acc from 0 to
  3,827 before, 34 now (docs/results.md, fortieth run). A foot in the air where none is planted
  yet (a stream that starts mid-step) steps on its own too, until it is down (under the foot
  slide's contact height). The tiny decoders' feet never lift that far: their feet glide, and
  step by the arc above;
- **apart** (``gap``, ``vae.foot_gap``): a planted foot is held where it was put while the body
  moves and turns over it, so it can come under or across the other foot, which the data's
  people never let happen: a held foot that comes nearer the other than ``gap`` along the hips'
  line steps to its decoded place (``step``) where that is wider and the other foot stands
  planted; where both could, the one held further from its decoded place steps, one foot at a
  time. Without it, on the fixture benchmark's 296 test windows, the recipe model's ankles came
  within 10 cm on the floor in 2.80 % of frames and crossed in 2.96 % (after the rigid skeleton:
  0.00 %; the data: never), the lock having moved one foot 19.5 cm from the decoded one; with it
  0.74 % and 0.42 %, the pose (FGD_local) 0.93x nearer the data (docs/results.md,
  hundred-and-second and hundred-and-third runs);
- **under the hip** (``lean``, ``vae.foot_lean``, off by default): a held foot whose ankle stands
  further than ``lean`` on the floor from under its hip steps to its decoded place where that is
  nearer under it and the other foot stands planted. It brings the recipe model's ankles nearer
  under its hips by stepping more often, further from the data in FGD_acc (docs/results.md,
  hundred-and-fifth run);
- **free**: a decoded foot higher than ``FREE_HEIGHT`` above the floor (a raised leg) follows the
  decoder;
- **stance** (given a decoded stance, ``vae.foot_lock_reads="stance"``): where the stance of a
  planted foot lifts, the foot steps as the data's people step, not by the arc above: over
  ``STANCE_SWING_FRAMES`` frames along the share of the way the data's steps travel frame by
  frame (``STEP_SHARE``), ``STANCE_LIFT`` above the decoded foot, to where the decoded foot will
  be when it lands, and is planted where it is when the stance lands (past the last frame it
  follows the decoded foot). A stance that stays planted while the decoded foot drifts
  ``stance_reach`` away (``vae.stance_reach``, not ``radius``) still steps (``step``), and a data
  step then lands after its ``STANCE_SWING_FRAMES`` frames whatever the stance says. With the data's own stance
  this took the benchmark VAE's reconstruction of the data from FGD_acc 624 to 278; a VAE of
  the same recipe with its own stance head reconstructs at 277 against 590 by drift, its legs'
  acceleration energy 0.90 of the data's against 0.60 (docs/results.md, seventieth run). Its
  drift steps taken along the data's profile rather than the arc took the benchmark model's
  FGD_acc from 516 to 380 on 96 tuning windows (4 and 6 frames: 407 and 435; seventy-first run).

Feet must not go under the floor: streamed on the fixture benchmark the shipped model's foot
joints were under it in 3.6 % of frames and as low as -4.5 cm (the ground truth's never go under
3 cm), and an arc lifted from a foot 2 cm under the floor was still under 5 cm when the foot
began to travel, so its first and last travelling frames made most of the benchmark's foot
slide. Lifted from the floor, most cleared it (0.0070 -> 0.0028 of frame steps; the ground
truth's 0). The sinking came from ``RigidSkeleton`` lengthening the decoder's short foot bones
down into the floor; it now keeps the decoded height (0.0006), and the floor here stays the
guarantee (docs/results.md, twenty-second run).

The leg follows the foot: the ankle moves with it and the knee is placed by two-bone inverse
kinematics on the hip (thigh and shin at the skeleton's lengths, bending the way the decoded
knee bends); shell points ride their bones (``rigid_skeleton.ShellFollow``). Run after
``RigidSkeleton``, whose lengths it shares.
"""

from __future__ import annotations

import numpy as np

from sarah_data.constants import FLOOR_HEIGHT
from sarah_data.skeleton import MotionLayout
from sarah_data.two_bone_ik import two_bone_ik

from ..config import FOOT_STEPS, MIN_SWING_FRAMES, VAEConfig
from ..evaluation.metrics.spec import FOOT_MAX_HEIGHT

from .rigid_skeleton import ShellFollow, finish, legs

SWING_FRAMES = VAEConfig.foot_swing_frames  # an arc step's swing by default, 0.4 s at 30 fps
STEP = VAEConfig.foot_step  # how a foot steps by drift by default
# m: the swing arc's height above the decoded foot (or the floor). The fixtures' steps rise 7.8 cm
# (median and 90th percentile of the 2,021 steps of the 104 seed-7 test windows). A 10 cm arc
# rose higher than any of them, and the shipped model's FGD_acc with it was 10 % (streamed) and
# 24 % (offline) above the 8 cm arc's (docs/results.md, twenty-third run).
LIFT = 0.08
FREE_HEIGHT = 0.12  # m: a foot higher than this is raised, not standing
# A stance step: the data's steps (4,070 of the fixtures' training corpus) travel above 0.15 m/s
# for 5 frames, these shares of their way by the end of each (median), lifting 3.5 cm in the
# frame before and 7.8 cm at the top; above the decoded foot, which has its own height, a 4 cm
# lift measured best of 0, 4 and 7.8 cm (FGD_acc, 32 test windows; seventieth run).
STANCE_SWING_FRAMES = 5
STEP_TIME = np.linspace(0.0, 1.0, STANCE_SWING_FRAMES + 1)
STEP_SHARE = np.array([0.0, 0.02, 0.29, 0.72, 0.98, 1.0])
STANCE_LIFT = 0.04
STANCE_REACH = VAEConfig.stance_reach  # m a foot drifts from where its stance plants it, by default
GAP = VAEConfig.foot_gap  # m along the hips' line a held foot keeps from the other, by default
LEAN = VAEConfig.foot_lean  # m a held ankle may stand from under its hip, by default
RELEASE = 0.02  # m above its planted height: the decoder is lifting the foot to step
RELEASE_FADE = 6  # frames over which a released foot's planted offset fades out
ON_FLOOR = np.array([1.0, 0.0, 1.0])  # times a vector: its part along the floor (y up)


def hips_line(left_hip: np.ndarray, right_hip: np.ndarray) -> np.ndarray:
    """(..., 3) hips -> (..., 3) the unit floor direction from the right hip to the left, along
    which a foot's gap to the other is measured (the left ankle's offset from the right: ``gap``,
    and ``scripts/decode_replay.py --feet``); zero where the hips stand one above the other."""
    line = (left_hip - right_hip) * ON_FLOOR
    length = np.linalg.norm(line, axis=-1, keepdims=True)
    return np.divide(line, length, out=np.zeros_like(line), where=length > 1e-6)


def floor_velocity(foot: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
    """The decoded foot's move on the floor plane since the frame before, per frame (y = 0)."""
    return (foot - (foot if previous is None else previous)) * ON_FLOOR


class FootLock:
    """Causal filter of one stream's motion, in metres with y up and the floor at y = 0; call it on
    the stream's frames in order. ``lengths`` are the skeleton's (one per ``layout.bones``);
    ``softness``: the legs' reach eased over their last ``softness`` metres, as the rigid
    skeleton's (``vae.leg_softness``)."""

    def __init__(self, layout: MotionLayout, lengths, radius: float,
                 swing_frames: int = SWING_FRAMES, lift: float = LIFT, step: str = STEP,
                 stance_reach: float = STANCE_REACH, gap: float = GAP, lean: float = LEAN,
                 softness: float = 0.0) -> None:
        if not radius > 0:
            raise ValueError(f"foot lock radius must be positive, got {radius}")
        if not stance_reach > 0:
            raise ValueError(f"foot lock stance reach must be positive, got {stance_reach}")
        self.stance_reach = stance_reach
        if not gap >= 0:
            raise ValueError(f"foot lock gap must be >= 0 (0: off), got {gap}")
        self.gap = gap
        if not lean >= 0:
            raise ValueError(f"foot lock lean must be >= 0 (0: off), got {lean}")
        self.lean = lean
        if not softness >= 0:
            raise ValueError(f"foot lock leg softness must be >= 0 (0: off), got {softness}")
        self.softness = softness
        if step not in FOOT_STEPS:
            raise ValueError(f"foot lock step must be one of {FOOT_STEPS}, got {step!r}")
        self.step = step
        if swing_frames < MIN_SWING_FRAMES:
            raise ValueError(f"a step needs at least {MIN_SWING_FRAMES} swing frames, got {swing_frames}")
        self.layout, self.radius, self.swing_frames, self.lift = layout, radius, swing_frames, lift
        self.legs = legs(layout, lengths)
        if not self.legs:
            raise ValueError("foot lock: the motion's layout has no hips, knees, ankles and feet")
        self.reset()

    def reset(self) -> None:
        self.shell = ShellFollow(self.layout)
        self._planted: list[np.ndarray | None] = [None] * len(self.legs)
        # (start, frame, (velocity, beyond), placed): where the swing left, its frame, the
        # decoded foot's velocity then, how far beyond it lands and where it is
        self._swing: list[tuple | None] = [None] * len(self.legs)
        # (landing height, horizontal offset, frame): a foot the decoder lifted to step, the
        # height under which it is down again, its planted spot's offset and for how many
        # frames it has followed the decoder
        self._lifted: list[tuple | None] = [None] * len(self.legs)
        self._previous: list[np.ndarray | None] = [None] * len(self.legs)  # decoded foot
        # (start, frame, placed, by_stance): a step along the data's profile, where it left, its
        # frame, where the foot is, and whether it lands when the stance does (True) or after
        # its frames (False: a drift step, ``step="data"``)
        self._data_step: list[tuple | None] = [None] * len(self.legs)
        # where each ankle was put in its latest frame: what the other foot's gap is measured to
        self._ankles: list[np.ndarray | None] = [None] * len(self.legs)

    def __call__(self, motion: np.ndarray, stance: np.ndarray | None = None,
                 user: np.ndarray | None = None) -> np.ndarray:
        """``stance`` (frames, legs) bool: the decoded stance of these frames (True: planted),
        or None to step by drift alone."""
        x = np.asarray(motion, dtype=np.float64)
        icosahedra, shell = self.layout.split(x)
        joints = icosahedra.mean(axis=-2)
        correction = np.zeros_like(joints)
        targets: list[list[tuple[int, np.ndarray]]] = [[] for _ in self.legs]
        lines = hips_line(joints[:, self.legs[0][0]], joints[:, self.legs[1][0]])
        all_ankles = joints[:, [leg[2] for leg in self.legs]]
        all_hips = joints[:, [leg[0] for leg in self.legs]]
        for t in range(len(x)):
            across, ankles = lines[t], all_ankles[t]
            for side, leg in enumerate(self.legs):
                foot = joints[t, leg[3]]
                on_floor = foot
                if foot[1] < FLOOR_HEIGHT:  # sunk into the floor: stand (and lift off) on it
                    on_floor = np.array([foot[0], FLOOR_HEIGHT, foot[2]])
                stands = None if stance is None else bool(stance[t, side])
                target = self._target(side, on_floor, stands, ankles, across, all_hips[t])
                if target is None and on_floor is not foot:
                    target = on_floor
                if target is not None:
                    targets[side].append((t, target))
                self._ankles[side] = ankles[side] + (0.0 if target is None else target - foot)
        # The state advances frame by frame; the legs then reach for a block's targets at once.
        for leg, reached in zip(self.legs, targets):
            if reached:
                frames = np.array([t for t, _ in reached])
                correction[frames] += self._reach(joints[frames], leg, np.stack([g for _, g in reached]))
        return finish(motion, icosahedra, shell, correction, self.shell(shell, joints, correction))

    def _target(self, side: int, foot: np.ndarray, stands: bool | None = None,
                ankles: np.ndarray | None = None, across: np.ndarray | None = None,
                hips: np.ndarray | None = None) -> np.ndarray | None:
        """Where this frame puts the foot (None: where the decoder put it); advances the state.
        ``stands``: the decoded stance of this foot now, True where it is planted (None: none
        given); ``ankles`` both legs' decoded ankles now and ``across`` the hips' line
        (``hips_line``; zero, or None: the foot is not kept apart from the other); ``hips`` both
        legs' hips now (None: the foot may stand as far from under its hip as it drifts)."""
        previous, self._previous[side] = self._previous[side], foot.copy()
        if foot[1] > FREE_HEIGHT:
            self._planted[side] = self._swing[side] = self._lifted[side] = None
            self._data_step[side] = None
            return None
        if self._lifted[side] is not None:
            return self._follow_lifted(side, foot)
        if self._data_step[side] is not None or (
                stands is False and self._swing[side] is None and self._planted[side] is not None):
            return self._step_as_data(side, foot, previous, stands)
        planted = self._planted[side]
        if planted is None and self._swing[side] is None and foot[1] > FOOT_MAX_HEIGHT:
            # In the air where nothing is planted yet (a stream that starts mid-step, a raised
            # leg coming down): stepping, until it is down where the foot slide counts contact.
            self._lifted[side] = (FOOT_MAX_HEIGHT, np.zeros(3), 0)
            return None
        if planted is not None and self._swing[side] is None and foot[1] > planted[1] + RELEASE:
            self._planted[side] = None
            self._lifted[side] = (planted[1] + 0.5 * RELEASE,
                                  (planted - foot) * ON_FLOOR, 0)
            return foot + self._lifted[side][1]
        swing = self._swing[side]
        if swing is not None:
            start, frame, lead, placed = swing
            frame += 1
            n = self.swing_frames
            # The foot lifts off in the first frame and is set down in the last two, vertically;
            # in between it travels to the decoded foot plus the lead, starting and landing at
            # rest (a smoothstep).
            if frame < n - 1:
                velocity, beyond = lead
                landing = foot + velocity * (n - frame) + beyond
                travel = min(max((frame - 1) / (n - 3), 0.0), 1.0)
                placed = start + (landing - start) * (travel * travel * (3.0 - 2.0 * travel))
            target = placed.copy()
            target[1] = foot[1] + self.lift * np.sin(np.pi * frame / n)
            if frame >= n:
                self._swing[side], self._planted[side] = None, target.copy()
            else:
                self._swing[side] = (start, frame, lead, placed)
            return target
        planted = self._planted[side]
        if planted is None:
            self._planted[side] = foot.copy()
            return None
        target = np.array([planted[0], foot[1], planted[2]])
        reach = self.radius if stands is None else self.stance_reach
        drifted = (np.hypot(*(foot - planted)[[0, 2]]) > reach
                   or self._crowded(side, target - foot, ankles, across)
                   or self._leaning(side, target - foot, ankles, hips))
        if drifted and self.step == "data":
            return self._step_as_data(side, foot, previous, stands, by_stance=False)
        if drifted:
            # Step to where the decoded foot will be when the step lands, and further on in its
            # direction (as far again, at most ``radius``), so that the body walks into the step
            # instead of dragging the foot behind; further, the foot would be released at once.
            velocity = floor_velocity(foot, previous)
            beyond = self.swing_frames * velocity
            beyond *= min(1.0, 0.5 * self.radius / max(np.linalg.norm(beyond), 1e-9))
            lead = (velocity, beyond)
            self._planted[side], self._swing[side] = None, (target, 0, lead, target)
        return target

    def _crowded(self, side: int, held: np.ndarray, ankles: np.ndarray | None,
                 across: np.ndarray | None) -> bool:
        """Whether this planted foot, ``held`` this far from the decoded one, is to step because
        it stands nearer the other foot than ``gap`` along the hips' line: if the other is
        planted too, and stepping to its decoded place would widen the feet's gap, and either the
        other's step would not or this foot is held further from its decoded place (one foot
        steps at a time)."""
        other = 1 - side
        if (not self.gap or ankles is None or across is None or self._planted[other] is None
                or self._ankles[other] is None):
            return False
        outward = across if side == 0 else -across  # LEGS: the left leg first
        standing = self._ankles[other]  # where the other foot's ankle stands, held
        kept = float(np.dot(ankles[side] + held - standing, outward))
        if kept >= self.gap or float(np.dot(ankles[side] - standing, outward)) <= kept:
            return False
        if float(np.dot(ankles[side] + held - ankles[other], outward)) <= kept:
            return True  # the other foot's step would not widen the gap
        return np.hypot(*held[[0, 2]]) >= np.hypot(*(standing - ankles[other])[[0, 2]])

    def _leaning(self, side: int, held: np.ndarray, ankles: np.ndarray | None,
                 hips: np.ndarray | None) -> bool:
        """Whether this planted foot, ``held`` this far from the decoded one, is to step because
        its ankle stands further than ``lean`` on the floor from under its hip, the decoded ankle
        stands nearer under it, and the other foot is planted (one foot steps at a time)."""
        if not self.lean or ankles is None or hips is None or self._planted[1 - side] is None:
            return False
        leaning = np.linalg.norm((ankles[side] + held - hips[side]) * ON_FLOOR)
        return leaning > self.lean and np.linalg.norm((ankles[side] - hips[side]) * ON_FLOOR) < leaning

    def _step_as_data(self, side: int, foot: np.ndarray, previous: np.ndarray | None,
                      stands: bool | None, by_stance: bool = True) -> np.ndarray:
        """A step along the data's profile (see the module docstring): one the decoded stance
        takes (``by_stance``), planted where the stance lands, or a drift step, planted after its
        frames; ``by_stance`` matters only for the step's first frame, its state keeps it."""
        step = self._data_step[side]
        if step is None:
            step = (self._planted[side], 0, self._planted[side], by_stance)
            self._planted[side] = None
        start, frame, placed, by_stance = step
        if by_stance and stands and frame > 0:
            self._data_step[side], self._planted[side] = None, placed.copy()
            return np.array([placed[0], foot[1], placed[2]])
        frame += 1
        n = STANCE_SWING_FRAMES
        landing = foot + floor_velocity(foot, previous) * max(n - frame, 0)
        placed = start + (landing - start) * np.interp(min(frame / n, 1.0), STEP_TIME, STEP_SHARE)
        target = placed.copy()
        target[1] = foot[1] + STANCE_LIFT * np.sin(np.pi * min(frame, n) / (n + 1))
        if not by_stance and frame >= n:
            self._data_step[side], self._planted[side] = None, placed.copy()
        else:
            self._data_step[side] = (start, frame, placed, by_stance)
        return target

    def _follow_lifted(self, side: int, foot: np.ndarray) -> np.ndarray | None:
        """A foot the decoder lifted: the decoded foot plus what is left of the planted offset;
        planted again where it comes down."""
        landing, offset, frame = self._lifted[side]
        frame += 1
        target = foot + offset * max(0.0, 1.0 - frame / RELEASE_FADE)
        if foot[1] < landing or frame >= self.swing_frames:
            # down, or in the air for as long as a step swings: planted where it is
            self._lifted[side], self._planted[side] = None, target.copy()
        else:
            self._lifted[side] = (landing, offset, frame)
        return target if frame < RELEASE_FADE else None

    def _reach(self, joints: np.ndarray, leg: tuple, foot_target: np.ndarray) -> np.ndarray:
        """The corrections (n, J, 3) that put the leg's foot at ``foot_target`` (n, 3) in each of
        ``joints``' n frames: the ankle moved with the foot, the knee by two-bone IK on the hip;
        a target out of reach is reached for."""
        hip, knee, ankle, foot, thigh, shin, _ = leg
        correction = np.zeros_like(joints)
        knee_at, ankle_at = two_bone_ik(joints[:, hip], joints[:, knee],
                                        joints[:, ankle] + foot_target - joints[:, foot], thigh, shin,
                                        self.softness)
        correction[:, knee] = knee_at - joints[:, knee]
        correction[:, ankle] = correction[:, foot] = ankle_at - joints[:, ankle]
        return correction
