"""Rigid bones: decoded joints put back on a skeleton whose bones keep their length.

The decoder emits every joint's icosahedron on its own, so nothing holds a bone to one length:
on the fixture benchmark the shipped model's streamed bones stretched and shrank by 30 % (p95
over frames and body bones; its VAE reconstructing the ground truth: 25 %), led by the head,
the wrists, the feet and the hips, and a limb that changes length is the first thing a viewer
sees (docs/results.md, seventeenth run). ``RigidSkeleton`` keeps what the decoder says about
the pose, each bone's direction, and takes each bone's length from the training data's skeleton
(``stats.h5``'s ``bone_length``): walking the skeleton from the root, every joint is placed at
its parent's corrected position plus the bone's length along its decoded direction, and its
icosahedron moves with it (its rotation is the decoder's). Given an agent's own bone lengths
(an avatar's, a captured person's: ``sampling.decoding.stream_decoding``'s ``bone_lengths``), the
bones take those, and the body is lowered (or raised) by how much shorter (or longer) the agent's
legs are than the training data's (``leg_height_change``), so that its knees bend as the decoded
ones do over feet where the decoder put them. The legs are the exception: their
ankles stay where the decoder put them, as far as the legs reach (two-bone inverse kinematics
on the hips, bending the way the decoded knees bend), and the foot joints at the decoded
feet's height (``foot_at_its_height``), so that feet stay on the floor. The skull is the
other (``SKULL``, given the training data's mean motion): the head, the jaw and the eyes sit
3-12 cm from their parents, too near for the decoder's points to say which way, and decoded
they lay 65-90 degrees around the head from where their parent's decoded rotation puts them
(the demo's clip; the fingers 10-30, the limbs 6-13), so they are placed as a body places
them: at their bone's length along the direction that rotation carries the bone to
(``skull_directions``; docs/results.md, ninety-ninth run). The hips are the third (``HIPS``,
given ``piece_directions``): each sits 10 cm from the pelvis, and decoded each on its own the two
came within centimetres of each other and the knees crossed, so the pelvis is placed as one
piece (``piece_frames``) and each leg moves with its hip; the collars likewise with the chest
(``COLLARS``: decoded, they folded as the hips did, and the shoulders with them), and each
hand's five knuckles with its wrist (``HANDS``: decoded, the palm narrowed and widened); each
arm moves with its collar and each finger with its knuckle, as every child moves with its
parent. Past the knuckles the fingers keep their decoded directions, and the knuckles are
turned by the piece their decoded bones span, not by the wrist's decoded rotation: against the
ground truth (the VAE's reconstructions) the wrist's rotation would put them further from the
data's, where the skull so placed and the pieces come nearer (docs/models.md has the figures).
Shell
points ride their bones (``ShellFollow``): each is carried and turned with the body bone
nearest it in the stream's first frame, as a skinned mesh's vertices are.

Causal: a stream decoded block by block and the same frames at once agree exactly.
"""

from __future__ import annotations

import numpy as np

from sarah_data.bone_turns import shortest_rotation, unit
from sarah_data.constants import BODY_JOINTS, JOINT_NAMES
from sarah_data.icosahedron import DEFAULT_RADIUS, axis, decode
from sarah_data.skeleton import ROOT, MotionLayout
from sarah_data.two_bone_ik import two_bone_ik

LEGS = (("left_hip", "left_knee", "left_ankle", "left_foot"),
        ("right_hip", "right_knee", "right_ankle", "right_foot"))
# Joints placed along their bone's direction in their parent's rotation rather than along the
# decoded one: the head on the neck, the jaw and the eyes on the head (module docstring).
SKULL = ("head", "jaw", "left_eye_smplhf", "right_eye_smplhf")
# Pieces: bones of one parent placed with it as one rigid piece (``piece_frames``), the first two
# spanning its frame: the pelvis's two hip bones, the chest's two collar bones, and each hand's
# five knuckle bones (its index and its little finger across the palm).
HIPS = ("left_hip", "right_hip")
COLLARS = ("left_collar", "right_collar")
HANDS = tuple(tuple(f"{side}_{finger}1" for finger in ("index", "pinky", "middle", "ring", "thumb"))
              for side in ("left", "right"))
