"""Which CPU matmul kernel reads the paper-size flow's weights fastest for a streamed evaluation.

One flow evaluation of a streamed chunk multiplies 6 rows (2 guidance branches x 3 tokens) by
every Linear of the 4 transformer blocks (qkv 1024->3072, out 1024->1024, MLP 1024->4096->1024:
48 M weights). This times that stack per evaluation with each kernel torch offers on this CPU,
next to the time to merely read the same number of int8 bytes, so a reader can see how far the
kernel in use (`accel.linears.Int8Linear`, fbgemm's dynamic int8) is from the memory floor.

A second table does the same for the 36 Linears of one streamed VAE decoder step (5 rows: the
latent token and the block's 4 frames) with the precisions the decoder may run in: fp32 and
bf16 through ``F.linear``, and the same over oneDNN-packed weights (``accel.linears.PackedLinear``,
in use where torch has oneDNN).

``chunk_weight_bytes`` and ``read_floor_ms`` give the floor under a whole streamed chunk: the
weight bytes its Linears read, in the order they read them (the flow's per-evaluation weights
once per evaluation, then the decoder's), and the time this machine takes merely to read that
many bytes. No kernel computes a chunk faster than it can read its weights once; where a
chunk's weights do not fit in the last-level cache, every evaluation reads them from memory
again, and ``sarah-bench`` reports the fps that floor allows beside the fps measured.

    python -m sarah_bench.kernels [--threads 1 2]
"""

from __future__ import annotations

import argparse
import time
from typing import Callable

import torch
from torch import Tensor, nn

from sarah_cli.arguments import HelpFormatter, positive_int
from sarah_data.features import get_extractor
from sarah_models.accel import optimize_for_inference
from sarah_models.accel.linears import (
    BF16Linear,
    ByRowsLinear,
    Int8Linear,
    PackedLinear,
    PerStreamLinear,
    decoder_linears,
    flow_block_linears,
    flow_outer_linears,
    packed_linears_available,
)
from sarah_models.config import STREAMED_TOKENS, STRIDE, FlowConfig, StreamConfig, VAEConfig
from sarah_models.nn.flow import FlowModel
from sarah_models.nn.vae import CausalVAE
from sarah_models.sampling.solver import time_grid
from sarah_models.testing import random_models
from sarah_models.training.checkpoint import unpack_models

from .timing import percentiles, torch_threads

ROWS = 2 * STREAMED_TOKENS  # guidance branches x tokens a streamed evaluation sees
DECODER_ROWS = STRIDE + 1  # a streamed decoder step: the latent token and the block's frames


def block_shapes(config: FlowConfig) -> list[tuple[int, int]]:
    """(in, out) of the Linears a streamed evaluation reads in the flow's transformer blocks:
    all but the AdaLN modulation, which the fast path's time cache computes once per solver step
    grid (docs/performance.md)."""
    model = FlowModel(config, VAEConfig.paper().latent_dim, STRIDE, audio_dim=1)
    return [(m.in_features, m.out_features) for name, m in model.blocks.named_modules()
            if isinstance(m, nn.Linear) and "modulation" not in name]


def decoder_shapes(config: VAEConfig) -> list[tuple[int, int]]:
    """(in, out) of the Linears inside the decoder's transformer layers (one streamed step runs
    each once)."""
    model = CausalVAE(config, motion_dim=3)
    return [(m.in_features, m.out_features) for m in model.decoder.modules()
            if isinstance(m, nn.Linear)]


def decoder_kernels(shapes: list[tuple[int, int]], rows: int = DECODER_ROWS, seed: int = 0
                    ) -> dict[str, Callable[[], list[Tensor]]]:
    """name -> one decoder step's Linears computed each way, over the same weights and rows."""
    generator = torch.Generator().manual_seed(seed)
    linears = []
    for i, o in shapes:
        linear = nn.Linear(i, o)
        linear.weight.data = torch.randn(o, i, generator=generator) / i ** 0.5
        linear.bias.data = torch.randn(o, generator=generator) * 0.1
        linears.append(linear)
    x = {i: torch.randn(rows, i, generator=generator) for i in {i for i, _ in shapes}}

    def run(layers: list[nn.Module]) -> Callable[[], list[Tensor]]:
        calls = [(layer.in_features, layer.function() if hasattr(layer, "function") else layer)
                 for layer in layers]
        return lambda: [call(x[i]) for i, call in calls]

    table = {"fp32, F.linear (MKL)": run(linears), "bf16, F.linear": run([BF16Linear(m) for m in linears])}
    if packed_linears_available():
        table["fp32, oneDNN-packed"] = run([PackedLinear(m) for m in linears])
    if packed_linears_available(torch.bfloat16):
        table["bf16, oneDNN-packed"] = run([PackedLinear(m, torch.bfloat16) for m in linears])
    return table


