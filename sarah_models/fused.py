"""Fused inference forwards: the streaming step's maths in fewer tensor operations.

Why: after int8 quantization, a streamed chunk at paper size on 2 CPU cores spends about half its
time in the flow's Linears (bound by reading ~50 MB of weights per network evaluation) and the
other half in some 150 small operations per evaluation and 9 x 40 in the VAE decoder step, each
a few microseconds of dispatch on tensors of 3 tokens. Those are what this module removes; the
maths is the same, only rounding differs (checked in ``tests/test_fused.py``).

Flow model (``fuse_flow``), for the solver's calls (one float tau for every row, cached
condition tokens, no KV cache, the default causal mask and positions):

* AdaLN-Zero modulation folded into LayerNorm's affine: ``LN(x) * (1 + scale) + shift`` is
  ``layer_norm(x, weight=1 + scale, bias=shift)`` when all rows share tau, which the solver's do.
  The folded vectors and gates are computed per tau from the blocks' own modulation layers.
* Residual gates as one ``addcmul``; the time MLP is not run at all (only the modulations use it).
* RoPE of q and k in one pass from tables: ``x * [cos, cos] + roll(x, Dh/2) * [-sin, sin]`` is
  rotate-half RoPE.
* The square causal mask as ``is_causal=True``.
* Linears called as their kernels (``linear_kernel``): a quantized dynamic Linear's module call
  adds ~10 us of Python to a ~15 us kernel call, 16 times per evaluation. The kernels are taken
  when the forward is installed, so install it after quantizing (``fast.optimize_for_inference``
  does).

Any other call (training, autograd, KV caches, explicit masks or positions, per-row tau) goes to
the model's own forward.

VAE decoder (``fuse_decoder``): the rotary angles of its ever-growing positions come from a
table (``RopeTable``) extended in blocks, computed exactly as ``RopeAngles`` computes them
(bit-identical, used in every optimized mode). With ``steps=True`` the streaming step itself is
``FusedDecoderStep``: the angles are looked up once for all 9 layers instead of per layer and
q and k rotated in one pass (not bit-identical: int8 and bf16 modes only).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .flow import FlowModel
from .layers import AdaLNZeroBlock, RopeAngles, causal_mask, timestep_embedding
from .vae import CausalVAE


@dataclass(frozen=True)
class BlockModulation:
    """One block's AdaLN-Zero terms at one tau, as (hidden,) vectors: LayerNorm weights
    ``1 + scale`` and biases ``shift`` of the attention and MLP branches, and their gates."""

    attn_weight: Tensor
    attn_bias: Tensor
    attn_gate: Tensor
    mlp_weight: Tensor
    mlp_bias: Tensor
    mlp_gate: Tensor


@dataclass(frozen=True)
class TimeTerms:
    blocks: tuple[BlockModulation, ...]
    out_weight: Tensor
    out_bias: Tensor


def rope_tables_at(angles: nn.Module, positions: Tensor) -> tuple[Tensor, Tensor]:
    """(L, Dh) multipliers of x and of roll(x, Dh/2) for rotate-half RoPE at ``positions``."""
    cos, sin = angles(positions)
    return torch.cat((cos, cos), -1), torch.cat((-sin, sin), -1)


def apply_rope(x: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
    """Rotate-half RoPE of x (..., Dh) with tables from ``rope_tables_at`` broadcast against it."""
    return torch.addcmul(x * cos, x.roll(x.shape[-1] // 2, -1), sin)


def linear_kernel(module: nn.Module) -> Callable[[Tensor], Tensor]:
    """The function a Linear-like module computes, without the module call: the int8 kernel
    for a dynamic quantized Linear, ``F.linear`` for an ``nn.Linear``, the module otherwise."""
    from torch.ao.nn.quantized.dynamic import Linear as DynamicQuantizedLinear

    if isinstance(module, DynamicQuantizedLinear) and module._packed_params.dtype == torch.qint8:
        packed, op = module._packed_params._packed_params, torch.ops.quantized.linear_dynamic
        # the module's own call for its version (>= 4): reduce_range=True
        return lambda x: op(x, packed, True)
    if type(module) is nn.Linear:
        weight, bias = module.weight, module.bias
        return lambda x: F.linear(x, weight, bias)
    return module


class BlockKernels(NamedTuple):
    qkv: Callable[[Tensor], Tensor]
    out: Callable[[Tensor], Tensor]
    fc1: Callable[[Tensor], Tensor]
    fc2: Callable[[Tensor], Tensor]
    gelu: str  # the MLP's GELU approximation

    @classmethod
    def of(cls, block: nn.Module) -> "BlockKernels":
        mlp = block.mlp
        return cls(*(linear_kernel(m) for m in (block.attn.qkv, block.attn.out, mlp[0], mlp[2])),
                   mlp[1].approximate)

    def mlp(self, h: Tensor) -> Tensor:
        return self.fc2(F.gelu(self.fc1(h), approximate=self.gelu))


class FusedFlowForward:
    """Installed as ``flow.forward`` by ``fuse_flow``; see the module docstring."""

    def __init__(self, flow: FlowModel, max_entries: int = 64) -> None:
        self.flow = flow
        self.kernels = [BlockKernels.of(block) for block in flow.blocks]
        self.module_forward = type(flow).forward.__get__(flow)
        self.max_entries = max_entries
        self._terms: OrderedDict[tuple, TimeTerms] = OrderedDict()
        self._rope: dict[tuple, tuple[Tensor, Tensor]] = {}
        self.fused_calls = 0

    def __call__(self, z_tau: Tensor, tau, cond=None, drop_mask=None, *, cond_tokens=None,
                 attn_mask=None, positions=None, caches=None, commit: bool = True) -> Tensor:
        if (torch.is_grad_enabled() or cond_tokens is None or not isinstance(tau, float)
                or attn_mask is not None or positions is not None or caches is not None):
            return self.module_forward(z_tau, tau, cond, drop_mask, cond_tokens=cond_tokens,
                                       attn_mask=attn_mask, positions=positions, caches=caches,
                                       commit=commit)
        self.fused_calls += 1
        flow = self.flow
        terms = self.time_terms(tau, cond_tokens.dtype)
        cos, sin = self.rope(z_tau.shape[1], z_tau.device, cond_tokens.dtype)
        x = flow.latent_in(z_tau.to(cond_tokens.dtype)) + cond_tokens
        for block, kernels, mod in zip(flow.blocks, self.kernels, terms.blocks):
            x = fused_block(block, kernels, x, mod, cos, sin)
        out = flow.out
        return out.proj(F.layer_norm(x, x.shape[-1:], terms.out_weight, terms.out_bias,
                                     out.norm.eps))

    def rope(self, length: int, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """Tables shaped (L, 1, 1, Dh) for q and k laid out as (B, L, 2, H, Dh)."""
        key = (length, str(device), dtype)
        if key not in self._rope:
            cos, sin = rope_tables_at(self.flow.blocks[0].attn.rope.angles,
                                      torch.arange(length, device=device))
            self._rope[key] = (cos.to(dtype)[:, None, None], sin.to(dtype)[:, None, None])
        return self._rope[key]

    @torch.inference_mode()
    def time_terms(self, tau: float, dtype: torch.dtype) -> TimeTerms:
        """The modulation terms at ``tau``, computed by the model's own time path (batch 1)."""
        key = (tau, dtype)
        terms = self._terms.get(key)
        if terms is not None:
            self._terms.move_to_end(key)
            return terms
        flow = self.flow
        device = flow.cond_in.weight.device
        t_in = torch.as_tensor(tau, device=device, dtype=torch.float32).expand(1)
        t = flow.time_mlp(timestep_embedding(t_in, flow.config.time_dim)).to(dtype)
        blocks = []
        for block in flow.blocks:
            shift1, scale1, gate1, shift2, scale2, gate2 = block.modulation(t)[0].chunk(6, -1)
            blocks.append(BlockModulation(1 + scale1, shift1.contiguous(), gate1.contiguous(),
                                          1 + scale2, shift2.contiguous(), gate2.contiguous()))
        shift, scale = flow.out.modulation(t)[0].chunk(2, -1)
        terms = TimeTerms(tuple(blocks), 1 + scale, shift.contiguous())
        self._terms[key] = terms
        if len(self._terms) > self.max_entries:
            self._terms.popitem(last=False)
        return terms