# How far a piece's sideways axis leans on the last frame's, in its pair's widths against the
# decoded pair's line: where the decoded hips come together their line points anywhere, and a
# pelvis turned by it alone swung the legs about; leaning more, it lags a turn (docs/models.md).
LINE_MEMORY = 0.5


def _mean_rotation(icosahedra: np.ndarray, joint: int) -> np.ndarray | None:
    """The mean over the frames of ``joint``'s rotation, from a mean motion's icosahedra (its
    axes are linear in the vertices: ``icosahedron.axis``); None where it holds no rotation to
    solve with: a mean of no body (a normalizer fitted to no motion: zeros). The fixtures' neck
    and head: |det| 0.11-0.17, the turns about the vertical averaging out, condition number 2-3;
    the pelvis: 0.10 and 3.2."""
    rotation = np.stack([axis(icosahedra[joint], c) for c in range(3)], axis=-1) / DEFAULT_RADIUS
    return None if abs(np.linalg.det(rotation)) < 1e-3 else rotation


def _mean_bones(icosahedra: np.ndarray, parent: int, children: list[int],
                origin: np.ndarray) -> np.ndarray | None:
    """(len(children), 3) unit directions of ``children``'s mean bones from ``origin`` (the
    parent's mean point) in ``parent``'s frame, solved against its mean rotation
    (``skull_directions`` says why that is exact); None where the mean holds no rotation."""
    rotation = _mean_rotation(icosahedra, parent)
    if rotation is None:
        return None
    bones = np.linalg.solve(rotation, (icosahedra[children].mean(axis=-2) - origin).T).T
    return bones / np.linalg.norm(bones, axis=-1, keepdims=True)


def skull_directions(layout: MotionLayout, mean_motion) -> dict[int, np.ndarray]:
    """The training data's bone directions of the skull in their parents' frames, from its mean
    motion vector (the normalizer's ``motion`` mean): ``{child joint: (3,) unit vector}`` for
    each of ``SKULL`` whose parent is in ``layout``.

    A joint's icosahedron axes are linear in its vertices (``icosahedron.axis``), so the mean
    vertices give M, the mean of the parent's rotation over the frames, and the mean bone is M
    times the bone in the parent's frame: solved for it, exact for a rigid body whatever poses
    the frames hold (the fixtures' training persons' mean rest skeleton within 1.3 mm, the head's
    bone within 0.1 mm: the statistics weigh persons by their frames; ninety-ninth
    run). The skull's parents are not the root, so a root-relative mean (``Normalizer
    .set_root_relative``: every other point less the root's floor place) gives the same bones."""
    mean = np.asarray(mean_motion, dtype=np.float64)
    icosahedra, _ = layout.split(mean)
    centres = icosahedra.mean(axis=-2)
    out = {}
    for child, parent in layout.bones:
        if layout.joint_names[child] not in SKULL or layout.joint_names[parent] == ROOT:
            continue
        bone = _mean_bones(icosahedra, parent, [child], centres[parent])
        if bone is not None:  # else that bone keeps its decoded direction
            out[child] = bone[0]
    return out