def median_ms(step, repeats: int = 40, seconds: float = 3.0) -> float:
    """Median of up to ``repeats`` timed calls after two warm-up calls; a kernel 100x slower
    than the rest gets at least 5 calls, not ``repeats``."""
    step(), step()
    times: list[float] = []
    while len(times) < repeats and (len(times) < 5 or sum(times) < seconds):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return percentiles(times)["p50"]


def kernels(shapes: list[tuple[int, int]], rows: int = ROWS, seed: int = 0) -> dict[str, Callable[[], list[Tensor]]]:
    """name -> one evaluation's products with that kernel: the same int8 weights (per output
    channel scales) times the same rows, so every kernel returns the same numbers up to its
    rounding (``tests/test_fast.py`` checks that), except the memory floor, which only reads."""
    generator = torch.Generator().manual_seed(seed)
    weights = [torch.randint(-127, 128, (o, i), generator=generator, dtype=torch.int8) for i, o in shapes]
    scales = [torch.rand(o, generator=generator) * 1e-2 + 1e-3 for _, o in shapes]
    x = {i: torch.randn(rows, i, generator=generator) for i in {i for i, _ in shapes}}
    linears = []
    for w, s in zip(weights, scales):
        linear = nn.Linear(w.shape[1], w.shape[0], bias=False)
        linear.weight.data = w.float() * s[:, None]
        linears.append(linear)
    fbgemm = [Int8Linear(linear) for linear in linears]
    x_bf16 = {i: v.bfloat16() for i, v in x.items()}
    # _int_mm multiplies int8 by int8: the rows are quantized too, one scale per row
    row_scale = {i: v.abs().amax(1, keepdim=True) / 127 for i, v in x.items()}
    x_int8 = {i: (v / row_scale[i]).round().to(torch.int8) for i, v in x.items()}
    weights_t = [w.t().contiguous() for w in weights]
    floor = torch.zeros(sum(i * o for i, o in shapes) // 8, dtype=torch.int64)
    return {
        "read the int8 bytes (memory floor)": lambda: [floor.sum()],
        "fbgemm dynamic int8 (in use)": lambda: [m(x[m.in_features]) for m in fbgemm],
        "fp32 (MKL)": lambda: [m(x[m.in_features]) for m in linears],
        "_weight_int8pack_mm, bf16 rows": lambda: [
            torch.ops.aten._weight_int8pack_mm(x_bf16[w.shape[1]], w, s.bfloat16()).float()
            for w, s in zip(weights, scales)],
        "_weight_int8pack_mm, fp32 rows": lambda: [
            torch.ops.aten._weight_int8pack_mm(x[w.shape[1]], w, s) for w, s in zip(weights, scales)],
        "_int_mm (int8 x int8)": lambda: [
            torch._int_mm(x_int8[w.shape[0]], w).float() * row_scale[w.shape[0]] * s
            for w, s in zip(weights_t, scales)],
    }


# The flow's Linears outside its blocks that run at every evaluation (the condition encoders and
# ``cond_in`` run once per chunk: ``StreamingGenerator`` caches the condition tokens).
FLOW_EVALUATION_OUTER = ("latent_in", "out.proj")


def weight_bytes(module: nn.Module) -> int:
    """Bytes of weights one call of a Linear-like module reads (bias left out)."""
    if isinstance(module, ByRowsLinear):  # a streamed call's few rows: its int8 kernel
        return weight_bytes(module.few)
    if isinstance(module, Int8Linear):
        return module.in_features * module.out_features
    if isinstance(module, BF16Linear):
        return module.in_features * module.out_features * 2
    if isinstance(module, PackedLinear):
        return module.in_features * module.out_features * torch.finfo(module.dtype).bits // 8
    if isinstance(module, (nn.Linear, PerStreamLinear)):
        return module.weight.numel() * module.weight.element_size()
    raise TypeError(f"not a Linear: {type(module).__name__}")


def chunk_weight_bytes(models, config: StreamConfig = StreamConfig()) -> dict[str, int]:
    """The weight bytes one streamed chunk reads, by group: ``evaluation`` (the flow's block
    Linears and its latent input and output projection, read once per solver evaluation),
    ``evaluations`` (how many a chunk runs), ``chunk`` (the condition encoders and ``cond_in``,
    once per chunk) and ``decoder`` (one VAE decoder step). ``models`` as for
    ``optimize_for_inference`` (optimized or plain: each Linear counts in its own precision);
    the AdaLN modulations and the time path are not counted, as the fast path memoizes them."""
    vae, flow, _ = unpack_models(models)
    outer = flow_outer_linears(flow)
    once = [n for n in outer if n not in FLOW_EVALUATION_OUTER]
    per_evaluation = flow_block_linears(flow) + [n for n in outer if n in FLOW_EVALUATION_OUTER]
    return {
        "evaluation": sum(weight_bytes(flow.get_submodule(n)) for n in per_evaluation),
        "evaluations": len(time_grid(config.steps, config.solver)),
        "chunk": sum(weight_bytes(flow.get_submodule(n)) for n in once),
        "decoder": sum(weight_bytes(vae.get_submodule(n)) for n in decoder_linears(vae)),
    }


def total_bytes(weights: dict[str, int]) -> int:
    """All the bytes of ``chunk_weight_bytes``'s groups that one chunk reads."""
    return weights["evaluation"] * weights["evaluations"] + weights["chunk"] + weights["decoder"]


def read_floor_ms(weights: dict[str, int], thread_counts: tuple[int, ...],
                  repeats: int = 20) -> dict[int, float]:
    """Per thread count, the median ms to read ``chunk_weight_bytes``'s bytes in a chunk's order
    (the per-evaluation weights ``evaluations`` times, then the per-chunk and the decoder's): the
    time no kernel can beat."""
    buffers = {key: torch.ones(max(weights[key] // 8, 1), dtype=torch.int64)
               for key in ("evaluation", "chunk", "decoder")}

    def chunk() -> None:
        for _ in range(weights["evaluations"]):
            buffers["evaluation"].sum()
        buffers["chunk"].sum()
        buffers["decoder"].sum()

    floors = {}
    for threads in thread_counts:
        with torch_threads(threads):
            floors[threads] = median_ms(chunk, repeats=repeats)
    return floors


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m sarah_bench.kernels", formatter_class=HelpFormatter,
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=positive_int, nargs="+", default=[1, 2],
                        help="intra-op thread counts to time")
    args = parser.parse_args()
    shapes = block_shapes(FlowConfig.paper())
    megabytes = sum(i * o for i, o in shapes) / 2**20
    print(f"one paper-size flow evaluation: {ROWS} rows x {megabytes:.0f} MB of int8 weights")
    for threads in args.threads:
        with torch_threads(threads):
            timed = {name: median_ms(step) for name, step in kernels(shapes).items()}
        for name, ms in timed.items():
            print(f"threads {threads}  {name:34s} {ms:8.2f} ms / evaluation "
                  f"({megabytes / 1024 / (ms / 1e3):5.1f} GB/s counted in int8 bytes)")
    shapes = decoder_shapes(VAEConfig.paper())
    print(f"one paper-size VAE decoder step: {DECODER_ROWS} rows x {len(shapes)} Linears "
          f"({sum(i * o for i, o in shapes) / 1e6:.1f} M weights)")
    for threads in args.threads:
        with torch_threads(threads):
            timed = {name: median_ms(step) for name, step in decoder_kernels(shapes).items()}
        for name, ms in timed.items():
            print(f"threads {threads}  {name:34s} {ms:8.2f} ms / step")
    models = random_models("paper", audio_dim=get_extractor("logmel").dim)  # as sarah-bench's
    weights = chunk_weight_bytes(optimize_for_inference(models, "int8"))
    print(f"one streamed paper-size chunk, int8 fast path: {total_bytes(weights) / 2**20:.0f} MB "
          "of weights read")
    for threads, ms in read_floor_ms(weights, tuple(args.threads)).items():
        print(f"threads {threads}  {'read them (memory floor)':34s} {ms:8.2f} ms / chunk "
              f"({1000 * STRIDE / ms:5.0f} fps at most)")


if __name__ == "__main__":
    main()
