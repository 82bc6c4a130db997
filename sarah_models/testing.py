"""What tests and benchmarks share: models with random weights, synthetic inputs, and how far
one model's generated stream moves from another's (the tolerance checks of every speed-up).

Random weights: AdaLN-Zero starts every block and the output at zero, which would make the flow
predict x1 = 0 whatever its input; ``random_models`` draws those parameters N(0, init_std) so
that conditioning, noise and history all matter, as in a trained model.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from sarah_data import icosahedron
from sarah_data.constants import AUDIO_SAMPLE_RATE, JOINT, SAMPLES_PER_FRAME
from sarah_data.skeleton import HEAD, MotionLayout

from .config import RunConfig, StreamConfig
from .nn.flow import FlowModel
from .nn.normalizer import Normalizer
from .nn.vae import CausalVAE
from .sampling.stream import StreamingGenerator
from .training.checkpoint import build_models, unpack_models


def random_models(size: str = "paper", audio_dim: int = 80, shell_points: int = 256,
                  seed: int = 0, motion_std: float = 0.1, *, init_std: float = 0.02,
                  audio_mean: float = -5.0, audio_std: float = 3.0, latent_mean_std: float = 0.0,
                  overrides: tuple[str, ...] = ()) -> tuple[CausalVAE, FlowModel, Normalizer]:
    """VAE + flow of the ``size`` preset with random weights, in eval mode, with a normalizer.

    AdaLN-Zero starts every block and the output at zero, which would make the flow predict
    x1 = 0 whatever its input; those parameters are drawn N(0, init_std) so that conditioning,
    noise and history all matter, as in a trained model. The normalizer: a standing pose as the
    motion mean with per-coordinate std ``motion_std`` m, constant audio statistics, and latent
    means drawn N(0, latent_mean_std) with unit std. ``overrides``: ``section.field=value``
    strings applied to the preset (``RunConfig.with_overrides``)."""
    config = RunConfig.preset(size).with_overrides(overrides)
    layout = MotionLayout(shell_points=shell_points)
    dims = {"motion": layout.width, "audio": audio_dim}
    torch.manual_seed(seed)
    vae, flow = build_models(config, dims)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in flow.parameters():
            if not p.any():
                p.copy_(torch.randn(p.shape, generator=g) * init_std)
    rng = np.random.default_rng(seed)
    joints = layout.num_joints
    positions = np.stack([np.zeros(joints), np.linspace(0.1, 1.7, joints), np.zeros(joints)], 1)
    ico = icosahedron.encode(positions, np.broadcast_to(np.eye(3), (joints, 3, 3)))
    shell = rng.normal(0, 0.2, (shell_points, 3)) + [0, 1, 0]
    dz = config.vae.latent_dim
    normalizer = Normalizer({
        "motion": (np.concatenate([ico.reshape(-1), shell.reshape(-1)]),
                   np.full(dims["motion"], motion_std)),
        "user_head": (np.zeros(2), np.full(2, 1.5)),
        "audio": (np.full(audio_dim, audio_mean), np.full(audio_dim, audio_std)),
        "latent": (rng.normal(0, latent_mean_std, dz) if latent_mean_std else np.zeros(dz), np.ones(dz)),
    })
    return vae.eval(), flow.eval(), normalizer


def arc_trajectory(frames: int) -> np.ndarray:
    """A user walking an arc 1.6 m in front of the agent, (frames, 2) float32 floor (x, z)."""
    angle = np.linspace(-0.8, 0.8, frames)
    return np.stack([1.6 * np.sin(angle), 1.6 * np.cos(angle)], 1).astype(np.float32)


def synthetic_inputs(frames: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A user walking an arc (frames, 2) and two 48 kHz tracks of amplitude-modulated noise."""
    rng = np.random.default_rng(seed)
    n = frames * SAMPLES_PER_FRAME
    envelope = 0.5 + 0.5 * np.sin(2 * np.pi * 4.5 * np.arange(n) / AUDIO_SAMPLE_RATE)
    return {
        "user_head": arc_trajectory(frames),
        "agent_wave": (0.1 * envelope * rng.standard_normal(n)).astype(np.float32),
        "user_wave": (0.05 * rng.standard_normal(n)).astype(np.float32),
    }


