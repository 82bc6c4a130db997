"""Causal motion models of SARAH, in rooms:

``nn`` the reference model (layers, causal VAE, causal flow matcher, normalizer);
``sampling`` path, solver, guidance and the streaming / offline generators;
``training`` objectives, loop, stages, checkpoints, DDP;
``evaluation`` metrics registry, baselines, Table 1 / Table 2;
``generation`` inputs -> motion.npz and pictures;
``accel`` inference speed-ups by module replacement; ``testing`` shared test fixtures.
``config`` holds every default once.
"""

from .config import FlowConfig, RunConfig, StreamConfig, TrainConfig, VAEConfig
from .nn import (
           MODALITIES,
           CausalVAE,
           FlowModel,
           KVCache,
           Normalizer,
           build_block_mask,
           causal_mask,
)

__all__ = ["CausalVAE", "FlowConfig", "FlowModel", "KVCache", "MODALITIES", "Normalizer",
           "RunConfig", "StreamConfig", "TrainConfig", "VAEConfig", "build_block_mask",
           "causal_mask"]
