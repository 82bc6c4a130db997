"""The reference model, readable top to bottom: transformer layers, the causal VAE, the causal
flow matcher and the standardization that travels inside checkpoints. Nothing here knows about
inference speed-ups (``sarah_models.accel`` swaps modules of copies of these models)."""

from .flow import MODALITIES, FlowModel, build_block_mask
from .layers import KVCache, causal_mask
from .normalizer import Normalizer
from .vae import CausalVAE

__all__ = ["CausalVAE", "FlowModel", "KVCache", "MODALITIES", "Normalizer", "build_block_mask",
           "causal_mask"]
