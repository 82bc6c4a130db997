"""Linear layers with fewer bytes of weights to read: int8 and bfloat16 replacements.

At inference on a CPU the flow's Linears are bound by reading their weights (a chunk runs 8
evaluations over 3 tokens x 2 guidance branches), so weight bytes are the first cost to cut.

* ``Int8Linear``: dynamic int8 quantization -- int8 weights with one symmetric scale per output
  channel, activations quantized per call, or per stream when a batch holds several
  (``nn.streams``) (to the full 8 bits where the CPU has VNNI, else 7)
  -- computed by torch's ``quantized::linear_dynamic`` kernel (fbgemm). With 7-bit rows
  bit-identical to ``torch.ao.quantization.quantize_dynamic`` with
  ``per_channel_dynamic_qconfig``, built from public calls only (observer,
  ``quantize_per_channel``, ``linear_prepack``) and called as one kernel (the eager quantized
  module adds ~10 us of Python to a ~15 us call).
  Only for Linears large enough to gain from it (``worth_quantizing``).
* ``PerStreamLinear``: fp32, each stream's rows of a batch computed as they are alone -- where a
  Linear is too small for int8 to pay, and in the exact fp32 mode's solve.
* ``BF16Linear``: bfloat16 weights and activations, output in the input dtype.
* ``PackedLinear``: fp32 or bfloat16 weights reordered once into oneDNN's blocked GEMM layout
  (``cpu.onednn_linear_ops``). ``F.linear`` repacks its weight at every call: for the few rows
  of a streamed step that repacking, not the arithmetic, is the call (36 Linears of the paper
  decoder, 5 rows, 1 thread on the AMD EPYC of 2026-11-25: 6.5 ms in fp32 through MKL, 3.1 ms
  in bf16, 2.4 ms packed fp32, 1.7 ms packed bf16). Packed fp32 differs from ``F.linear`` by
  summation order only (~1e-6). A oneDNN call has a fixed cost of its own, though, and below
  ``PACK_MIN_WEIGHTS`` weights it is larger than the repacking it saves (``worth_packing``).
* ``ByRowsLinear``: one Linear, two of the above, chosen per call by how many rows it brings:
  where the CPU has AMX, the int8 one for a streamed evaluation's few rows (bound by reading
  the weights) and the bf16 one for an offline window's hundreds (bound by arithmetic, which
  AMX does in bf16 and fbgemm does not).
"""

from __future__ import annotations

import warnings
from typing import Callable, Iterable, Iterator

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..nn.streams import stream_groups
from .cpu import amx_bf16_available, int8_full_range, onednn_bf16_available, onednn_linear_ops


class ComputedLinear(nn.Module):
    """A Linear replacement whose computation is a plain callable, ``self._compute``, built
    once with its weights; ``function()`` hands it out (see ``linear_function``)."""

    _compute: Callable[[Tensor], Tensor]

    def forward(self, x: Tensor) -> Tensor:
        return self._compute(x)

    def function(self) -> Callable[[Tensor], Tensor]:
        """This layer's computation as a plain callable (see ``linear_function``)."""
        return self._compute


class Int8Linear(ComputedLinear):
    """``reduce_range``: activations quantized to 7 bits (torch's default, and bit-identical to
    ``quantize_dynamic``) or 8; None: 8 where the CPU has VNNI (``cpu.int8_full_range``)."""

    def __init__(self, linear: nn.Linear, reduce_range: bool | None = None) -> None:
        super().__init__()
        self.reduce_range = not int8_full_range() if reduce_range is None else reduce_range
        from torch.ao.quantization.observer import PerChannelMinMaxObserver

        self.in_features, self.out_features = linear.in_features, linear.out_features
        weight = linear.weight.detach().float().cpu()
        observer = PerChannelMinMaxObserver(ch_axis=0, dtype=torch.qint8,
                                            qscheme=torch.per_channel_symmetric)
        observer(weight)
        scale, zero_point = observer.calculate_qparams()
        bias = None if linear.bias is None else linear.bias.detach().float().cpu()
        with warnings.catch_warnings():  # torch marks quantized tensor creation as deprecated
            warnings.simplefilter("ignore")
            qweight = torch.quantize_per_channel(weight, scale.double(), zero_point.long(), 0,
                                                 torch.qint8)
        self.packed = torch.ops.quantized.linear_prepack(qweight, bias)
        self._compute = self._computation()

    def _computation(self) -> Callable[[Tensor], Tensor]:
        """The kernel takes one activation scale per call, so a batch of several streams
        (``nn.streams.independent_streams``) is computed one stream's rows at a time: a
        stream's output must not depend on the other streams' activations."""
        op, packed, reduce_range = torch.ops.quantized.linear_dynamic.default, self.packed, self.reduce_range

        def compute(x: Tensor) -> Tensor:
            groups = streams_in(x)
            if groups == 1:
                return op(x, packed, reduce_range)
            return torch.cat([op(rows, packed, reduce_range) for rows in x.chunk(groups)])
        return compute

    def extra_repr(self) -> str:
        bits = 7 if self.reduce_range else 8
        return f"in_features={self.in_features}, out_features={self.out_features}, int8 ({bits}-bit rows)"


