"""What a generation is conditioned on: a window of prepared shards, or raw files.

Inputs are world-frame (y up, metres, floor (x, z), 30 fps):

* shard: the user's floor-projected head and both persons' stored audio features of one
  sequence; the generation frame is the agent's real pose at ``start`` (as in training windows).
* raw: a (T, 2) user trajectory (.npy or .csv, x and z per frame at 30 fps) and two audio files
  (any rate, resampled to 48 kHz) streamed through the checkpoint's feature extractor in its
  causal mode; the agent starts at ``agent_start`` (x, z, yaw; default the origin facing +z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sarah_data.constants import AUDIO_SAMPLE_RATE, FPS, SAMPLES_PER_FRAME
from sarah_data.dataset import tracked_runs
from sarah_data.frames import WindowTransform, rotation_about_y, window_transform

from ..config import WINDOW

DEFAULT_FRAMES = WINDOW  # the paper's T for shard windows


class GenerateError(Exception):
    """A problem with the inputs of a generation, stated in one line."""


@dataclass
class Inputs:
    """World-frame conditioning of one generation (T frames at 30 fps)."""

    user_head: np.ndarray  # (T, 2)
    agent_speaking: np.ndarray  # (T,) bool
    user_speaking: np.ndarray  # (T,) bool
    anchor: WindowTransform  # world -> generation frame (the agent's initial pose)
    source: dict[str, Any]  # where the inputs came from, for motion.npz
    agent_audio: np.ndarray | None = None  # (T, D) features (shard input)
    user_audio: np.ndarray | None = None
    agent_wave: np.ndarray | None = None  # (N,) float32 at 48 kHz (raw input)
    reference_icosahedra: np.ndarray | None = None  # (T, J, 12, 3) the real agent (shard input)
    user_wave: np.ndarray | None = None
    # The agent's body for export: betas (B,), rest_joints (55, 3), gender, source (motion.npz
    # keys of the same names). Raw inputs have no person: neutral zero betas, no rest joints.
    body_shape: dict[str, Any] | None = None

    @property
    def frames(self) -> int:
        return int(self.user_head.shape[0])


def _frames_multiple(frames: int, stride: int, what: str) -> int:
    usable = frames - frames % stride
    if usable < stride:
        raise GenerateError(f"{what}: {frames} frames, need at least one block of {stride}")
    return usable


def _default_window(valid: np.ndarray, frames: int | None) -> tuple[int, int]:
    """(start, length) of the first tracked run that holds ``frames`` frames, else the longest
    tracked run (whole); length 0 when no frame is tracked. ``frames`` None: the longest run."""
    runs = tracked_runs(valid)
    if frames is not None:
        for first, stop in runs:
            if stop - first >= frames:
                return first, frames
    first, stop = max(runs, key=lambda run: run[1] - run[0], default=(0, 0))
    return first, stop - first


def _choose_window(shards, shards_dir: Path, split: str, names: list[str], sequence: str | None,
                   agent: str | None, start: int | None, frames: int | None
                   ) -> tuple[str, str, str, int, int | None]:
    """(sequence, agent, user, start, tracked length or None for an explicit start)."""
    best = None
    for name in [sequence] if sequence is not None else names:
        group = shards.group(name)
        persons = [str(p) for p in group.attrs["persons"]]
        chosen = persons[0] if agent is None else agent
        if chosen not in persons:
            if sequence is None:
                continue  # --agent without --sequence: the sequences this person is in
            raise GenerateError(f"{shards_dir}: sequence {name} has no person {agent!r} "
                                f"(persons: {', '.join(persons)})")
        user = persons[1 - persons.index(chosen)]
        if start is not None:
            return name, chosen, user, start, None
        first, length = _default_window(group[chosen]["valid"][:].astype(bool)
                                        & group[user]["valid"][:].astype(bool), frames)
        if best is None or length > best[4]:
            best = (name, chosen, user, first, length)
        if frames is not None and length >= frames:
            break
    if best is None:
        raise GenerateError(f"{shards_dir}: no person {agent!r} in any sequence of split {split!r}")
    if best[4] == 0:
        raise GenerateError(f"{best[0]}: no frame is tracked for both persons")
    return best


def shard_inputs(shards_dir: str | Path, split: str, sequence: str | None, agent: str | None,
                 features: str, audio_dim: int, stride: int, start: int | None = None,
                 frames: int | None = DEFAULT_FRAMES) -> Inputs:
    """One window of a prepared sequence, with ``agent`` as the agent and the other as user.

    Defaults: the sequence's first person as agent; without ``start``, the first frame from
    which ``frames`` frames are tracked for both persons (or the longest tracked run, when no
    run is that long), in ``sequence`` or else in the split's first sequence that has one.
    An explicit ``start`` is taken as given, and a window with untracked frames is an error."""
    from sarah_data.shards import ShardError, ShardSet

    shards_dir = Path(shards_dir)
    try:
        shards = ShardSet(shards_dir)
    except ShardError as exc:
        raise GenerateError(str(exc)) from None
    try:
        names = shards.sequences(split)
        if not names:
            raise GenerateError(f"{shards_dir}: split {split!r} has no sequences")
        if sequence is not None and sequence not in names:
            hint = ", ".join(names[:5]) + (" ..." if len(names) > 5 else "")
            raise GenerateError(f"{shards_dir}: no sequence {sequence!r} in split {split!r} "
                                f"(it has {len(names)}: {hint or 'none'})")
        sequence, agent, user, start, tracked = _choose_window(shards, shards_dir, split, names,
                                                               sequence, agent, start, frames)
        group = shards.group(sequence)
        a, u = group[agent], group[user]
        stored = sorted(a["audio"]) if "audio" in a else []
        if features not in stored:
            raise GenerateError(f"{shards_dir}: mismatched feature extractor: the checkpoint "
                                f"uses {features!r}, the shards hold {stored or 'no features'}")
        total = int(a["valid"].shape[0])
        if not 0 <= start < total:
            raise GenerateError(f"{sequence}: --start {start} is outside its {total} frames")
        count = total - start if frames is None else min(int(frames), total - start)
        count = _frames_multiple(count if tracked is None else min(count, tracked), stride,
                                 f"{sequence} from frame {start}")
        window = slice(start, start + count)
        width = int(a["audio"][features].shape[-1])
        if width != audio_dim:
            raise GenerateError(f"{shards_dir}: mismatched feature extractor: {features!r} "
                                f"features have {width} channels, the checkpoint expects {audio_dim}")
        valid = a["valid"][window].astype(bool) & u["valid"][window].astype(bool)
        if not valid.all():
            bad = np.flatnonzero(~valid)
            raise GenerateError(f"{sequence}: frames {start + bad[0]}..{start + bad[-1]} are not "
                                f"tracked for both persons; choose --start/--frames inside a "
                                f"tracked run, or leave --start out to have one found")
        anchor = window_transform(a["root_position"][start], a["root_rotation"][start])
        return Inputs(
            user_head=u["head"][window].astype(np.float32),
            agent_speaking=a["speaking"][window].astype(bool),
            user_speaking=u["speaking"][window].astype(bool),
            anchor=anchor,
            agent_audio=a["audio"][features][window].astype(np.float32),
            user_audio=u["audio"][features][window].astype(np.float32),
            reference_icosahedra=a["icosahedra"][window].astype(np.float32),
            body_shape=({"betas": a["betas"][()], "rest_joints": a["rest_joints"][()],
                         "gender": str(a.attrs.get("gender", "neutral")),
                         "body_shape_source": f"agent {agent} of {sequence} in {shards_dir}"}
                        if "betas" in a else None),
            source={"kind": "shard", "shards": str(shards_dir), "split": split,
                    "sequence": sequence, "agent": agent, "user": user,
                    "start": int(start), "reference_gaze": a["gaze"][window].astype(np.float32)},
        )
    finally:
        shards.close()


def read_trajectory(path: str | Path) -> np.ndarray:
    """(T, 2) float32 floor (x, z) positions from .npy or .csv (an optional header line)."""
    path = Path(path)
    if not path.is_file():
        raise GenerateError(f"{path}: no such trajectory file")
    try:
        if path.suffix.lower() == ".npy":
            data = np.load(path, allow_pickle=False)
        elif path.suffix.lower() == ".csv":
            data = _read_csv_rows(path)
        else:
            raise GenerateError(f"{path}: trajectory must be .npy or .csv")
    except (ValueError, OSError) as exc:
        raise GenerateError(f"{path}: cannot read trajectory ({exc})") from None
    data = np.asarray(data)
    if data.ndim != 2 or data.shape[1] != 2 or not np.issubdtype(data.dtype, np.number):
        raise GenerateError(f"{path}: trajectory must be (T, 2) numbers (x, z), got shape "
                            f"{data.shape}")
    if len(data) == 0:
        raise GenerateError(f"{path}: trajectory has no rows")
    if not np.isfinite(data).all():
        row = int(np.flatnonzero(~np.isfinite(data).all(axis=1))[0])
        raise GenerateError(f"{path}: trajectory contains non-finite values (first at frame {row})")
    return data.astype(np.float32)


def _read_csv_rows(path: Path) -> np.ndarray:
    """x,z rows of a CSV file, an optional header line first; errors name the file's line."""
    rows = []
    with open(path, newline="") as handle:
        for number, line in enumerate(handle, start=1):
            text = line.strip()
            if not text:
                continue
            cells = [c.strip() for c in text.split(",")]
            try:
                values = [float(c) for c in cells]
            except ValueError:
                if not rows and number == 1:
                    continue  # a header such as "x,z"
                raise GenerateError(f"{path}: line {number}: {text!r} is not two numbers x,z") from None
            if len(values) != 2:
                raise GenerateError(f"{path}: line {number}: {len(values)} values, expected 2 (x,z)")
            rows.append(values)
    return np.asarray(rows, dtype=np.float64).reshape(-1, 2)


