"""Causal flow matcher over latent blocks (paper 3.3 and 3.4).

One token per latent block k (s frames). Token input::

    h_k = W_z z_tau_k + W_c [e_py(k); e_a(k); e_b(k); e_g(k)] + bias + P[min(k, K_train - 1)]

which is exactly a Linear over the channel concatenation [z_tau_k; c_k] (split into two matrices
so the tau-independent half can be cached). Each modality m in ``MODALITIES`` has its own encoder
e_m: the s frames of block k are stacked, (K, s*D_m), and mapped by Linear -> SiLU -> Linear to
``cond_dim`` (the frame's place inside the block is its place in the stacked vector; time across
blocks is RoPE over the block index, relative only, so P, a learned embedding of the token's
index in the stream, tells the first token -- the agent at the window origin -- from the rest;
streaming passes each block's stream index, so it sees what offline generation sees). Not in
the paper, the user_head encoder may also read the head's velocity inside the block
(``head_velocity``) and the user's running mean head speed (``head_travel_seconds``,
``nn/head_travel.py``, which a stream carries from block to block) and the user's head as
seen from where the agent stands (``user_relative``, ``nn/user_offset.py``). Flow time tau enters
every block via AdaLN-Zero, from a sinusoidal embedding and an MLP. Attention over blocks is
causal (``build_block_mask``).

Classifier-free guidance: ``drop_mask`` (B, 4) bool, True = modality dropped for that sample.
A dropped modality's encoding is replaced by its own learned null vector (``null_<name>``), so
"no user position" differs from "user at the origin". Training drops each modality
independently with probability ``FlowConfig.drop_prob`` (0.05, ``sampling.guidance``); guidance at
inference runs once with all False and once with the modalities to guide dropped.

Prediction is x1 (the clean latent): ``forward`` returns z1_pred. The probability path (how
z_tau is formed, and the velocity an x1 prediction implies) is ``sampling/path.py``; the
training objective is ``training/objectives.py``.

What can be cached while streaming (imputation re-noises the history at every solver step):

* ``encode_condition(cond, drop_mask)`` -> (B, K, hidden) depends on neither tau nor z: compute
  it once per block and CFG branch and pass it as ``cond_tokens`` to every solver step (and to
  later chunks, where that block is history).
* Attention keys/values of history tokens depend on tau (AdaLN) and on their re-noised z_tau, so
  they are valid for one solver step only. They can be reused across chunks only when a history
  token's noise eps is fixed once, the tau grid is fixed and the token's causal context is
  unchanged (no window truncation); ``forward(..., caches=..., commit=...)`` supports such
  per-step caches. The recommended streaming path does not: with the paper's window of 2 history
  blocks + 1 new block, a full forward over 3 tokens per evaluation costs less than managing
  per-step caches, and it stays exact. With trajectory imputation (``StreamConfig.imputation``)
  a history token's state at each solver time never changes, so per-evaluation caches would be
  valid for as long as the token stays in the window; the stream recomputes its
  ``context_tokens`` instead, which is as exact.
"""

from __future__ import annotations

from typing import Mapping

import torch
from torch import Tensor, nn

from sarah_data.constants import FPS

from ..config import FlowConfig
from .head_travel import TravelState, head_travel
from .layers import (
    AdaLNZeroBlock,
    AdaLNZeroOutput,
    KVCache,
    TimestepEmbedding,
    causal_mask,
)

MODALITIES = ("user_head", "agent_audio", "user_audio", "gaze")


def build_block_mask(num_queries: int, num_keys: int | None = None, window: int | None = None,
                     device: torch.device | str | None = None) -> Tensor:
    """Causal mask over latent blocks: (num_queries, num_keys) bool, True = attend.

    The queries are the last ``num_queries`` blocks (lower-right aligned, so it is right for
    queries that follow cached keys); ``window`` limits each block to the latest ``window``."""
    return causal_mask(num_queries, num_keys, window=window, device=device)


def modality_dims(audio_dim: int) -> dict[str, int]:
    return {"user_head": 2, "agent_audio": audio_dim, "user_audio": audio_dim, "gaze": 1}


