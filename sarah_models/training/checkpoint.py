"""Checkpoints: atomic writes, ``weights_only=True`` loads, RNG capture, model rebuilding.

A checkpoint is one dict of plain values and tensors::

    format "sarah-checkpoint", version 1, stage "vae" | "flow", step, total_steps
    config     RunConfig.to_dict()              dims {"motion": Dx, "audio": Da}
    features   audio feature extractor name     normalizer  Normalizer.state_dict()
    vae        CausalVAE.state_dict()           flow        FlowModel.state_dict() (flow stage)
    optimizer  optimizer.state_dict()           generator   training torch.Generator state
    rng        {"python", "numpy", "torch", "cuda"} global RNG states
    trained    with train.ema_decay: the stage's trained weights, its own key then holding
               their average (``weight_average``), which everything but --resume reads

The flow checkpoint carries its frozen VAE, so ``runs/NAME/flow.pt`` alone is enough to generate.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sarah_data.atomic import atomic_path

from ..config import RunConfig
from ..nn.flow import FlowModel
from ..nn.normalizer import Normalizer
from ..nn.vae import CausalVAE

FORMAT = "sarah-checkpoint"
VERSION = 1


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> None:
    """Write ``payload`` to a temporary file beside ``path`` and rename it into place."""
    with atomic_path(path, durable=True) as tmp:
        torch.save({"format": FORMAT, "version": VERSION, **payload}, tmp)


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load with ``weights_only=True``; raise ValueError naming the file when it is not ours."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such checkpoint")
    try:
        data = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # corrupt, truncated, or holding non-plain objects
        raise ValueError(f"{path}: not a readable checkpoint ({exc})") from exc
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{path}: not a SARAH checkpoint")
    if data.get("version") != VERSION:
        raise ValueError(f"{path}: checkpoint version {data.get('version')}, expected {VERSION}")
    return data


def seed_global_rngs(seed: int) -> None:
    """Seed every global RNG a checkpoint captures (python, numpy legacy, torch and cuda), so
    that the same inputs, config and seed give byte-identical checkpoints, their saved RNG
    states included, and not only identical weights."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def capture_rng_state() -> dict[str, Any]:
    """Global RNG states as plain values/tensors (python, numpy legacy, torch, cuda)."""
    version, internal, gauss = random.getstate()
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "python": [version, list(internal), gauss],
        "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss),
                  float(cached)],
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
    }


def restore_rng_state(state: dict[str, Any]) -> None:
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    kind, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(state["torch"])
    if state["cuda"] and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


@dataclass
class LoadedModels:
    """Models rebuilt from a checkpoint, in eval mode on the requested device."""

    vae: CausalVAE
    flow: FlowModel | None
    normalizer: Normalizer
    config: RunConfig
    dims: dict[str, int]
    features: str
    step: int
    stage: str


def build_models(config: RunConfig, dims: dict[str, int],
                 flow_seed: int | None = None) -> tuple[CausalVAE, FlowModel]:
    """Fresh VAE and flow model for the given configs and feature widths. ``flow_seed``: the
    global RNGs are seeded with it just before the flow is built, so the flow's initial weights
    depend on that seed and the flow's own config only, not on how many draws the VAE's
    construction took (a stochastic decoder's extra input once gave a flow stage another flow)."""
    vae = CausalVAE(config.vae, dims["motion"])
    if flow_seed is not None:
        seed_global_rngs(flow_seed)
    flow = FlowModel(config.flow, config.vae.latent_dim, config.vae.stride, dims["audio"])
    return vae, flow


def load_models(path: str | Path, device: str | torch.device | None = None) -> LoadedModels:
    """Rebuild the VAE (and the flow model for a flow checkpoint) with their normalizer."""
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    data = load_checkpoint(path)
    config = RunConfig.from_dict(data["config"])
    vae, flow = build_models(config, data["dims"])
    vae.load_state_dict(data["vae"])
    if data["stage"] == "flow":
        flow.load_state_dict(data["flow"])
    else:
        flow = None
    normalizer = Normalizer.from_state_dict(data["normalizer"])
    for module in (vae, flow, normalizer):
        if module is not None:
            module.to(device).eval()
    return LoadedModels(vae, flow, normalizer, config, dict(data["dims"]), data["features"],
                        int(data["step"]), data["stage"])


def unpack_models(models) -> tuple[CausalVAE, FlowModel | None, Normalizer | None]:
    """(vae, flow, normalizer) from ``LoadedModels`` or a ``(vae, flow[, normalizer])`` tuple."""
    if isinstance(models, LoadedModels) or (hasattr(models, "vae") and hasattr(models, "flow")):
        return models.vae, models.flow, getattr(models, "normalizer", None)
    if isinstance(models, (tuple, list)) and len(models) in (2, 3):
        return models[0], models[1], (models[2] if len(models) == 3 else None)
    raise TypeError("expected LoadedModels or a (vae, flow[, normalizer]) tuple, got "
                    f"{type(models).__name__}")
