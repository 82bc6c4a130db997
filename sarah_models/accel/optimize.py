"""Inference speed-ups for generation on a CPU: copies of the models with modules REPLACED.

Nothing here patches a method or reads a private field: ``optimize_for_inference`` deep-copies
the models and puts subclasses of the reference modules (or memo wrappers around them) where
the reference modules were, so the reference model's own ``forward``, ``decoder_step`` and
solver run unchanged on top of them. Each swap is checked against the plain fp32 models
(``sarah_models.testing.stream_deviation``, ``tests/test_fast.py``, ``tests/test_fused.py``).

Where the time goes (paper size, streaming, 2 CPU cores): in plain fp32 ~95 % is ``nn.Linear``
of the flow model, bound by reading the weights -- a chunk runs 8 network evaluations over only
3 tokens x 2 guidance branches, so every evaluation streams all ~75 M flow weights from memory.
Once those are int8, the many small operations around them are the other half of the time.

* time cache (every mode but "none", exact): the flow-time embedding and MLP, and every AdaLN
  modulation, depend on the flow time only; the solver visits a fixed grid (``solver.time_grid``),
  so they are ``InputMemo``-wrapped and filled up front (``warm_up``). That removes ~27 M of the
  ~77 M weights from every evaluation.
* rope cache (every mode but "none", exact): the flow's rotary angles are memoized; the VAE
  decoder's come from a growing table (``RopeTable``, bit-identical).
* per stream (fp32 mode): the Linears of the flow's solve become ``PerStreamLinear``, so that a
  stream served beside others gets exactly what it gets alone (``F.linear`` on all the streams'
  rows moved it by 0.1 mm over 256 frames); one stream alone runs the very same calls.
* int8: the Linears of the flow's blocks become ``Int8Linear`` (4x fewer weight bytes) where
  they are large enough for the bytes to be the cost (``linears.worth_quantizing``: the paper
  size's are, the tiny preset's are not); the others stay fp32 as ``PerStreamLinear``, no slower,
  and ~1000x closer to fp32 on the shipped model (0.005 against 3.6 mm). Where the CPU has AMX,
  each int8 Linear is a ``ByRowsLinear`` whose calls of many rows (offline generation) run in
  bf16 on AMX instead (``linears.int8_linear``); a streamed evaluation's few rows stay int8.
* bf16: the same Linears become ``BF16Linear`` (2x fewer; ``PackedLinear`` in bf16 where
  oneDNN is there).
* decoder (int8 and bf16 modes): the VAE decoder's Linears in fp32 (``decoder="auto"``, or
  "fp32") or, asked for, bfloat16 ("bf16"). Not bf16 by default: on the shipped fixture model a
  bf16 decoder moved joints by up to 45 mm over 64 streamed frames (the fp32 one by 0.00 mm),
  and once packed it saves only 0.1-0.7 ms per step (docs/performance.md).
* packed (int8 and bf16 modes, CPU with oneDNN): every Linear that stays fp32 or bf16, runs
  per evaluation or step -- the flow's latent input, output projection and condition encoders,
  the VAE decoder's -- and is large enough (``linears.worth_packing``) becomes ``PackedLinear``
  (weights reordered once; ``F.linear`` repacks them at every call, which for a few rows is
  most of the call; for a small weight oneDNN's own per-call cost is more). fp32 ones change
  only the summation order. The flow's latent input and output projection are packed at any
  size (``linears.BATCHED_OUTER_LINEARS``: a stream gets the same rows whatever shares the call).
* fused (int8 and bf16 modes): the flow's blocks and output layer become
  ``FusedAdaLNZeroBlock`` / ``FusedAdaLNZeroOutput`` and the decoder's attention
  ``FusedAttention`` (fewer operations; rounding differs at the 1e-6 level, so the exact "fp32"
  mode does not use them).
* traced (int8 mode where the flow's blocks are quantized, ``trace=True``, the default): the
  fused flow blocks replay their maths from TorchScript traces, one per call shape
  (``TracedAdaLNZeroBlock``): no Python between a block's ~25 operations. Bit-identical to the
  eager fused blocks; a streamed paper-size chunk 0.88x side by side. Not the tiny preset's fp32
  blocks (their chunk measured 1.03-1.04x traced) nor the bf16 mode's (unmeasured; its
  oneDNN-packed weights, a plain attribute of ``PackedLinear``, are no module state a trace
  holds) (docs/performance.md).
* threads: ``torch.set_num_threads`` (process-wide).
* compile: ``torch.compile`` of the flow's transformer blocks (optional; measured on 2 CPU cores:
  about a minute to compile and no gain over eager, so off by default).

Not used, and why: KV caching in the flow model is not exact for the paper's protocol (history
tokens are re-noised at every solver step and the 3-token window truncates their causal
context, see ``nn/flow.py``); batched guidance and per-block condition caching are already what
``StreamingGenerator`` does; the VAE decoder already streams with a KV cache.
"""

from __future__ import annotations

import copy
import dataclasses
from functools import partial

import torch
from torch import nn