class FlowModel(nn.Module):
    def __init__(self, config: FlowConfig, latent_dim: int, stride: int, audio_dim: int) -> None:
        super().__init__()
        self.config = config
        self.latent_dim, self.stride, self.audio_dim = latent_dim, stride, audio_dim
        h, c = config.hidden, config.cond_dim
        self.dims = modality_dims(audio_dim)
        widths = {name: stride * d for name, d in self.dims.items()}
        if not config.user_absolute:
            widths["user_head"] = 0
        if config.head_velocity:
            widths["user_head"] += (stride - 1) * self.dims["user_head"]
        if config.head_travel_seconds is not None:
            widths["user_head"] += stride
        if config.user_relative:
            widths["user_head"] += stride * self.dims["user_head"]
        self.encoders = nn.ModuleDict({
            name: nn.Sequential(nn.Linear(width, c), nn.SiLU(), nn.Linear(c, c))
            for name, width in widths.items()})
        self.nulls = nn.ParameterDict({name: nn.Parameter(torch.randn(c) * 0.02)
                                       for name in MODALITIES})
        self.cond_in = nn.Linear(len(MODALITIES) * c, h)
        if config.position_embedding:
            self.token_positions = nn.Embedding(config.position_tokens, h)
            nn.init.normal_(self.token_positions.weight, std=0.02)
        self.latent_in = nn.Linear(latent_dim, h, bias=False)
        self.time_embedding = TimestepEmbedding(config.time_dim)
        self.time_mlp = nn.Sequential(nn.Linear(config.time_dim, h), nn.SiLU(), nn.Linear(h, h))
        self.blocks = nn.ModuleList(
            AdaLNZeroBlock(h, config.heads, h, config.mlp_ratio, config.rope_base)
            for _ in range(config.layers))
        self.out = AdaLNZeroOutput(h, h, latent_dim)

    @property
    def context_tokens(self) -> int | None:
        """How many tokens, itself included, the last token's prediction depends on: each layer
        reaches ``attention_window - 1`` tokens further back; None without a window (all)."""
        window = self.config.attention_window
        return None if window is None else self.config.layers * (window - 1) + 1

    def _stack(self, name: str, value: Tensor, num_blocks: int | None,
               travel: Tensor | None = None, offset: Tensor | None = None) -> Tensor:
        if name == "gaze" and value.dim() == 2:
            value = value[..., None]
        b, t, d = value.shape
        if d != self.dims[name]:
            raise ValueError(f"condition {name!r} has {d} channels, the model expects "
                             f"{self.dims[name]}")
        if t % self.stride or (num_blocks is not None and t != num_blocks * self.stride):
            raise ValueError(f"condition {name!r} has {t} frames; expected "
                             f"{'a multiple of ' + str(self.stride) if num_blocks is None else num_blocks * self.stride}")
        blocks = value.reshape(b, t // self.stride, self.stride, d)
        stacked = blocks.flatten(2)
        if name == "user_head" and not self.config.user_absolute:
            stacked = stacked[..., :0]  # the offset below stands for it
        if name == "user_head" and self.config.head_velocity:
            # within the block only, so a streamed block and the same block offline see the same
            velocity = torch.diff(blocks, dim=2) * FPS
            stacked = torch.cat([stacked, velocity.flatten(2)], dim=-1)
        if name == "user_head" and self.config.head_travel_seconds is not None:
            if travel is None:  # the stream starts with these frames
                travel, _ = head_travel(value, self.config.head_travel_seconds)
            if travel.shape[:2] != value.shape[:2]:
                raise ValueError(f"head_travel has shape {tuple(travel.shape)}, expected "
                                 f"({b}, {t}, 1)")
            stacked = torch.cat([stacked, travel.reshape(b, t // self.stride, self.stride)], -1)
        if name == "user_head" and self.config.user_relative:
            if offset is None:
                raise KeyError("conditioning is missing 'user_offset' (flow.user_relative: the "
                               "user's head less where the agent stands, nn/user_offset.py)")
            if offset.shape != value.shape:
                raise ValueError(f"user_offset has shape {tuple(offset.shape)}, expected "
                                 f"{tuple(value.shape)}")
            stacked = torch.cat([stacked, offset.reshape(b, t // self.stride, -1)], -1)
        return stacked

    def encode_condition(self, cond: Mapping[str, Tensor], drop_mask: Tensor | None = None,
                         num_blocks: int | None = None, first_token: int = 0,
                         positions: Tensor | None = None) -> Tensor:
        """Per-block conditioning contribution (B, K, hidden); independent of tau and z_tau.

        cond: user_head (B,T,2), agent_audio and user_audio (B,T,Da), gaze (B,T) or (B,T,1),
        all standardized; T = K*s; with ``head_travel_seconds``, optionally head_travel (B,T,1)
        (``nn/head_travel.py``, carried by a stream past its first block; without it the
        frames are a stream's first); with ``user_relative``, user_offset (B,T,2) in metres
        (``nn/user_offset.py``). drop_mask (B, 4) bool in ``MODALITIES`` order.
        first_token: the stream index of the first block (its position embedding; dropping
        modalities never drops the position), or ``positions`` (K,) every block's index."""
        missing = [m for m in MODALITIES if m not in cond]
        if missing:
            raise KeyError(f"conditioning is missing {missing}")
        parts = []
        for i, name in enumerate(MODALITIES):
            enc = self.encoders[name](self._stack(name, cond[name], num_blocks,
                                                  cond.get("head_travel"), cond.get("user_offset")))
            if drop_mask is not None:
                enc = torch.where(drop_mask[:, i, None, None], self.nulls[name].to(enc.dtype), enc)
            parts.append(enc)
        tokens = self.cond_in(torch.cat(parts, dim=-1))
        if self.config.position_embedding:
            if positions is None:
                positions = self.token_index(first_token, tokens.shape[1], tokens.device)
            else:
                positions = positions.to(tokens.device).clamp(0, self.config.position_tokens - 1)
            tokens = tokens + self.token_positions(positions)
        return tokens

    def carry_condition(self, cond: Mapping[str, Tensor], state: TravelState | None
                        ) -> tuple[Mapping[str, Tensor], TravelState | None]:
        """A stream's next blocks' ``cond`` with what it carries from its earlier blocks (the
        user's head travel, for a flow that reads it), and the state to carry on; ``state`` None
        at the stream's start. ``encode_condition`` of the result then encodes the blocks as the
        whole stream's call would."""
        seconds = self.config.head_travel_seconds
        if seconds is None:
            return cond, state
        travel, state = head_travel(cond["user_head"], seconds, state)
        return {**cond, "head_travel": travel}, state

    def token_index(self, first_token: int, count: int, device: torch.device | None = None) -> Tensor:
        """Position-embedding indices of ``count`` tokens from stream index ``first_token``:
        the index itself, the last embedding for every token past ``position_tokens``."""
        if first_token < 0:
            raise ValueError(f"first_token must be >= 0, got {first_token}")
        index = torch.arange(first_token, first_token + count, device=device)
        return index.clamp_max(self.config.position_tokens - 1)

    def forward(self, z_tau: Tensor, tau: Tensor | float, cond: Mapping[str, Tensor] | None = None,
                drop_mask: Tensor | None = None, *, cond_tokens: Tensor | None = None,
                attn_mask: Tensor | None = None, positions: Tensor | None = None,
                caches: list[KVCache] | None = None, commit: bool = True) -> Tensor:
        """Predict the clean latent z1 (B, K, Dz) from z_tau (B, K, Dz).

        tau: float, (B,) or (B, K) (per-token flow time). Give ``cond`` (+ ``drop_mask``) or the
        cached ``cond_tokens``. ``attn_mask`` None means ``build_block_mask(K, len(cache)+K)``
        and ``positions`` (RoPE block indices) default to ``len(cache) + arange(K)``. With ``caches``
        (one KVCache per block), z_tau holds only the new tokens; ``commit=False`` leaves the
        caches untouched."""
        b, k, _ = z_tau.shape
        past = 0 if caches is None else len(caches[0])
        if positions is None:
            positions = torch.arange(past, past + k, device=z_tau.device)
        if attn_mask is None and self.config.attention_window is not None:
            attn_mask = build_block_mask(k, past + k, window=self.config.attention_window,
                                         device=z_tau.device)
        if cond_tokens is None:
            if cond is None:
                raise ValueError("FlowModel.forward needs cond or cond_tokens")
            cond_tokens = self.encode_condition(cond, drop_mask, num_blocks=k,
                                                positions=positions if positions.dim() == 1 else None)
        tau = torch.as_tensor(tau, device=z_tau.device, dtype=torch.float32)
        if tau.dim() == 0:  # one flow time for all rows: its terms are computed once, broadcast
            tau = tau.reshape(1)
        t = self.time_mlp(self.time_embedding(tau)).to(cond_tokens.dtype)
        x = self.latent_in(z_tau.to(cond_tokens.dtype)) + cond_tokens
        for i, block in enumerate(self.blocks):
            x = block(x, t, attn_mask, positions, None if caches is None else caches[i], commit)
        return self.out(x, t)
