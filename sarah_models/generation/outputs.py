"""What a generation writes: motion.npz, and the summary lines ``sarah-generate`` prints."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sarah_data.atomic import atomic_path
from sarah_data.constants import FPS, JOINT, NUM_BETAS
from sarah_data.gaze import gaze_score, head_points
from sarah_data.skeleton import HEAD, MotionLayout

from ..config import StreamConfig
from .inputs import Inputs


@dataclass
class Result:
    motion: np.ndarray  # (T, Dx) world-frame motion vector (icosahedra then shell)
    agent_audio: np.ndarray  # (T, D) the features the model saw
    user_audio: np.ndarray
    latencies: list[float] = field(default_factory=list)  # seconds per chunk (streaming)
    seconds: float = 0.0  # total generation time
    # (K, Dz) the flow's standardized latents, one per block of s frames (None: not recorded,
    # e.g. a remote stream): where a sample differs from the encoder's latents of real motion
    # (scripts/motion_anatomy.py)
    latents: np.ndarray | None = None

    @property
    def fps(self) -> float:
        return self.motion.shape[0] / max(self.seconds, 1e-12)


def head_gaze(positions: np.ndarray, rotations: np.ndarray, user_head: np.ndarray) -> np.ndarray:
    """Per-frame gaze score of the agent toward the user, from decoded joints (paper eq. 6-8)."""
    head = JOINT[HEAD]
    front, back = head_points(positions[:, head], rotations[:, head])
    return gaze_score(front, back, user_head).astype(np.float32)


def _atomic_savez(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def write_motion(path: Path, result: Result, inputs: Inputs, config: StreamConfig,
                 positions: np.ndarray, rotations: np.ndarray, gaze: np.ndarray,
                 settings: dict[str, Any]) -> Path:
    """motion.npz: icosahedra (T,J,12,3), shell (T,V,3), joint_positions (T,J,3),
    joint_rotations (T,J,3,3) global, world frame; gaze_score (T,) achieved; gaze_target
    (scalar, NaN = none); fps; user_head (T,2), agent_audio/user_audio (T,D) features,
    agent_speaking/user_speaking (T,) -- the inputs used; anchor (4,) [yaw, x, z, 0];
    source_* (where the inputs came from); settings (JSON string); the agent's body for
    export: betas (B,), rest_joints (55, 3) (shard inputs only), gender, body_shape_source."""
    ico, shell = MotionLayout.from_width(result.motion.shape[-1]).split(result.motion)
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
    shape = inputs.body_shape or {"betas": np.zeros(NUM_BETAS, np.float32), "gender": "neutral",
                                  "body_shape_source": "neutral zero betas (no person: raw inputs "
                                                       "or shards without body shapes)"}
    arrays.update({key: np.asarray(value) for key, value in shape.items()})
    _atomic_savez(path, arrays)
    return path


def motion_figures(positions: np.ndarray, rotations: np.ndarray, user_head: np.ndarray,
                   gaze: np.ndarray | None = None) -> dict[str, float]:
    """What a person sees first in a clip, by the evaluation's own metrics: the mean gaze score
    toward the user (``gaze``, the per-frame scores, when already computed), foot slide, wrist
    and pelvis speed (cm/s: how much it gestures and walks), the distance it keeps from the user
    and how fast it walks toward or away from them (cm, cm/s) and bone-length error (p95, %)."""
    from ..evaluation.metrics import foot_slide, wrist_speed
    from ..evaluation.metrics.bone_length import bone_length_error
    from ..evaluation.metrics.pelvis_speed import pelvis_speed
    from ..evaluation.metrics.radial_speed import radial_speed
    from ..evaluation.metrics.user_distance import user_distance

    if gaze is None:
        gaze = head_gaze(positions, rotations, user_head)
    return {"gaze score": float(gaze.mean()),
            "foot slide": foot_slide(positions), "wrist speed": wrist_speed(positions) * 100.0,
            "pelvis speed": pelvis_speed(positions) * 100.0,
            "user distance": user_distance(positions, user_head) * 100.0,
            "radial speed": radial_speed(positions, user_head) * 100.0,
            "bone length": bone_length_error(positions)}


FIGURE_FORMATS = {"gaze score": "{:.3f}", "foot slide": "{:.3f}", "wrist speed": "{:.1f} cm/s",
                  "pelvis speed": "{:.1f} cm/s", "user distance": "{:.0f} cm",
                  "radial speed": "{:.1f} cm/s", "bone length": "{:.1f} % (p95)"}


@dataclass
class Summary:
    frames: int
    fps: float
    latency_p50_ms: float | None
    latency_p99_ms: float | None
    chunks: int
    mean_gaze: float
    paths: list[Path]
    figures: dict[str, float] = field(default_factory=dict)
    reference_figures: dict[str, float] | None = None  # the real agent of the same window

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
        if self.figures:
            parts = []
            for name, value in self.figures.items():
                text = f"{name} {FIGURE_FORMATS[name].format(value)}"
                if self.reference_figures is not None:
                    text += f" (ground truth {FIGURE_FORMATS[name].format(self.reference_figures[name])})"
                parts.append(text)
            out.append("generated motion: " + ", ".join(parts))
        out.append("wrote " + ", ".join(str(p) for p in self.paths))
        return out