def streams_in(x: Tensor) -> int:
    """How many streams' rows the batch ``x`` holds (``nn.streams.stream_groups``), checked."""
    groups = stream_groups()
    if x.shape[0] % groups:
        raise ValueError(f"a batch of {x.shape[0]} rows does not split into {groups} streams")
    return groups


class PerStreamLinear(ComputedLinear):
    """A Linear in fp32 (the same weights) that gives each stream's rows of a batch what they
    get alone. MKL's ``F.linear`` rounds a row differently with the number of rows in the call
    (another path at up to 3), so over all the streams' rows at once a stream would move with
    what else a server batches beside it. Several streams go through one batched matmul with
    one matrix per stream, which computes each as ``F.linear`` does alone (tested bit for bit:
    ``tests/test_fast.py``), at 1.1-2x the cost of one ``F.linear`` over all the rows where a
    call per stream cost 3-9x (8 streams of 6 rows, 128-512 wide). For the fp32 fast path's
    solve and Linears too small to be worth ``Int8Linear`` (``worth_quantizing``)."""

    def __init__(self, linear: nn.Linear) -> None:
        super().__init__()
        self.in_features, self.out_features = linear.in_features, linear.out_features
        self.weight, self.bias = linear.weight, linear.bias
        weight, bias = self.weight, self.bias
        size_in, size_out = self.in_features, self.out_features

        def compute(x: Tensor) -> Tensor:
            groups = streams_in(x)
            if groups == 1:
                return F.linear(x, weight, bias)
            rows = x.reshape(groups, -1, size_in)
            # the transpose taken per call, a view: a trace (``traced.py``) can hold the
            # parameter, not a tensor derived from it that requires grad
            weights = weight.t().expand(groups, size_in, size_out)
            y = torch.bmm(rows, weights) if bias is None else torch.baddbmm(bias, rows, weights)
            return y.reshape(*x.shape[:-1], size_out)
        self._compute = compute

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, fp32 per stream"


class BF16Linear(ComputedLinear):
    """A Linear computed in bfloat16 (weights stored in bfloat16); output in the input dtype."""

    def __init__(self, linear: nn.Linear) -> None:
        super().__init__()
        self.in_features, self.out_features = linear.in_features, linear.out_features
        self.weight = nn.Parameter(linear.weight.detach().to(torch.bfloat16), requires_grad=False)
        self.bias = (None if linear.bias is None else
                     nn.Parameter(linear.bias.detach().to(torch.bfloat16), requires_grad=False))
        weight, bias = self.weight, self.bias
        self._compute = lambda x: F.linear(x.to(torch.bfloat16), weight, bias).to(x.dtype)