STEREO_CORRELATION_WARNING = 0.3  # below this, two channels are likely two different voices


def read_audio(path: str | Path, warnings: list[str] | None = None) -> np.ndarray:
    """Mono float32 at 48 kHz from any file soundfile reads (channels averaged, resampled).
    Channels that hardly correlate (two voices in one file?) add a line to ``warnings``."""
    import soundfile as sf
    import torchaudio

    path = Path(path)
    if not path.is_file():
        raise GenerateError(f"{path}: no such audio file")
    try:
        wave, rate = sf.read(path, dtype="float32", always_2d=True)
    except (RuntimeError, sf.LibsndfileError) as exc:
        raise GenerateError(f"{path}: cannot read audio ({exc})") from None
    if wave.shape[1] > 1 and warnings is not None:
        left, right = wave[:, 0] - wave[:, 0].mean(), wave[:, 1] - wave[:, 1].mean()
        energy = float(np.sqrt((left ** 2).sum() * (right ** 2).sum()))
        if energy > 0 and float((left * right).sum()) / energy < STEREO_CORRELATION_WARNING:
            warnings.append(f"{path}: its {wave.shape[1]} channels differ a lot (two speakers mixed "
                            f"into one file?); they are averaged into one voice")
    wave = wave.mean(axis=1)
    if rate != AUDIO_SAMPLE_RATE:
        wave = torchaudio.functional.resample(torch.from_numpy(wave), rate,
                                              AUDIO_SAMPLE_RATE).numpy()
    if not np.isfinite(wave).all():
        raise GenerateError(f"{path}: audio contains non-finite samples")
    return np.ascontiguousarray(wave, dtype=np.float32)


