"""The rigid skeleton and the foot lock (sampling.rigid_skeleton, sampling.foot_lock), the
skeleton they read (stats.h5's bone_length) and the decoding chain that runs them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sarah_data.constants import FLOOR_HEIGHT, JOINT
from sarah_data.dataset import WindowDataset
from sarah_data.export.kinematics import rest_offsets_from_motion
from sarah_data.icosahedron import decode
from sarah_data.skeleton import MotionLayout, bone_lengths
from sarah_data.stats import load_stats
from sarah_models.evaluation.metrics import foot_slide
from sarah_models.sampling.foot_lock import (FREE_HEIGHT, LIFT, RELEASE, STANCE_LIFT,
                                             STANCE_SWING_FRAMES, SWING_FRAMES, FootLock)
from sarah_models.sampling.rigid_skeleton import (COLLARS, HANDS, HIPS, SKULL, RigidSkeleton, ShellFollow,
                                                  piece_directions, skull_directions)

FEET = [JOINT["left_foot"], JOINT["right_foot"]]


@pytest.fixture(scope="module")
def windows(prepared_shards):
    return WindowDataset(prepared_shards, "train", extractor="logmel", window=60, seed=0, length=8)


@pytest.fixture(scope="module")
def skeleton(prepared_shards):
    return load_stats(prepared_shards)["bone_length/mean"].astype(np.float64)


def joints_of(motion: np.ndarray, layout: MotionLayout) -> np.ndarray:
    return layout.split(np.asarray(motion, np.float64))[0].mean(axis=-2)


def standing(window: dict, layout: MotionLayout) -> np.ndarray:
    """(T, Dx): the window's first frame held still (a body standing on the floor)."""
    motion = window["motion"].numpy().astype(np.float64)
    return np.repeat(motion[:1], len(motion), axis=0)


def shift_joints(motion: np.ndarray, layout: MotionLayout, shifts: np.ndarray) -> np.ndarray:
    """Every joint's icosahedron moved by its own (T, J, 3) shift; shell points as they were."""
    icosahedra, shell = layout.split(motion.copy())
    icosahedra += shifts[:, :, None]
    return np.concatenate([icosahedra.reshape(len(motion), -1), shell.reshape(len(motion), -1)], 1)


def first_frames(windows, frames: int):
    """The layout, shell points (T, P, 3) and joints (T, J, 3) of a window's first frames."""
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[1]["motion"].numpy().astype(np.float64)[:frames]
    icosahedra, shell = layout.split(motion)
    return layout, shell, icosahedra.mean(axis=-2)


def test_stats_carry_every_bones_training_length(prepared_shards, windows, skeleton):
    layout = MotionLayout.from_width(windows.motion_dim)
    assert skeleton.shape == (len(layout.bones),) == (54,)
    truth = bone_lengths(joints_of(windows[0]["motion"].numpy(), layout), layout.bones)
    # Fixture persons differ in height and girth by a few percent; their bones do not stretch.
    np.testing.assert_allclose(truth.std(axis=0), 0.0, atol=1e-4)
    assert np.all(np.abs(truth[0] / skeleton - 1.0) < 0.1)


def test_rigid_skeleton_keeps_directions_and_puts_every_bone_at_its_length(windows, skeleton):
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[1]["motion"].numpy().astype(np.float64)
    rng = np.random.default_rng(0)
    noisy = shift_joints(motion, layout, rng.normal(scale=0.02, size=(len(motion), 55, 3)))
    out = RigidSkeleton(layout, skeleton)(noisy)
    before, after = joints_of(noisy, layout), joints_of(out, layout)
    np.testing.assert_allclose(bone_lengths(after, layout.bones),
                               np.broadcast_to(skeleton, (len(out), 54)), rtol=1e-9)
    legs = {(JOINT[child], JOINT[parent]) for side in ("left", "right")
            for parent, child in ((f"{side}_hip", f"{side}_knee"), (f"{side}_knee", f"{side}_ankle"),
                                  (f"{side}_ankle", f"{side}_foot"))}
    for child, parent in set(layout.bones) - legs:
        a, b = before[:, child] - before[:, parent], after[:, child] - after[:, parent]
        cosine = np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
        np.testing.assert_allclose(cosine, 1.0, atol=1e-9)
    np.testing.assert_allclose(after[:, 0], before[:, 0], atol=1e-12)  # the root stays
    # The ankles stay where the decoder put them (the feet on the floor), the knees bending.
    for ankle, knee, hip in ((7, 4, 1), (8, 5, 2)):
        reach = np.linalg.norm(before[:, ankle] - after[:, hip], axis=-1)
        longest = (skeleton[layout.bones.index((knee, hip))]
                   + skeleton[layout.bones.index((ankle, knee))])
        within = reach < 0.999 * longest
        assert within.mean() > 0.3  # a standing leg is nearly straight
        np.testing.assert_allclose(after[within, ankle], before[within, ankle], atol=1e-9)
    # The feet at their decoded height, heading the decoded way on the floor.
    for foot, ankle in ((10, 7), (11, 8)):
        length = skeleton[layout.bones.index((foot, ankle))]
        reachable = np.abs(before[:, foot, 1] - after[:, ankle, 1]) < length
        assert reachable.mean() > 0.9
        np.testing.assert_allclose(after[reachable, foot, 1], before[reachable, foot, 1], atol=1e-9)
        a, b = ((x[:, foot] - x[:, ankle]) * [1, 0, 1] for x in (before, after))
        cosine = np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
        np.testing.assert_allclose(cosine[reachable], 1.0, atol=1e-9)
    shapes = [layout.split(m)[0] - joints_of(m, layout)[:, :, None] for m in (noisy, out)]
    np.testing.assert_allclose(shapes[0], shapes[1], atol=1e-9)  # rotations are the decoder's
    # A body already at those lengths is left as it is, shell points included: exactly once its
    # lengths are the skeleton's (a second pass changes nothing), and the data's own body within
    # its float32 rounding. Its bone lengths vary by ~3e-7 m between frames (how much depends on
    # the CPU that wrote the shards), and a joint moves by at most the sum of its chain's errors
    # (10 bones from the pelvis to a fingertip).
    lengths = bone_lengths(joints_of(motion, layout), layout.bones)
    rigid = RigidSkeleton(layout, lengths[0])
    once = rigid(motion)
    np.testing.assert_allclose(rigid(once), once, atol=1e-12)
    spread = np.abs(lengths - lengths[0]).max()
    assert spread < 1e-5
    np.testing.assert_allclose(once, motion, atol=10 * spread)


def test_a_short_decoded_foot_stays_on_the_floor_and_lies_flatter(windows, skeleton):
    """The decoder's foot bones come out short and steep; lengthened along their direction, the
    feet went into the floor (docs/results.md, twenty-second run)."""
    layout = MotionLayout.from_width(windows.motion_dim)
    body = next(b for b in (standing(windows[i], layout) for i in range(len(windows)))
                if joints_of(b, layout)[0, FEET, 1].max() < 0.05)  # both feet on the floor
    joints = joints_of(body, layout)
    lengths = bone_lengths(joints, layout.bones)[0]
    shifts = np.zeros((len(body), 55, 3))
    for foot in FEET:  # the foot joint 60 % of the way to the ankle on the floor, at its height
        shifts[:, foot] = 0.6 * (joints[:, foot - 3] - joints[:, foot]) * [1, 0, 1]
    decoded = joints_of(shift_joints(body, layout, shifts), layout)
    steep = decoded[:, FEET] - decoded[:, [f - 3 for f in FEET]]
    along = decoded[:, [f - 3 for f in FEET], 1] + steep[..., 1] * (
        lengths[[layout.bones.index((f, f - 3)) for f in FEET]] / np.linalg.norm(steep, axis=-1))
    assert along.max() < FLOOR_HEIGHT  # lengthened along its decoded direction: in the floor
    out = joints_of(RigidSkeleton(layout, lengths)(shift_joints(body, layout, shifts)), layout)
    np.testing.assert_allclose(out[:, FEET, 1], joints[:, FEET, 1], atol=1e-9)
    np.testing.assert_allclose(out[:, FEET], joints[:, FEET], atol=1e-9)  # as it stood


