"""What an export reads: a ``sarah-generate`` motion.npz, or one person of a shard sequence (a
whole sequence or a window of it), as world-frame joints, global rotations and a body shape."""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sarah_data import icosahedron
from sarah_data.constants import FPS, NUM_JOINTS
from sarah_data.loading import DataProblem

from .kinematics import SkeletonFit, fit_skeleton, rest_offsets_from_motion


class ExportError(DataProblem):
    """Input an export cannot use: ``path`` and ``reason`` (one line)."""


@dataclass
class BodyShape:
    """Whose body the motion is: SMPL-X betas, the rest skeleton those betas give (joints at zero
    pose, (55, 3), from the body model), the model's gender, and where they came from."""

    betas: np.ndarray | None  # (B,) None: unknown
    rest_joints: np.ndarray | None  # (55, 3) None: unknown (needs the body model)
    gender: str = "neutral"
    source: str = "unknown"

    @property
    def known(self) -> bool:
        return self.betas is not None and self.rest_joints is not None


@dataclass
class ExportMotion:
    name: str  # file stem for the outputs
    positions: np.ndarray  # (T, 55, 3) world joints, metres, y up
    rotations: np.ndarray  # (T, 55, 3, 3) global joint rotations
    shape: BodyShape
    fps: int = FPS
    source: str = ""

    @property
    def frames(self) -> int:
        return int(self.positions.shape[0])

    def skeleton(self) -> np.ndarray:
        """(55, 3) the rest skeleton the exported body is built on: the body's, or, for motion
        without a body shape, one fitted to the motion (BVH and glTF only: SMPL-X needs betas)."""
        if self.shape.rest_joints is not None:
            return np.asarray(self.shape.rest_joints, np.float64)
        return rest_offsets_from_motion(self.positions, self.rotations)

    def fit(self, pose_from: str = "joints") -> SkeletonFit:
        """The rigid body every exporter writes, in our world (y up): ``skeleton()`` posed to
        follow the motion (``kinematics.fit_skeleton``). Fitted once, written in every format."""
        return fit_skeleton(self.positions, self.rotations, self.skeleton(), pose_from=pose_from)


MOTION_KEYS = ("joint_positions", "joint_rotations")


def neutral_shape(body_model: str | Path, why: str = "") -> BodyShape:
    """Zero betas and the rest skeleton they give with ``body_model`` (a SMPL-X .npz): the body
    of motion that belongs to no captured person. ExportError when the file cannot be loaded."""
    return avatar_shape(body_model, None, why)


def avatar_shape(body_model: str | Path, betas=None, why: str = "") -> BodyShape:
    """``betas`` (zero when None; fewer than the model has are padded with zeros) and the rest
    skeleton they give with ``body_model`` (a SMPL-X .npz): an avatar's body. ExportError when
    the file cannot be loaded or the betas do not fit it."""
    from sarah_data.body import BodyModel

    try:
        model = BodyModel.from_file(body_model, device="cpu")
    except Exception as error:  # noqa: BLE001 - any unreadable model file is one line
        raise ExportError(body_model, f"cannot load as a SMPL-X model ({error})") from None
    given = np.zeros(0) if betas is None else np.asarray(betas, dtype=np.float64).reshape(-1)
    if len(given) > model.num_betas or not np.isfinite(given).all():
        raise ExportError(body_model, f"{len(given)} betas for a model of {model.num_betas} shape "
                                      f"components (finite numbers, at most that many)")
    full = np.zeros(model.num_betas)
    full[:len(given)] = given
    shown = ", ".join(f"{b:.4g}" for b in given[:4]) + (", ..." if len(given) > 4 else "")
    kind = "neutral zero betas" if not given.any() else f"betas [{shown}]"
    source = f"{kind} of {model.name}" + (f" ({why})" if why else "")
    return BodyShape(full, model.rest_joints(full), model.gender, source)


