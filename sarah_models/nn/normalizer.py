"""Per-channel standardization held as module buffers, so it travels inside checkpoints.

Keys used by the models: ``motion`` (Dx), ``user_head`` (2), ``audio`` (Da, shared by agent and
user audio unless ``agent_audio``/``user_audio`` have their own) and, after the VAE stage,
``latent`` (Dz: the frozen encoder's latents, standardized so the flow starts from N(0, I)).
The gaze score is in [-1, 1] already and is not standardized. ``bone_length`` (the training
split's mean length of every bone, ``MotionLayout.bones`` order) standardizes nothing: it travels
here, with the other statistics of the training data, for the rigid decoding
(``sampling.rigid_skeleton``).

Root-relative motion (``set_root_relative``; ``vae.root_relative``, not in the paper). Where the
normalizer holds ``motion_root`` (the point indices of the root's icosahedron), ``motion`` is
standardized root-relative: every other point's x and z less the root's (the mean of those
points), the root's own points as they are, so the map is exact both ways. The agents walk, so
an absolute x/z channel's std is ~1 m and a head turn's 10 cm offsets are a tenth of it, lost
among channels that move together; relative to the root they are most of their channel's range.
The motion's statistics are then the root-relative channels' (fitted on the first training
batches by ``training.stages``).

Root steps (``set_root_relative(..., steps=True)``; ``vae.root_steps``). The root's own points
then carry their floor displacement (x, z) since the frame before instead of their place: time
is the motion's second-to-last axis, and before a window's first frame is the window frame's
origin, where the agent starts. ``denormalize`` sums the steps back into places, from the origin
or from ``before``, the frame a stream decoded last, so a stream decoded a block at a time and
the same frames decoded at once are the same motion.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import torch
from torch import Tensor, nn

# Batch key -> candidate statistics keys, first present wins.
BATCH_STATS = {
    "motion": ("motion",),
    "user_head": ("user_head",),
    "agent_audio": ("agent_audio", "audio"),
    "user_audio": ("user_audio", "audio"),
}


class Normalizer(nn.Module):
    def __init__(self, stats: Mapping[str, tuple[np.ndarray | Tensor, np.ndarray | Tensor]] = (),
                 min_std: float = 1e-6) -> None:
        super().__init__()
        self.min_std = min_std
        for key, (mean, std) in dict(stats).items():
            self.set(key, mean, std)

    @property
    def keys(self) -> list[str]:
        return sorted(name[: -len("_mean")] for name, _ in self.named_buffers()
                      if name.endswith("_mean"))

    def set(self, key: str, mean: np.ndarray | Tensor, std: np.ndarray | Tensor) -> None:
        """Register (or replace) the statistics of ``key``; a std below min_std becomes 1 so
        constant channels pass through centred instead of exploding."""
        mean_t = torch.as_tensor(np.asarray(mean, dtype=np.float32)).reshape(-1)
        std_t = torch.as_tensor(np.asarray(std, dtype=np.float32)).reshape(-1)
        if mean_t.shape != std_t.shape:
            raise ValueError(f"stats {key!r}: mean {tuple(mean_t.shape)} and std "
                             f"{tuple(std_t.shape)} differ")
        if not (torch.isfinite(mean_t).all() and torch.isfinite(std_t).all()):
            raise ValueError(f"stats {key!r} contain non-finite values")
        std_t = torch.where(std_t < self.min_std, torch.ones_like(std_t), std_t)
        device = next(self.buffers(), mean_t).device
        self.register_buffer(f"{key}_mean", mean_t.to(device))
        self.register_buffer(f"{key}_std", std_t.to(device))

    def _stats(self, key: str, x: Tensor) -> tuple[Tensor, Tensor]:
        if not hasattr(self, f"{key}_mean"):
            raise KeyError(f"no normalization statistics for {key!r}; have {self.keys}")
        mean, std = getattr(self, f"{key}_mean"), getattr(self, f"{key}_std")
        if x.shape[-1] != mean.shape[0]:
            raise ValueError(f"{key!r} has {x.shape[-1]} channels, statistics have {mean.shape[0]}")
        return mean.to(x.dtype), std.to(x.dtype)

    def normalize(self, key: str, x: Tensor) -> Tensor:
        mean, std = self._stats(key, x)
        if key == "motion":
            x = self.relative_motion(x)
        return (x - mean) / std

    def denormalize(self, key: str, x: Tensor, before: Tensor | None = None) -> Tensor:
        """Statistics' units back to the data's. For root-step motion (module docstring),
        ``before`` (..., 3P) is the frame before ``x``'s first, in metres; None: the origin."""
        mean, std = self._stats(key, x)
        x = x * std + mean
        if key == "motion" and self.root_relative:
            if self.root_steps:
                x = self.root_places(x, before)
            x = x + self.root_offset(x)  # the root's own points are absolute in both forms
        return x

    @property
    def root_relative(self) -> bool:
        return hasattr(self, "motion_root")

    @property
    def root_steps(self) -> bool:
        return hasattr(self, "motion_root_steps")

    def set_root_relative(self, root_points: Tensor | np.ndarray | list[int],
                          steps: bool = False) -> None:
        """Standardize ``motion`` root-relative from now on, the root being the mean of these
        points (indices of 3-channel points in the motion vector), with ``steps`` the root's
        points as their floor steps (module docstring). The motion statistics must then be the
        root-relative channels'."""
        points = torch.as_tensor(np.asarray(root_points, dtype=np.int64)).reshape(-1)
        if points.numel() == 0 or bool((points < 0).any()):
            raise ValueError(f"root points must be non-negative point indices, got {points.tolist()}")
        device = next(self.buffers(), points).device
        self.register_buffer("motion_root", points.to(device))
        if steps:  # a buffer, so that the form travels in checkpoints with the statistics
            self.register_buffer("motion_root_steps", torch.ones(1, dtype=torch.bool, device=device))

    def relative_motion(self, x: Tensor) -> Tensor:
        """Motion (..., 3P) as this normalizer standardizes it: root-relative where it is so, else
        as given (what its statistics describe); with root steps, (..., T, 3P)."""
        if not self.root_relative:
            return x
        relative = x - self.root_offset(x)
        if not self.root_steps:
            return relative
        before = torch.cat([torch.zeros_like(x[..., :1, :]), x[..., :-1, :]], dim=-2)
        return torch.where(self.root_floor(x), x - before, relative)

    def root_places(self, steps: Tensor, before: Tensor | None = None) -> Tensor:
        """Motion (..., T, 3P) whose root points hold their floor steps -> the same with their
        places: the steps summed over time from ``before``'s (..., 3P) places, or the origin."""
        floor = self.root_floor(steps)
        places = torch.cumsum(torch.where(floor, steps, 0.0), dim=-2)
        if before is not None:
            places = places + torch.where(floor, before.to(steps.dtype), 0.0).unsqueeze(-2)
        return torch.where(floor, places, steps)

    def root_floor(self, x: Tensor) -> Tensor:
        """(3P,) bool: the root's points' x and z channels of a motion like ``x``."""
        channels = torch.zeros(x.shape[-1] // 3, 3, dtype=torch.bool, device=x.device)
        channels[self.motion_root, 0] = True
        channels[self.motion_root, 2] = True
        return channels.flatten()

    def root_offset(self, x: Tensor) -> Tensor:
        """(..., 3P) -> the (..., 3P) offset that is the root's (x, 0, z) on every point but the
        root's own and 0 on those."""
        points = x.unflatten(-1, (-1, 3))
        root = points[..., self.motion_root, :].mean(-2, keepdim=True)
        others = torch.ones(points.shape[-2], 1, dtype=x.dtype, device=x.device)
        others[self.motion_root] = 0
        floor = torch.tensor([1.0, 0.0, 1.0], dtype=x.dtype, device=x.device)
        return (root * floor * others).flatten(-2)

    def stats_key(self, batch_key: str) -> str:
        for key in BATCH_STATS[batch_key]:
            if hasattr(self, f"{key}_mean"):
                return key
        raise KeyError(f"no normalization statistics for {batch_key!r} (looked for "
                       f"{BATCH_STATS[batch_key]}); have {self.keys}")

    def normalize_batch(self, batch: Mapping[str, Tensor], device: torch.device | str) -> dict[str, Tensor]:
        """Model inputs from a dataset batch: standardized motion, user_head, agent/user audio,
        and gaze as (B, T, 1), all float32 on ``device``."""
        out = {}
        for key in BATCH_STATS:
            if key in batch:
                x = batch[key].to(device=device, dtype=torch.float32, non_blocking=True)
                out[key] = self.normalize(self.stats_key(key), x)
        if "gaze" in batch:
            gaze = batch["gaze"].to(device=device, dtype=torch.float32, non_blocking=True)
            out["gaze"] = gaze[..., None] if gaze.dim() == 2 else gaze
        return out

    @classmethod
    def from_state_dict(cls, state: Mapping[str, Tensor]) -> "Normalizer":
        """Rebuild from ``state_dict()`` (the buffer names carry the keys)."""
        keys = [name[: -len("_mean")] for name in state if name.endswith("_mean")]
        norm = cls()
        for key in keys:
            norm.register_buffer(f"{key}_mean", state[f"{key}_mean"].clone())
            norm.register_buffer(f"{key}_std", state[f"{key}_std"].clone())
        if "motion_root" in state:
            norm.set_root_relative(state["motion_root"].clone(), steps="motion_root_steps" in state)
        return norm