def piece_directions(layout: MotionLayout, mean_motion, piece: tuple[str, ...] = HIPS,
                     root_relative: bool = False, root_steps: bool = False) -> np.ndarray | None:
    """The training data's bones of ``piece`` (``HIPS``, ``COLLARS``, ``HANDS``) in their common
    parent's frame, (len(piece), 3) unit vectors, from its mean motion vector as
    ``skull_directions`` solves the skull's; None where the layout lacks them or the mean holds no
    rotation. ``root_relative``: the mean is of root-relative motion
    (``Normalizer.set_root_relative``), every point but the root's own less the root's floor
    place, so the hips' mean bones from the root are their points less the root's height alone
    (the other pieces' parents are not the root: no matter).
    ``root_steps``: the root's own points hold their floor steps, whose mean holds no rotation
    (None for a piece on the root: the hips keep their decoded directions); so does a mean whose
    first two bones point the same way (a normalizer fitted to no body, or to a made-up one)."""
    if not all(n in layout.joint_names for n in piece):
        return None
    children = [layout.joint(n) for n in piece]
    parent_of = {child: parent for child, parent in layout.bones}
    parent = parent_of.get(children[0])
    if parent is None or any(parent_of.get(child) != parent for child in children):
        return None
    on_root = layout.joint_names[parent] == ROOT
    if on_root and root_steps:
        return None
    icosahedra, _ = layout.split(np.asarray(mean_motion, dtype=np.float64))
    origin = icosahedra[parent].mean(axis=-2)
    if on_root and root_relative:
        origin = origin * np.array([0.0, 1.0, 0.0])
    bones = _mean_bones(icosahedra, parent, children, origin)
    if bones is None or not _frames(bones[0] - bones[1], _middles(bones[0], bones[1]))[1]:
        return None
    return bones


def _middles(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """(..., 3) pairs of bones -> the (..., 3) unit mean of their directions; straight down where
    a bone or their sum vanishes (a pair of opposite bones points no way in between)."""
    return unit(unit(left) + unit(right), fallback=np.array([0.0, -1.0, 0.0]))


def _frames(line: np.ndarray, middle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) -> (..., 3, 3) frames whose columns are ``line`` made square to ``middle``
    (sideways), ``middle``, and their cross product, and (...) whether each is one: not where
    ``line`` runs along ``middle``."""
    side = line - middle * np.sum(line * middle, axis=-1, keepdims=True)
    norm = np.sqrt(np.sum(side * side, axis=-1, keepdims=True))
    ok = norm[..., 0] > 1e-9
    side = side / np.where(ok[..., None], norm, 1.0)
    return np.stack([side, middle, np.cross(side, middle)], axis=-1), ok


def piece_frames(left: np.ndarray, right: np.ndarray, rest: np.ndarray,
                 sideways: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Bones and their parent as one rigid piece (the pelvis and its hips, the chest and its
    collars, a hand and its knuckles): each piece's rotation in each frame from the decoded
    bones ``left`` and ``right`` of the two that span it ((T, P, 3) for P pieces: each child less
    the parent) and those two's ``rest`` bones ((P, 2, 3) in the parent's frame, metres:
    ``piece_directions`` at the bones' lengths). A piece's middle is the mean of the two bones'
    directions (the hips': down; the collars': up; the knuckles': along the hand), which stays
    put when both swing in together (a piece folded on one side tilts with it); sideways is
    their line, leaning on the frame before's by ``LINE_MEMORY`` of their widths.
    ``sideways``: each piece's last axis before these frames ((P, 3); None at a stream's start).
    -> (rotations (T, P, 3, 3) taking the rest bones to this frame's, the last frame's sideways
    axes (P, 3))."""
    rest_frames, _ = _frames(rest[:, 0] - rest[:, 1], _middles(rest[:, 0], rest[:, 1]))
    to_rest = np.swapaxes(rest_frames, -1, -2)
    leans = LINE_MEMORY * np.linalg.norm(rest[:, 0] - rest[:, 1], axis=-1, keepdims=True)
    middles, lines = _middles(left, right), left - right
    out = np.empty(left.shape[:2] + (3, 3))
    for t in range(len(left)):
        line = lines[t] if sideways is None else lines[t] + leans * sideways
        frame, ok = _frames(line, middles[t])
        # The pair on one point at a stream's start: any sideways will do.
        for axis in ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)):
            if ok.all():
                break
            other, other_ok = _frames(np.broadcast_to(axis, line.shape), middles[t])
            frame, ok = np.where(ok[:, None, None], frame, other), ok | other_ok
        sideways = frame[..., 0]
        out[t] = frame @ to_rest
    return out, sideways