def motion_from_file(path: str | Path) -> ExportMotion:
    """A motion.npz written by ``sarah-generate``; ExportError for anything else."""
    path = Path(path)
    if not path.is_file():
        raise ExportError(path, "no such file")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in MOTION_KEYS if k not in data.files]
            if missing:
                raise ExportError(path, f"not a sarah-generate motion.npz (no {', '.join(missing)})")
            arrays = {k: data[k] for k in data.files
                      if k in (*MOTION_KEYS, "fps", "betas", "rest_joints", "gender", "body_shape_source")}
    except ExportError:
        raise
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as error:
        raise ExportError(path, f"unreadable npz ({type(error).__name__}: {error})") from None
    positions, rotations = arrays["joint_positions"], arrays["joint_rotations"]
    frames = positions.shape[0] if positions.ndim else 0
    if positions.shape != (frames, NUM_JOINTS, 3) or rotations.shape != (frames, NUM_JOINTS, 3, 3):
        raise ExportError(path, f"joint_positions {positions.shape} / joint_rotations "
                                f"{rotations.shape}: expected (T, {NUM_JOINTS}, 3) and (T, {NUM_JOINTS}, 3, 3)")
    if frames < 1:
        raise ExportError(path, "has no frames")
    if not (np.isfinite(positions).all() and np.isfinite(rotations).all()):
        raise ExportError(path, "joint positions or rotations contain NaN or infinite values")
    fps = int(arrays.get("fps", FPS))
    if fps != FPS:
        raise ExportError(path, f"fps {fps}: the toolkit's motion is {FPS} fps")
    shape = BodyShape(
        betas=arrays["betas"].astype(np.float64) if "betas" in arrays else None,
        rest_joints=arrays["rest_joints"].astype(np.float64) if "rest_joints" in arrays else None,
        gender=str(arrays.get("gender", "neutral")),
        source=str(arrays.get("body_shape_source", "not recorded (motion.npz from an older toolkit)")))
    stem = path.stem if path.stem != "motion" else path.parent.name or "motion"
    return ExportMotion(stem, positions.astype(np.float64), rotations.astype(np.float64), shape,
                        FPS, f"{path}")


def motion_from_shards(shards_dir: str | Path, sequence: str, person: str | None = None,
                       start: int = 0, frames: int | None = None) -> ExportMotion:
    """One person of a prepared sequence (the first person unless ``person``), frames
    ``start`` .. ``start + frames`` (all by default), ground truth in world coordinates."""
    from sarah_data.shards import ShardError, ShardSet

    shards_dir = Path(shards_dir)
    try:
        shards = ShardSet(shards_dir)
    except ShardError as error:
        raise ExportError(error.path, error.reason) from None
    try:
        names = shards.sequences()
        if sequence not in names:
            hint = ", ".join(names[:5]) + (" ..." if len(names) > 5 else "")
            raise ExportError(shards_dir, f"no sequence {sequence!r} (it has {len(names)}: "
                                          f"{hint or 'none'})")
        group = shards.group(sequence)
        persons = [str(p) for p in group.attrs["persons"]]
        person = persons[0] if person is None else person
        if person not in persons:
            raise ExportError(shards_dir, f"sequence {sequence} has persons {persons}, not {person!r}")
        g = group[person]
        total = int(g["valid"].shape[0])
        stop = total if frames is None else start + int(frames)
        if not (0 <= start < total) or stop > total or stop <= start:
            raise ExportError(shards_dir, f"{sequence}: frames {start}..{stop} are outside its "
                                          f"{total} frames")
        ico = g["icosahedra"][start:stop].astype(np.float64)
        if "betas" in g:
            shape = BodyShape(g["betas"][()].astype(np.float64), g["rest_joints"][()].astype(np.float64),
                              str(g.attrs.get("gender", "neutral")),
                              f"{sequence}/{person} in {shards_dir}")
        else:
            shape = BodyShape(None, None, "neutral", f"{shards_dir}: schema 1 shards hold no body "
                                                     f"shape (prepare them again for it)")
    finally:
        shards.close()
    positions, rotations = icosahedron.decode(ico)
    suffix = "" if (start, stop) == (0, total) else f"_{start}-{stop}"
    return ExportMotion(f"{sequence}_{person}{suffix}", positions, rotations, shape, FPS,
                        f"{shards_dir} {sequence}/{person} frames {start}..{stop}")
