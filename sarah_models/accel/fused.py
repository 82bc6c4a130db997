"""Fused inference blocks: the same maths as the reference layers in fewer tensor operations.

Why: after int8 quantization, a streamed chunk at paper size on 2 CPU cores spends about half its
time in the flow's Linears (bound by reading ~50 MB of weights per evaluation) and the other half
in some 150 small operations per evaluation and 9 x 40 in the VAE decoder step, each a few
microseconds of dispatch on tensors of 3 tokens. These subclasses remove most of those; they
replace the reference modules in an optimized copy (``optimize.py``) and fall back to the
reference forward for anything they do not cover (autograd, per-sample positions, rows with
different flow times). Only rounding differs (``tests/test_fused.py``).

* Linears are called as plain functions (``linears.linear_function``), the MLP as
  fc2(gelu(fc1(h))): a module call costs ~10 us of Python, tens of times per evaluation. So
  build these blocks after the Linears are final (``optimize.py`` does).
* ``FusedAttention``: q and k rotated in one pass from memoized tables
  (``x * [cos, cos] + roll(x, Dh/2) * [-sin, sin]`` is rotate-half RoPE), one table lookup per
  stack of layers, and ``is_causal=True`` for the square causal case (no cache, no mask given).
* ``FusedTransformerBlock`` (the VAE decoder's): LayerNorms as functions, fused attention.
* ``FusedAdaLNZeroBlock``, ``FusedAdaLNZeroOutput``: the AdaLN-Zero modulation folded into the
  LayerNorm affine -- ``LN(x) * (1 + scale) + shift`` is ``layer_norm(x, 1 + scale, shift)``
  when every row shares the conditioning vector, as the solver's rows do (one flow time) -- and
  the residual gates as one ``addcmul``. The folded terms are computed once per conditioning
  vector by the block's own modulation layer and memoized.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..nn.layers import (MLP, AdaLNZeroBlock, AdaLNZeroOutput, Attention, KVCache, TransformerBlock,
                         causal_mask)
from .linears import linear_function
from .memo import RopeTables, TensorMemo


def apply_rope(x: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
    """Rotate-half RoPE of x (..., Dh) with ``RopeTables`` multipliers broadcast against it."""
    return torch.addcmul(x * cos, x.roll(x.shape[-1] // 2, -1), sin)


class FusedAttention(Attention):
    """``Attention`` with shared rotary tables and the causal flag (see the module docstring)."""

    def __init__(self, attention: Attention, tables: RopeTables) -> None:
        nn.Module.__init__(self)
        self.heads = attention.heads
        self.qkv, self.out, self.rope = attention.qkv, attention.out, attention.rope
        self.tables = tables
        self.project_qkv, self.project_out = linear_function(self.qkv), linear_function(self.out)

    def forward(self, x: Tensor, mask: Tensor | None, positions: Tensor,
                cache: KVCache | None = None, commit: bool = True) -> Tensor:
        if torch.is_grad_enabled() or positions.dim() != 1:
            return super().forward(x, mask, positions, cache, commit)
        return self.attend(x, mask, positions, cache, commit)

    def attend(self, x: Tensor, mask: Tensor | None, positions: Tensor,
               cache: KVCache | None = None, commit: bool = True) -> Tensor:
        """The fused computation (inference, 1-D positions), without the module call."""
        cos, sin = self.tables(positions.to(x.device), x.dtype)
        return self.attend_rotated(x, mask, cos, sin, cache, commit)

    def attend_rotated(self, x: Tensor, mask: Tensor | None, cos: Tensor, sin: Tensor,
                       cache: KVCache | None = None, commit: bool = True) -> Tensor:
        """``attend`` with the positions' rotary tables already looked up."""
        # One view or op per step, no shapes read: a trace (``traced.py``) records each
        # indexing step and each shape read as operations of its own.
        qkv = self.project_qkv(x).unflatten(-1, (3, self.heads, -1))  # (B, L, 3, H, Dh)
        q, k = apply_rope(qkv.narrow(2, 0, 2), cos, sin).transpose(1, 3).unbind(2)  # (B, H, L, Dh)
        v = qkv.select(2, 2).transpose(1, 2)
        if cache is not None:
            k, v = cache.extend(k, v, commit=commit)
        if mask is None and cache is None:
            out = F.scaled_dot_product_attention(q, k, v, is_causal=True)
        else:
            if mask is None:
                mask = causal_mask(x.shape[1], k.shape[2], device=x.device)
            out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
        return self.project_out(out.transpose(1, 2).flatten(2))