def at_length(direction: np.ndarray, length: np.ndarray) -> np.ndarray:
    """(T, B, 3) bone directions -> the bones at ``length`` (B, 1) along them. A bone the decoder
    collapsed to a point has no direction to keep: it is left as it is."""
    norm = np.linalg.norm(direction, axis=-1, keepdims=True)
    return direction * np.divide(length, norm, out=np.ones_like(norm), where=norm > 1e-9)


def legs(layout: MotionLayout, lengths) -> list[tuple]:
    """Each leg's (hip, knee, ankle, foot) joint indices and its (thigh, shin, foot) bone lengths
    from ``lengths`` (one per ``layout.bones``); none when the layout lacks a leg joint."""
    if not all(name in layout.joint_names for leg in LEGS for name in leg):
        return []
    length_of = dict(zip(layout.bones, np.asarray(lengths, dtype=np.float64)))
    out = []
    for names in LEGS:
        hip, knee, ankle, foot = (layout.joint(n) for n in names)
        out.append((hip, knee, ankle, foot, length_of[(knee, hip)], length_of[(ankle, knee)],
                    length_of[(foot, ankle)]))
    return out


def check_lengths(layout: MotionLayout, lengths, whose: str = "") -> np.ndarray:
    """``lengths`` as (bones,) float64 metres; ValueError unless there is one finite positive
    length per ``layout.bones``."""
    lengths = np.asarray(lengths, dtype=np.float64).reshape(-1)
    if len(lengths) != len(layout.bones):
        raise ValueError(f"rigid skeleton: {len(lengths)} {whose}bone lengths for a layout of "
                         f"{len(layout.bones)} bones")
    if not (np.all(np.isfinite(lengths)) and np.all(lengths > 0)):
        raise ValueError(f"rigid skeleton: {whose}bone lengths must be finite and positive")
    return lengths


def leg_height_change(layout: MotionLayout, lengths, reference) -> float:
    """Metres by which a body on ``lengths`` stands higher than one on ``reference`` (both one
    per ``layout.bones``): the mean over the two legs of pelvis-to-hip, thigh and shin, the
    part of a standing body's height its legs hold (the hip bones point two thirds down: taken
    whole, they leave a smaller body's knees a few millimetres more bent rather than its ankles
    short of the decoder's); 0 for a layout without legs or a pelvis."""
    if ROOT not in layout.joint_names:
        return 0.0
    root, index = layout.joint(ROOT), {bone: i for i, bone in enumerate(layout.bones)}
    difference = np.asarray(lengths) - np.asarray(reference)
    change = [difference[[index[(hip, root)], index[(knee, hip)], index[(ankle, knee)]]].sum()
              for hip, knee, ankle, *_ in legs(layout, lengths)]
    return float(np.mean(change)) if change else 0.0


