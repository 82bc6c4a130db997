"""The library behind ``sarah-generate``: inputs (a shard window or raw files) -> motion + plots.

Inputs are world-frame (y up, metres, floor (x, z), 30 fps):

* shard: the user's floor-projected head and both persons' stored audio features of one
  sequence; the generation frame is the agent's real pose at ``start`` (as in training windows).
* raw: a (T, 2) user trajectory (.npy or .csv, x and z per frame at 30 fps) and two audio files
  (any rate, resampled to 48 kHz) streamed through the checkpoint's feature extractor in its
  causal mode; the agent starts at ``agent_start`` (x, z, yaw; default the origin facing +z).

Outputs in ``out``: ``motion.npz`` (see ``write_motion``), ``topview.png``, ``skeleton.gif``.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from sarah_data import icosahedron
from sarah_data.constants import (AUDIO_SAMPLE_RATE, FPS, JOINT, JOINT_PARENTS, NUM_JOINTS,
                                  SAMPLES_PER_FRAME)
from sarah_data.dataset import tracked_runs
from sarah_data.frames import WindowTransform, rotation_about_y, window_transform
from sarah_data.gaze import gaze_score, head_points

from .checkpoint import LoadedModels, load_models
from .stream import StreamConfig, StreamingGenerator, StreamingSession, check_gaze, generate_offline

DEFAULT_FRAMES = 400  # the paper's T for shard windows


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
    user_wave: np.ndarray | None = None

    @property
    def frames(self) -> int:
        return int(self.user_head.shape[0])


@dataclass
class Result:
    motion: np.ndarray  # (T, Dx) world-frame motion vector (icosahedra then shell)
    agent_audio: np.ndarray  # (T, D) the features the model saw
    user_audio: np.ndarray
    latencies: list[float] = field(default_factory=list)  # seconds per chunk (streaming)
    seconds: float = 0.0  # total generation time

    @property
    def fps(self) -> float:
        return self.motion.shape[0] / max(self.seconds, 1e-12)


# --------------------------------------------------------------------------- checkpoint


def load_run(run: str | Path, checkpoint: str | Path | None = None,
             device: str | None = None, need_flow: bool = True) -> tuple[LoadedModels, Path]:
    """The flow-stage models of a run (``run/flow.pt`` unless ``checkpoint`` is given);
    ``need_flow=False`` also accepts a VAE-stage checkpoint."""
    run = Path(run)
    if not run.is_dir():
        raise GenerateError(f"{run}: run folder does not exist")
    if checkpoint is None:
        path = run / "flow.pt"
    else:
        path = Path(checkpoint)
        if not path.is_file() and (run / path).is_file():
            path = run / path
    if not path.is_file():
        raise GenerateError(f"{path}: no such checkpoint (train the flow stage first, or pass "
                            f"--checkpoint)")
    try:
        models = load_models(path, device=device)
    except (ValueError, KeyError, RuntimeError) as exc:
        raise GenerateError(f"{path}: cannot load checkpoint ({exc})") from None
    if need_flow and models.flow is None:
        raise GenerateError(f"{path}: a {models.stage}-stage checkpoint; generation needs the "
                            f"flow stage (flow.pt)")
    return models, path


# --------------------------------------------------------------------------- inputs


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
            try:
                data = np.loadtxt(path, delimiter=",", ndmin=2)
            except ValueError:
                data = np.loadtxt(path, delimiter=",", ndmin=2, skiprows=1)
        else:
            raise GenerateError(f"{path}: trajectory must be .npy or .csv")
    except (ValueError, OSError) as exc:
        raise GenerateError(f"{path}: cannot read trajectory ({exc})") from None
    data = np.asarray(data)
    if data.ndim != 2 or data.shape[1] != 2 or not np.issubdtype(data.dtype, np.number):
        raise GenerateError(f"{path}: trajectory must be (T, 2) numbers (x, z), got shape "
                            f"{data.shape}")
    if not np.isfinite(data).all():
        raise GenerateError(f"{path}: trajectory contains non-finite values")
    return data.astype(np.float32)


def read_audio(path: str | Path) -> np.ndarray:
    """Mono float32 at 48 kHz from any file soundfile reads (channels averaged, resampled)."""
    import soundfile as sf
    import torchaudio

    path = Path(path)
    if not path.is_file():
        raise GenerateError(f"{path}: no such audio file")
    try:
        wave, rate = sf.read(path, dtype="float32", always_2d=True)
    except (RuntimeError, sf.LibsndfileError) as exc:
        raise GenerateError(f"{path}: cannot read audio ({exc})") from None
    wave = wave.mean(axis=1)
    if rate != AUDIO_SAMPLE_RATE:
        wave = torchaudio.functional.resample(torch.from_numpy(wave), rate,
                                              AUDIO_SAMPLE_RATE).numpy()
    if not np.isfinite(wave).all():
        raise GenerateError(f"{path}: audio contains non-finite samples")
    return np.ascontiguousarray(wave, dtype=np.float32)


def raw_inputs(trajectory: str | Path, agent_audio: str | Path, user_audio: str | Path,
               stride: int, frames: int | None = None,
               agent_start: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Inputs:
    """Raw files; ``agent_start`` = (x, z, yaw in degrees, 0 = facing +z) of the agent."""
    from sarah_data.speaking import SpeakingConfig, speaking_labels

    head = read_trajectory(trajectory)
    count = head.shape[0] if frames is None else min(int(frames), head.shape[0])
    count = _frames_multiple(count, stride, str(trajectory))
    head = head[:count]
    waves = {}
    for name, path in (("agent", agent_audio), ("user", user_audio)):
        wave = read_audio(path)
        if len(wave) < count * SAMPLES_PER_FRAME:
            raise GenerateError(f"{path}: audio shorter than the trajectory "
                                f"({len(wave) / AUDIO_SAMPLE_RATE:.2f} s < {count / FPS:.2f} s "
                                f"for {count} frames)")
        waves[name] = wave[: count * SAMPLES_PER_FRAME]
    x, z, yaw_deg = (float(v) for v in agent_start)
    # The transform that puts a root at (x, z) with heading yaw at the origin facing +z.
    anchor = window_transform(np.array([x, 0.0, z]), rotation_about_y(math.radians(yaw_deg)))
    labels = {name: speaking_labels(waves[name], waves[other], SpeakingConfig(),
                                    AUDIO_SAMPLE_RATE)[:count]
              for name, other in (("agent", "user"), ("user", "agent"))}
    return Inputs(user_head=head, agent_speaking=labels["agent"], user_speaking=labels["user"],
                  anchor=anchor, agent_wave=waves["agent"], user_wave=waves["user"],
                  source={"kind": "raw", "trajectory": str(trajectory),
                          "agent_audio": str(agent_audio), "user_audio": str(user_audio),
                          "agent_start": np.array([x, z, yaw_deg], np.float32)})


# --------------------------------------------------------------------------- generation


def make_extractor(name: str, options: dict[str, Any] | None = None):
    from sarah_data.features import get_extractor

    try:
        return get_extractor(name, **(options or {}))
    except (KeyError, TypeError, ValueError) as exc:
        raise GenerateError(f"audio feature extractor {name!r}: {exc}") from None


def generate(models: LoadedModels, inputs: Inputs, config: StreamConfig, offline: bool = False,
             extractor=None) -> Result:
    """Run the streaming generator chunk by chunk (or the offline protocol) on ``inputs``."""
    vae, flow, normalizer = models.vae, models.flow, models.normalizer
    s, count = vae.stride, inputs.frames
    if inputs.agent_audio is None:
        extractor = extractor or make_extractor(models.features)
        if extractor.dim != flow.audio_dim:
            raise GenerateError(f"mismatched feature extractor: {extractor.name!r} gives "
                                f"{extractor.dim} channels, the checkpoint expects {flow.audio_dim}")
    if offline:
        if inputs.agent_audio is None:
            a, b = (extractor.extract(w, count) for w in (inputs.agent_wave, inputs.user_wave))
        else:
            a, b = inputs.agent_audio, inputs.user_audio
        tick = time.perf_counter()
        motion = generate_offline(vae, flow, normalizer, inputs.user_head, a, b, config,
                                  inputs.anchor)
        _synchronize(flow)
        return Result(motion, a, b, seconds=time.perf_counter() - tick)

    generator = StreamingGenerator(vae, flow, normalizer, config, inputs.anchor)
    chunks, latencies = [], []
    if inputs.agent_audio is not None:
        a, b = inputs.agent_audio, inputs.user_audio
        for i in range(0, count, s):
            tick = time.perf_counter()
            chunks.append(generator.step(inputs.user_head[i:i + s], a[i:i + s], b[i:i + s]))
            _synchronize(flow)
            latencies.append(time.perf_counter() - tick)
    else:
        session = StreamingSession(generator, extractor)
        n = s * SAMPLES_PER_FRAME
        for i in range(0, count, s):
            k = i * SAMPLES_PER_FRAME
            tick = time.perf_counter()
            chunks.append(session.push(inputs.user_head[i:i + s], inputs.agent_wave[k:k + n],
                                       inputs.user_wave[k:k + n]))
            _synchronize(flow)
            latencies.append(time.perf_counter() - tick)
        a, b = session.features("agent"), session.features("user")
    motion = np.concatenate(chunks)
    if motion.shape[0] != count:
        raise RuntimeError(f"streaming produced {motion.shape[0]} of {count} frames")
    return Result(motion, a, b, latencies, seconds=float(sum(latencies)))


def _synchronize(module: torch.nn.Module) -> None:
    device = next(module.parameters()).device
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# --------------------------------------------------------------------------- outputs


def split_motion(motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, Dx) motion vector -> icosahedra (T, J, 12, 3) and shell points (T, V, 3)."""
    t = motion.shape[0]
    ico = motion[:, : NUM_JOINTS * 36].reshape(t, NUM_JOINTS, 12, 3)
    return ico, motion[:, NUM_JOINTS * 36:].reshape(t, -1, 3)