class PackedLinear(ComputedLinear):
    """A Linear over oneDNN-packed weights (see the module docstring), computed in ``dtype``
    (float32 or bfloat16), output in the input dtype. CPU only; ``packed_linears_available()``
    says whether this torch can build one."""

    def __init__(self, linear: nn.Linear, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        ops = onednn_linear_ops()
        if ops is None:
            raise RuntimeError("PackedLinear needs torch's oneDNN linear ops (torch.ops.mkldnn), "
                               "which this torch does not have")
        if dtype not in (torch.float32, torch.bfloat16):
            raise ValueError(f"PackedLinear computes in float32 or bfloat16, not {dtype}")
        if dtype == torch.bfloat16 and not onednn_bf16_available():
            raise RuntimeError("oneDNN packs bfloat16 weights only on a CPU with AVX-512 BF16 or "
                               "AVX-NE-CONVERT; use BF16Linear on this one")
        reorder, self._op = ops
        self.in_features, self.out_features, self.dtype = linear.in_features, linear.out_features, dtype
        weight = linear.weight.detach().cpu().to(dtype).contiguous()
        # plain attributes, not buffers: an opaque oneDNN tensor has no storage to copy or save
        self.packed = reorder(weight)
        self.packed_bias = None if linear.bias is None else linear.bias.detach().cpu().to(dtype)
        op, packed, bias = self._op, self.packed, self.packed_bias
        if dtype == torch.float32:
            self._compute = lambda x: op(x, packed, bias, "none", [], "")
        else:
            self._compute = lambda x: op(x.to(dtype), packed, bias, "none", [], "").to(x.dtype)

    def extra_repr(self) -> str:
        return (f"in_features={self.in_features}, out_features={self.out_features}, "
                f"{str(self.dtype).removeprefix('torch.')}, oneDNN-packed")


class ByRowsLinear(ComputedLinear):
    """A Linear computed by ``few`` when a call brings fewer than ``min_rows`` rows, or the rows
    of several streams (``nn.streams``: ``few`` computes each stream's as alone), and by
    ``many`` otherwise. ``few`` and ``many`` are two replacements of the same Linear."""

    def __init__(self, few: nn.Module, many: nn.Module, min_rows: int) -> None:
        super().__init__()
        if (few.in_features, few.out_features) != (many.in_features, many.out_features):
            raise ValueError("few and many must replace the same Linear")
        self.few, self.many, self.min_rows = few, many, min_rows
        self.in_features, self.out_features = few.in_features, few.out_features
        compute_few, compute_many = linear_function(few), linear_function(many)
        least = min_rows * self.in_features

        def compute(x: Tensor) -> Tensor:
            if x.numel() >= least and stream_groups() == 1:
                return compute_many(x)
            return compute_few(x)
        self._compute = compute

    def extra_repr(self) -> str:
        return f"min_rows={self.min_rows}"


# From how many rows of one stream a ``ByRowsLinear`` of the int8 mode computes in bf16 on AMX.
# The Xeon with AMX of 2026-12-03, one paper-size block's 4 Linears (qkv, out, MLP), int8 /
# bf16 per call: 6 rows 891 / 1,514 us (1 thread), 614 / 1,023 (2); 24 rows 1,647 / 1,744,
# 1,033 / 1,152; 32 rows 2,015 / 1,812, 1,217 / 1,222; 100 rows 5,112 / 2,986, 2,925 / 2,193.
# A streamed evaluation brings 6 rows (3 tokens x 2 guidance branches), an offline window 200.
AMX_MIN_ROWS = 32


def int8_linear(linear: nn.Linear) -> nn.Module:
    """The int8 mode's replacement of a large Linear (``worth_quantizing``): an ``Int8Linear``,
    or where the CPU has AMX a ``ByRowsLinear`` that computes ``AMX_MIN_ROWS`` rows or more in
    bf16 (oneDNN-packed). On the Xeon with AMX of 2026-12-03 (paper size, 1024 -> 4096, 2
    threads, p50 per call, in turns): 6 rows int8 182 us, bf16 454; 400 rows int8 3.4 ms, bf16
    1.9 ms; paper-size offline generation 1.3x faster, and nearer fp32 (docs/performance.md).
    AMX alone: the same VM with oneDNN held to AVX-512 BF16 computed 32-200 rows in bf16
    3.9-4.4x slower than int8."""
    if amx_bf16_available() and packed_linears_available(torch.bfloat16):
        return ByRowsLinear(Int8Linear(linear), PackedLinear(linear, torch.bfloat16), AMX_MIN_ROWS)
    return Int8Linear(linear)


# The smallest weight (in x out entries) worth a ``PackedLinear``. Timed on the AMD EPYC of
# 2026-11-27 (1 thread, 4-5 rows, us per call, F.linear / packed): 128 x 128 27 / 69,
# 128 x 512 32 / 53, 512 x 128 51 / 69, 256 x 256 35 / 53 -- oneDNN's per-call cost is larger
# than the repacking it saves -- while 256 x 768 89 / 78, 256 x 1024 112 / 88 and 128 x 2748
# 133 / 123. The tiny preset's Linears are all small but its frame output; the paper size's
# are large but its decoder's 256 x 256 ones and the condition encoders.
PACK_MIN_WEIGHTS = 2 ** 17


def worth_packing(linear: nn.Linear) -> bool:
    """Whether a ``PackedLinear`` computes ``linear`` faster than ``F.linear`` (a few rows)."""
    return linear.in_features * linear.out_features >= PACK_MIN_WEIGHTS


# The smallest weight (in x out entries) worth an ``Int8Linear``. Below it a call costs what
# the kernel's own overhead costs, not what reading the weights does, and int8 saves nothing
# (timed on the AMD EPYC of 2026-11-27, 1 thread, 6 rows, us per call, F.linear / int8: 128 x
# 128 17 / 38, 128 x 384 32 / 29, 128 x 512 51 / 41, 512 x 128 41 / 30 -- the tiny preset's
# blocks, equal in sum -- against 1024 x 1024 705 / 186 and 1024 x 4096 5,864 / 358), while its
# 7-bit activations cost millimetres on trained weights (docs/performance.md).
INT8_MIN_WEIGHTS = 2 ** 17


def worth_quantizing(linear: nn.Linear) -> bool:
    """Whether an ``Int8Linear`` is worth its rounding for ``linear`` (see INT8_MIN_WEIGHTS)."""
    return linear.in_features * linear.out_features >= INT8_MIN_WEIGHTS


# A Linear as it stands before or after ``optimize_for_inference`` swapped it.
LINEAR_KINDS = (nn.Linear, Int8Linear, PerStreamLinear, BF16Linear, PackedLinear, ByRowsLinear)


def packed_linears_available(dtype: torch.dtype = torch.float32) -> bool:
    """Whether a ``PackedLinear`` in ``dtype`` can be built here: torch's oneDNN linear ops, and
    for bfloat16 a CPU that oneDNN computes it on (AVX-512 BF16 or AVX-NE-CONVERT); an AVX2-only
    CPU refuses to pack bfloat16 weights, and ``BF16Linear`` stands in."""
    if onednn_linear_ops() is None:
        return False
    return dtype != torch.bfloat16 or onednn_bf16_available()


def linear_function(module: nn.Module) -> Callable[[Tensor], Tensor]:
    """What a Linear-like module computes, as a plain callable without the module call: the
    fused blocks call their Linears some 30 times per evaluation, and a module call costs
    ~10 us of Python next to a ~40 us int8 kernel. Take it once the layer is final (after any
    swap): it holds that layer's weights."""
    if isinstance(module, ComputedLinear):
        return module.function()
    if type(module) is nn.Linear:
        weight, bias = module.weight, module.bias
        return lambda x: F.linear(x, weight, bias)
    return module


def replace_module(root: nn.Module, name: str, module: nn.Module) -> None:
    """Put ``module`` where ``root.get_submodule(name)`` is."""
    parent, _, child = name.rpartition(".")
    setattr(root.get_submodule(parent) if parent else root, child, module)


def swap_linears(root: nn.Module, names: Iterable[str],
                 kind: Callable[[nn.Linear], nn.Module]) -> nn.Module:
    """Replace the Linears ``names`` of ``root`` by ``kind(linear)`` (in place)."""
    for name in names:
        replace_module(root, name, kind(root.get_submodule(name)))
    return root


def named_linears(root: nn.Module) -> Iterator[tuple[str, nn.Module]]:
    """Every Linear-like module of ``root`` with its name; a ``ByRowsLinear`` counts as one
    Linear (its two kernels are not listed apart)."""
    inside: list[str] = []
    for name, module in root.named_modules():
        if any(name.startswith(prefix) for prefix in inside):
            continue
        if isinstance(module, ByRowsLinear):
            inside.append(name + ".")
        if isinstance(module, LINEAR_KINDS):
            yield name, module


def flow_block_linears(flow: nn.Module) -> list[str]:
    """The Linears inside the flow's transformer blocks that run at every evaluation (attention
    and MLP: ~97 % of an evaluation's weights). The AdaLN modulations run once per flow time
    (memoized) and stay fp32, as do input/output projections and condition encoders: quantizing
    them too multiplied the deviation by ten for a 2 % gain in speed."""
    return [name for name, _ in named_linears(flow)
            if name.startswith("blocks.") and ".modulation." not in name]


def flow_outer_linears(flow: nn.Module) -> list[str]:
    """The flow's Linears outside its blocks that run at every evaluation or chunk: the
    latent input, the output projection, the condition encoders and ``cond_in`` (not the time
    path or the AdaLN modulations, which the time cache memoizes)."""
    return [name for name, _ in named_linears(flow)
            if name in ("latent_in", "out.proj", "cond_in") or name.startswith("encoders.")]


# The flow's Linears outside its blocks that ``step_together`` calls on many streams' rows at
# once. In the fused modes they stay oneDNN-packed whatever their size (in the exact fp32 mode
# they are ``PerStreamLinear``): MKL's ``F.linear`` rounds a row differently with the number of
# rows beside it, and a stream served with three others then came out up to 3.2 mm from itself
# alone (the shipped model through its decoding chain), where the packed kernel gives it the
# same frames.
BATCHED_OUTER_LINEARS = ("latent_in", "out.proj")


def decoder_linears(vae: nn.Module) -> list[str]:
    """The Linears a streamed VAE decode step runs: the latent input, every decoder layer's and
    the frame output."""
    return [name for name, _ in named_linears(vae)
            if name.startswith("decoder.") or name in ("latent_in", "frame_out")]