from ..config import StreamConfig
from ..nn.flow import FlowModel
from ..nn.layers import AdaLNZeroBlock, TransformerBlock
from ..nn.vae import CausalVAE
from ..sampling.solver import time_grid
from ..sampling.stream import kept_history
from ..training.checkpoint import unpack_models
from .fused import FusedAdaLNZeroBlock, FusedAdaLNZeroOutput, FusedTransformerBlock
from .linears import (
    BATCHED_OUTER_LINEARS,
    BF16Linear,
    PackedLinear,
    PerStreamLinear,
    decoder_linears,
    flow_block_linears,
    flow_outer_linears,
    int8_linear,
    packed_linears_available,
    swap_linears,
    worth_packing,
    worth_quantizing,
)
from .memo import InputMemo, RopeTable, RopeTables
from .traced import TracedAdaLNZeroBlock

MODES = ("none", "fp32", "bf16", "int8")
DECODER_PRECISIONS = ("auto", "fp32", "bf16")
MODE_HELP = {
    "none": "the plain models (only the thread count is set)",
    "fp32": "fp32 with the flow-time path memoized for the solver grid (exact; a served "
            "stream's rows computed on their own)",
    "bf16": "fp32 time cache + bfloat16 Linear layers + fused blocks + the other Linears "
            "oneDNN-packed",
    "int8": "fp32 time cache + dynamic int8 Linear layers where large enough to gain "
            "(per-channel weight scales, 8-bit rows with VNNI; offline, bf16 on AMX) + fused "
            "blocks (int8 ones traced) + the other Linears oneDNN-packed",
}


def memoize_time_path(flow: FlowModel, fused: bool) -> None:
    """Memo-wrap the time embedding and MLP; without ``fused`` every AdaLN modulation too (the
    fused blocks fold and memoize their modulations themselves)."""
    flow.time_embedding = InputMemo(flow.time_embedding)
    flow.time_mlp = InputMemo(flow.time_mlp)
    if not fused:
        for module in [*flow.blocks, flow.out]:
            module.modulation = InputMemo(module.modulation)


def fuse_flow(flow: FlowModel, traced: bool = False) -> None:
    """Blocks and output layer -> their fused subclasses, sharing one rotary table memo; with
    ``traced`` the blocks replay their fused maths from traces (``traced.py``)."""
    tables = RopeTables(flow.blocks[0].attn.rope.angles)
    blocks = [FusedAdaLNZeroBlock(block, tables) for block in flow.blocks]
    flow.blocks = nn.ModuleList(TracedAdaLNZeroBlock(b) if traced else b for b in blocks)
    flow.out = FusedAdaLNZeroOutput(flow.out)


def memoize_flow_rope(flow: FlowModel) -> None:
    for block in flow.blocks:
        block.attn.rope.angles = InputMemo(block.attn.rope.angles, max_entries=16)


def table_decoder_rope(vae: CausalVAE, fused: bool) -> None:
    """Every decoder layer's rotary angles from one growing ``RopeTable``; with ``fused`` the
    decoder's blocks become ``FusedTransformerBlock`` over shared rotary tables."""
    table = RopeTable(vae.decoder[0].attn.rope.angles)
    tables = RopeTables(table)
    for block in vae.decoder:
        block.attn.rope.angles = table
    if fused:
        vae.decoder = nn.ModuleList(FusedTransformerBlock(block, tables) for block in vae.decoder)


def resolve_decoder(decoder: str, mode: str) -> str:
    """The decoder precision ``optimize_for_inference`` uses: "fp32" or "bf16"."""
    if decoder not in DECODER_PRECISIONS:
        raise ValueError(f"unknown decoder precision {decoder!r}; choose from {DECODER_PRECISIONS}")
    if mode in ("none", "fp32"):
        if decoder == "bf16":
            raise ValueError(f"mode {mode!r} keeps the models in fp32: a bf16 decoder needs mode "
                             "int8 or bf16")
        return "fp32"
    return "fp32" if decoder == "auto" else decoder


def packed_where_worth_it(root: nn.Module, names: list[str], dtype: torch.dtype = torch.float32
                          ) -> list[str]:
    """``names`` of ``root`` that ``worth_packing`` become ``PackedLinear`` in ``dtype``;
    returns the others."""
    big = [name for name in names if worth_packing(root.get_submodule(name))]
    swap_linears(root, big, partial(PackedLinear, dtype=dtype))
    return [name for name in names if name not in big]


def swap_decoder_linears(vae: CausalVAE, precision: str, packed: bool) -> None:
    """The VAE decoder's Linears in ``precision`` ("fp32" or "bf16"), oneDNN-packed when
    ``packed`` and large enough (never int8: 2.7 mm from fp32 at paper size, over the 1 mm
    limit)."""
    dtype = torch.bfloat16 if precision == "bf16" else torch.float32
    rest = decoder_linears(vae)
    if packed and packed_linears_available(dtype):
        rest = packed_where_worth_it(vae, rest, dtype)
    if precision == "bf16":
        swap_linears(vae, rest, BF16Linear)