class RigidSkeleton:
    """(n, Dx) motion vectors in metres -> the same frames on a skeleton with ``lengths``
    (metres, one per ``layout.bones``). Call it on a stream's frames in order (``reset`` starts
    another stream): each shell point rides the bone nearest it in the first frame.
    ``reference``: the lengths of the body the decoder's motion was made for (the training
    data's) where ``lengths`` are another body's (an agent's own): the body moves up or down by
    ``leg_height_change`` from it; None: ``lengths`` are that body's. ``skull``:
    ``skull_directions``, which places those joints by their parent's decoded rotation; None:
    along their decoded directions, as every other bone. ``pieces``: ``{piece: its
    piece_directions}`` (``HIPS``, ``COLLARS``, ``HANDS``), which places each piece's bones with
    their parent as one piece (``piece_frames``), each leg moved with its hip, each arm with its
    collar and each finger with its knuckle; a piece left out: along their decoded
    directions. ``lift`` (metres): the body raised this much more on its legs, the feet where
    the decoder put them (``vae.stand_lift``: a decoder that stands lower than the data's
    people); ``softness``: the legs' reach eased over their last ``softness`` metres
    (``two_bone_ik.soft_reach``, ``vae.leg_softness``)."""

    def __init__(self, layout: MotionLayout, lengths, reference=None,
                 skull: dict[int, np.ndarray] | None = None,
                 pieces: dict[tuple[str, ...], np.ndarray] | None = None,
                 lift: float = 0.0, softness: float = 0.0) -> None:
        lengths = check_lengths(layout, lengths)
        self.layout, self.lengths, self.softness = layout, lengths, softness
        self.root = layout.joint(ROOT) if ROOT in layout.joint_names else None
        if reference is not None:
            lift += leg_height_change(layout, lengths, check_lengths(layout, reference, "reference "))
        self.lift = 0.0 if self.root is None else lift
        # Bones a level at a time (parents placed before their children), as index arrays.
        depth: dict[int, int] = {}
        for child, parent in layout.bones:
            depth[child] = depth.get(parent, 0) + 1
        self._levels = []
        skull = skull or {}
        parent_of = dict(layout.bones)
        # Bones turned onto a rotation rather than along their decoded direction: the skull's onto
        # its parents' decoded rotations, each piece's bones onto the piece's (``piece_frames``,
        # after the skull's parents in the rotations); each such bone's row there and its
        # direction in that frame.
        self._skull_parents = sorted({parent for child, parent in layout.bones if child in skull})
        onto = {child: (self._skull_parents.index(parent), skull[child])
                for child, parent in layout.bones if child in skull}
        # Each piece: its parent, the two joints that span it and their rest bones at their
        # lengths (the piece's shape, which ``piece_frames`` turns), all pieces at once.
        parents, spans, rests = [], [], []
        for piece, directions in (pieces or {}).items():
            children = [layout.joint(name) for name in piece]
            directions = np.asarray(directions, dtype=np.float64).reshape(len(children), 3)
            parent = parent_of[children[0]]
            row = len(self._skull_parents) + len(parents)
            onto.update({child: (row, directions[side]) for side, child in enumerate(children)})
            parents.append(parent)
            spans.append(children[:2])
            rests.append(directions[:2] * [[lengths[layout.bones.index((child, parent))]]
                                           for child in children[:2]])
        self._piece_parents = np.array(parents, dtype=np.int64)
        self._piece_spans = np.array(spans, dtype=np.int64).reshape(-1, 2)
        self._piece_rests = np.array(rests).reshape(-1, 2, 3)
        for level in sorted(set(depth.values())):
            rows = [i for i, (child, _) in enumerate(layout.bones) if depth[child] == level]
            bones = np.array([layout.bones[i] for i in rows])
            turned = [(column, *onto[child]) for column, child in enumerate(bones[:, 0])
                      if child in onto]
            self._levels.append((bones[:, 0], bones[:, 1], lengths[rows, None], turned))
        self.legs = legs(layout, lengths)
        self.shell = ShellFollow(layout, carried=tuple(onto))
        self.reset()

    def reset(self) -> None:
        self.shell.reset()
        self._sideways = None  # each piece's last sideways axis (``piece_frames``)

    def __call__(self, motion: np.ndarray, stance: np.ndarray | None = None,
                 user: np.ndarray | None = None) -> np.ndarray:
        x = np.asarray(motion, dtype=np.float64)
        icosahedra, shell = self.layout.split(x)
        joints = icosahedra.mean(axis=-2)
        placed = joints.copy()
        if self.lift:
            placed[:, self.root, 1] += self.lift
        rotations = [np.empty((len(x), 0, 3, 3))]
        if self._skull_parents:
            rotations = [decode(icosahedra[:, self._skull_parents])[1]]
        if len(self._piece_parents):
            parents = joints[:, self._piece_parents]
            pieces, self._sideways = piece_frames(
                joints[:, self._piece_spans[:, 0]] - parents,
                joints[:, self._piece_spans[:, 1]] - parents, self._piece_rests, self._sideways)
            rotations.append(pieces)
        rotations = np.concatenate(rotations, axis=1)
        moved = np.zeros_like(joints)  # how far a turned bone moved its joint from its decoded way
        for child, parent, length, turned in self._levels:
            direction = joints[:, child] - joints[:, parent]
            if turned:
                columns = [column for column, _, _ in turned]
                decoded_way = placed[:, parent[columns]] + at_length(direction[:, columns],
                                                                     length[columns])
                for column, row, bone in turned:
                    direction[:, column] = rotations[:, row] @ bone
            placed[:, child] = placed[:, parent] + at_length(direction, length)
            if turned:
                moved[:, child[columns]] = placed[:, child[columns]] - decoded_way
        # The feet stay where the decoder put them, as far as the legs reach: the skeleton's legs
        # are longer or shorter than the decoded ones, and lengthened from the hips down the feet
        # went through the floor. A leg whose hip the pelvis's piece moved moves with it: held
        # to its decoded ankle, it swung in to it, the knees together (docs/models.md).
        for hip, knee, ankle, foot, thigh, shin, foot_bone in self.legs:
            shift = moved[:, hip]
            placed[:, knee], placed[:, ankle] = two_bone_ik(placed[:, hip], joints[:, knee] + shift,
                                                            joints[:, ankle] + shift, thigh, shin,
                                                            self.softness)
            placed[:, foot] = foot_at_its_height(placed[:, ankle], joints[:, ankle] + shift,
                                                 joints[:, foot] + shift, foot_bone)
        correction = placed - joints
        return finish(motion, icosahedra, shell, correction, self.shell(shell, joints, correction))


