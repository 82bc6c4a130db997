"""Transformer parts shared by the VAE and the flow model.

Attention always takes an explicit boolean mask (True = may attend), built by ``causal_mask``.
``F.scaled_dot_product_attention(is_causal=True)`` is never used: it aligns the triangle to the
upper-left corner, which is wrong as soon as queries are fewer than keys (a KV cache).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def causal_mask(num_queries: int, num_keys: int | None = None, window: int | None = None,
                device: torch.device | str | None = None) -> Tensor:
    """(num_queries, num_keys) bool mask, lower-right aligned: the queries are the last
    ``num_queries`` of the ``num_keys`` positions and each sees itself and everything before it
    (only the latest ``window`` positions when ``window`` is given)."""
    num_keys = num_queries if num_keys is None else num_keys
    if num_keys < num_queries:
        raise ValueError(f"causal_mask: {num_keys} keys cannot precede {num_queries} queries")
    q = torch.arange(num_queries, device=device)[:, None] + (num_keys - num_queries)
    k = torch.arange(num_keys, device=device)[None, :]
    allowed = k <= q
    if window is not None:
        if window < 1:
            raise ValueError(f"causal_mask: window must be >= 1, got {window}")
        allowed &= k > q - window
    return allowed


class RopeAngles(nn.Module):
    """cos and sin of the rotary angles of integer positions: (..., L) -> (2, ..., L, head_dim/2)
    float32, computed in float64 so that long streams (large positions) keep their precision.

    A module of its own because it depends on the positions only: inference swaps in a memo
    (``accel``), since every solver evaluation of a chunk uses the same positions."""

    def __init__(self, head_dim: int, base: float = 10_000.0) -> None:
        super().__init__()
        self.half, self.base = head_dim // 2, float(base)

    def forward(self, positions: Tensor) -> Tensor:
        inv_freq = self.base ** (-torch.arange(self.half, device=positions.device,
                                               dtype=torch.float64) / self.half)
        angles = positions.to(torch.float64)[..., None] * inv_freq
        return torch.stack((angles.cos(), angles.sin())).float()


class RotaryEmbedding(nn.Module):
    """Rotary position embedding (rotate-half form) applied to (..., B, H, L, Dh) tensors."""

    def __init__(self, head_dim: int, base: float = 10_000.0) -> None:
        super().__init__()
        if head_dim % 2:
            raise ValueError(f"RoPE needs an even head dimension, got {head_dim}")
        self.head_dim = head_dim
        self.angles = RopeAngles(head_dim, base)

    def forward(self, x: Tensor, positions: Tensor) -> Tensor:
        cos, sin = self.angles(positions.to(x.device)).to(x.dtype)
        if cos.dim() == 3:  # per-sample positions (B, L, half) -> (B, 1, L, half)
            cos, sin = cos[:, None], sin[:, None]
        # x may carry leading dims (e.g. q and k stacked): cos/sin broadcast from the right
        half = self.head_dim // 2
        x1, x2 = x[..., :half], x[..., half:]
        return torch.cat((x1 * cos - x2 * sin, x1 * sin + x2 * cos), dim=-1)


class KVCache:
    """Keys and values (after RoPE) of the tokens seen so far by one attention layer.

    New keys/values are written into a preallocated buffer after the valid region and a view is
    returned (``torch.cat`` of the whole cache at every step was half the cost of a streaming VAE
    decode step); the buffer grows, or is compacted by moving the valid region to the front, only
    when full, so a call costs amortized O(new tokens). ``max_tokens`` keeps only the most recent
    tokens when committing (a sliding window); without it incremental outputs equal a full
    forward pass exactly.
    """

    def __init__(self, max_tokens: int | None = None) -> None:
        self.max_tokens = max_tokens
        self._k: Tensor | None = None
        self._v: Tensor | None = None
        self._start = 0
        self._length = 0

    @property
    def k(self) -> Tensor | None:
        return None if not self._length else self._k[:, :, self._start:self._start + self._length]

    @property
    def v(self) -> Tensor | None:
        return None if not self._length else self._v[:, :, self._start:self._start + self._length]

    def __len__(self) -> int:
        return self._length

    def extend(self, k: Tensor, v: Tensor, commit: bool = True) -> tuple[Tensor, Tensor]:
        """Return cached + new keys/values; store them only when ``commit``."""
        new = k.shape[2]
        if not self._length and not commit:
            return k, v
        self._reserve(k, new)
        end = self._start + self._length
        self._k[:, :, end:end + new] = k
        self._v[:, :, end:end + new] = v
        full_k, full_v = self._k[:, :, self._start:end + new], self._v[:, :, self._start:end + new]
        if commit:
            self._length += new
            if self.max_tokens is not None and self._length > self.max_tokens:
                self._start += self._length - self.max_tokens
                self._length = self.max_tokens
        return full_k, full_v

    def _reserve(self, k: Tensor, new: int) -> None:
        end = self._start + self._length + new
        if self._k is not None and end <= self._k.shape[2] and self._k.shape[:2] == k.shape[:2]:
            return
        keep = self._length + new
        capacity = 2 * max(keep, self.max_tokens or 0) + new
        shape = (*k.shape[:2], capacity, k.shape[3])
        buf_k, buf_v = k.new_empty(shape), k.new_empty(shape)
        if self._length:
            buf_k[:, :, :self._length] = self.k
            buf_v[:, :, :self._length] = self.v
        self._k, self._v, self._start = buf_k, buf_v, 0

    def reset(self) -> None:
        self._k = self._v = None
        self._start = self._length = 0


class Attention(nn.Module):
    """Multi-head self-attention with RoPE and a boolean mask (None: causal)."""

    def __init__(self, dim: int, heads: int, rope_base: float = 10_000.0) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"hidden size {dim} is not divisible by {heads} heads")
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.out = nn.Linear(dim, dim)
        self.rope = RotaryEmbedding(dim // heads, rope_base)

    def forward(self, x: Tensor, mask: Tensor | None, positions: Tensor,
                cache: KVCache | None = None, commit: bool = True) -> Tensor:
        """x (B, L, dim); positions (L,) or (B, L); mask (L, L_cache + L) bool, True = attend, or
        None for ``causal_mask`` (the new tokens follow the cached ones)."""
        b, n, d = x.shape
        qkv = self.qkv(x).view(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        # q and k rotated in one pass: at inference the tensors are tiny and op count is the cost
        q, k = self.rope(qkv[:2], positions)
        v = qkv[2]
        if cache is not None:
            k, v = cache.extend(k, v, commit=commit)
        if mask is None and k.shape[2] == n:
            # The square lower triangle as SDPA's causal flag: it skips the masked half of the
            # scores, the same bits as the mask forward and backward (tests/test_masks.py);
            # the VAE's 500-token windows attend in 0.6-0.8x the time (2026-12-06).
            out = F.scaled_dot_product_attention(q, k, v, is_causal=True)
        else:
            if mask is None:
                mask = causal_mask(n, k.shape[2], device=x.device)
            if mask.dtype != torch.bool:
                raise TypeError(f"attention mask must be bool (True = attend), got {mask.dtype}")
            if mask.shape[-2:] != (n, k.shape[2]):
                raise ValueError(f"attention mask {tuple(mask.shape)} does not match "
                                 f"{n} queries x {k.shape[2]} keys")
            out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
        return self.out(out.transpose(1, 2).reshape(b, n, d))


class MLP(nn.Sequential):
    def __init__(self, dim: int, ratio: float) -> None:
        inner = int(dim * ratio)
        super().__init__(nn.Linear(dim, inner), nn.GELU(approximate="tanh"), nn.Linear(inner, dim))


class TransformerBlock(nn.Module):
    """Plain pre-norm block: x + attn(LN x), then x + mlp(LN x)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float = 4.0, rope_base: float = 10_000.0):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = Attention(dim, heads, rope_base)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = MLP(dim, mlp_ratio)

    def forward(self, x: Tensor, mask: Tensor | None, positions: Tensor,
                cache: KVCache | None = None, commit: bool = True) -> Tensor:
        x = x + self.attn(self.norm1(x), mask, positions, cache, commit)
        return x + self.mlp(self.norm2(x))