@torch.inference_mode()
def warm_up(flow: FlowModel, config: StreamConfig) -> int:
    """Evaluate the flow once at every flow time of ``config``'s solver grid so that every memo
    holds its entries before the first chunk (a scalar flow time's terms are computed for one
    row and broadcast, so one evaluation serves any batch), then once at every shape a stream's
    solve brings (1 to history + 1 tokens, one or both guidance branches) so that traced blocks
    (``traced.py``) trace them now, not in a stream's first chunks (~0.1 s each at paper size);
    returns the number of evaluations."""
    device = next(flow.parameters()).device
    grid = time_grid(config.steps, config.solver)
    calls = [(tau, 1, 1) for tau in grid]  # (flow time, branches, tokens)
    history = kept_history(flow, config)
    if history is not None:
        calls += [(grid[0], branches, tokens) for tokens in range(1, history + 2)
                  for branches in (1, 2)]
    for tau, branches, tokens in calls:
        z = torch.zeros(branches, tokens, flow.latent_dim, device=device)
        flow(z, tau, cond_tokens=torch.zeros(branches, tokens, flow.config.hidden, device=device))
    return len(calls)


def compile_blocks(module: nn.Module) -> nn.Module:
    """``torch.compile`` every transformer block in place (hooks and names stay as they are)."""
    for m in module.modules():
        if isinstance(m, (AdaLNZeroBlock, TransformerBlock)):
            m.compile(dynamic=False)
    return module


def optimize_for_inference(models, mode: str = "int8", *, stream_config: StreamConfig | None = None,
                           threads: int | None = None, compile: bool = False,
                           decoder: str = "auto", trace: bool = True):
    """Optimized copies of ``models`` for generation; the originals are not modified.

    models: ``training.checkpoint.LoadedModels`` or a ``(vae, flow[, normalizer])`` tuple; the
    same kind is returned. mode: one of ``MODES`` (see ``MODE_HELP``). stream_config: whose
    solver grid to precompute (default the paper's). threads: ``torch.set_num_threads`` when
    given. compile: also ``torch.compile`` the flow's blocks. decoder: the VAE decoder's Linears
    in int8 and bf16 modes, one of ``DECODER_PRECISIONS`` (``resolve_decoder``). trace: in int8
    mode, where the flow's blocks are quantized (the paper size's), they run from TorchScript
    traces (bit-identical to computing them eagerly; False computes them eagerly)."""
    if mode not in MODES:
        raise ValueError(f"unknown optimization mode {mode!r}; choose from {MODES}")
    if threads is not None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        torch.set_num_threads(threads)
    try:
        vae, flow, normalizer = unpack_models(models)
    except TypeError as error:
        raise TypeError(f"optimize_for_inference: {error}") from None
    if flow is None:
        raise ValueError("optimize_for_inference needs a flow model (a flow-stage checkpoint)")
    device = next(vae.parameters()).device
    precision = resolve_decoder(decoder, mode)
    if mode == "int8" and next(flow.parameters()).device.type != "cpu":
        raise ValueError(f"int8 dynamic quantization runs on the CPU only, models are on "
                         f"{next(flow.parameters()).device}")
    vae, flow = copy.deepcopy(vae).eval(), copy.deepcopy(flow).eval()
    if mode != "none":
        fused = mode != "fp32"  # fused blocks round differently: not in the exact mode
        packed = fused and device.type == "cpu" and packed_linears_available()
        traced = False  # where tracing measured faster: int8 blocks (``traced.py``)
        swap_decoder_linears(vae, precision, packed)
        if packed:  # fp32 kept (see the module docstring), packed: summation order only
            outer = flow_outer_linears(flow)
            swap_linears(flow, [n for n in outer if n in BATCHED_OUTER_LINEARS], PackedLinear)
            packed_where_worth_it(flow, [n for n in outer if n not in BATCHED_OUTER_LINEARS])
        if mode == "int8":
            blocks = flow_block_linears(flow)
            large = [name for name in blocks if worth_quantizing(flow.get_submodule(name))]
            swap_linears(flow, large, int8_linear)
            swap_linears(flow, [name for name in blocks if name not in large], PerStreamLinear)
            traced = trace and bool(large) and not compile
        elif mode == "fp32":  # exact, and a stream's rows as alone whatever shares the solve
            swap_linears(flow, [*flow_block_linears(flow), *BATCHED_OUTER_LINEARS], PerStreamLinear)
        elif mode == "bf16":  # at any size: the solve calls them on many streams' rows
            bf16_packed = packed and packed_linears_available(torch.bfloat16)
            swap_linears(flow, flow_block_linears(flow),
                         partial(PackedLinear, dtype=torch.bfloat16) if bf16_packed else BF16Linear)
        table_decoder_rope(vae, fused)
        memoize_time_path(flow, fused)
        if fused:
            fuse_flow(flow, traced)
        else:
            memoize_flow_rope(flow)
        warm_up(flow, stream_config or StreamConfig())
    if compile:  # the flow only: the VAE decoder's growing KV cache would recompile per step
        compile_blocks(flow)
    if dataclasses.is_dataclass(models):
        return dataclasses.replace(models, vae=vae, flow=flow)
    return (vae, flow) if normalizer is None else (vae, flow, normalizer)