def foot_at_its_height(ankle: np.ndarray, decoded_ankle: np.ndarray, decoded_foot: np.ndarray,
                       length: float) -> np.ndarray:
    """(..., 3) -> where a foot bone of ``length`` from ``ankle`` puts the foot joint: at the
    decoded foot's height (as far as the bone reaches), pointing the way the decoded foot points
    on the floor. The decoder's foot bones come out short (8 cm where the skeleton's is 13.6,
    pointing ~40° down); lengthened along their decoded direction, the feet went 3-4 cm into the
    floor (docs/results.md, twenty-second run). Kept at their height, they lie flatter instead."""
    drop = np.clip(decoded_foot[..., 1] - ankle[..., 1], -length, length)
    flat = (decoded_foot - decoded_ankle) * np.array([1.0, 0.0, 1.0])
    norm = np.linalg.norm(flat, axis=-1, keepdims=True)
    heading = np.divide(flat, norm, out=np.zeros_like(flat), where=norm > 1e-9)
    reach = np.sqrt(np.maximum(length ** 2 - drop ** 2, 0.0))[..., None]
    out = ankle + heading * reach
    out[..., 1] += drop
    # A decoded foot right below its ankle points nowhere on the floor: straight down, full length.
    pointless = norm[..., 0] <= 1e-9
    out[pointless] = ankle[pointless] - np.array([0.0, length, 0.0])
    return out


def finish(motion, icosahedra, shell, correction, shell_correction) -> np.ndarray:
    """The motion vector with every icosahedron moved by its joint's correction and the shell
    points by theirs, in the input's dtype."""
    n = len(icosahedra)
    out = np.concatenate([(icosahedra + correction[:, :, None]).reshape(n, -1),
                          (shell + shell_correction).reshape(n, -1)], axis=1)
    return out.astype(np.asarray(motion).dtype)