def test_shell_points_follow_the_joints_near_them(windows, skeleton):
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[2]["motion"].numpy().astype(np.float64)[:4]
    lengths = bone_lengths(joints_of(motion, layout), layout.bones)[0]
    forearm = layout.bones.index((JOINT["left_wrist"], JOINT["left_elbow"]))
    lengths[forearm] *= 1.2  # the left hand moves out along the forearm
    out = RigidSkeleton(layout, lengths)(motion)
    moved = np.linalg.norm(layout.split(out)[1] - layout.split(motion)[1], axis=-1)[0]
    shell = layout.split(motion)[1][0]
    joints = joints_of(motion, layout)[0]
    near_hand = np.linalg.norm(shell - joints[JOINT["left_wrist"]], axis=-1) < 0.05
    far = np.linalg.norm(shell - joints[JOINT["left_wrist"]], axis=-1) > 0.5
    assert near_hand.any() and far.any()
    assert moved[near_hand].min() > 0.5 * 0.2 * lengths[forearm] / 1.2
    assert moved[far].max() < 1e-6


def test_shell_points_turn_with_a_bent_shin_as_a_skinned_mesh_does(windows):
    # The foot lock bends knees: the ankle and foot swing 40 degrees about the knee. The shin's
    # and foot's points turn with them (each keeps its distances to knee and ankle), the thigh's
    # and the other leg's stay; a blend of joint translations moved the mid-shin points along the
    # chord, nearer the knee.
    layout, shell, joints = first_frames(windows, 3)
    knee, ankle = joints[:, JOINT["left_knee"]], joints[:, JOINT["left_ankle"]]
    angle = np.deg2rad(40.0)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(angle), -np.sin(angle)],
                     [0.0, np.sin(angle), np.cos(angle)]])  # about x: the shin swings back
    correction = np.zeros_like(joints)
    for name in ("left_ankle", "left_foot"):
        j = JOINT[name]
        correction[:, j] = (joints[:, j] - knee) @ turn.T + knee - joints[:, j]
    follow = ShellFollow(layout)
    moved = shell + follow(shell, joints, correction)
    segment = follow.bones[follow.segment]
    shin = (segment[:, 0] == JOINT["left_ankle"]) & (segment[:, 1] == JOINT["left_knee"])
    thigh = (segment[:, 0] == JOINT["left_knee"]) & (segment[:, 1] == JOINT["left_hip"])
    right = np.isin(segment[:, 1], [JOINT[n] for n in ("right_hip", "right_knee", "right_ankle")])
    assert shin.sum() >= 3 and thigh.sum() >= 3 and right.sum() >= 3
    new_ankle = ankle + correction[:, JOINT["left_ankle"]]
    for old_end, new_end in ((knee, knee), (ankle, new_ankle)):
        before = np.linalg.norm(shell[:, shin] - old_end[:, None], axis=-1)
        after = np.linalg.norm(moved[:, shin] - new_end[:, None], axis=-1)
        np.testing.assert_allclose(after, before, atol=1e-9)
    assert np.linalg.norm(moved[:, shin] - shell[:, shin], axis=-1).min() > 0.01  # they did turn
    np.testing.assert_allclose(moved[:, thigh | right], shell[:, thigh | right], atol=1e-12)


def test_a_forearm_put_back_at_its_length_carries_the_hand_no_further_than_the_wrist(windows):
    # The decoder can shrink a forearm to a few centimetres while the hand's shell points stay
    # where the hand is; the skeleton puts the wrist back. Points past the wrist move with it;
    # stretched with the 3 cm bone, a hand point once flew 8 m.
    layout, shell, joints = first_frames(windows, 2)
    elbow, wrist = JOINT["left_elbow"], JOINT["left_wrist"]
    shrunk = joints.copy()
    shrunk[:, wrist] = joints[:, elbow] + 0.03 * (joints[:, wrist] - joints[:, elbow]) / np.linalg.norm(
        joints[:, wrist] - joints[:, elbow], axis=-1, keepdims=True)
    correction = joints - shrunk  # the skeleton's: the wrist back where it belongs
    follow = ShellFollow(layout)
    moved = follow(shell, shrunk, correction)
    on_forearm = np.all(follow.bones[follow.segment] == (wrist, elbow), axis=-1)
    assert on_forearm.sum() >= 3
    reach = np.linalg.norm(correction[:, wrist], axis=-1).max()
    assert np.linalg.norm(moved, axis=-1).max() <= reach + 1e-9
    bone = shrunk[0, wrist] - shrunk[0, elbow]
    past_wrist = on_forearm & ((shell[0] - shrunk[0, elbow]) @ bone > bone @ bone)
    assert past_wrist.sum() >= 3
    np.testing.assert_allclose(moved[:, past_wrist],
                               np.repeat(correction[:, wrist, None], past_wrist.sum(), 1), atol=1e-9)


def test_the_skulls_directions_come_from_the_mean_motion_root_relative_or_not(windows, prepared_shards):
    # A body is rigid: averaged over any frames, its mean vertices give back its bones in their
    # parents' frames. The training data's mean (stats.h5) gives its persons' skull.
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[1]["motion"].numpy().astype(np.float64)
    found = skull_directions(layout, motion.mean(axis=0))
    rest = rest_offsets_from_motion(*decode(layout.split(motion)[0]))  # the person's own skeleton
    assert sorted(found) == sorted(JOINT[name] for name in SKULL)
    for child, parent in layout.bones:
        if child in found:
            bone = rest[child] - rest[parent]
            np.testing.assert_allclose(found[child], bone / np.linalg.norm(bone), atol=1e-5)  # float32
    # Root-relative statistics (Normalizer.set_root_relative) move every point but the root's by
    # the root's floor place: the skull's bones stay.
    relative = skull_directions(layout, root_relative_mean(motion, layout))
    for child in found:
        np.testing.assert_allclose(relative[child], found[child], atol=1e-9)
    mean = load_stats(prepared_shards)["motion/mean"]
    for child, direction in skull_directions(layout, mean).items():
        assert np.degrees(np.arccos(np.clip(direction @ found[child], -1, 1))) < 2.0
    # A mean of no body holds no rotation: no directions, and the skull keeps its decoded ones.
    assert skull_directions(layout, np.zeros(windows.motion_dim)) == {}


def test_the_skull_sits_where_its_parents_rotation_puts_it(windows):
    # Decoded, the head sat 65 degrees off where the neck's rotation carries it and the eyes
    # 75 around the head (the demo's clip). Here the head is moved 5 cm and the jaw and the
    # eyes 4 cm each, their icosahedra's rotations left as they were: the skeleton puts them back.
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[3]["motion"].numpy().astype(np.float64)
    lengths = layout.motion_bone_lengths(motion)
    shifts = np.zeros((len(motion), 55, 3))
    rng = np.random.default_rng(1)
    shifts[:, JOINT["head"]] = [0.0, -0.03, 0.04]
    for name in ("jaw", "left_eye_smplhf", "right_eye_smplhf"):
        shifts[:, JOINT[name]] = rng.normal(size=3) * 0.04 / np.sqrt(3)
    noisy = shift_joints(motion, layout, shifts)
    skull = skull_directions(layout, motion.mean(axis=0))
    placed = joints_of(RigidSkeleton(layout, lengths, skull=skull)(noisy), layout)
    truth = joints_of(motion, layout)
    for name in SKULL:
        np.testing.assert_allclose(placed[:, JOINT[name]], truth[:, JOINT[name]], atol=1e-6)
    # Without the skull's directions, the decoded ones: the head stays off by centimetres.
    along_decoded = joints_of(RigidSkeleton(layout, lengths)(noisy), layout)
    assert np.linalg.norm(along_decoded[:, JOINT["head"]] - truth[:, JOINT["head"]], axis=-1).min() > 0.02