def fused_block(block: AdaLNZeroBlock, kernels: BlockKernels, x: Tensor, mod: BlockModulation,
                cos: Tensor, sin: Tensor) -> Tensor:
    """``AdaLNZeroBlock.forward`` for rows sharing tau, no cache, square causal mask."""
    b, n, d = x.shape
    heads = block.attn.heads
    h = F.layer_norm(x, (d,), mod.attn_weight, mod.attn_bias, block.norm1.eps)
    qkv = kernels.qkv(h).view(b, n, 3, heads, d // heads)
    qk = apply_rope(qkv[:, :, :2], cos, sin).transpose(1, 3)  # (B, H, 2, L, Dh)
    v = qkv[:, :, 2].transpose(1, 2)
    a = F.scaled_dot_product_attention(qk[:, :, 0], qk[:, :, 1], v, is_causal=True)
    x = torch.addcmul(x, mod.attn_gate, kernels.out(a.transpose(1, 2).reshape(b, n, d)))
    h = F.layer_norm(x, (d,), mod.mlp_weight, mod.mlp_bias, block.norm2.eps)
    return torch.addcmul(x, mod.mlp_gate, kernels.mlp(h))


def fuse_flow(flow: FlowModel) -> FlowModel:
    """Install ``FusedFlowForward`` as this instance's forward (in place)."""
    if not isinstance(flow.__dict__.get("forward"), FusedFlowForward):
        flow.forward = FusedFlowForward(flow)
    return flow


class RopeTable(nn.Module):
    """``RopeAngles`` for 1-D integer positions from a table grown in blocks of ``block``
    positions; each entry is computed by ``RopeAngles`` itself, so lookups are bit-identical."""

    def __init__(self, angles: RopeAngles, block: int = 4096) -> None:
        super().__init__()
        self.angles, self.block = angles, block
        self._table: Tensor | None = None

    def forward(self, positions: Tensor) -> Tensor:
        if positions.dim() != 1 or positions.numel() == 0 or torch.is_grad_enabled():
            return self.angles(positions)
        low, high = (int(v) for v in torch.aminmax(positions))
        if low < 0:
            return self.angles(positions)
        table = self._table
        if table is None or table.device != positions.device or high >= table.shape[1]:
            size = (high // self.block + 1) * self.block
            table = self._table = self.angles(torch.arange(size, device=positions.device))
        return table.index_select(1, positions)


def fuse_decoder(vae: CausalVAE, steps: bool = False) -> CausalVAE:
    """Give every decoder layer a ``RopeTable`` (in place; the encoder is untouched), and with
    ``steps`` install ``FusedDecoderStep`` as ``vae.decoder_step`` (not bit-identical)."""
    for block in vae.decoder:
        rope = block.attn.rope
        if not isinstance(rope.angles, RopeTable):
            rope.angles = RopeTable(rope.angles)
    if steps and not isinstance(vae.__dict__.get("decoder_step"), FusedDecoderStep):
        vae.decoder_step = FusedDecoderStep(vae)
    return vae


class FusedDecoderStep:
    """Installed as ``vae.decoder_step`` by ``fuse_decoder(vae, steps=True)``: the same step with
    the rotary tables looked up once for all layers and applied in one pass to q and k."""

    def __init__(self, vae: CausalVAE) -> None:
        self.vae = vae
        self.table = RopeTable(vae.decoder[0].attn.rope.angles)
        self.kernels = [BlockKernels.of(block) for block in vae.decoder]

    def __call__(self, z_k: Tensor, cache) -> Tensor:
        vae = self.vae
        if torch.is_grad_enabled():
            return type(vae).decoder_step(vae, z_k, cache)
        x = vae._decoder_tokens(z_k[:, None])
        b, n, d = x.shape
        positions = torch.arange(cache.position, cache.position + n, device=x.device)
        mask = causal_mask(n, len(cache.layers[0]) + n, device=x.device)
        cos, sin = rope_tables_at(self.table, positions)
        cos, sin = cos[:, None, None].to(x.dtype), sin[:, None, None].to(x.dtype)
        for block, kernels, layer_cache in zip(vae.decoder, self.kernels, cache.layers):
            heads = block.attn.heads
            h = F.layer_norm(x, (d,), block.norm1.weight, block.norm1.bias, block.norm1.eps)
            qkv = kernels.qkv(h).view(b, n, 3, heads, d // heads)
            qk = apply_rope(qkv[:, :, :2], cos, sin).transpose(1, 3)  # (B, H, 2, L, Dh)
            k, v = layer_cache.extend(qk[:, :, 1], qkv[:, :, 2].transpose(1, 2))
            a = F.scaled_dot_product_attention(qk[:, :, 0], k, v, attn_mask=mask)
            x = x + kernels.out(a.transpose(1, 2).reshape(b, n, d))
            x = x + kernels.mlp(F.layer_norm(x, (d,), block.norm2.weight, block.norm2.bias,
                                             block.norm2.eps))
        cache.position += n
        cache.blocks += 1
        return vae._decoder_frames(x)