_TWO_SQRT_2_OVER_PI = 2.0 * math.sqrt(2.0 / math.pi)
# MLPs at least this wide compute their tanh GELU as ``gelu_tanh``: below it, its six ops'
# dispatch costs more than it saves (one decoder step's 1 x 1024 values: 3 us against 9; 2 x 4096
# even). Chosen by width, never by rows, so that a stream's values do not depend on how many
# streams share its call (``nn.streams``).
SIGMOID_FORM_MIN_WIDTH = 4096


def gelu_tanh(x: Tensor) -> Tensor:
    """GELU's tanh approximation, ``F.gelu(x, approximate="tanh")``, computed as
    ``x * sigmoid(2u)`` with u = sqrt(2/pi) (x + 0.044715 x^3): the same function, since
    (1 + tanh u) / 2 = sigmoid(2u), to float rounding (4.8e-7). Why: torch's CPU tanh is a slow
    vector path; on one AMD EPYC thread (2026-12-05) the paper-size flow's MLP took 1.37 ms on an
    offline solve's 200 x 4096 values and 0.62 ms so, a streamed chunk's 6 x 4096 44 us and 26.
    Inference only: it works in place on its own intermediate."""
    u = x * x
    u.mul_(0.044715 * _TWO_SQRT_2_OVER_PI).add_(_TWO_SQRT_2_OVER_PI).mul_(x)
    return u.sigmoid_().mul_(x)


def mlp_function(mlp: MLP):
    """fc2(gelu(fc1(h))) of an ``MLP`` as one plain callable."""
    fc1, fc2, approximate = linear_function(mlp[0]), linear_function(mlp[2]), mlp[1].approximate
    if approximate == "tanh" and mlp[0].out_features >= SIGMOID_FORM_MIN_WIDTH:
        return lambda h: fc2(gelu_tanh(fc1(h)))
    return lambda h: fc2(F.gelu(fc1(h), approximate=approximate))


class FusedTransformerBlock(TransformerBlock):
    """The VAE decoder's block: the same residual maths, LayerNorms and MLP as functions."""

    def __init__(self, block: TransformerBlock, tables: RopeTables) -> None:
        nn.Module.__init__(self)
        self.norm1, self.norm2, self.mlp = block.norm1, block.norm2, block.mlp
        self.attn = FusedAttention(block.attn, tables)
        self.mlp_function = mlp_function(self.mlp)

    def forward(self, x: Tensor, mask: Tensor | None, positions: Tensor,
                cache: KVCache | None = None, commit: bool = True) -> Tensor:
        if torch.is_grad_enabled() or positions.dim() != 1:
            return super().forward(x, mask, positions, cache, commit)
        d = x.shape[-1]
        n1, n2 = self.norm1, self.norm2
        x = x + self.attn.attend(F.layer_norm(x, (d,), n1.weight, n1.bias, n1.eps), mask,
                                 positions, cache, commit)
        return x + self.mlp_function(F.layer_norm(x, (d,), n2.weight, n2.bias, n2.eps))