def head_gaze(positions: np.ndarray, rotations: np.ndarray, user_head: np.ndarray) -> np.ndarray:
    """Per-frame gaze score of the agent toward the user, from decoded joints (paper eq. 6-8)."""
    head = JOINT["head"]
    front, back = head_points(positions[:, head], rotations[:, head])
    return gaze_score(front, back, user_head).astype(np.float32)


def _atomic_savez(path: Path, arrays: dict[str, np.ndarray]) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_motion(path: Path, result: Result, inputs: Inputs, config: StreamConfig,
                 positions: np.ndarray, rotations: np.ndarray, gaze: np.ndarray,
                 settings: dict[str, Any]) -> Path:
    """motion.npz: icosahedra (T,J,12,3), shell (T,V,3), joint_positions (T,J,3),
    joint_rotations (T,J,3,3) global, world frame; gaze_score (T,) achieved; gaze_target
    (scalar, NaN = none); fps; user_head (T,2), agent_audio/user_audio (T,D) features,
    agent_speaking/user_speaking (T,) -- the inputs used; anchor (4,) [yaw, x, z, 0];
    source_* (where the inputs came from); settings (JSON string)."""
    ico, shell = split_motion(result.motion)
    arrays = {
        "icosahedra": ico, "shell": shell, "joint_positions": positions,
        "joint_rotations": rotations, "gaze_score": gaze,
        "gaze_target": np.float32(np.nan if config.gaze is None else config.gaze),
        "fps": np.int64(FPS), "user_head": inputs.user_head,
        "agent_audio": result.agent_audio, "user_audio": result.user_audio,
        "agent_speaking": inputs.agent_speaking, "user_speaking": inputs.user_speaking,
        "anchor": inputs.anchor.as_array(),
        "settings": np.array(json.dumps(settings, sort_keys=True)),
    }
    for key, value in inputs.source.items():
        arrays[f"source_{key}"] = np.asarray(value)
    _atomic_savez(path, arrays)
    return path


