"""Inference optimizations stay within their stated tolerance of the plain fp32 models, the
naive streaming reference computes what the generator computes, and sarah-bench runs.

Tolerances (a stream of fixed seed and inputs, joints = icosahedron centroids, world frame):
  fp32 (time cache + rotary tables)           identical frames (0 mm)
  bf16 Linears in the flow's blocks            max joint deviation <= 1 mm
  int8 Linears in the flow's blocks            max joint deviation <= 1 mm, paper size too
  both                                          |head-angle delta| <= 0.01, |wrist-speed delta| <= 0.01 m/s
Models have random weights and a motion std of 0.1 m per coordinate (testing.random_models).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

import sarah_models.accel.cpu as cpu_module
import sarah_models.accel.optimize as optimize_module
from helpers import spinning_processes
from sarah_data.skeleton import MotionLayout
from sarah_bench.naive import NaiveStreamer
from sarah_models.accel import optimize_for_inference, resolve_decoder
import sarah_models.accel.linears as linears_module
from sarah_models.accel.linears import (BF16Linear, ByRowsLinear, Int8Linear, PackedLinear,
                                        PerStreamLinear, decoder_linears, flow_block_linears,
                                        flow_outer_linears, packed_linears_available,
                                        worth_packing, worth_quantizing)
from sarah_models.accel.memo import InputMemo
from sarah_models.config import RunConfig, StreamConfig
from sarah_models.nn.layers import KVCache, RopeAngles
from sarah_models.nn.streams import independent_streams, stream_groups
from sarah_models.sampling.solver import time_grid
from sarah_models.sampling.stream import StreamingGenerator, generate_offline, kept_history
from sarah_models.testing import (generate_stream, random_models, stream_deviation, stream_inputs,
                                  without_foot_lock)
from sarah_models.training.checkpoint import LoadedModels

AUDIO_DIM = 8
SHELL = 4
TOLERANCE_MM = 1.0
METRIC_TOLERANCE = 0.01


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def tiny():
    return random_models("tiny", audio_dim=AUDIO_DIM, shell_points=SHELL, seed=0)


def test_fp32_mode_is_exact_and_fully_precomputed(tiny):
    fast = optimize_for_inference(tiny, "fp32")
    memos = [m for m in fast[1].modules() if isinstance(m, InputMemo)]
    rope = [m for m in memos if isinstance(m.module, RopeAngles)]
    time = [m for m in memos if m not in rope]
    assert len(time) == 3 + len(fast[1].blocks)  # time embedding and MLP, every block, output
    assert len(rope) == len(fast[1].blocks)
    misses = [m.misses for m in time]
    deviation = stream_deviation(tiny, fast, frames=24)
    assert deviation.max_joint_mm == 0.0
    assert deviation.head_angle_delta == 0.0
    # Every evaluation found its tau in the grid computed up front: nothing computed anew.
    assert [m.misses for m in time] == misses
    assert all(m.hits > 0 for m in time)
    # Rotary angles: computed once per context length (1, 2, then 3 tokens), then looked up.
    kept = kept_history(tiny[1], StreamConfig())
    assert all(m.misses == kept + 1 and m.hits > m.misses for m in rope)


def test_optimized_copies_leave_the_originals_alone(tiny):
    vae, flow, _ = tiny
    before = {k: v.clone() for k, v in flow.state_dict().items()}
    fast = optimize_for_inference(tiny, "int8")
    assert not any(isinstance(m, InputMemo) for m in flow.modules())
    assert all(torch.equal(before[k], v) for k, v in flow.state_dict().items())
    assert fast[0] is not vae and fast[2] is tiny[2]
    # the tiny preset's block Linears are too small to be worth int8 (linears.worth_quantizing)
    assert not any(isinstance(m, (torch.nn.Linear, Int8Linear)) for m in fast[1].blocks[0].mlp)
    assert any(isinstance(m, PerStreamLinear) for m in fast[1].blocks[0].mlp)


def test_loaded_models_in_loaded_models_out(tiny):
    vae, flow, normalizer = tiny
    loaded = LoadedModels(vae, flow, normalizer, RunConfig.preset("tiny"),
                          {"motion": vae.motion_dim, "audio": AUDIO_DIM}, "logmel", 0, "flow")
    fast = optimize_for_inference(loaded, "bf16")
    assert isinstance(fast, LoadedModels) and fast.features == "logmel"
    assert any(computes_in_bf16(m) for m in fast.flow.modules())
    assert fast.vae is not vae


def test_bad_arguments(tiny):
    with pytest.raises(ValueError, match="unknown optimization mode"):
        optimize_for_inference(tiny, "fp8")
    with pytest.raises(ValueError, match="threads"):
        optimize_for_inference(tiny, "fp32", threads=0)
    with pytest.raises(TypeError, match="LoadedModels"):
        optimize_for_inference(tiny[1], "fp32")


@pytest.mark.parametrize("mode", ["bf16", "int8"])
def test_reduced_precision_within_tolerance(tiny, mode):
    deviation = stream_deviation(tiny, optimize_for_inference(tiny, mode), frames=32)
    assert 0.0 < deviation.max_joint_mm <= TOLERANCE_MM, deviation
    assert deviation.head_angle_delta <= METRIC_TOLERANCE
    assert deviation.wrist_speed_delta <= METRIC_TOLERANCE


@pytest.mark.skipif(shutil.which("g++") is None and shutil.which("c++") is None,
                    reason="torch.compile on a CPU needs a C++ compiler")
def test_compiled_blocks_within_tolerance(tiny):
    """``compile=True``: the flow's blocks through torch.compile (inductor) stay within the
    tolerance of the plain models (the fp32 mode runs the blocks' own forwards)."""
    compiled = optimize_for_inference(tiny, "fp32", compile=True)
    assert any(type(m).__name__ == "OptimizedModule" or getattr(m, "_compiled_call_impl", None)
               for m in compiled[1].modules())
    deviation = stream_deviation(tiny, compiled, frames=16)
    assert deviation.max_joint_mm <= TOLERANCE_MM, deviation
    assert deviation.head_angle_delta <= METRIC_TOLERANCE


def computes_in_bf16(module: torch.nn.Module) -> bool:
    return isinstance(module, BF16Linear) or (isinstance(module, PackedLinear)
                                              and module.dtype == torch.bfloat16)


@pytest.mark.parametrize("decoder", ["fp32", "bf16"])
def test_int8_within_tolerance_at_paper_size(decoder):
    paper = random_models("paper", audio_dim=AUDIO_DIM, shell_points=SHELL, seed=1)
    fast = optimize_for_inference(paper, "int8", decoder=decoder)
    assert any(computes_in_bf16(m) for m in fast[0].modules()) == (decoder == "bf16")
    block_linears = [fast[1].get_submodule(name) for name in flow_block_linears(paper[1])]
    int8 = type(linears_module.int8_linear(torch.nn.Linear(8, 8)))  # this CPU's int8 kind
    assert block_linears and all(isinstance(m, int8) for m in block_linears)
    deviation = stream_deviation(paper, fast, frames=12)
    assert 0.0 < deviation.max_joint_mm <= TOLERANCE_MM, deviation
    assert deviation.head_angle_delta <= METRIC_TOLERANCE


def test_by_rows_linear_takes_its_kernel_by_the_rows_of_one_stream():
    torch.manual_seed(0)
    linear = torch.nn.Linear(64, 96)
    layer = ByRowsLinear(PerStreamLinear(linear), BF16Linear(linear), min_rows=8)
    few, many = torch.randn(6, 64), torch.randn(2, 5, 64)
    assert torch.equal(layer(few), layer.few(few))
    assert not torch.equal(layer(few), layer.many(few))
    assert torch.equal(layer(many), layer.many(many))
    assert not torch.equal(layer(many), layer.few(many))
    with independent_streams(2):  # two streams' rows: each computed as alone, by ``few``
        assert torch.equal(layer(many), layer.few(many))
    with pytest.raises(ValueError, match="same Linear"):
        ByRowsLinear(PerStreamLinear(linear), BF16Linear(torch.nn.Linear(64, 32)), min_rows=8)
    assert flow_block_linears(torch.nn.Module()) == []
    root = torch.nn.Module()
    root.blocks = torch.nn.ModuleList([layer])  # listed once, not with its two kernels
    assert flow_block_linears(root) == ["blocks.0"]


@pytest.mark.skipif(not packed_linears_available(torch.bfloat16),
                    reason="oneDNN packs bfloat16 weights only with AVX-512 BF16 or AVX-NE-CONVERT")
def test_int8_mode_on_amx_streams_as_int8_and_generates_offline_within_tolerance(monkeypatch):
    """Where the CPU has AMX the int8 mode's large Linears compute an offline window's rows in
    bf16 (linears.int8_linear): a stream must not change by a bit, offline stays within 1 mm."""
    paper = random_models("paper", audio_dim=AUDIO_DIM, shell_points=SHELL, seed=1)
    monkeypatch.setattr(linears_module, "amx_bf16_available", lambda: False)
    int8 = optimize_for_inference(paper, "int8")
    monkeypatch.setattr(linears_module, "amx_bf16_available", lambda: True)
    amx = optimize_for_inference(paper, "int8")
    blocks = [amx[1].get_submodule(name) for name in flow_block_linears(paper[1])]
    assert blocks and all(isinstance(m, ByRowsLinear) and isinstance(m.few, Int8Linear)
                          and m.many.dtype == torch.bfloat16 for m in blocks)
    inputs = stream_inputs(160, AUDIO_DIM, seed=2)  # offline: 40 tokens x 2 guidance branches
    streamed = [inputs[0][:48], inputs[1][:48], inputs[2][:48]]
    np.testing.assert_array_equal(generate_stream(amx, streamed), generate_stream(int8, streamed))
    layout = MotionLayout.from_width(paper[0].motion_dim)
    offline = {name: layout.joint_positions(generate_offline(*models, *inputs))
               for name, models in (("fp32", paper), ("int8", int8), ("amx", amx))}
    assert not np.array_equal(offline["amx"], offline["int8"])  # the wide rows ran in bf16
    deviation_mm = np.linalg.norm(offline["amx"] - offline["fp32"], axis=-1).max() * 1000.0
    assert 0.0 < deviation_mm <= TOLERANCE_MM


def test_bf16_decoder_converts_the_decode_path_only(tiny):
    fast = optimize_for_inference(tiny, "int8", decoder="bf16")
    vae, names = fast[0], decoder_linears(tiny[0])
    assert "frame_out" in names and "decoder.0.attn.qkv" in names
    for name in names:
        assert computes_in_bf16(vae.get_submodule(name)), name
    assert all(type(m) is torch.nn.Linear for m in vae.encoder.modules()
               if isinstance(m, (torch.nn.Linear, BF16Linear, PackedLinear)))
    deviation = stream_deviation(tiny, fast, frames=32)
    assert 0.0 < deviation.max_joint_mm <= TOLERANCE_MM, deviation


@pytest.mark.skipif(not packed_linears_available(), reason="this torch has no oneDNN linear")
@pytest.mark.parametrize("bias", [True, False])
def test_packed_linear_computes_the_linear(bias):
    """fp32: F.linear up to summation order; bf16 (where the CPU packs it): BF16Linear bit for
    bit, else one clear error; any leading dims, zero rows, and inside a module call too."""
    torch.manual_seed(0)
    linear = torch.nn.Linear(48, 40, bias=bias)
    packed = PackedLinear(linear)
    bf16 = packed_linears_available(torch.bfloat16)
    if bf16:
        packed_bf16 = PackedLinear(linear, torch.bfloat16)
    else:
        with pytest.raises(RuntimeError, match="AVX-512 BF16"):
            PackedLinear(linear, torch.bfloat16)
    with torch.inference_mode():
        for x in (torch.randn(2, 3, 48) * 3, torch.randn(5, 48), torch.randn(0, 48)):
            reference = linear(x)
            assert packed(x).shape == reference.shape and packed(x).dtype == torch.float32
            torch.testing.assert_close(packed(x), reference, rtol=1e-5, atol=1e-5)
            if bf16:
                assert torch.equal(packed_bf16(x), BF16Linear(linear)(x))
            assert torch.equal(packed.function()(x), packed(x))
        # a row comes out the same whatever rows share the call (F.linear's does not: up to 3
        # rows it takes another path), which is why many streams' rows may share one
        rows = torch.randn(16, 48)
        assert all(torch.equal(packed(rows[:m]), packed(rows)[:m]) for m in range(1, 16))
    with pytest.raises(ValueError, match="float32 or bfloat16"):
        PackedLinear(linear, torch.float16)


def test_bf16_mode_runs_where_the_cpu_cannot_pack_bf16(tiny, monkeypatch):
    """An AVX2-only CPU refuses oneDNN's bf16 packing (seen: `--speed bf16` crashed there): the
    bf16 mode then computes its bf16 layers with BF16Linear and packs only the fp32 ones."""
    monkeypatch.setattr(optimize_module, "packed_linears_available",
                        lambda dtype=torch.float32: dtype != torch.bfloat16)
    vae, flow = optimize_for_inference(tiny, "bf16", decoder="bf16")[:2]
    assert all(isinstance(vae.get_submodule(name), BF16Linear) for name in decoder_linears(vae))
    assert not any(isinstance(m, PackedLinear) and m.dtype == torch.bfloat16
                   for m in [*vae.modules(), *flow.modules()])
    deviation = stream_deviation(tiny, (vae, flow, tiny[2]), frames=16)
    assert 0.0 < deviation.max_joint_mm <= TOLERANCE_MM, deviation


@pytest.mark.skipif(not packed_linears_available(), reason="this torch has no oneDNN linear")
def test_fused_modes_pack_the_linears_worth_packing_the_exact_mode_none(tiny, monkeypatch):
    """oneDNN-packed where the weight is large enough to gain from it, the plain Linear (with
    its ``F.linear``) where oneDNN's per-call cost would be the larger."""
    outer, decoder = flow_outer_linears(tiny[1]), decoder_linears(tiny[0])
    assert {"latent_in", "out.proj", "cond_in", "encoders.gaze.0"} <= set(outer)
    sizes = sorted(tiny[0].get_submodule(n).weight.numel() for n in decoder)
    # a limit inside the tiny model's range, so that both sides of it are checked
    monkeypatch.setattr(linears_module, "PACK_MIN_WEIGHTS", sizes[len(sizes) // 2])
    vae, flow = optimize_for_inference(tiny, "int8", decoder="fp32")[:2]
    packed = {}
    for root, plain, names in ((flow, tiny[1], outer), (vae, tiny[0], decoder)):
        for name in names:
            layer = root.get_submodule(name)
            packed[name] = isinstance(layer, PackedLinear)
            always = root is flow and name in linears_module.BATCHED_OUTER_LINEARS
            assert packed[name] == (always or worth_packing(plain.get_submodule(name))), name
            assert packed[name] or type(layer) is torch.nn.Linear, name
    assert any(packed.values()) and not all(packed.values())
    assert not any(isinstance(m, PackedLinear) for m in optimize_for_inference(tiny, "fp32")[1].modules())
    monkeypatch.undo()
    # without oneDNN: the plain Linears and BF16Linear, as before
    monkeypatch.setattr(optimize_module, "packed_linears_available", lambda dtype=None: False)
    vae, flow = optimize_for_inference(tiny, "int8", decoder="bf16")[:2]
    assert not any(isinstance(m, PackedLinear) for m in [*vae.modules(), *flow.modules()])
    assert all(isinstance(vae.get_submodule(name), BF16Linear) for name in decoder_linears(vae))
    deviation = stream_deviation(tiny, (vae, flow, tiny[2]), frames=16)
    assert 0.0 < deviation.max_joint_mm <= TOLERANCE_MM, deviation


def test_decoder_precision_rules():
    assert resolve_decoder("auto", "int8") == "fp32"  # bf16 only when asked for: see below
    assert resolve_decoder("auto", "bf16") == "fp32"
    assert resolve_decoder("auto", "fp32") == "fp32"  # the exact mode stays exact
    assert resolve_decoder("bf16", "int8") == "bf16"
    assert resolve_decoder("fp32", "int8") == "fp32"
    with pytest.raises(ValueError, match="exact|fp32"):
        resolve_decoder("bf16", "fp32")
    with pytest.raises(ValueError, match="decoder precision"):
        resolve_decoder("fp16", "int8")


@pytest.fixture(scope="module")
def shipped():
    from sarah_models.pretrained import model_path
    from sarah_models.training.model_file import load_model_file

    return without_foot_lock(load_model_file(model_path("fixture-tiny")))


@pytest.mark.skipif(not packed_linears_available(), reason="this torch has no oneDNN linear")
def test_trained_model_decodes_the_same_through_the_default_fast_decoder(shipped):
    """Random weights hid it: on the shipped trained model a bf16 decoder moved joints by up to
    45 mm over 64 streamed frames. The default fast path's decoder (packed fp32) decodes what
    the plain one does (same flow, so the same latents), to summation order."""
    fast_vae = optimize_for_inference(shipped, "int8").vae
    deviation = stream_deviation(shipped, (fast_vae, shipped.flow, shipped.normalizer), frames=32)
    assert deviation.max_joint_mm < 0.01, deviation


@pytest.mark.parametrize("seed", [0, 1])
def test_trained_model_int8_mode_stays_within_tolerance(shipped, seed):
    """The default int8 mode on the shipped model over 64 streamed frames. Its block Linears
    are too small to be worth int8 (``linears.worth_quantizing``); in int8 they moved joints by
    3.3-3.6 mm with this CPU's 7-bit activations (2.8 mm with VNNI's 8-bit ones), in fp32 by
    0.002-0.005 mm (docs/performance.md)."""
    deviation = stream_deviation(shipped, optimize_for_inference(shipped, "int8"), frames=64,
                                 seed=seed)
    assert deviation.max_joint_mm <= TOLERANCE_MM, deviation
    assert deviation.head_angle_delta <= METRIC_TOLERANCE


@pytest.mark.parametrize("mode", ["int8", "fp32"])
def test_a_stream_served_with_others_gets_what_it_gets_alone(shipped, mode):
    """Four streams of the shipped model (two with trajectory imputation) through a fast path,
    stepped together: each gets exactly its own ``step``'s joints. One activation scale for all the rows of a call moved
    them by up to 8 mm (docs/performance.md); the int8 Linears quantize each stream's rows on
    their own. In fp32, ``F.linear`` on all streams' rows moved them by 0.002 mm over these 16
    frames and 0.1 mm over 256 with the decoding chain; the Linears of the solve now compute
    each stream's rows on their own (``PerStreamLinear``)."""
    from sarah_data.skeleton import MotionLayout
    from sarah_models.sampling.stream import step_together

    fast = optimize_for_inference(shipped, mode)
    rng = np.random.default_rng(0)
    streams = 4
    inputs = [(rng.normal(0.0, 1.0, (16, 2)).astype(np.float32),
               rng.normal(-8.0, 4.0, (16, fast.flow.audio_dim)).astype(np.float32),
               rng.normal(-8.0, 4.0, (16, fast.flow.audio_dim)).astype(np.float32))
              for _ in range(streams)]
    configs = [StreamConfig(seed=i, imputation=("final", "trajectory")[i % 2])
               for i in range(streams)]
    alone = [StreamingGenerator(fast.vae, fast.flow, fast.normalizer, c) for c in configs]
    together = [StreamingGenerator(fast.vae, fast.flow, fast.normalizer, c) for c in configs]
    layout = MotionLayout.from_width(fast.vae.motion_dim)
    worst = 0.0
    for k in range(0, 16, 4):
        block = [tuple(x[k:k + 4] for x in stream) for stream in inputs]
        expected = [g.step(*b) for g, b in zip(alone, block)]
        for e, g in zip(expected, step_together(together, block)):
            joints = [layout.split(m)[0].mean(axis=-2) for m in (e, g)]
            worst = max(worst, float(np.linalg.norm(joints[0] - joints[1], axis=-1).max()))
    assert worst == 0.0, f"{1000.0 * worst} mm"


def test_stream_groups_split_int8_batches_and_nothing_else():
    linear = torch.nn.Linear(16, 8)
    int8 = Int8Linear(linear)
    x = torch.randn(6, 3, 16)
    x[4:] *= 50.0  # the third stream's activations are far larger than the others'
    with independent_streams(3):
        grouped = int8(x)
        with pytest.raises(ValueError, match="does not split into 3 streams"):
            int8(x[:4])
    torch.testing.assert_close(grouped[:4], torch.cat([int8(x[:2]), int8(x[2:4])]), atol=0, rtol=0)
    assert not torch.equal(grouped[:2], int8(x)[:2])  # one scale for all: coarser for stream 1
    assert stream_groups() == 1
    with pytest.raises(ValueError, match="at least one stream"):
        with independent_streams(0):
            pass


def test_per_stream_linear_gives_each_stream_its_own_rows():
    """A stream's rows come out the same whatever shares the call (``F.linear`` may round a row
    differently with the number of rows beside it), and the same as the plain Linear's alone."""
    torch.manual_seed(0)
    for shape, bias in (((8, 3, 128), True), ((8, 1, 128), True), ((4, 1, 128), False)):
        linear = torch.nn.Linear(128, 384, bias=bias)
        layer = PerStreamLinear(linear)
        x = torch.randn(shape)
        with independent_streams(4):
            together = layer(x)
            with pytest.raises(ValueError, match="does not split into 4 streams"):
                layer(x[:6] if shape[0] == 8 else x[:3])
        step = shape[0] // 4  # one stream's rows: up to 3 is another path of MKL's F.linear
        for rows in range(0, shape[0], step):
            assert torch.equal(together[rows:rows + step], linear(x[rows:rows + step])), shape
        assert torch.equal(layer(x), linear(x))  # one stream: F.linear itself
    assert layer.weight is linear.weight and not worth_quantizing(linear)
    assert worth_quantizing(torch.nn.Linear(1024, 4096))


def test_time_grid_is_the_midpoint_grid():
    assert time_grid(4, "midpoint") == [0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875]
    assert time_grid(2, "euler") == [0.0, 0.5]


def test_int8_linear_is_the_dynamic_quantized_linear_bit_for_bit():
    import warnings

    from torch.ao.quantization import per_channel_dynamic_qconfig, quantize_dynamic

    torch.manual_seed(0)
    linear = torch.nn.Linear(48, 40)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reference = quantize_dynamic(torch.nn.Sequential(linear), {"0": per_channel_dynamic_qconfig},
                                     dtype=torch.qint8)
    x = torch.randn(2, 3, 48)
    assert torch.equal(Int8Linear(linear, reduce_range=True)(x), reference(x))
    assert Int8Linear(linear).reduce_range is not cpu_module.int8_full_range()


@pytest.mark.skipif(not cpu_module.int8_full_range(), reason="no VNNI: 8-bit rows could overflow")
def test_int8_full_range_rows_halve_the_error():
    """8-bit activations: about half the error of 7-bit ones, and no int16 overflow (VNNI sums
    in int32) even where every product is at its largest."""
    torch.manual_seed(0)
    linear = torch.nn.Linear(1024, 256)
    x = torch.randn(64, 1024)
    errors = {rr: (Int8Linear(linear, reduce_range=rr)(x) - linear(x)).abs().mean().item()
              for rr in (True, False)}
    assert errors[False] < 0.7 * errors[True], errors
    worst = torch.nn.Linear(1024, 16, bias=False)
    worst.weight.data = torch.full((16, 1024), 0.01)
    x = torch.ones(6, 1024)
    x[:, ::7] = -1.0  # activations at both ends of their range, every weight at its largest
    torch.testing.assert_close(Int8Linear(worst, reduce_range=False)(x), worst(x), rtol=0.02, atol=0.0)


def test_time_memo_computes_afresh_with_autograd():
    layer = InputMemo(torch.nn.Linear(3, 2))
    x = torch.ones(1, 3)
    with torch.inference_mode():
        stored = layer(x)
        assert layer(x) is stored and layer.hits == 1
    fresh = layer(x)
    assert fresh is not stored and fresh.requires_grad
    assert torch.equal(fresh.detach(), stored)


def _hammer(work, threads: int = 4) -> list[str]:
    """Run ``work(i)`` in ``threads`` threads that switch as often as the interpreter lets
    them; returns the errors they raised."""
    import sys
    import threading

    errors: list[str] = []

    def run(i: int) -> None:
        try:
            work(i)
        except Exception as error:  # noqa: BLE001 (collected, the test asserts there are none)
            errors.append(repr(error))

    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        pool = [threading.Thread(target=run, args=(i,)) for i in range(threads)]
        for t in pool:
            t.start()
        for t in pool:
            t.join()
    finally:
        sys.setswitchinterval(interval)
    return errors


def test_memos_serve_many_threads_at_once():
    """``sarah-serve --workers N`` runs N rounds at once on one optimized model: its memos'
    entries must not vanish between a lookup and its bookkeeping (a KeyError mid-round
    before the memos held a lock)."""
    from sarah_models.accel.memo import RopeTable, TensorMemo

    memo = TensorMemo(max_entries=2)
    keys = [torch.tensor([float(i)]) for i in range(4)]

    def look_up(i: int) -> None:
        for n in range(5_000):
            key = keys[(n * (i + 1)) % 4].clone()  # a new tensor: found by its bytes
            assert torch.equal(memo.get(key, lambda x: 2.0 * x), 2.0 * key)

    assert _hammer(look_up) == []
    table = RopeTable(RopeAngles(8), block=4, max_blocks=2)
    plain = RopeAngles(8)

    def rotate(i: int) -> None:
        for n in range(2_000):
            positions = torch.arange(4 * ((n * (i + 1)) % 5), 4 * ((n * (i + 1)) % 5) + 3)
            for got, want in zip(table(positions), plain(positions)):
                assert torch.equal(got, want)

    with torch.inference_mode():
        assert _hammer(rotate) == []


def test_streams_in_two_compute_threads_get_what_they_get_alone(tiny):
    """Two streams of one optimized model stepped in two threads at once (two ``sarah-serve``
    workers) give the frames each gives alone."""
    vae, flow, normalizer = optimize_for_inference(tiny, "int8")
    inputs = [stream_inputs(24, AUDIO_DIM, seed=i) for i in range(2)]

    def stream(i: int) -> list[np.ndarray]:
        torch.set_num_threads(1)  # per thread; a thread's outputs depend on its own count only
        g = StreamingGenerator(vae, flow, normalizer, StreamConfig(seed=i))
        head, a, b = inputs[i]
        return [g.step(head[k:k + 4], a[k:k + 4], b[k:k + 4]) for k in range(0, 24, 4)]

    alone = [stream(i) for i in range(2)]
    together: dict[int, list[np.ndarray]] = {}
    for _ in range(3):
        assert _hammer(lambda i: together.__setitem__(i, stream(i)), threads=2) == []
        for i in range(2):
            for want, got in zip(alone[i], together[i]):
                np.testing.assert_array_equal(got, want)


@settings(max_examples=40, deadline=None)
@given(max_tokens=st.one_of(st.none(), st.integers(1, 7)),
       calls=st.lists(st.tuples(st.integers(1, 5), st.booleans()), min_size=1, max_size=12))
def test_kv_cache_returns_the_concatenation_of_what_it_keeps(max_tokens, calls):
    """The preallocated cache gives what concatenating the kept keys would: every committed
    token (the latest ``max_tokens`` only, after each commit) followed by the new ones."""
    cache, kept_k, kept_v = KVCache(max_tokens), None, None
    g = torch.Generator().manual_seed(len(calls))
    for n, commit in calls:
        k, v = torch.randn(2, 3, n, 4, generator=g), torch.randn(2, 3, n, 4, generator=g)
        want_k = k if kept_k is None else torch.cat((kept_k, k), dim=2)
        want_v = v if kept_v is None else torch.cat((kept_v, v), dim=2)
        got_k, got_v = cache.extend(k, v, commit)
        assert torch.equal(got_k, want_k) and torch.equal(got_v, want_v)
        if commit:
            keep = want_k.shape[2] if max_tokens is None else max_tokens
            kept_k, kept_v = want_k[:, :, -keep:], want_v[:, :, -keep:]
        assert len(cache) == (0 if kept_k is None else kept_k.shape[2])
    if kept_k is not None:
        assert torch.equal(cache.k, kept_k) and torch.equal(cache.v, kept_v)
    cache.reset()
    assert len(cache) == 0 and cache.k is None


def stochastic_tiny():
    """The tiny random models with a stochastic decoder (``vae.detail_dim``) whose draws move
    the motion visibly."""
    models = random_models("tiny", audio_dim=AUDIO_DIM, shell_points=SHELL, seed=0,
                           overrides=("vae.detail_dim=4",))
    with torch.no_grad():
        models[0].detail_in.weight.normal_(0, 0.5, generator=torch.Generator().manual_seed(0))
    return models


def test_a_stochastic_decoder_takes_its_draws_through_the_fast_path():
    """The optimized copies decode the same per-token draws as the reference: exact in fp32,
    within the int8 tolerance in int8."""
    models = stochastic_tiny()
    assert stream_deviation(models, optimize_for_inference(models, "fp32"), frames=24).max_joint_mm == 0.0
    deviation = stream_deviation(models, optimize_for_inference(models, "int8"), frames=24)
    assert deviation.max_joint_mm <= TOLERANCE_MM, deviation


@pytest.mark.parametrize("stochastic, interval", [(False, (0.0, 1.0)), (True, (0.0, 1.0)),
                                                  (False, (0.2, 0.6))])
def test_naive_reference_computes_what_the_generator_computes(tiny, stochastic, interval):
    vae, flow, normalizer = stochastic_tiny() if stochastic else tiny
    head, a, b = stream_inputs(24, AUDIO_DIM, seed=3)
    config = StreamConfig(decoder_frames=400, cfg_scale=3.0, guidance_interval=interval)
    generator = StreamingGenerator(vae, flow, normalizer, config)
    naive = NaiveStreamer(vae, flow, normalizer, config)
    for i in range(0, 24, 4):
        timings: dict[str, float] = {}
        expected = generator.step(head[i:i + 4], a[i:i + 4], b[i:i + 4])
        got = naive.step(head[i:i + 4], a[i:i + 4], b[i:i + 4], timings)
        np.testing.assert_allclose(got, expected, atol=1e-4)
        assert timings["flow"] > 0 and timings["decode"] > 0


def test_last_level_cache_reads_the_highest_level_sysfs_states(tmp_path):
    from sarah_models.accel.cpu import last_level_cache

    assert last_level_cache(tmp_path) == ""  # no cache folders: unknown, not a guess
    for index, (level, size) in enumerate([(1, "48K"), (1, "32K"), (2, "2048K"), (3, "266240K")]):
        folder = tmp_path / f"index{index}"
        folder.mkdir()
        (folder / "level").write_text(f"{level}\n")
        (folder / "size").write_text(f"{size}\n")
    assert last_level_cache(tmp_path) == "L3 260 MiB"
    (tmp_path / "index3" / "size").write_text("garbled\n")  # an unreadable level is skipped
    assert last_level_cache(tmp_path) == "L2 2 MiB"
    (tmp_path / "index2" / "size").write_text("512K\n")
    assert last_level_cache(tmp_path) == "L2 512 KiB"


def test_bench_quick_runs_end_to_end(tmp_path):
    from sarah_cli.bench import main

    history = tmp_path / "performance.md"
    history.write_text("| date | cpu |\n| --- | --- |\n| old | row |\n\nafter the table\n")
    out = tmp_path / "bench.json"
    assert main(["--quick", "--threads", "1", "--json", str(out), "--history", str(history)]) == 0
    results = json.loads(out.read_text())
    assert results["environment"]["threads"] == 1
    # the instruction set beside the CPU's name: two "AMD EPYC" VMs ran int8 2x apart
    from sarah_models.accel import vector_isa

    assert vector_isa() in ("AMX", "AVX-512 VNNI", "AVX-512", "AVX2", "")
    assert not vector_isa() or results["environment"]["cpu"].endswith(f" ({vector_isa()})")
    assert results["environment"]["cpu"] in history.read_text()
    # ... and what tells apart VMs of one name: family, model, last-level cache (Linux)
    from sarah_models.accel import cpu_identity

    assert results["environment"]["cpu_identity"] == cpu_identity()
    tiny_stream = results["streaming"]["tiny"]
    assert tiny_stream["fps"] > 0 and tiny_stream["naive"]["fps"] > 0
    assert set(tiny_stream["stages_ms"]) == {"audio", "flow", "decode", "other"}
    latency = tiny_stream["latency_ms"]  # 8 chunks: a p99 with an open upper end, not a max
    assert latency["n"] == tiny_stream["frames"] // 4 and latency["p99_interval"][1] is None
    assert tiny_stream["deviation"]["max_joint_mm"] <= TOLERANCE_MM
    fewer = tiny_stream["fewer_steps"]
    assert fewer["steps"] == 1 and fewer["fps"] > 0
    assert fewer["deviation"]["max_joint_mm"] > 0  # fewer steps are not exact: measured, not hidden
    shipped = tiny_stream["deviation_shipped"]  # trained weights, measured in every run
    assert shipped["frames"] == 16 and shipped["max_joint_mm"] <= TOLERANCE_MM
    assert results["prep"]["logmel"]["rtf"] > 0 and results["loader"]["workers_2"]["windows"] > 0
    goals = {g["goal"]: g for g in results["goals"]}
    assert goals["prep.logmel.rtf"]["met"] is not None
    assert goals["streaming.tiny.deviation_shipped.max_joint_mm"]["value"] == shipped["max_joint_mm"]
    assert goals["offline.paper.fps"]["met"] is None  # the quick run has no paper-size model
    floor = results["memory_floor"]["tiny"]
    assert "1" in floor["threads"]  # every thread count up to this process's cores
    for row in floor["threads"].values():
        assert row["ms"] > 0 and row["fps"] == pytest.approx(4000.0 / row["ms"])
    lines = history.read_text().splitlines()
    assert lines[3].startswith("| ") and "int8" in lines[3] and lines[-1] == "after the table"


def test_bench_background_load_reports_both_sides(tmp_path, capsys):
    """--background-load 1 (automatic threads): every timed figure again beside a busy process,
    the fixed every-core stream for comparison, concurrent streams both ways; the busy process
    is gone afterwards."""
    from sarah_cli.bench import main

    out = tmp_path / "bench.json"
    assert main(["--quick", "--no-prep", "--no-loader", "--background-load", "1", "--rounds", "2",
                 "--json", str(out)]) == 0
    results = json.loads(out.read_text())
    assert results["environment"]["threads"] == "auto"
    idle, loaded = results["streaming"]["tiny"], results["loaded"]["streaming"]["tiny"]
    for row in (idle, loaded, loaded["fixed_threads"]):
        assert row["fps"] > 0 and sum(row["threads_used"].values()) == pytest.approx(1.0)
    assert set(idle["calibration_ms"]) <= {str(n) for n in range(1, os.cpu_count() + 1)}
    assert loaded["fixed_threads"]["threads"] == len(os.sched_getaffinity(0))
    assert results["loaded"]["offline"]["tiny"]["fps"] > 0
    for side in (results["concurrent"]["tiny"], results["loaded"]["concurrent"]["tiny"]):
        for schedule in (side, side["round_robin"], side["shipped"]):
            assert schedule["rows"][0]["streams"] == 1 and schedule["fit"] in (0, 1, 2)
            # a count that failed ends the list; only a list that never failed says "more may fit"
            assert schedule["every_count_held"] == all(r["real_time"] for r in schedule["rows"])
            last = schedule["rows"][-1]["streams"]
            assert schedule["every_count_held"] == (schedule["fit"] == last)
        assert (side["schedule"], side["round_robin"]["schedule"], side["shipped"]["schedule"]) == (
            "together", "round robin", "together")
    for side in ("idle", "loaded"):  # --rounds: each figure per round, and its median and range
        for figure in results["rounds"]["tiny"][side].values():
            assert len(figure["rounds"]) == 2 and all(v > 0 for v in figure["rounds"])
            assert figure["min"] <= figure["median"] <= figure["max"]
    goals = {g["goal"]: g for g in results["goals"]}
    assert goals["rounds.paper.loaded.fps.median"]["met"] is None  # no paper size in --quick
    report = capsys.readouterr().out
    assert "under background load (1 busy processes" in report and "loaded / idle" in report
    assert "round robin (one solve per stream): idle" in report
    assert "the shipped fixture-tiny (trained, its decoding chain on), one solve per round" in report
    assert "2 more rounds, each idle then beside 1 busy processes" in report
    assert "tiny stream fps" in report.split("2 more rounds")[1]
    assert spinning_processes() == []


def test_latency_percentiles_carry_distribution_free_intervals():
    """A percentile's interval is a pair of order statistics that covers the true quantile at
    least 95 % of the time, whatever the distribution; an end no order statistic can bound is
    left open (None) rather than clipped to the sample's extreme."""
    from sarah_bench.timing import percentiles, quantile_interval

    rng = np.random.default_rng(0)
    for n, q in ((400, 0.99), (101, 0.5)):
        truth = -np.log(1.0 - q)  # the exponential distribution's q-quantile
        covered = 0
        for _ in range(2000):
            sample = rng.exponential(size=n)
            low, high = quantile_interval(sample, q)
            assert low in sample and high in sample and low <= np.quantile(sample, q) <= high
            covered += low <= truth <= high
        assert 0.95 <= covered / 2000 <= 0.99
    assert quantile_interval(np.arange(100.0), 0.99)[1] is None  # p99 of T's 100 chunks: open
    assert quantile_interval(np.arange(400.0), 0.99) == (391.0, 399.0)  # 4 x T: closed
    row = percentiles([0.001 * i for i in range(1, 9)])
    assert row["n"] == 8 and row["p99_interval"][1] is None and row["p99_interval"][0] <= row["p99"]
    assert percentiles([])["p99_interval"] == [None, None]


def test_bench_config_rejects_bad_values():
    from sarah_bench.config import BenchConfig

    with pytest.raises(ValueError, match="multiple of 4"):
        BenchConfig(stream_frames=10)
    with pytest.raises(ValueError, match="sizes"):
        BenchConfig(sizes=("huge",))
    with pytest.raises(ValueError, match="background_load"):
        BenchConfig(background_load=-1)
    with pytest.raises(ValueError, match="rounds"):
        BenchConfig(rounds=2)  # rounds compare idle with loaded: they need a background load
    with pytest.raises(ValueError, match="threads"):
        BenchConfig(threads=0)
    assert dataclasses.replace(BenchConfig.quick(), threads=1).sizes == ("tiny",)


def test_every_kernel_of_the_kernel_bench_computes_the_same_product():
    """sarah_bench.kernels compares kernels' speed; the comparison is fair only if each computes
    the same int8-weight product (to its rounding: fbgemm and _int_mm quantize the rows too)."""
    from sarah_bench.kernels import block_shapes, kernels
    from sarah_models.config import FlowConfig

    table = kernels(block_shapes(FlowConfig.tiny()))
    reference = table["fp32 (MKL)"]()
    compared = [name for name in table if "floor" not in name]
    assert len(compared) == 5
    for name in compared:
        for out, ref in zip(table[name](), reference, strict=True):
            assert out.shape == ref.shape, name
            assert ((out - ref).abs().max() / ref.abs().max()).item() < 0.05, name


def test_every_decoder_kernel_of_the_kernel_bench_computes_the_same_product():
    from sarah_bench.kernels import decoder_kernels, decoder_shapes
    from sarah_models.config import VAEConfig

    table = decoder_kernels(decoder_shapes(VAEConfig.tiny()))
    assert len(table) == 2 + packed_linears_available() + packed_linears_available(torch.bfloat16)
    reference = table["fp32, F.linear (MKL)"]()
    for name, step in table.items():
        for out, ref in zip(step(), reference, strict=True):
            assert out.shape == ref.shape and out.dtype == torch.float32, name
            tolerance = 1e-5 if name.startswith("fp32") else 0.02
            assert ((out - ref).abs().max() / ref.abs().max()).item() < tolerance, name


@pytest.mark.parametrize("mode", ["none", "int8", "bf16"])
def test_chunk_weight_bytes_counts_every_linear_a_chunk_reads_in_its_precision(mode):
    """The bench's memory floor is only a floor if it counts every weight a streamed chunk
    reads: the flow's block Linears and its latent input and output projection per evaluation
    (int8: a byte each where ``worth_quantizing``, else four; bf16: two; fp32: four), the
    condition encoders once, the decoder's once. A flow 256 wide has blocks of both kinds."""
    from sarah_bench.kernels import chunk_weight_bytes

    wide = random_models("tiny", audio_dim=AUDIO_DIM, shell_points=SHELL, seed=0,
                         overrides=("flow.hidden=256",))
    plain_vae, plain_flow, _ = wide
    numel = lambda root, names: sum(root.get_submodule(n).weight.numel() for n in names)
    blocks = [plain_flow.get_submodule(n) for n in flow_block_linears(plain_flow)]
    assert {worth_quantizing(m) for m in blocks} == {True, False}
    per_weight = {"none": lambda m: 4, "bf16": lambda m: 2,
                  "int8": lambda m: 1 if worth_quantizing(m) else 4}[mode]
    block = sum(per_weight(m) * m.weight.numel() for m in blocks)
    outer = numel(plain_flow, ["latent_in", "out.proj"])
    once = numel(plain_flow, [n for n in flow_outer_linears(plain_flow)
                              if n == "cond_in" or n.startswith("encoders.")])
    models = wide if mode == "none" else optimize_for_inference(wide, mode)
    weights = chunk_weight_bytes(models, StreamConfig(steps=3))
    assert weights == {"evaluation": block + 4 * outer, "evaluations": 6,
                       "chunk": 4 * once,
                       "decoder": 4 * numel(plain_vae, decoder_linears(plain_vae))}