@dataclass(frozen=True)
class Deviation:
    """How far a generated stream moves from the reference model's, for the same inputs/seed.

    Joint positions are the icosahedron centroids in metres (world frame); reported in mm.
    ``motion_scale_mm`` is the reference's RMS joint distance from its own mean pose, the size
    of the motion the deviation is compared with."""

    frames: int
    max_joint_mm: float
    mean_joint_mm: float
    motion_scale_mm: float
    wrist_speed_delta: float  # m/s, |optimized - reference| of metrics.wrist_speed
    head_angle_delta: float  # |optimized - reference| of metrics.head_angle (gaze score)

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def stream_inputs(frames: int, audio_dim: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Deterministic test inputs: a user walking an arc around the agent and two noise-like
    standardized feature tracks; (frames, 2), (frames, Da), (frames, Da) float32."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(frames, audio_dim))
    b = rng.normal(size=(frames, audio_dim))
    return arc_trajectory(frames), a.astype(np.float32), b.astype(np.float32)


def generate_stream(models, inputs: tuple[np.ndarray, np.ndarray, np.ndarray],
                    config: StreamConfig = StreamConfig()) -> np.ndarray:
    """World motion (T, Dx) streamed chunk by chunk through ``StreamingGenerator``."""
    vae, flow, normalizer = unpack_models(models)
    generator = StreamingGenerator(vae, flow, normalizer, config)
    head, a, b = inputs
    s = generator.stride
    return np.concatenate([generator.step(head[i:i + s], a[i:i + s], b[i:i + s])
                           for i in range(0, head.shape[0] - head.shape[0] % s, s)])


def without_foot_lock(models):
    """``models`` (LoadedModels, changed in place) decoding without the foot lock, for precision
    comparisons: its steps fire on thresholds, so a micrometre of kernel rounding can fire one a
    frame earlier and move a foot by centimetres, which says nothing about the kernels."""
    import dataclasses

    models.vae.config = dataclasses.replace(models.vae.config, foot_lock=0.0)
    return models


def stream_deviation(reference, optimized, frames: int = 64, seed: int = 0,
                     config: StreamConfig = StreamConfig(),
                     inputs: tuple[np.ndarray, ...] | None = None,
                     optimized_config: StreamConfig | None = None) -> Deviation:
    """Stream the same inputs (same seed) through both models; compare their joints and the
    cheap metrics (wrist speed, head angle). Both are ``(vae, flow, normalizer)`` or
    LoadedModels; the normalizer of ``reference`` is used for both when ``optimized`` has none.
    ``optimized_config`` (default ``config``) streams the optimized side with other settings,
    e.g. fewer solver steps."""
    from .evaluation.metrics import head_angle, wrist_speed

    ref_vae, ref_flow, ref_norm = unpack_models(reference)
    opt_vae, opt_flow, opt_norm = unpack_models(optimized)
    if inputs is None:
        inputs = stream_inputs(frames, ref_flow.audio_dim, seed)
    ref = generate_stream((ref_vae, ref_flow, ref_norm), inputs, config)
    opt = generate_stream((opt_vae, opt_flow, opt_norm or ref_norm), inputs,
                          optimized_config or config)
    layout = MotionLayout.from_width(ref.shape[-1])
    p_ref, p_opt = layout.joint_positions(ref), layout.joint_positions(opt)
    dist = np.linalg.norm(p_opt.astype(np.float64) - p_ref, axis=-1) * 1000.0
    scale = np.sqrt(np.mean(np.sum((p_ref - p_ref.mean(axis=0)) ** 2, axis=-1))) * 1000.0
    head = JOINT[HEAD]
    angles = []
    for motion in (ref, opt):
        pos, rot = icosahedron.decode(layout.split(motion)[0].astype(np.float64))
        angles.append(head_angle(pos[:, head], rot[:, head], inputs[0][: motion.shape[0]]))
    return Deviation(frames=int(ref.shape[0]), max_joint_mm=float(dist.max()),
                     mean_joint_mm=float(dist.mean()), motion_scale_mm=float(scale),
                     wrist_speed_delta=abs(wrist_speed(p_opt) - wrist_speed(p_ref)),
                     head_angle_delta=abs(angles[1] - angles[0]))
