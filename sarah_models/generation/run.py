"""The library behind ``sarah-generate``: load a run, read inputs (``inputs.py``: a shard
window or raw files), generate (streaming or offline), write motion and plots (``outputs.py``,
``plots.py``).

Outputs in ``out``: ``motion.npz`` (see ``write_motion``), ``topview.png``, ``skeleton.gif``.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from sarah_data import icosahedron
from sarah_data.constants import FPS, JOINT, JOINT_PARENTS, SAMPLES_PER_FRAME
from sarah_data.gaze import FACING_AXIS
from sarah_data.skeleton import HEAD, MotionLayout

from ..config import StreamConfig, check_gaze
from ..sampling.decoding import body_bone_lengths, takes_bone_lengths
from ..sampling.stream import StreamingGenerator, StreamingSession, offline_with_latents
from ..training.checkpoint import LoadedModels, load_models
from ..training.model_file import MODEL_FILE, flow_source, load_model_file
from .inputs import (
    DEFAULT_FRAMES,
    GenerateError,
    Inputs,
    make_extractor,
    raw_inputs,
    shard_inputs,
)
from .outputs import Result, Summary, head_gaze, motion_figures, write_motion

# --------------------------------------------------------------------------- checkpoint


def load_run(run: str | Path, checkpoint: str | Path | None = None,
             device: str | None = None, need_flow: bool = True) -> tuple[LoadedModels, Path]:
    """The flow-stage models of a run: ``checkpoint`` when given (a training checkpoint or a
    ``.safetensors`` model file), else the run's model file ``run/model.safetensors`` (its
    finished model, with the decoding it was written with; loads without pickle), else
    ``run/flow.pt`` (``model_file.flow_source``); ``run`` may itself be such a file (a shared or
    shipped model, ``sarah_models.pretrained``); ``need_flow=False`` also accepts a VAE-stage
    checkpoint."""
    run = Path(run)
    if run.is_file():
        if checkpoint is not None:
            raise GenerateError(f"{run} is a model file; --checkpoint {checkpoint} needs a run "
                                f"folder")
        checkpoint = run
    elif not run.is_dir():
        raise GenerateError(f"{run}: no such run folder or model file")
    if checkpoint is None:
        path = flow_source(run)
    else:
        path = Path(checkpoint)
        if not path.is_file() and (run / path).is_file():
            path = run / path
    if not path.is_file():
        raise GenerateError(f"{path}: no such checkpoint (train the flow stage first, or pass "
                            f"--checkpoint; a shared model is {MODEL_FILE})")
    try:
        if path.suffix == ".safetensors":
            models = load_model_file(path, device=device)
        else:
            models = load_models(path, device=device)
    except (ValueError, KeyError, RuntimeError) as exc:
        raise GenerateError(f"{path}: cannot load checkpoint ({exc})") from None
    if need_flow and models.flow is None:
        raise GenerateError(f"{path}: a {models.stage}-stage checkpoint; generation needs the "
                            f"flow stage (flow.pt)")
    return models, path


# Whose bones the decoding puts the generated motion on (``sampling.decoding.stream_decoding``).
SKELETONS = {
    "agent": "the agent's own: --body-model's, else a shard window's person's rest skeleton, so "
             "that the motion is the body its export poses; else (raw inputs) the training data's",
    "training": "the training data's mean bone lengths, whoever the agent is (what sarah-eval "
                "scores)",
}


def skeleton_of(models: LoadedModels, inputs: Inputs, skeleton: str,
                avatar=None) -> tuple[np.ndarray | None, str]:
    """The agent's bone lengths the decoding takes (None: the training data's) and a phrase
    saying whose bones the motion is on: ``avatar``'s (a ``BodyShape``: --body-model) where
    given, else the input's person's."""
    if not takes_bone_lengths(models.vae):
        return None, "the decoder's own bones (this model's decoding keeps no bone lengths)"
    rest = avatar.rest_joints if avatar is not None else (inputs.body_shape or {}).get("rest_joints")
    if skeleton == "training" or rest is None:
        why = "" if skeleton == "training" else " (the input has no person's body)"
        return None, "the training data's mean bone lengths" + why
    whose = (f"the avatar's ({avatar.source})" if avatar is not None
             else "the agent's own (its rest skeleton in the shards)")
    return body_bone_lengths(models.vae, rest), whose


def generate(models: LoadedModels, inputs: Inputs, config: StreamConfig, offline: bool = False,
             extractor=None, policy=None, bone_lengths=None) -> Result:
    """Run the streaming generator chunk by chunk (or the offline protocol) on ``inputs``.
    ``policy`` (an ``accel.ThreadPolicy``) sets the intra-op threads before every chunk;
    ``bone_lengths`` is the skeleton the motion is decoded on (``skeleton_of``)."""
    vae, flow, normalizer = models.vae, models.flow, models.normalizer
    apply_threads = (lambda: None) if policy is None else policy.apply
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
        apply_threads()
        tick = time.perf_counter()
        motion, z = offline_with_latents(vae, flow, normalizer, inputs.user_head, a, b, config,
                                         inputs.anchor, bone_lengths)
        _synchronize(flow)
        return Result(motion, a, b, seconds=time.perf_counter() - tick,
                      latents=z.float().cpu().numpy())

    generator = StreamingGenerator(vae, flow, normalizer, config, inputs.anchor, bone_lengths)
    chunks, latencies, latents = [], [], []
    if inputs.agent_audio is not None:
        a, b = inputs.agent_audio, inputs.user_audio
        for i in range(0, count, s):
            tick = time.perf_counter()
            apply_threads()
            chunks.append(generator.step(inputs.user_head[i:i + s], a[i:i + s], b[i:i + s]))
            _synchronize(flow)
            latencies.append(time.perf_counter() - tick)
            latents.append(generator.last_latent)
    else:
        session = StreamingSession(generator, extractor)
        n = s * SAMPLES_PER_FRAME
        for i in range(0, count, s):
            k = i * SAMPLES_PER_FRAME
            tick = time.perf_counter()
            apply_threads()
            chunks.append(session.push(inputs.user_head[i:i + s], inputs.agent_wave[k:k + n],
                                       inputs.user_wave[k:k + n]))
            _synchronize(flow)
            latencies.append(time.perf_counter() - tick)
        a, b = session.features("agent"), session.features("user")
    motion = np.concatenate(chunks)
    if motion.shape[0] != count:
        raise RuntimeError(f"streaming produced {motion.shape[0]} of {count} frames")
    # A push of raw audio may generate no block or several: latents are kept from features only.
    z = torch.stack(latents).float().cpu().numpy() if latents else None
    return Result(motion, a, b, latencies, seconds=float(sum(latencies)), latents=z)


def _synchronize(module: torch.nn.Module) -> None:
    device = next(module.parameters()).device
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run(run_dir: str | Path, out: str | Path, config: StreamConfig, *,
        checkpoint: str | Path | None = None, device: str | None = None,
        shards: str | Path | None = None, split: str = "test", sequence: str | None = None,
        agent: str | None = None, start: int | None = None, frames: int | None = None,
        trajectory: str | Path | None = None, agent_audio: str | Path | None = None,
        user_audio: str | Path | None = None,
        agent_start: tuple[float, float, float] = (0.0, 0.0, 0.0),
        feature_options: dict[str, Any] | None = None, offline: bool = False, pad: bool = False,
        animation: bool = True, speed: str = "fp32", threads: int | None = None,
        skeleton: str = "agent", body_model: str | Path | None = None, betas=None,
        echo: Callable[[str], None] = print) -> Summary:
    """Everything ``sarah-generate`` does: load, read inputs, generate, write, plot.

    speed: the inference fast path of ``accel.optimize_for_inference`` ("fp32" is exact; "int8"
    stays within 1 mm of it and is the real-time setting on a CPU; "none" the plain models).
    threads: intra-op threads on a CPU; None picks them from the cores other processes leave
    free (``accel.ThreadPolicy``), re-measured while streaming. skeleton: whose bones the motion
    is on (``SKELETONS``). body_model, betas: the agent is that SMPL-X body (an avatar's) in
    place of the input's person (``sarah_data.export.motion.avatar_shape``)."""
    from ..accel import ThreadPolicy, optimize_for_inference
    from ..accel.threads import stream_probe
    from .plots import animate_skeleton, plot_topview

    try:
        check_gaze(config.gaze)
    except ValueError as exc:
        raise GenerateError(str(exc)) from None
    if skeleton not in SKELETONS:
        raise GenerateError(f"unknown skeleton {skeleton!r}; choose from {', '.join(SKELETONS)}")
    avatar = None
    if body_model is not None:  # read before any generating work: a bad file is one line now
        from sarah_data.export.motion import avatar_shape

        avatar = avatar_shape(body_model, betas, "sarah-generate --body-model")
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
        warnings: list[str] = []
        inputs = raw_inputs(trajectory, agent_audio, user_audio, stride, frames, agent_start,
                            pad=pad, warnings=warnings)
        for warning in warnings:
            echo(f"warning: {warning}")
        extractor = make_extractor(models.features, feature_options)
    if avatar is not None:
        inputs.body_shape = {"betas": avatar.betas, "rest_joints": avatar.rest_joints,
                             "gender": avatar.gender, "body_shape_source": avatar.source}
    where = (f"{inputs.source['sequence']} (agent {inputs.source['agent']}, from frame "
             f"{inputs.source['start']})" if shards is not None else "raw files")
    policy, on = None, str(next(models.flow.parameters()).device)
    if on == "cpu":
        policy = ThreadPolicy(threads)
        if not offline:
            policy.calibrate(stream_probe(models, config))
        on = f"cpu, threads {policy.describe()}"
    bone_lengths, bones = skeleton_of(models, inputs, skeleton, avatar)
    echo(f"checkpoint {ckpt} (step {models.step}, features {models.features!r}) on "
         f"{on}; {inputs.frames} frames of {where}; skeleton: {bones}")
    result = generate(models, inputs, config, offline, extractor, policy, bone_lengths)

    positions, rotations = icosahedron.decode(MotionLayout.from_width(result.motion.shape[-1])
                                              .split(result.motion)[0])
    gaze = head_gaze(positions, rotations, inputs.user_head)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    settings = {"run": str(run_dir), "checkpoint": str(ckpt), "step": models.step,
                "features": models.features, "offline": offline, "stream": asdict(config),
                "skeleton": bones}
    paths = [write_motion(out / "motion.npz", result, inputs, config, positions, rotations,
                          gaze, settings)]
    head = JOINT[HEAD]
    facing = rotations[:, head, :, FACING_AXIS][:, [0, 2]]
    target = "none" if config.gaze is None else f"{config.gaze:g}"
    paths.append(plot_topview(out / "topview.png", positions[:, head][:, [0, 2]], facing,
                              inputs.user_head, FPS,
                              title=f"gaze target {target}, mean gaze score {gaze.mean():.2f}"))
    if animation:
        echo(f"drawing {out / 'skeleton.gif'} ({inputs.frames} frames; --no-animation skips it)")
        paths.append(animate_skeleton(out / "skeleton.gif", positions, JOINT_PARENTS,
                                      inputs.user_head, inputs.agent_speaking,
                                      inputs.user_speaking, FPS))
    lat = np.asarray(result.latencies) * 1000.0
    reference = None
    if inputs.reference_icosahedra is not None:
        reference = motion_figures(*icosahedron.decode(inputs.reference_icosahedra.astype(np.float64)),
                                   inputs.user_head)
    summary = Summary(inputs.frames, result.fps,
                      float(np.percentile(lat, 50)) if lat.size else None,
                      float(np.percentile(lat, 99)) if lat.size else None,
                      int(lat.size), float(gaze.mean()), paths,
                      motion_figures(positions, rotations, inputs.user_head, gaze), reference)
    for line in summary.lines(config, offline):
        echo(line)
    return summary