@dataclass
class Summary:
    frames: int
    fps: float
    latency_p50_ms: float | None
    latency_p99_ms: float | None
    chunks: int
    mean_gaze: float
    paths: list[Path]

    def lines(self, config: StreamConfig, offline: bool) -> list[str]:
        seconds = self.frames / FPS
        mode = "offline" if offline else "streaming"
        out = [f"{mode}: generated {self.frames} frames ({seconds:.1f} s of motion) at "
               f"{self.fps:.1f} frames/s ({config.steps} {config.solver} steps, "
               f"{config.steps * config.nfe_per_step} NFE per chunk, cfg {config.cfg_scale})"]
        if self.latency_p50_ms is not None:
            out.append(f"chunk latency: p50 {self.latency_p50_ms:.1f} ms, p99 "
                       f"{self.latency_p99_ms:.1f} ms over {self.chunks} chunks")
        target = "none" if config.gaze is None else f"{config.gaze:g}"
        out.append(f"mean gaze score {self.mean_gaze:.3f} (target {target})")
        out.append("wrote " + ", ".join(str(p) for p in self.paths))
        return out


def run(run_dir: str | Path, out: str | Path, config: StreamConfig, *,
        checkpoint: str | Path | None = None, device: str | None = None,
        shards: str | Path | None = None, split: str = "test", sequence: str | None = None,
        agent: str | None = None, start: int | None = None, frames: int | None = None,
        trajectory: str | Path | None = None, agent_audio: str | Path | None = None,
        user_audio: str | Path | None = None,
        agent_start: tuple[float, float, float] = (0.0, 0.0, 0.0),
        feature_options: dict[str, Any] | None = None, offline: bool = False,
        animation: bool = True, speed: str = "fp32", echo: Callable[[str], None] = print) -> Summary:
    """Everything ``sarah-generate`` does: load, read inputs, generate, write, plot.

    speed: the inference fast path of ``fast.optimize_for_inference`` ("fp32" is exact; "int8"
    stays within 1 mm of it and is the real-time setting on a CPU; "none" the plain models)."""
    from .fast import optimize_for_inference
    from .plots import animate_skeleton, plot_topview

    try:
        check_gaze(config.gaze)
    except ValueError as exc:
        raise GenerateError(str(exc)) from None
    models, ckpt = load_run(run_dir, checkpoint, device)
    if speed != "none":
        models = optimize_for_inference(models, mode=speed, stream_config=config)
    stride = models.vae.stride
    if shards is not None:
        if trajectory is not None or agent_audio is not None or user_audio is not None:
            raise GenerateError("give either --shards (with --sequence and --agent) or the raw "
                                "files, not both")
        inputs = shard_inputs(shards, split, sequence, agent, models.features,
                              models.flow.audio_dim, stride, start,
                              DEFAULT_FRAMES if frames is None else frames)
        extractor = None
    else:
        if trajectory is None or agent_audio is None or user_audio is None:
            raise GenerateError("give --shards/--sequence/--agent, or --user-trajectory with "
                                "--agent-audio and --user-audio")
        inputs = raw_inputs(trajectory, agent_audio, user_audio, stride, frames, agent_start)
        extractor = make_extractor(models.features, feature_options)
    where = (f"{inputs.source['sequence']} (agent {inputs.source['agent']}, from frame "
             f"{inputs.source['start']})" if shards is not None else "raw files")
    echo(f"checkpoint {ckpt} (step {models.step}, features {models.features!r}) on "
         f"{next(models.flow.parameters()).device}; {inputs.frames} frames of {where}")
    result = generate(models, inputs, config, offline, extractor)

    positions, rotations = icosahedron.decode(split_motion(result.motion)[0])
    gaze = head_gaze(positions, rotations, inputs.user_head)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    settings = {"run": str(run_dir), "checkpoint": str(ckpt), "step": models.step,
                "features": models.features, "offline": offline, "stream": asdict(config)}
    paths = [write_motion(out / "motion.npz", result, inputs, config, positions, rotations,
                          gaze, settings)]
    head = JOINT["head"]
    facing = rotations[:, head, :, 2][:, [0, 2]]
    target = "none" if config.gaze is None else f"{config.gaze:g}"
    paths.append(plot_topview(out / "topview.png", positions[:, head][:, [0, 2]], facing,
                              inputs.user_head, FPS,
                              title=f"gaze target {target}, mean gaze score {gaze.mean():.2f}"))
    if animation:
        paths.append(animate_skeleton(out / "skeleton.gif", positions, JOINT_PARENTS,
                                      inputs.user_head, inputs.agent_speaking,
                                      inputs.user_speaking, FPS))
    lat = np.asarray(result.latencies) * 1000.0
    summary = Summary(inputs.frames, result.fps,
                      float(np.percentile(lat, 50)) if lat.size else None,
                      float(np.percentile(lat, 99)) if lat.size else None,
                      int(lat.size), float(gaze.mean()), paths)
    for line in summary.lines(config, offline):
        echo(line)
    return summary