def agent_anchor(agent_start: tuple[float, float, float]) -> WindowTransform:
    """The transform that puts an agent at floor (x, z) with heading yaw (degrees, 0 = facing +z)
    at the origin facing +z: where a generation without a real agent starts."""
    x, z, yaw_deg = (float(v) for v in agent_start)
    return window_transform(np.array([x, 0.0, z]), rotation_about_y(math.radians(yaw_deg)))


def raw_inputs(trajectory: str | Path, agent_audio: str | Path, user_audio: str | Path,
               stride: int, frames: int | None = None,
               agent_start: tuple[float, float, float] = (0.0, 0.0, 0.0), pad: bool = False,
               warnings: list[str] | None = None) -> Inputs:
    """Raw files; ``agent_start`` = (x, z, yaw in degrees, 0 = facing +z) of the agent.
    Audio shorter than the trajectory is an error, or with ``pad`` is padded with silence (a line
    in ``warnings``)."""
    warnings = [] if warnings is None else warnings
    from sarah_data.speaking import SpeakingConfig, speaking_labels

    head = read_trajectory(trajectory)
    count = head.shape[0] if frames is None else min(int(frames), head.shape[0])
    count = _frames_multiple(count, stride, str(trajectory))
    head = head[:count]
    waves = {}
    for name, path in (("agent", agent_audio), ("user", user_audio)):
        wave = read_audio(path, warnings)
        if len(wave) < count * SAMPLES_PER_FRAME:
            if not pad:
                raise GenerateError(f"{path}: audio shorter than the trajectory "
                                    f"({len(wave) / AUDIO_SAMPLE_RATE:.2f} s < {count / FPS:.2f} s "
                                    f"for {count} frames); --pad pads it with silence")
            warnings.append(f"{path}: {len(wave) / AUDIO_SAMPLE_RATE:.2f} s of audio padded with "
                            f"silence to the trajectory's {count / FPS:.2f} s")
            wave = np.pad(wave, (0, count * SAMPLES_PER_FRAME - len(wave)))
        waves[name] = wave[: count * SAMPLES_PER_FRAME]
    x, z, yaw_deg = (float(v) for v in agent_start)
    anchor = agent_anchor(agent_start)
    labels = {name: speaking_labels(waves[name], waves[other], SpeakingConfig(),
                                    AUDIO_SAMPLE_RATE)[:count]
              for name, other in (("agent", "user"), ("user", "agent"))}
    return Inputs(user_head=head, agent_speaking=labels["agent"], user_speaking=labels["user"],
                  anchor=anchor, agent_wave=waves["agent"], user_wave=waves["user"],
                  source={"kind": "raw", "trajectory": str(trajectory),
                          "agent_audio": str(agent_audio), "user_audio": str(user_audio),
                          "agent_start": np.array([x, z, yaw_deg], np.float32)})


def make_extractor(name: str, options: dict[str, Any] | None = None):
    """The audio feature extractor ``name`` (the checkpoint's), its errors as GenerateError."""
    from sarah_data.features import get_extractor

    try:
        return get_extractor(name, **(options or {}))
    except (KeyError, TypeError, ValueError) as exc:
        raise GenerateError(f"audio feature extractor {name!r}: {exc}") from None
