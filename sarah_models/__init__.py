"""Causal motion models of SARAH: the interleaved-latent causal VAE, the causal flow matcher,
their shared transformer layers, and staged training with checkpoints."""

from .config import FlowConfig, RunConfig, TrainConfig, VAEConfig
from .flow import MODALITIES, FlowModel, build_block_mask
from .layers import KVCache, causal_mask
from .normalizer import Normalizer
from .vae import CausalVAE

__all__ = ["CausalVAE", "FlowConfig", "FlowModel", "KVCache", "MODALITIES", "Normalizer",
           "RunConfig", "TrainConfig", "VAEConfig", "build_block_mask", "causal_mask"]
