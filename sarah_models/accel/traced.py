"""Flow blocks whose fused maths run as TorchScript traces: no Python between their operations.

Why: once the flow's Linears are int8, a streamed evaluation at paper size is ~100 small
tensor operations around 16 kernel calls, on 6 rows each, and each operation called from
Python costs several microseconds of dispatch before its kernel starts. A trace of the fused
block (``FusedAdaLNZeroBlock.modulated``, the same code, recorded once) replays those
operations from C++. Measured side by side on the 2-core Xeon of 2026-12-03 (paper size,
int8, 400 streamed chunks with the decoder, mean time traced / eager): 0.88 on 2 threads,
0.88-0.91 on one, 0.89 beside a busy process, the frames equal to the bit
(docs/performance.md). The tiny preset's fp32 blocks streamed 1.03-1.04x as long traced, so
``optimize_for_inference`` traces the int8 mode's quantized blocks only.

Why TorchScript and not ``torch.compile``: dynamo cannot put fbgemm's packed int8 weights (a
TorchScript class) into a graph ("Failed to convert args/kwargs to proxy"), so a compiled block
breaks at each of its four Linears; a trace records them as any other operation.
``torch.jit.trace`` is deprecated in favour of those two, so its FutureWarning is silenced
where it is called; where it is gone or fails, the block computes eagerly, as before.

A trace records one path through the Python: it holds for calls of the same shapes, dtype,
mask presence and number of batched streams (``nn.streams``; the int8 Linears quantize each
stream's rows alone, and ``ByRowsLinear`` picks its kernel by rows), so traces are kept per
such key, the most recent ``max_traces`` of them. Calls with a KV cache (which the cache
itself mutates) compute eagerly; the flow's streamed and offline solves use none.

Not traced: the VAE decoder's step. Replayed from two traces per layer around its KV cache (its
packed weights made module state, their op called through a scripted function) it gave the
same bits and no speed, 1.01 (0.995-1.03) side by side on 2026-12-03: its ops are ~95 % of
its time (docs/performance.md).
"""

from __future__ import annotations

import threading
import warnings
from typing import Callable

import torch
from torch import Tensor, nn

from ..nn.layers import KVCache
from ..nn.streams import stream_groups
from .fused import FoldedModulation, FusedAdaLNZeroBlock
from .memo import KeyedMemo


# One trace at a time in the process: ``warnings.catch_warnings`` changes the process's filters
# and is not thread-safe (two ``sarah-serve`` workers tracing at once let TracerWarnings through),
# and traces are made once per key, so waiting for one costs nothing that recurs.
TRACING = threading.Lock()


class ModulatedCall(nn.Module):
    """What a trace records: one block's ``FusedAdaLNZeroBlock.modulated`` over tensors only
    (the folded terms and rotary tables as inputs), with or without an attention mask."""

    def __init__(self, block: FusedAdaLNZeroBlock) -> None:
        super().__init__()
        self.block = block

    def forward(self, x: Tensor, attn_weight: Tensor, attn_bias: Tensor, attn_gate: Tensor,
                mlp_weight: Tensor, mlp_bias: Tensor, mlp_gate: Tensor, cos: Tensor, sin: Tensor,
                mask: Tensor | None = None) -> Tensor:
        terms = FoldedModulation(attn_weight, attn_bias, attn_gate, mlp_weight, mlp_bias, mlp_gate)
        return FusedAdaLNZeroBlock.modulated(self.block, x, terms, cos, sin, mask)


class TracedAdaLNZeroBlock(FusedAdaLNZeroBlock):
    """A fused flow block that replays its cache-free calls from traces (module docstring).
    A call that cannot be traced (through a ``PackedLinear``, whose oneDNN-packed weights are a
    plain attribute, not module state a trace holds, and whose op's list argument does not
    trace: the int8 mode's offline rows on AMX) computes eagerly, as before;
    ``untraced`` says which keys and why."""

    def __init__(self, block: FusedAdaLNZeroBlock, max_traces: int = 16) -> None:
        nn.Module.__init__(self)
        self.norm1, self.norm2, self.attn = block.norm1, block.norm2, block.attn
        self.mlp, self.modulation, self.folded = block.mlp, block.modulation, block.folded
        self.mlp_function = block.mlp_function
        self.traces = KeyedMemo(max_traces)  # shared by sarah-serve's compute threads
        self.untraced: dict[tuple, str] = {}

    def modulated(self, x: Tensor, terms: FoldedModulation, cos: Tensor, sin: Tensor,
                  mask: Tensor | None, cache: KVCache | None = None, commit: bool = True) -> Tensor:
        if cache is not None:
            return super().modulated(x, terms, cos, sin, mask, cache, commit)
        inputs = (x, terms.attn_weight, terms.attn_bias, terms.attn_gate, terms.mlp_weight,
                  terms.mlp_bias, terms.mlp_gate, cos, sin) + (() if mask is None else (mask,))
        key = (tuple(x.shape), x.dtype, None if mask is None else (tuple(mask.shape), mask.dtype),
               stream_groups())
        return self.traces.get(key, lambda: self._trace(key, inputs))(*inputs)

    def _trace(self, key: tuple, inputs: tuple[Tensor, ...]) -> Callable:
        """A trace of ``ModulatedCall`` over ``inputs``, or the call itself where tracing fails."""
        call = ModulatedCall(self)
        try:
            with TRACING, warnings.catch_warnings():  # deprecation, shape reads the key pins
                warnings.simplefilter("ignore", FutureWarning)
                warnings.simplefilter("ignore", torch.jit.TracerWarning)
                return torch.jit.trace(call, inputs, check_trace=False)
        except Exception as error:  # noqa: BLE001 -- whatever stops a trace, eager computes it
            self.untraced[key] = f"{type(error).__name__}: {str(error).splitlines()[0]}"
            return call