class ShellFollow:
    """How shell points follow corrections of the joints: each rides the body bone it lies on.

    The shell is the body's skinned mesh, and a mesh vertex moves with its bone: rebuilt from the
    ground truth's joints alone, each point carried by the rotation and position of the body
    bone nearest it, the fixtures' shell comes back with an FGD_acc of 73 against the ground
    truth (real against real: 76), its legs 26. A blend of the joints' translations (this class
    until the twenty-fifth run) gave 390 on the legs of the same ground truth: when the foot lock
    bent a knee for a step, a shin point moved along the chord between knee and ankle instead of
    turning with the shin (docs/results.md, twenty-fifth run).

    Each point belongs to the body bone (of ``BODY_JOINTS``) whose segment is nearest it in the
    first frame the class sees (``reset`` forgets it, like a body's skinning weights); a hand's
    points ride the forearm, not finger bones of 2-3 cm whose decoded directions swing. The
    point moves with the bone's parent joint, turns about it by the shortest rotation from the
    bone's old direction to its new one (no twist: a joint correction says nothing of it), and
    keeps its share along the bone when the bone's length changes (a lengthened forearm carries
    the hand's points out with the wrist; a point past the bone's end moves with that end).

    ``carried``: child joints whose bone moves its points without turning them. The skull's
    (``SKULL``) are turned onto their parent's rotation, not by the pose changing: the head's
    own rotation stays the decoder's, and so does the face the decoder drew around it. Turned
    with the neck's bone on the demo's clip, the head's points came 14 cm from the person's head
    shape on average, carried 6.1 cm, and left where they were 9.7 (ninety-ninth run)."""

    def __init__(self, layout: MotionLayout, carried: tuple[int, ...] = ()) -> None:
        body = set(JOINT_NAMES[:BODY_JOINTS])
        self.bones = np.array([bone for bone in layout.bones if layout.joint_names[bone[0]] in body],
                              dtype=np.int64).reshape(-1, 2)  # (child, parent)
        self.carried = np.isin(self.bones[:, 0], list(carried))
        self.reset()

    def reset(self) -> None:
        self.segment: np.ndarray | None = None  # per shell point, its row of ``bones``

    def _nearest_segments(self, points: np.ndarray, joints: np.ndarray) -> np.ndarray:
        child, parent = joints[self.bones[:, 0]], joints[self.bones[:, 1]]
        bone = child - parent
        along = np.einsum("pbc,bc->pb", points[:, None] - parent[None], bone)
        along = np.clip(along / np.maximum(np.sum(bone ** 2, axis=-1), 1e-12), 0.0, 1.0)
        nearest = parent[None] + along[..., None] * bone[None]
        return np.argmin(np.sum((points[:, None] - nearest) ** 2, axis=-1), axis=1)

    def __call__(self, shell: np.ndarray, joints: np.ndarray, correction: np.ndarray) -> np.ndarray:
        """(T, P, 3) shell points, (T, J, 3) joints and their corrections -> the points'
        (T, P, 3) corrections."""
        if not len(self.bones):
            return np.zeros_like(shell)
        if self.segment is None:
            self.segment = self._nearest_segments(shell[0], joints[0])
        child, parent = self.bones[:, 0], self.bones[:, 1]
        corrected = joints + correction
        bone_before = joints[:, child] - joints[:, parent]  # (T, B, 3)
        bone_after = corrected[:, child] - corrected[:, parent]
        turns = shortest_rotation(bone_before, bone_after)
        turns[:, self.carried] = np.eye(3)
        turn = turns[:, self.segment]  # (T, P, 3, 3)
        before, after = bone_before[:, self.segment], bone_after[:, self.segment]
        anchor = parent[self.segment]  # each point's bone's parent joint
        # Where along the segment the point lies, 0 at the parent, 1 at the child: that share
        # stretches with the bone; the rest turns rigidly about it. Unclipped, a hand point
        # 20 cm past a forearm the decoder had shrunk to 3 cm stretched with it sevenfold when
        # the skeleton put the forearm back at 24 cm, and flew 8 m (an offline window).
        offset = shell - joints[:, anchor]
        along = np.clip(np.sum(offset * before, axis=-1, keepdims=True) / np.maximum(
            np.sum(before ** 2, axis=-1, keepdims=True), 1e-12), 0.0, 1.0)
        moved = corrected[:, anchor] + along * after + np.einsum(
            "tpij,tpj->tpi", turn, offset - along * before)
        return moved - shell