def root_relative_mean(motion: np.ndarray, layout: MotionLayout) -> np.ndarray:
    """The mean of ``motion`` as root-relative statistics hold it (Normalizer.set_root_relative):
    every point but the root's own less the root's floor place."""
    points = motion.reshape(len(motion), -1, 3).copy()
    root = layout.split(motion)[0][:, layout.joint("pelvis")].mean(axis=-2) * [1.0, 0.0, 1.0]
    others = np.ones(points.shape[1], bool)
    others[layout.joint_slice("pelvis").start // 3:layout.joint_slice("pelvis").stop // 3] = False
    points[:, others] -= root[:, None]
    return points.reshape(len(motion), -1).mean(axis=0)


def test_the_hips_directions_come_from_the_mean_motion_root_relative_or_not(windows):
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[1]["motion"].numpy().astype(np.float64)
    found = piece_directions(layout, motion.mean(axis=0))
    rest = rest_offsets_from_motion(*decode(layout.split(motion)[0]))  # the person's own skeleton
    for side, name in enumerate(HIPS):
        bone = rest[JOINT[name]] - rest[JOINT["pelvis"]]
        np.testing.assert_allclose(found[side], bone / np.linalg.norm(bone), atol=1e-5)  # float32
    # Root-relative statistics leave the root's own points where they were: its height is
    # what a hip's mean point is taken from.
    np.testing.assert_allclose(piece_directions(layout, root_relative_mean(motion, layout), HIPS, True),
                               found, atol=1e-9)
    # A root that holds its floor steps, or a mean of no body, holds no rotation to solve with.
    assert piece_directions(layout, motion.mean(axis=0), root_steps=True) is None
    assert piece_directions(layout, np.zeros(windows.motion_dim)) is None


def descendants(layout: MotionLayout, joint: int) -> list[int]:
    """``joint`` and every joint below it in ``layout``'s skeleton."""
    out = [joint]
    for child, parent in layout.bones:  # parents come before their children
        if parent in out:
            out.append(child)
    return out


def pinched(motion: np.ndarray, layout: MotionLayout, frames: slice, by: float,
            pair: tuple[str, str] = HIPS, toward=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Both bones of ``pair`` swung ``by`` of the way from their direction to ``toward`` in
    ``frames`` (ramped in and out over 4 frames each), every joint below each moving with it: the
    model's narrow pelvis (the demo's clip: its hips 3 cm apart, both bones at their length
    nearly straight down). ``toward`` None: the mean of the two bones' directions in each frame,
    a fold that leaves the piece's middle where it was."""
    joints = joints_of(motion, layout)
    weight = np.zeros(len(motion))
    weight[frames] = by
    weight = np.convolve(weight, np.ones(5) / 5, mode="same")[:, None]
    shifts = np.zeros((len(motion), 55, 3))
    parent_of = dict(layout.bones)
    bones = {name: joints[:, JOINT[name]] - joints[:, parent_of[JOINT[name]]] for name in pair}
    if toward is None:
        toward = sum(bone / np.linalg.norm(bone, axis=-1, keepdims=True) for bone in bones.values())
        toward = toward / np.linalg.norm(toward, axis=-1, keepdims=True)
    for name in pair:
        child, bone = JOINT[name], bones[name]
        length = np.linalg.norm(bone, axis=-1, keepdims=True)
        swung = (1 - weight) * bone / length + weight * np.asarray(toward)
        shift = length * swung / np.linalg.norm(swung, axis=-1, keepdims=True) - bone
        for joint in descendants(layout, child):
            shifts[:, joint] = shift
    return shift_joints(motion, layout, shifts)


def test_the_pelvis_keeps_its_hips_and_a_leg_moves_with_its_hip(windows):
    # Decoded, the model's hips came as near as 3 cm and its knees crossed. Here the hip bones
    # swing 80 % of the way to straight down for 20 frames, the legs with them: the pelvis keeps
    # its width, and each leg comes back with its hip to within millimetres of where it was.
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[3]["motion"].numpy().astype(np.float64)
    lengths = layout.motion_bone_lengths(motion)
    hips = piece_directions(layout, motion.mean(axis=0))
    narrow = pinched(motion, layout, slice(20, 40), 0.8)
    truth = joints_of(motion, layout)
    width = np.linalg.norm(truth[:, JOINT["left_hip"]] - truth[:, JOINT["right_hip"]], axis=-1)
    decoded = joints_of(narrow, layout)
    assert np.linalg.norm(decoded[:, JOINT["left_hip"]] - decoded[:, JOINT["right_hip"]], axis=-1).min() < 0.4 * width.min()
    placed = joints_of(RigidSkeleton(layout, lengths, pieces={HIPS: hips})(narrow), layout)
    placed_width = np.linalg.norm(placed[:, JOINT["left_hip"]] - placed[:, JOINT["right_hip"]], axis=-1)
    np.testing.assert_allclose(placed_width, placed_width[0], rtol=1e-12)  # one piece in every frame
    np.testing.assert_allclose(placed_width, width, rtol=1e-5)  # the mean's directions: float32
    for name in ("left_hip", "right_hip", "left_knee", "left_ankle", "right_knee", "right_ankle"):
        assert np.linalg.norm(placed[:, JOINT[name]] - truth[:, JOINT[name]], axis=-1).max() < 0.01, name
    # Along their decoded directions the hips pinch, and the leg stays where it was decoded.
    along = joints_of(RigidSkeleton(layout, lengths)(narrow), layout)
    assert np.linalg.norm(along[:, JOINT["left_hip"]] - along[:, JOINT["right_hip"]], axis=-1).min() < 0.5 * width.min()
    assert np.linalg.norm(along[:, JOINT["left_ankle"]] - truth[:, JOINT["left_ankle"]], axis=-1).max() > 0.05


def test_the_collars_directions_come_from_the_mean_motion_root_relative_or_not(windows):
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[1]["motion"].numpy().astype(np.float64)
    found = piece_directions(layout, motion.mean(axis=0), COLLARS)
    rest = rest_offsets_from_motion(*decode(layout.split(motion)[0]))
    for side, name in enumerate(COLLARS):
        bone = rest[JOINT[name]] - rest[JOINT["spine3"]]
        np.testing.assert_allclose(found[side], bone / np.linalg.norm(bone), atol=1e-5)
    # The chest is not the root: root-relative statistics, or a root holding its steps, change
    # nothing.
    np.testing.assert_allclose(piece_directions(layout, root_relative_mean(motion, layout), COLLARS,
                                                True, True), found, atol=1e-9)


def test_the_chest_keeps_its_collars_and_an_arm_moves_with_its_collar(windows):
    # Decoded each along its own direction, the model's collars folded as its hips did (under
    # 80 % of their width in 16 % of frames), the shoulders with them. Here both collar bones
    # swing 80 % of the way to their middle for 20 frames, the arms with them: the chest keeps its
    # width, and each arm comes back with its collar to within a centimetre of where it was (the
    # person's collars move about their mean's: the piece holds the mean's), the pelvis and
    # the legs untouched. (Folded toward straight up instead, which the collars' middle leans
    # forward of, the chest tilts with the fold: ``piece_frames``.)
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[3]["motion"].numpy().astype(np.float64)
    lengths = layout.motion_bone_lengths(motion)
    pieces = {pair: piece_directions(layout, motion.mean(axis=0), pair) for pair in (HIPS, COLLARS)}
    narrow = pinched(motion, layout, slice(20, 40), 0.8, COLLARS, None)
    truth, decoded = joints_of(motion, layout), joints_of(narrow, layout)

    def width(joints, pair):
        return np.linalg.norm(joints[:, JOINT[pair[0]]] - joints[:, JOINT[pair[1]]], axis=-1)

    assert width(decoded, COLLARS).min() < 0.4 * width(truth, COLLARS).min()
    placed = joints_of(RigidSkeleton(layout, lengths, pieces=pieces)(narrow), layout)
    np.testing.assert_allclose(width(placed, COLLARS), width(truth, COLLARS), rtol=1e-5)
    for side in ("left", "right"):
        for name in ("collar", "shoulder", "elbow", "wrist", "hip", "knee", "ankle"):
            error = np.linalg.norm(placed[:, JOINT[f"{side}_{name}"]] - truth[:, JOINT[f"{side}_{name}"]], axis=-1)
            assert error.max() < 0.01, (side, name)
    # Along their decoded directions the collars pinch and the shoulders with them.
    along = joints_of(RigidSkeleton(layout, lengths, pieces={HIPS: pieces[HIPS]})(narrow), layout)
    shoulders = ("left_shoulder", "right_shoulder")
    assert width(along, shoulders).min() < 0.8 * width(truth, shoulders).min()


def test_a_hand_keeps_its_palm_and_a_finger_moves_with_its_knuckle(windows):
    # Decoded each along its own direction, the model's knuckles swung apart and together (the
    # palm under 80 % of its width in 8-11 % of frames). Here each hand's index and little
    # finger swing 80 % of the way to their middle for 20 frames, the fingers with them: the palm
    # keeps its width and every finger joint comes back to within a centimetre of its place.
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[3]["motion"].numpy().astype(np.float64)
    lengths = layout.motion_bone_lengths(motion)
    narrow = motion
    for hand in HANDS:
        narrow = pinched(narrow, layout, slice(20, 40), 0.8, hand[:2], None)
    truth, decoded = joints_of(motion, layout), joints_of(narrow, layout)
    placed = joints_of(RigidSkeleton(layout, lengths, pieces={
        hand: piece_directions(layout, motion.mean(axis=0), hand) for hand in HANDS})(narrow), layout)
    for hand in HANDS:
        index, pinky = JOINT[hand[0]], JOINT[hand[1]]
        width = np.linalg.norm(truth[:, index] - truth[:, pinky], axis=-1)
        assert np.linalg.norm(decoded[:, index] - decoded[:, pinky], axis=-1).min() < 0.5 * width.min()
        np.testing.assert_allclose(np.linalg.norm(placed[:, index] - placed[:, pinky], axis=-1),
                                   width, rtol=1e-4)
        side = hand[0].split("_")[0]
        for joint in descendants(layout, JOINT[f"{side}_wrist"]):
            error = np.linalg.norm(placed[:, joint] - truth[:, joint], axis=-1)
            assert error.max() < 0.01, layout.joint_names[joint]


def test_pieces_streamed_block_by_block_are_the_pieces_decoded_at_once(windows):
    # Each piece's sideways axis leans on its own frame before, across a stream's blocks as
    # within one; ``reset`` starts a new stream.
    layout = MotionLayout.from_width(windows.motion_dim)
    truth = windows[3]["motion"].numpy().astype(np.float64)
    motion = pinched(pinched(truth, layout, slice(6, 30), 0.9), layout, slice(10, 50), 0.9,
                     COLLARS, None)
    lengths = layout.motion_bone_lengths(truth)
    motion = pinched(motion, layout, slice(3, 45), 0.9, HANDS[0][:2], None)
    skeleton = RigidSkeleton(layout, lengths, pieces={
        piece: piece_directions(layout, truth.mean(axis=0), piece) for piece in (HIPS, COLLARS, *HANDS)})
    at_once = skeleton(motion)
    skeleton.reset()
    blocks = np.concatenate([skeleton(motion[t:t + 4]) for t in range(0, len(motion), 4)])
    np.testing.assert_array_equal(blocks, at_once)
    skeleton.reset()
    np.testing.assert_array_equal(skeleton(motion), at_once)


def test_the_heads_points_move_with_the_head_and_do_not_turn_with_its_bone(windows):
    # The skull's bones turn onto their parent's rotation, not because the pose changed: the
    # face the decoder drew around the head goes where the head goes. Turned with the neck's
    # bone, the demo's head points came 14 cm from the person's head shape, carried 6.1.
    layout, shell, joints = first_frames(windows, 3)
    head, neck = JOINT["head"], JOINT["neck"]
    correction = np.zeros_like(joints)
    bone = joints[:, head] - joints[:, neck]
    sideways = np.cross(bone, [1.0, 0.0, 0.0])
    correction[:, head] = 0.05 * sideways / np.linalg.norm(sideways, axis=-1, keepdims=True)
    carried, turned = ShellFollow(layout, carried=(head,)), ShellFollow(layout)
    moved = carried(shell, joints, correction)
    on_head = np.all(carried.bones[carried.segment] == (head, neck), axis=-1)
    past_head = on_head & (np.einsum("pc,c->p", shell[0] - joints[0, neck], bone[0]) > bone[0] @ bone[0])
    assert past_head.sum() >= 3
    np.testing.assert_allclose(moved[:, past_head],
                               np.repeat(correction[:, head, None], past_head.sum(), 1), atol=1e-12)
    swung = turned(shell, joints, correction)
    assert np.linalg.norm(swung[:, past_head] - moved[:, past_head], axis=-1).max() > 0.02
    np.testing.assert_allclose(moved[:, ~on_head], swung[:, ~on_head], atol=1e-12)


def test_a_planted_foot_stays_put_while_the_decoder_jitters_and_the_leg_keeps_its_bones(windows, skeleton):
    layout = MotionLayout.from_width(windows.motion_dim)
    body = standing(windows[3], layout)
    lengths = bone_lengths(joints_of(body, layout), layout.bones)[0]
    rng = np.random.default_rng(1)
    shifts = np.zeros((len(body), 55, 3))
    for foot in FEET:  # foot and ankle jitter by millimetres, horizontally
        jitter = rng.normal(scale=0.004, size=(len(body), 3)) * [1, 0, 1]
        shifts[:, foot] = shifts[:, foot - 3] = jitter
    decoded = shift_joints(body, layout, shifts)
    assert foot_slide(joints_of(decoded, layout)) > 0.5
    rigid = RigidSkeleton(layout, lengths)(decoded)  # as the decoding chains them
    out = FootLock(layout, lengths, radius=0.05)(rigid)
    after = joints_of(out, layout)
    assert foot_slide(after) == 0.0
    legs = [layout.bones.index((JOINT[child], JOINT[parent])) for parent, child in
            (("left_hip", "left_knee"), ("left_knee", "left_ankle"),
             ("right_hip", "right_knee"), ("right_knee", "right_ankle"))]
    np.testing.assert_allclose(bone_lengths(after, layout.bones)[:, legs],
                               np.broadcast_to(lengths[legs], (len(out), 4)), rtol=1e-9)


@pytest.mark.parametrize("step, lift, swing", [("data", STANCE_LIFT, STANCE_SWING_FRAMES),
                                              ("arc", LIFT, SWING_FRAMES)])
def test_a_gliding_body_steps_and_a_stream_gets_the_frames_at_once_gets(windows, skeleton, step,
                                                                        lift, swing):
    layout = MotionLayout.from_width(windows.motion_dim)
    body = standing(windows[4], layout)
    frames = len(body)
    glide = np.zeros((frames, layout.width // 3, 3))
    glide[:, :, 0] = 0.5 / 30 * np.arange(frames)[:, None]  # 0.5 m/s along x, feet dragged along
    decoded = body + glide.reshape(frames, -1)
    lengths = bone_lengths(joints_of(body, layout), layout.bones)[0]
    lock = FootLock(layout, lengths, radius=0.1, step=step)
    out = lock(decoded)
    feet, dragged = joints_of(out, layout)[:, FEET], joints_of(decoded, layout)[:, FEET]
    assert foot_slide(joints_of(decoded, layout)) == 1.0
    assert foot_slide(joints_of(out, layout)) < 0.15
    speed = np.linalg.norm(np.diff(feet[..., [0, 2]], axis=0), axis=-1) * 30
    assert np.mean(speed < 1e-6) > 0.4  # planted (or lifted and set down) half of the time...
    moving = speed > 1e-6
    assert np.all(np.sum(moving[1:] & ~moving[:-1], axis=0) >= 2)  # ...and walking: steps
    assert np.all((feet[..., 1] - dragged[..., 1]).max(axis=0) > 0.9 * lift)  # lifted to step
    assert np.all(np.abs(feet[..., 0] - dragged[..., 0]) < 0.1 + 0.5 / 30 * 3 * swing)
    lock.reset()
    blocks = np.concatenate([lock(decoded[i:i + 4]) for i in range(0, frames, 4)])
    np.testing.assert_array_equal(blocks, out)


def test_the_steps_take_the_configured_frames(windows, skeleton):
    """vae.foot_swing_frames reaches the lock: a gliding body's arc steps (vae.foot_step), from
    lift-off to landing, take that many frames; the data's steps take the data's."""
    from sarah_models.sampling.decoding import stream_decoding
    from sarah_models.testing import random_models

    layout = MotionLayout.from_width(windows.motion_dim)
    body = standing(windows[4], layout)
    glide = np.zeros((len(body), layout.width // 3, 3))
    glide[:, :, 0] = 0.5 / 30 * np.arange(len(body))[:, None]
    decoded = body + glide.reshape(len(body), -1)
    lengths = bone_lengths(joints_of(body, layout), layout.bones)[0]
    vae, _, normalizer = random_models("tiny")
    normalizer.set("bone_length", lengths, np.zeros_like(lengths))
    for step, frames in (("arc", 6), ("arc", SWING_FRAMES), ("data", STANCE_SWING_FRAMES)):
        vae.config = dataclasses.replace(vae.config, foot_lock=0.1, foot_swing_frames=6,
                                         foot_step=step)
        if step == "arc":
            vae.config = dataclasses.replace(vae.config, foot_swing_frames=frames)
        lock = stream_decoding(vae, normalizer).filters[-1]
        assert isinstance(lock, FootLock) and lock.step == step
        feet = joints_of(lock(decoded), layout)[:, FEET]
        lifted = (feet[..., 1] - joints_of(decoded, layout)[:, FEET, 1] > 1e-6)[:, 0]
        edges = np.flatnonzero(np.diff(lifted.astype(int)))  # the frames before each change
        runs = np.diff(edges)[::2] if lifted[edges[0] + 1] else np.diff(edges)[1::2]
        # in the air between lift and landing (an arc sets the foot down in its last frame)
        assert len(runs) >= 2 and np.all(runs == (frames - 1 if step == "arc" else frames))
    with pytest.raises(ValueError, match="foot_swing_frames must be >= 4"):
        dataclasses.replace(vae.config, foot_swing_frames=3)
    with pytest.raises(ValueError, match="foot_step must be one of"):
        dataclasses.replace(vae.config, foot_step="hop")


def test_a_step_rises_as_high_as_the_datas_steps(prepared_shards):
    """The foot lock's swing rises as the ground truth's steps do (7.8 cm on the fixtures); the
    10 cm it rose before was higher than any fixture step, and its vertical acceleration
    showed in FGD_acc (docs/results.md, twenty-third run)."""
    from sarah_models.evaluation.metrics import foot_steps

    long_windows = WindowDataset(prepared_shards, "train", extractor="logmel", window=300, seed=0,
                                 length=8)
    layout = MotionLayout.from_width(long_windows.motion_dim)
    rises = []
    for i in range(len(long_windows)):
        feet = joints_of(long_windows[i]["motion"].numpy(), layout)[:, FEET]
        for side, steps in enumerate(foot_steps(feet)):
            rises += [feet[a:b + 1, side, 1].max() - feet[max(a - 1, 0), side, 1] for a, b in steps]
    assert len(rises) >= 10
    assert abs(np.median(rises) - LIFT) < 0.01


def test_real_steps_pass_the_lock_as_they_came(prepared_shards, skeleton):
    """Real feet lift before they travel, so the lock lets them step on their own: fixture
    motion with its steps comes out of the rigid skeleton and the lock with every foot within a
    centimetre of where it went in (the fixtures' feet slide ~1.5 cm on the floor in the two
    frames before they lift, which the lock holds and then fades out). The lock used to start its own arc 10 cm into each real
    step, and the rigid skeleton and lock put the ground truth's FGD_acc at 3,827 (docs/results.md, fortieth run)."""
    from sarah_models.evaluation.metrics import foot_steps

    long_windows = WindowDataset(prepared_shards, "train", extractor="logmel", window=300, seed=0,
                                 length=8)
    layout = MotionLayout.from_width(long_windows.motion_dim)
    steps = 0
    for i in range(len(long_windows)):
        real = long_windows[i]["motion"].numpy().astype(np.float64)
        rigid = RigidSkeleton(layout, skeleton)(real)
        feet = joints_of(rigid, layout)[:, FEET]
        steps += sum(len(s) for s in foot_steps(feet))
        locked = joints_of(FootLock(layout, skeleton, radius=0.1)(rigid), layout)[:, FEET]
        assert np.abs(locked - feet).max() < 0.01
    assert steps >= 10  # the windows walk: the property is about steps, not standing


def test_a_foot_the_decoder_lifts_steps_where_the_decoder_takes_it(windows, skeleton):
    """A planted foot lifted past RELEASE follows the decoder, its planted offset fading out, and
    is planted again where it comes down."""
    layout = MotionLayout.from_width(windows.motion_dim)
    body = next(b for b in (standing(windows[i], layout) for i in range(len(windows)))
                if joints_of(b, layout)[0, FEET, 1].max() < 0.05)  # both feet on the floor
    frames = len(body)
    lengths = bone_lengths(joints_of(body, layout), layout.bones)[0]
    shifts = np.zeros((frames, 55, 3))
    t = np.arange(frames)
    # frames 0-9 planted with 3 mm of glide, 10-19 a step 6 cm high and 30 cm long that lifts
    # before it travels, as people step, then planted
    up = (t >= 10) & (t < 20)
    glide = np.where(t < 10, 0.0003 * t, 0.0)
    travel = np.clip((t - 12) / 6, 0, 1) * 0.3
    for j in (FEET[0], FEET[0] - 3):
        shifts[:, j, 0] = glide + travel
        shifts[:, j, 1] = np.where(up, 0.06 * np.sin(np.pi * (t - 10) / 10), 0.0)
    decoded = shift_joints(body, layout, shifts)
    before = joints_of(decoded, layout)[:, FEET[0]]
    after = joints_of(FootLock(layout, lengths, radius=0.1)(decoded), layout)[:, FEET[0]]
    assert np.abs(after[:10, [0, 2]] - before[0, [0, 2]]).max() < 1e-9  # planted: the glide is gone
    lifted = np.flatnonzero(before[:, 1] > before[0, 1] + RELEASE)
    # released: the decoded foot plus an offset that fades (here 2.7 mm), then the decoder's own
    assert np.abs(after[lifted] - before[lifted]).max() < 0.003
    np.testing.assert_allclose(after[lifted[-1]], before[lifted[-1]], atol=1e-9)  # faded out
    assert np.ptp(after[21:], axis=0).max() < 1e-9  # planted where it came down...
    # ...as far as the leg reaches (this decoder moved the foot and ankle only, 30 cm)
    assert after[-1, 0] - after[0, 0] > 0.25


def test_a_body_the_decoder_sank_into_the_floor_stands_and_steps_on_it(windows, skeleton):
    """Decoded feet sink under the floor, most before they step; a swing lifted from there
    travelled under the foot slide's 5 cm (docs/results.md, twenty-second run)."""
    layout = MotionLayout.from_width(windows.motion_dim)
    body = next(b for b in (standing(windows[i], layout) for i in range(len(windows)))
                if joints_of(b, layout)[0, FEET, 1].max() < 0.05)  # both feet on the floor
    frames = len(body)
    shifts = np.zeros((frames, 55, 3))
    shifts[:, :, 0] = 0.5 / 30 * np.arange(frames)[:, None]  # gliding at 0.5 m/s: it must step
    shifts[:, :, 1] = -0.05  # 5 cm low: the foot joints ~2 cm under the floor
    decoded = shift_joints(body, layout, shifts)
    assert joints_of(decoded, layout)[:, FEET, 1].max() < FLOOR_HEIGHT
    lengths = bone_lengths(joints_of(body, layout), layout.bones)[0]
    for step, lift in (("data", STANCE_LIFT), ("arc", LIFT)):
        feet = joints_of(FootLock(layout, lengths, radius=0.1, step=step)(decoded), layout)[:, FEET]
        assert feet[..., 1].min() >= FLOOR_HEIGHT - 1e-9  # standing on the floor, not in it
        # every foot swings its full height above the floor
        np.testing.assert_allclose(feet[..., 1].max(axis=0), FLOOR_HEIGHT + lift, atol=1e-9)


def test_a_raised_foot_is_left_to_the_decoder(windows, skeleton):
    layout = MotionLayout.from_width(windows.motion_dim)
    body = standing(windows[5], layout)
    shifts = np.zeros((len(body), 55, 3))
    shifts[:, FEET[0], 1] = shifts[:, FEET[0] - 3, 1] = FREE_HEIGHT + 0.1
    shifts[:, FEET[0], 0] = np.linspace(0, 0.3, len(body))  # swinging a raised leg
    raised = shift_joints(body, layout, shifts)
    out = FootLock(layout, bone_lengths(joints_of(body, layout), layout.bones)[0], 0.05)(raised)
    np.testing.assert_allclose(joints_of(out, layout)[:, FEET[0]],
                               joints_of(raised, layout)[:, FEET[0]], atol=1e-12)


def test_an_agents_own_skeleton_takes_the_bones_and_its_legs_set_the_bodys_height(windows, skeleton):
    # The motion of one fixture person decoded on another's skeleton: every bone at the agent's
    # length, the body lower by as much as its thighs and shins are shorter than the skeleton the
    # decoder made the motion for, so its knees bend as they did over the same ankles.
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[1]["motion"].numpy().astype(np.float64)
    made_for = layout.motion_bone_lengths(motion)
    np.testing.assert_allclose(made_for, bone_lengths(joints_of(motion, layout)[0], layout.bones),
                               atol=1e-5)
    agent = made_for * 0.94  # a person 6 % smaller in every bone
    out = RigidSkeleton(layout, agent, reference=made_for)(motion)
    before, after = joints_of(motion, layout), joints_of(out, layout)
    np.testing.assert_allclose(bone_lengths(after, layout.bones),
                               np.broadcast_to(agent, (len(out), 54)), rtol=1e-9)
    legs = [[layout.bones.index(bone) for bone in (
        (JOINT[f"{side}_hip"], JOINT["pelvis"]), (JOINT[f"{side}_knee"], JOINT[f"{side}_hip"]),
        (JOINT[f"{side}_ankle"], JOINT[f"{side}_knee"]))] for side in ("left", "right")]
    shorter = np.mean([0.06 * made_for[leg].sum() for leg in legs])
    from sarah_models.sampling.rigid_skeleton import leg_height_change

    assert leg_height_change(layout, agent, made_for) == pytest.approx(-shorter)
    np.testing.assert_allclose(after[:, 0] - before[:, 0], [[0.0, -shorter, 0.0]] * len(out), atol=1e-12)
    # Its ankles stand where the decoder's did, at the knee angles the data's own legs had.
    ankles = [JOINT["left_ankle"], JOINT["right_ankle"]]
    reached = np.linalg.norm(after[:, ankles] - before[:, ankles], axis=-1) < 1e-9
    assert reached.mean() > 0.9

    def knee_angle(j, side):
        hip, knee, ankle = (j[:, JOINT[f"{side}_{n}"]] for n in ("hip", "knee", "ankle"))
        a, b = hip - knee, ankle - knee
        return np.degrees(np.arccos(np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)))

    for k, side in enumerate(("left", "right")):
        both = reached[:, k]
        assert np.abs(knee_angle(after, side) - knee_angle(before, side))[both].mean() < 5.0
    # Left at the decoded height, the smaller body's nearly straight legs fall short of them.
    unlowered = joints_of(RigidSkeleton(layout, agent)(motion), layout)
    assert (np.linalg.norm(unlowered[:, ankles] - before[:, ankles], axis=-1) > 0.01).mean() > 0.5
    # The skeleton it was made for changes nothing; its own lengths given as the agent's neither.
    np.testing.assert_allclose(RigidSkeleton(layout, made_for, reference=made_for)(motion),
                               RigidSkeleton(layout, made_for)(motion), atol=0)
    with pytest.raises(ValueError, match="53 reference bone lengths"):
        RigidSkeleton(layout, agent, reference=made_for[:53])


def test_a_stream_decodes_on_the_agents_skeleton_when_given_one(windows, skeleton):
    from sarah_models.sampling.decoding import stream_decoding, takes_bone_lengths
    from sarah_models.sampling.foot_lock import FootLock
    from sarah_models.testing import random_models

    vae, _, normalizer = random_models("tiny")
    normalizer.set("bone_length", skeleton, np.zeros(54))
    vae.config = dataclasses.replace(vae.config, rigid_bones=True, foot_lock=0.1)
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[1]["motion"].numpy().astype(np.float64)
    agent = layout.motion_bone_lengths(motion) * 1.05
    assert takes_bone_lengths(vae)
    decoding = stream_decoding(vae, normalizer, agent)
    rigid, lock = decoding.filters[1], decoding.filters[2]
    assert isinstance(lock, FootLock)
    np.testing.assert_array_equal(rigid.lengths, agent)  # the lock's legs are the agent's too
    thigh = layout.bones.index((JOINT["left_knee"], JOINT["left_hip"]))
    assert lock.legs[0][4] == agent[thigh]
    out = decoding(motion)
    np.testing.assert_allclose(bone_lengths(joints_of(out, layout), layout.bones)[:, thigh], agent[thigh])
    # Block by block as a stream decodes, the same frames.
    again = stream_decoding(vae, normalizer, agent)
    np.testing.assert_allclose(np.concatenate([again(motion[i:i + 4]) for i in range(0, 60, 4)]), out,
                               atol=1e-12)
    with pytest.raises(ValueError, match="10 the agent's bone lengths for a layout of 54"):
        stream_decoding(vae, normalizer, agent[:10])
    # A decoding that keeps no lengths puts nothing on the agent's bones, and says so.
    vae.config = dataclasses.replace(vae.config, rigid_bones=False, foot_lock=0.0)
    assert not takes_bone_lengths(vae)


def test_the_decoding_needs_a_skeleton_and_says_where_to_get_one():
    from sarah_models.sampling.decoding import stream_decoding
    from sarah_models.testing import random_models

    vae, _, normalizer = random_models("tiny")
    vae.config = dataclasses.replace(vae.config, rigid_bones=True)
    with pytest.raises(ValueError, match="--stage model --init-from MODEL --shards SHARDS"):
        stream_decoding(vae, normalizer)
    normalizer.set("bone_length", np.full(54, 0.1), np.zeros(54))
    decoding = stream_decoding(vae, normalizer)
    assert [type(f).__name__ for f in decoding.filters] == ["SeamInertia", "RigidSkeleton"]


def whole_body_moved(motion: np.ndarray, path: np.ndarray) -> np.ndarray:
    """``motion`` with every point moved on the floor by ``path`` (T, 2) in x and z."""
    points = motion.reshape(len(motion), -1, 3).copy()
    points[..., 0] += path[:, None, 0]
    points[..., 2] += path[:, None, 1]
    return points.reshape(motion.shape)


def test_a_wandering_body_holds_its_place_and_a_walking_one_follows_smoothly(windows):
    from sarah_data.skeleton import ROOT
    from sarah_models.sampling.root_hold import FOLLOW, RootHold

    layout = MotionLayout.from_width(windows.motion_dim)
    body = standing(windows[0], layout)
    root = lambda m: layout.joint_positions(m, [ROOT])[:, 0]  # noqa: E731
    t = np.arange(len(body))
    # wandering up to 4.2 cm away (the decoder's wander): the body stands where it started
    wander = np.stack([0.03 * np.sin(t / 3.0), 0.015 * (np.cos(t / 5.0) - 1.0)], axis=-1)
    # (the window's pelvis is at the origin to float32 rounding; the held body exactly)
    out = RootHold(layout, radius=0.05)(whole_body_moved(body, wander))
    np.testing.assert_allclose(root(out), root(body), atol=1e-6)
    np.testing.assert_allclose(out, body, atol=1e-6)  # pose and heights as decoded
    # walking at 1 m/s from frame 10 after standing: it follows at a bounded lag, without a jump
    speed, radius = 1.0 / 30, 0.05
    walk = np.stack([np.clip(t - 10, 0, None) * speed, np.zeros(len(t))], axis=-1)
    walking = whole_body_moved(body, walk)
    out = RootHold(layout, radius=radius)(walking)
    lag = np.linalg.norm((root(walking) - root(out))[:, [0, 2]], axis=-1)
    steady = radius + speed * (1 - FOLLOW) / FOLLOW
    assert lag.max() <= steady + 1e-9
    assert abs(lag[-1] - steady) < 0.002  # walking on at the decoded pace
    velocity = np.diff(root(out)[:, 0])
    assert np.abs(np.diff(velocity)).max() < 0.25 * speed  # it starts walking smoothly
    np.testing.assert_allclose(out[:, 1::3], walking[:, 1::3])  # every height as decoded
    # causal: a stream fed in chunks gets the frames it gets at once
    hold = RootHold(layout, radius=radius)
    chunks = np.concatenate([hold(walking[i:i + 4]) for i in range(0, len(walking), 4)])
    np.testing.assert_array_equal(chunks, out)
    # decoded 12 cm off the origin from its first frame: the body starts at the origin, where
    # the generation frame puts the agent, and stands there
    offset = np.tile([0.12, -0.0], (len(t), 1)) + wander
    out = RootHold(layout, radius=0.2)(whole_body_moved(body, offset))
    np.testing.assert_allclose(root(out), root(body), atol=1e-6)
    assert np.abs(root(out)[:, [0, 2]]).max() < 1e-12
    with pytest.raises(ValueError, match="radius"):
        RootHold(layout, radius=0.0)


def test_a_body_the_decoder_throws_across_the_room_walks_there_no_faster_than_the_data(windows):
    """The decoded pelvis runs at up to 7 m/s streamed and 15 offline; nobody in the data walks
    faster than 2 (docs/results.md, twenty-sixth run)."""
    from sarah_data.constants import FPS
    from sarah_data.skeleton import ROOT
    from sarah_models.sampling.root_hold import MAX_SPEED, RootHold

    layout = MotionLayout.from_width(windows.motion_dim)
    body = standing(windows[0], layout)
    t = np.arange(len(body))
    thrown = np.stack([np.where(t >= 5, 1.5, 0.0), np.zeros(len(t))], axis=-1)  # 1.5 m in a frame
    out = RootHold(layout, radius=0.1)(whole_body_moved(body, thrown))
    pelvis = layout.joint_positions(out, [ROOT])[:, 0, [0, 2]]
    speed = np.linalg.norm(np.diff(pelvis, axis=0), axis=-1) * FPS
    np.testing.assert_allclose(speed.max(), MAX_SPEED)  # it walks, at the data's fastest...
    assert abs(pelvis[-1, 0] - 1.4) < 1e-3  # ...and arrives where the hold puts it
    with pytest.raises(ValueError, match="max_speed"):
        RootHold(layout, radius=0.1, max_speed=0.0)


def test_a_hold_reading_the_feet_holds_a_gliding_body_and_lets_a_stepping_one_walk(windows):
    """A walking person moves over a standing foot; a wandering decoder glides the whole body,
    feet too. Read on the pelvis, the hold delays both (sampling.root_hold)."""
    from sarah_data.skeleton import ROOT
    from sarah_models.sampling.root_hold import RootHold

    layout = MotionLayout.from_width(windows.motion_dim)
    floor = lambda m: layout.joint_positions(m, [ROOT])[:, 0, [0, 2]]  # noqa: E731
    t = np.arange(len(windows[0]["motion"]))
    wander = np.stack([0.03 * np.sin(t / 3.0), 0.015 * (np.cos(t / 5.0) - 1.0)], axis=-1)
    # a body standing still, glided about within the radius: it stands where it started
    body = standing(windows[0], layout)
    out = RootHold(layout, radius=0.05, reads="feet")(whole_body_moved(body, wander))
    np.testing.assert_allclose(out, body, atol=1e-6)
    # the fixtures' people walk on planted feet: read on the feet, the hold leaves them walking
    # where they walk, and holds what a decoder's wander adds to them; read on the pelvis, it
    # holds their first steps back
    travel = [np.linalg.norm(np.diff(floor(w["motion"].numpy()), axis=0), axis=-1).sum()
              for w in (windows[i] for i in range(len(windows)))]
    walker = windows[int(np.argmax(travel))]["motion"].numpy().astype(np.float64)
    assert max(travel) > 0.3  # a window in which the agent walks
    lag = lambda out: np.abs(floor(out) - floor(walker)).max()  # noqa: E731
    assert lag(RootHold(layout, radius=0.2, reads="pelvis")(walker)) > 0.2
    assert lag(RootHold(layout, radius=0.2, reads="feet")(walker)) < 0.02
    wandering = whole_body_moved(walker, wander)
    assert np.abs(floor(wandering) - floor(walker)).max() > 0.025
    held = RootHold(layout, radius=0.2, reads="feet")(wandering)
    assert lag(held) < 0.02
    np.testing.assert_allclose(held[:, 1::3], walker[:, 1::3])  # every height as decoded
    # causal: a stream fed in chunks gets the frames it gets at once
    hold = RootHold(layout, radius=0.2, reads="feet")
    chunks = np.concatenate([hold(wandering[i:i + 4]) for i in range(0, len(t), 4)])
    np.testing.assert_array_equal(chunks, held)
    with pytest.raises(ValueError, match="reads"):
        RootHold(layout, radius=0.2, reads="hands")


def test_a_held_body_turns_to_face_its_user_as_the_decoded_body_does(windows):
    """Held back from where the decoder walked it, the body faces its user from another place;
    with ``turn`` it turns about its pelvis by the change in bearing, at a bounded rate, causal
    as the hold is (sampling.root_hold)."""
    from sarah_data import icosahedron
    from sarah_data.constants import FPS
    from sarah_data.skeleton import ROOT
    from sarah_models.evaluation.metrics.head_angle import head_angle
    from sarah_models.sampling.root_hold import TURN_RATE, RootHold

    layout = MotionLayout.from_width(windows.motion_dim)
    body = standing(windows[0], layout)
    t = np.arange(len(body))
    floor = lambda m: layout.joint_positions(m, [ROOT])[:, 0, [0, 2]]  # noqa: E731
    head = JOINT["head"]

    def gaze(motion, user):  # the head's gaze score toward the user, frame by frame
        positions, rotations = icosahedron.decode(layout.split(motion)[0])
        return np.array([head_angle(positions[i:i + 1, head], rotations[i:i + 1, head], user[i:i + 1])
                         for i in range(len(motion))])

    # decoded walking sideways at 0.75 m/s away from a user 2 m off to its side, held with a 0.5 m
    # radius
    walk = np.stack([np.minimum(t, 40) * 0.025, np.zeros(len(t))], axis=-1)
    walking = whole_body_moved(body, walk)
    user = np.tile(floor(body)[:1] + [-1.5, 1.3], (len(t), 1))
    held = RootHold(layout, radius=0.5)(walking)
    out = RootHold(layout, radius=0.5, turn=1.0)(walking, None, user)
    np.testing.assert_allclose(floor(out), floor(held), atol=1e-9)  # it stands where it is held
    np.testing.assert_allclose(out[:, 1::3], walking[:, 1::3])  # every height as decoded
    settled = slice(-8, None)
    assert np.abs(gaze(held, user)[settled] - gaze(walking, user)[settled]).max() > 0.02
    np.testing.assert_allclose(gaze(out, user)[settled], gaze(walking, user)[settled], atol=0.002)
    # half the turn: half way
    half = RootHold(layout, radius=0.5, turn=0.5)(walking, None, user)
    assert (np.abs(gaze(half, user) - gaze(walking, user))[settled]
            < np.abs(gaze(held, user) - gaze(walking, user))[settled]).all()
    # a user who walks right past it: the bearing swings by half a turn, the body turns no faster
    # than TURN_RATE
    passing = np.stack([np.linspace(-3.0, 3.0, len(t)), np.full(len(t), 0.3)], axis=-1)
    out = RootHold(layout, radius=0.5, turn=1.0)(walking, None, passing)
    point = layout.joint_positions(out, ["left_wrist"])[:, 0, [0, 2]] - floor(out)
    yaw = np.unwrap(np.arctan2(point[:, 1], point[:, 0]))
    assert np.abs(np.diff(yaw)).max() <= TURN_RATE / FPS + 1e-9
    # causal: a stream fed in chunks gets the frames it gets at once
    hold = RootHold(layout, radius=0.5, turn=1.0)
    chunks = np.concatenate([hold(walking[i:i + 4], None, passing[i:i + 4])
                             for i in range(0, len(t), 4)])
    np.testing.assert_array_equal(chunks, out)
    with pytest.raises(ValueError, match="user's floor path"):
        RootHold(layout, radius=0.5, turn=1.0)(walking)
    with pytest.raises(ValueError, match="turn"):
        RootHold(layout, radius=0.5, turn=1.5)


def test_a_turn_without_a_hold_or_past_a_whole_one_is_refused():
    from sarah_models.config import VAEConfig

    with pytest.raises(ValueError, match="vae.root_hold is 0"):
        VAEConfig(root_hold_turn=0.5)
    with pytest.raises(ValueError, match=r"root_hold_turn must be in \[0, 1\]"):
        VAEConfig(root_hold=0.5, root_hold_turn=1.5)
    assert VAEConfig(root_hold=0.5, root_hold_turn=1.0).root_hold_turn == 1.0


def test_a_soft_reach_eases_toward_the_full_length_and_never_gets_there():
    from sarah_data.two_bone_ik import soft_reach

    distance = np.linspace(0.0, 1.2, 1201)[:, None]
    np.testing.assert_array_equal(soft_reach(distance, 0.8, 0.0), distance)
    eased = soft_reach(distance, 0.8, 0.02)
    short = distance[:, 0] <= 0.78
    np.testing.assert_array_equal(eased[short], distance[short])  # all the way until 2 cm short
    assert np.all(np.diff(eased[:, 0]) > 0) and np.all(eased < 0.8)  # further, never straight
    assert eased[-1, 0] == pytest.approx(0.8, abs=1e-6)
    slopes = np.diff(eased[:, 0]) / np.diff(distance[:, 0])
    assert np.abs(np.diff(slopes)).max() < 0.05  # no kink where the easing begins
    assert soft_reach(np.array([0.8]), 0.8, 0.02)[0] == pytest.approx(0.8 - 0.02 / np.e)


def test_a_soft_leg_bends_its_knee_where_a_stiff_one_locks_straight():
    from sarah_data.two_bone_ik import two_bone_ik

    hip = np.zeros((3, 3))
    knee = np.array([[0.0, -0.4, 0.1]] * 3)
    ankle = np.array([[0.0, -0.78, 0.0], [0.0, -0.8, 0.0], [0.0, -0.805, 0.0]])  # short, at, past
    stiff_knee, stiff_end = two_bone_ik(hip, knee, ankle, 0.4, 0.4)
    soft_knee, soft_end = two_bone_ik(hip, knee, ankle, 0.4, 0.4, softness=0.01)
    np.testing.assert_allclose(soft_end[0], ankle[0], atol=1e-12)  # within reach: reached
    np.testing.assert_allclose(np.linalg.norm(stiff_end[1:], axis=-1), 0.8, rtol=1e-5)
    reach = np.linalg.norm(soft_end[1:], axis=-1)
    assert np.all(reach < 0.8 - 0.002) and reach[0] < reach[1]
    np.testing.assert_allclose(np.linalg.norm(soft_knee, axis=-1), 0.4, atol=1e-12)  # bones kept
    np.testing.assert_allclose(np.linalg.norm(soft_end - soft_knee, axis=-1), 0.4, atol=1e-12)
    assert np.all(np.abs(soft_knee[1:, 2]) > 0.02) and np.all(np.abs(stiff_knee[1:, 2]) < 0.002)


def knee_angles(joints: np.ndarray) -> np.ndarray:
    """(T, J, 3) -> (T, 2) the left and right knees' angles, degrees (180: straight)."""
    out = []
    for side in ("left", "right"):
        hip, knee, ankle = (joints[:, JOINT[f"{side}_{n}"]] for n in ("hip", "knee", "ankle"))
        a, b = hip - knee, ankle - knee
        out.append(np.degrees(np.arccos(np.clip(np.sum(a * b, -1) / np.linalg.norm(a, axis=-1)
                                                / np.linalg.norm(b, axis=-1), -1, 1))))
    return np.stack(out, axis=1)


def test_a_body_raised_on_its_legs_keeps_its_feet_and_straightens_its_knees(windows):
    layout = MotionLayout.from_width(windows.motion_dim)
    motion = windows[1]["motion"].numpy().astype(np.float64)
    # thighs and shins 4 % longer than the motion's: over its ankles they bend, as the decoder's do
    lengths = layout.motion_bone_lengths(motion)
    for side in ("left", "right"):
        for child, parent in (("knee", "hip"), ("ankle", "knee")):
            lengths[layout.bones.index((JOINT[f"{side}_{child}"], JOINT[f"{side}_{parent}"]))] *= 1.04
    base = joints_of(RigidSkeleton(layout, lengths)(motion), layout)
    raised = joints_of(RigidSkeleton(layout, lengths, lift=0.01)(motion), layout)
    legs = [JOINT[f"{side}_{n}"] for side in ("left", "right") for n in ("knee", "ankle", "foot")]
    body = [j for j in range(base.shape[1]) if j not in legs]
    np.testing.assert_allclose(raised[:, body] - base[:, body],
                               np.broadcast_to([0.0, 0.01, 0.0], (len(base), len(body), 3)), atol=1e-12)
    np.testing.assert_allclose(bone_lengths(raised, layout.bones), bone_lengths(base, layout.bones),
                               atol=1e-9)
    ankles = [JOINT["left_ankle"], JOINT["right_ankle"]]
    reached = np.all(np.linalg.norm(raised[:, ankles] - base[:, ankles], axis=-1) < 1e-9, axis=1)
    assert reached.mean() > 0.9  # the feet where the decoder put them, as far as the legs reach
    np.testing.assert_allclose(raised[reached][:, [JOINT["left_foot"], JOINT["right_foot"]]],
                               base[reached][:, [JOINT["left_foot"], JOINT["right_foot"]]], atol=1e-9)
    straighter = knee_angles(raised)[reached] - knee_angles(base)[reached]
    assert np.all(straighter > 0) and straighter.mean() > 1.0
    # with an agent's skeleton the lift comes on top of the legs' own height change
    assert RigidSkeleton(layout, lengths * 0.94, reference=lengths, lift=0.01).lift == pytest.approx(
        RigidSkeleton(layout, lengths * 0.94, reference=lengths).lift + 0.01)


def test_the_lift_and_the_legs_softness_reach_the_chain_and_are_checked():
    from sarah_models.config import VAEConfig, decoding_settings
    from sarah_models.sampling.decoding import stream_decoding
    from sarah_models.testing import random_models

    assert {"vae.stand_lift", "vae.leg_softness"} <= set(decoding_settings())
    vae, _, normalizer = random_models("tiny")
    normalizer.set("bone_length", np.full(54, 0.1), np.zeros(54))
    vae.config = dataclasses.replace(vae.config, rigid_bones=True, foot_lock=0.1, stand_lift=0.007,
                                     leg_softness=0.01)
    _, rigid, lock = stream_decoding(vae, normalizer).filters
    assert (rigid.lift, rigid.softness, lock.softness) == (0.007, 0.01, 0.01)
    with pytest.raises(ValueError, match="leg_softness"):
        VAEConfig(leg_softness=-0.01)
    with pytest.raises(ValueError, match="stand_lift raises the body on the rigid skeleton"):
        VAEConfig(stand_lift=0.01)
    with pytest.raises(ValueError, match="stand_lift"):
        VAEConfig(rigid_bones=True, stand_lift=float("nan"))
    with pytest.raises(ValueError, match="leg softness"):
        FootLock(MotionLayout.from_width(vae.motion_dim), np.full(54, 0.1), 0.1, softness=-1.0)