@dataclass(frozen=True)
class FoldedModulation:
    """One block's AdaLN-Zero terms for one conditioning vector, as (hidden,) vectors: LayerNorm
    weights ``1 + scale`` and biases ``shift`` of the attention and MLP branches, and gates."""

    attn_weight: Tensor
    attn_bias: Tensor
    attn_gate: Tensor
    mlp_weight: Tensor
    mlp_bias: Tensor
    mlp_gate: Tensor


def fold(modulation: nn.Module, cond: Tensor, parts: int) -> tuple[Tensor, ...] | None:
    """``modulation(cond[:1])`` split in ``parts`` contiguous (hidden,) vectors, or None when
    the rows of ``cond`` differ (then nothing can be folded)."""
    if cond.dim() != 2 or not torch.equal(cond, cond[:1].expand_as(cond)):
        return None
    return tuple(part.contiguous() for part in modulation(cond[:1])[0].chunk(parts, -1))


class FusedAdaLNZeroBlock(AdaLNZeroBlock):
    def __init__(self, block: AdaLNZeroBlock, tables: RopeTables, max_entries: int = 64) -> None:
        nn.Module.__init__(self)
        self.norm1, self.norm2 = block.norm1, block.norm2
        self.attn = FusedAttention(block.attn, tables)
        self.mlp, self.modulation = block.mlp, block.modulation
        self.folded = TensorMemo(max_entries)
        self.mlp_function = mlp_function(self.mlp)

    def _fold(self, cond: Tensor) -> FoldedModulation | None:
        terms = fold(self.modulation, cond, 6)
        if terms is None:
            return None
        shift1, scale1, gate1, shift2, scale2, gate2 = terms
        return FoldedModulation(1 + scale1, shift1, gate1, 1 + scale2, shift2, gate2)

    def forward(self, x: Tensor, cond: Tensor, mask: Tensor | None, positions: Tensor,
                cache: KVCache | None = None, commit: bool = True) -> Tensor:
        terms = None if torch.is_grad_enabled() else self.folded.get(cond, self._fold)
        if terms is None or positions.dim() != 1:
            return super().forward(x, cond, mask, positions, cache, commit)
        cos, sin = self.attn.tables(positions.to(x.device), x.dtype)
        return self.modulated(x, terms, cos, sin, mask, cache, commit)

    def modulated(self, x: Tensor, terms: FoldedModulation, cos: Tensor, sin: Tensor,
                  mask: Tensor | None, cache: KVCache | None = None, commit: bool = True) -> Tensor:
        """The fused computation: the block under its folded modulation ``terms``, with the
        positions' rotary tables ``cos``, ``sin`` (``RopeTables``)."""
        d = x.shape[-1]
        h = F.layer_norm(x, (d,), terms.attn_weight, terms.attn_bias, self.norm1.eps)
        attended = self.attn.attend_rotated(h, mask, cos, sin, cache, commit)
        x = torch.addcmul(x, terms.attn_gate, attended)
        h = F.layer_norm(x, (d,), terms.mlp_weight, terms.mlp_bias, self.norm2.eps)
        return torch.addcmul(x, terms.mlp_gate, self.mlp_function(h))


class FusedAdaLNZeroOutput(AdaLNZeroOutput):
    def __init__(self, output: AdaLNZeroOutput, max_entries: int = 64) -> None:
        nn.Module.__init__(self)
        self.norm, self.modulation, self.proj = output.norm, output.modulation, output.proj
        self.folded = TensorMemo(max_entries)
        self.project = linear_function(self.proj)

    def _fold(self, cond: Tensor) -> tuple[Tensor, Tensor] | None:
        terms = fold(self.modulation, cond, 2)
        return None if terms is None else (1 + terms[1], terms[0])

    def forward(self, x: Tensor, cond: Tensor) -> Tensor:
        terms = None if torch.is_grad_enabled() else self.folded.get(cond, self._fold)
        if terms is None:
            return super().forward(x, cond)
        weight, bias = terms
        return self.project(F.layer_norm(x, x.shape[-1:], weight, bias, self.norm.eps))