def modulate(x: Tensor, shift: Tensor, scale: Tensor) -> Tensor:
    return x * (1 + scale) + shift


def _per_token(mod: Tensor) -> Tensor:
    """Modulation from a (B, C) vector broadcasts over tokens; (B, L, C) is already per token."""
    return mod[:, None] if mod.dim() == 2 else mod


class AdaLNZeroBlock(nn.Module):
    """DiT block: LayerNorm shift/scale and residual gates regressed from a conditioning vector.

    The modulation layer starts at zero, so every gate is 0 and the block is the identity at
    initialisation. ``cond`` is (B, C) for one vector per sample or (B, L, C) per token.
    """

    def __init__(self, dim: int, heads: int, cond_dim: int, mlp_ratio: float = 4.0,
                 rope_base: float = 10_000.0) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.attn = Attention(dim, heads, rope_base)
        self.norm2 = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.mlp = MLP(dim, mlp_ratio)
        self.modulation = nn.Sequential(nn.SiLU(), nn.Linear(cond_dim, 6 * dim))
        nn.init.zeros_(self.modulation[1].weight)
        nn.init.zeros_(self.modulation[1].bias)

    def forward(self, x: Tensor, cond: Tensor, mask: Tensor | None, positions: Tensor,
                cache: KVCache | None = None, commit: bool = True) -> Tensor:
        shift1, scale1, gate1, shift2, scale2, gate2 = _per_token(self.modulation(cond)).chunk(6, -1)
        h = self.attn(modulate(self.norm1(x), shift1, scale1), mask, positions, cache, commit)
        x = x + gate1 * h
        return x + gate2 * self.mlp(modulate(self.norm2(x), shift2, scale2))


class AdaLNZeroOutput(nn.Module):
    """DiT final layer: modulated LayerNorm then a zero-initialised projection."""

    def __init__(self, dim: int, cond_dim: int, out_dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.modulation = nn.Sequential(nn.SiLU(), nn.Linear(cond_dim, 2 * dim))
        self.proj = nn.Linear(dim, out_dim)
        for layer in (self.modulation[1], self.proj):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def forward(self, x: Tensor, cond: Tensor) -> Tensor:
        shift, scale = _per_token(self.modulation(cond)).chunk(2, -1)
        return self.proj(modulate(self.norm(x), shift, scale))


class TimestepEmbedding(nn.Module):
    """``timestep_embedding`` as a module (no weights): a seam where inference swaps in a memo,
    since a solver visits the same few flow times over and over."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, t: Tensor) -> Tensor:
        return timestep_embedding(t, self.dim)


def timestep_embedding(t: Tensor, dim: int, max_period: float = 10_000.0) -> Tensor:
    """Sinusoidal embedding of flow time t in [0, 1] (scaled by 1000 as in DiT), shape (..., dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device,
                                                           dtype=torch.float32) / half)
    args = (t.float() * 1000.0)[..., None] * freqs
    emb = torch.cat((args.cos(), args.sin()), dim=-1)
    return F.pad(emb, (0, dim % 2))
