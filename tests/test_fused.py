"""The fused inference blocks compute what the reference modules compute, and the optimized
models are the reference models with modules replaced, nothing patched.

Flow: a flow whose blocks and output layer are the fused subclasses equals the reference forward
to float32 rounding (relative 1e-5) for any solver call (1 or 2 guidance branches, 1 to 3
tokens, any tau); calls they do not cover (per-row tau, autograd) run the reference maths
unchanged (to float rounding: the attention is still the fused one). Traced blocks (the int8
mode's quantized ones) give the eager fused blocks' frames to the bit. Decoder: table lookups of
rotary angles are bit-identical, and fused attention streams the reference decoder's joints to
within 1e-3 mm."""

from __future__ import annotations

import ast
import copy
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings, strategies as st

from sarah_models.accel import linears as linears_module
from sarah_models.accel import optimize_for_inference
from sarah_models.accel.fused import (SIGMOID_FORM_MIN_WIDTH, FusedAdaLNZeroBlock,
                                      FusedAdaLNZeroOutput, FusedAttention, gelu_tanh,
                                      mlp_function)
from sarah_models.accel.linears import (ByRowsLinear, PackedLinear, packed_linears_available,
                                        replace_module)
from sarah_models.accel.memo import RopeTable
from sarah_models.accel.optimize import fuse_flow, table_decoder_rope
from sarah_models.accel.traced import TracedAdaLNZeroBlock
from sarah_models.config import StreamConfig
from sarah_models.nn.flow import FlowModel
from sarah_models.nn.layers import MLP, AdaLNZeroBlock, RopeAngles
from sarah_models.nn.vae import CausalVAE
from sarah_models.sampling.stream import StreamingGenerator, generate_offline, step_together
from sarah_models.testing import random_models, stream_deviation, stream_inputs

AUDIO_DIM = 8
ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "sarah_models"


@pytest.fixture(scope="module")
def models():
    vae, flow, normalizer = random_models("tiny", audio_dim=AUDIO_DIM, shell_points=4, seed=3,
                                          init_std=0.05)
    return vae.eval(), flow.eval(), normalizer


def fused_copy(flow: FlowModel) -> FlowModel:
    fused = copy.deepcopy(flow)
    fuse_flow(fused)
    return fused


@settings(max_examples=25, deadline=None)
@given(rows=st.integers(1, 12), scale=st.sampled_from([0.1, 1.0, 4.0, 30.0]),
       seed=st.integers(0, 2**16))
def test_the_sigmoid_form_of_gelu_is_torchs_tanh_gelu(rows, scale, seed):
    """Small and saturating inputs, the input left untouched, and a wide MLP through it."""
    x = torch.randn(rows, 64, generator=torch.Generator().manual_seed(seed)) * scale
    x[0, :3] = torch.tensor([0.0, -50.0, 50.0]) * scale
    before = x.clone()
    torch.testing.assert_close(gelu_tanh(x), F.gelu(x, approximate="tanh"), rtol=1e-5, atol=1e-6)
    assert torch.equal(x, before)
    mlp = MLP(8, SIGMOID_FORM_MIN_WIDTH // 8).eval()
    assert mlp[0].out_features == SIGMOID_FORM_MIN_WIDTH
    h = x[:, :8]
    with torch.inference_mode():
        torch.testing.assert_close(mlp_function(mlp)(h), mlp(h), rtol=1e-5, atol=1e-6)


@settings(max_examples=30, deadline=None)
@given(branches=st.integers(1, 2), tokens=st.integers(1, 3),
       tau=st.floats(0.0, 0.999, allow_nan=False), seed=st.integers(0, 2**16))
def test_fused_flow_equals_the_module_forward(models, branches, tokens, tau, seed):
    _, flow, _ = models
    fused = fused_copy(flow)
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(branches, tokens, flow.latent_dim, generator=g)
    cond = torch.randn(branches, tokens, flow.config.hidden, generator=g)
    with torch.inference_mode():
        want = flow(z, tau, cond_tokens=cond)
        got = fused(z, tau, cond_tokens=cond)
    assert all(block.folded.misses == 1 for block in fused.blocks)  # the folded path ran
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-5 * want.abs().max().item())


def test_calls_the_fused_blocks_do_not_cover_run_the_reference_maths(models):
    _, flow, _ = models
    fused = fused_copy(flow)
    z = torch.randn(2, 3, flow.latent_dim)
    cond = torch.randn(2, 3, flow.config.hidden)
    tau = torch.tensor([0.25, 0.5])  # rows with different flow times: nothing to fold
    with torch.inference_mode():
        torch.testing.assert_close(fused(z, tau, cond_tokens=cond), flow(z, tau, cond_tokens=cond))
        assert all(block.folded.misses == 1 and block.folded.hits == 0 for block in fused.blocks)
        positions = torch.tensor([4, 5, 6])
        torch.testing.assert_close(fused(z, 0.25, cond_tokens=cond, positions=positions),
                                   flow(z, 0.25, cond_tokens=cond, positions=positions))
    out = fused(z, 0.25, cond_tokens=cond)  # autograd on (training): the reference forward
    assert out.requires_grad
    assert torch.equal(out, flow(z, 0.25, cond_tokens=cond))


@settings(max_examples=30, deadline=None)
@given(start=st.integers(0, 20_000), length=st.integers(1, 12))
def test_rope_table_is_bit_identical(start, length):
    angles = RopeAngles(16)
    table = RopeTable(angles, block=512)
    positions = torch.arange(start, start + length)
    with torch.inference_mode():
        assert torch.equal(table(positions), angles(positions))
        scattered = torch.tensor([3, 1, start, 7])
        assert torch.equal(table(scattered), angles(scattered))


def test_rope_table_memory_is_bounded_however_long_the_stream():
    angles = RopeAngles(16)
    table = RopeTable(angles, block=256, max_blocks=3)
    with torch.inference_mode():
        for start in range(0, 50_000, 5):  # a decoder step's positions, stream after stream
            positions = torch.arange(start, start + 5)
            assert torch.equal(table(positions), angles(positions))
    assert table.cached_positions <= 3 * 256


def test_decoder_rope_tables_stream_identical_frames(models):
    vae, flow, normalizer = models
    tabled = copy.deepcopy(vae)
    table_decoder_rope(tabled, fused=False)
    assert all(isinstance(b.attn.rope.angles, RopeTable) for b in tabled.decoder)
    assert stream_deviation(models, (tabled, flow, normalizer), frames=24).max_joint_mm == 0.0


def test_fused_decoder_attention_matches_the_module_step(models):
    vae, flow, normalizer = models
    fused_vae = copy.deepcopy(vae)
    table_decoder_rope(fused_vae, fused=True)
    assert all(isinstance(b.attn, FusedAttention) for b in fused_vae.decoder)
    assert not any(isinstance(b.attn, FusedAttention) for b in fused_vae.encoder)
    # a stream long enough for the decoder's sliding window (decoder_frames) to drop blocks
    config = StreamConfig(decoder_frames=12)
    deviation = stream_deviation(models, (fused_vae, flow, normalizer), frames=40, config=config)
    assert deviation.max_joint_mm < 1e-3
    z = torch.randn(1, vae.config.latent_dim)
    assert fused_vae.decoder_step(z, fused_vae.new_decoder_cache()).requires_grad


def test_int8_mode_swaps_modules_and_keeps_the_reference_forwards(models):
    fast = optimize_for_inference(models, "int8")
    vae, flow = fast[0], fast[1]
    assert all(isinstance(b, FusedAdaLNZeroBlock) and isinstance(b, AdaLNZeroBlock)
               for b in flow.blocks)
    assert isinstance(flow.out, FusedAdaLNZeroOutput)
    # nothing patched on the instances: the class's own forward and decoder step run
    assert "forward" not in vars(flow) and "decoder_step" not in vars(vae)
    assert "new_decoder_cache" not in vars(vae)
    assert type(flow) is FlowModel and type(vae) is CausalVAE
    stream_deviation(models, fast, frames=8)
    assert all(block.folded.hits > 0 for block in flow.blocks)


def _streamed_and_offline(models) -> list:
    """A stream alone (8 chunks), two streams served together (8 rounds) and the offline solve
    of the same inputs, as frames."""
    vae, flow, normalizer = models
    head, a, b = stream_inputs(64, AUDIO_DIM, seed=5)
    first, second = StreamingGenerator(vae, flow, normalizer), StreamingGenerator(vae, flow, normalizer)
    alone = [first.step(head[i:i + 4], a[i:i + 4], b[i:i + 4]) for i in range(0, 32, 4)]
    together = [step_together([first, second], [(head[i:i + 4], a[i:i + 4], b[i:i + 4])] * 2)
                for i in range(32, 64, 4)]
    return [*alone, *(frames for both in together for frames in both),
            generate_offline(vae, flow, normalizer, head, a, b)]


@pytest.mark.parametrize("amx", [None, False], ids=["this-cpu", "without-amx"])
def test_traced_blocks_give_the_eager_fused_blocks_bits(models, amx, monkeypatch):
    """The int8 mode's default where the flow's blocks are quantized (a 256-wide flow's are):
    the fused blocks replayed from traces, against the same blocks computed eagerly
    (``trace=False``): every frame of a stream, of two streams served together and of the
    offline solve equal to the bit, each call shape traced once. The tiny preset's fp32 blocks
    are not traced (slower so)."""
    assert not any(isinstance(b, TracedAdaLNZeroBlock)
                   for b in optimize_for_inference(models, "int8")[1].blocks)
    if amx is not None:  # every CPU's path: int8 offline rows too, where AMX would take them
        monkeypatch.setattr(linears_module, "amx_bf16_available", lambda: amx)
    wide = random_models("tiny", audio_dim=AUDIO_DIM, shell_points=4, seed=3, init_std=0.05,
                         overrides=("flow.hidden=256",))
    traced = optimize_for_inference(wide, "int8")
    eager = optimize_for_inference(wide, "int8", trace=False)
    assert all(isinstance(b, TracedAdaLNZeroBlock) for b in traced[1].blocks)
    assert not any(isinstance(b, TracedAdaLNZeroBlock) for b in eager[1].blocks)
    # warmed up: a stream's windows of 1, 2 and 3 tokens, one or both guidance branches
    assert all(len(block.traces) == 6 for block in traced[1].blocks)
    with torch.inference_mode():
        got, want = _streamed_and_offline(traced), _streamed_and_offline(eager)
    assert all((g == w).all() for g, w in zip(got, want))
    for block in traced[1].blocks:
        assert len(block.traces) == 8  # and two streams' 3 tokens, the offline window
        # where the CPU has AMX, an offline window's rows go to oneDNN-packed bf16 weights,
        # which no trace holds: that call computes eagerly (and gave the same bits above)
        on_amx = isinstance(block.attn.qkv, ByRowsLinear)
        assert [key[0] for key in block.untraced] == ([(2, 16, 256)] if on_amx else [])


def test_threads_that_trace_the_same_blocks_at_once_get_the_eager_bits():
    """Two ``sarah-serve`` workers' rounds on one optimized model, each serving a number of
    streams no trace holds yet, so both trace the same blocks at once: every frame as the
    eager fused blocks give it, and one trace per key kept."""
    import threading

    wide = random_models("tiny", audio_dim=AUDIO_DIM, shell_points=4, seed=3, init_std=0.05,
                         overrides=("flow.hidden=256",))
    traced = optimize_for_inference(wide, "int8")
    eager = optimize_for_inference(wide, "int8", trace=False)
    counts = (2, 3)
    inputs = {g: [stream_inputs(16, AUDIO_DIM, seed=10 * g + i) for i in range(g)] for g in counts}

    def serve(models, count: int) -> list:
        torch.set_num_threads(1)  # per thread; a thread's outputs depend on its own count only
        streams = [StreamingGenerator(*models, StreamConfig(seed=i)) for i in range(count)]
        return [step_together(streams, [(h[k:k + 4], a[k:k + 4], b[k:k + 4])
                                        for h, a, b in inputs[count]]) for k in range(0, 16, 4)]

    want = {g: serve(eager, g) for g in counts}
    got, errors, start = {}, [], threading.Barrier(len(counts))

    def worker(count: int) -> None:
        try:
            start.wait()
            got[count] = serve(traced, count)
        except Exception as error:  # noqa: BLE001 (collected, asserted empty)
            errors.append(repr(error))

    pool = [threading.Thread(target=worker, args=(g,)) for g in counts]
    for thread in pool:
        thread.start()
    for thread in pool:
        thread.join()
    assert errors == []
    for g in counts:
        assert all((x == y).all() for rw, rg in zip(want[g], got[g]) for x, y in zip(rw, rg))
    for block in traced[1].blocks:  # warm-up's 6, and G streams of 1, 2 and 3 tokens each
        assert len(block.traces) == 6 + 3 * len(counts) and block.untraced == {}


@pytest.mark.skipif(not packed_linears_available(), reason="needs torch's oneDNN linear ops")
def test_a_block_a_trace_cannot_hold_computes_eagerly(models):
    """oneDNN-packed weights are an opaque tensor no trace holds: such a block says so for the
    call's key and gives what the eager fused block gives."""
    _, flow, _ = models
    eager, traced = copy.deepcopy(flow), copy.deepcopy(flow)
    for copied, trace in ((eager, False), (traced, True)):
        replace_module(copied, "blocks.0.mlp.0", PackedLinear(copied.blocks[0].mlp[0]))
        fuse_flow(copied, traced=trace)
    z = torch.randn(2, 3, flow.latent_dim)
    cond = torch.randn(2, 3, flow.config.hidden)
    with torch.inference_mode():
        assert torch.equal(traced(z, 0.5, cond_tokens=cond), eager(z, 0.5, cond_tokens=cond))
    (key, reason), = traced.blocks[0].untraced.items()
    assert key[0] == (2, 3, flow.config.hidden) and "Tensor" in reason
    assert traced.blocks[1].untraced == {} and len(traced.blocks[1].traces) == 1


# The only private fields of other projects read here, each in one function whose comment names
# the version it was checked against: shared memory without a copy, torchaudio's file name,
# oneDNN's linear over prepacked weights (what inductor's freezing uses; no public call has it).
TORCH_PRIVATE = {"sarah_data/dataset.py": ("_new_shared",),
                 "sarah_data/features/hubert.py": ("_path",),
                 "sarah_models/accel/cpu.py": ("_reorder_linear_weight", "_linear_pointwise",
                                                 "_is_mkldnn_bf16_supported")}


def _python_files(folder: Path) -> list[Path]:
    return sorted(folder.rglob("*.py"))


def test_no_module_assigns_methods_or_reads_another_modules_private_fields():
    """Issue #15's rules, checked on the source of both packages: no ``x.forward = ...`` (or
    decoder_step / new_decoder_cache) anywhere, no ``obj._name`` read where obj is not
    ``self``/``cls``, and no ``from module import _name``."""
    patched, private = [], []
    for path in _python_files(PACKAGE) + _python_files(ROOT / "sarah_data"):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign):
                for target in node.targets:
                    if isinstance(target, ast.Attribute) and target.attr in (
                            "forward", "decoder_step", "new_decoder_cache"):
                        patched.append(f"{path.name}:{node.lineno}")
            if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                    and not node.attr.startswith("__")
                    and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))
                    and node.attr not in TORCH_PRIVATE.get(path.relative_to(ROOT).as_posix(), ())):
                private.append(f"{path.relative_to(ROOT)}:{node.lineno} .{node.attr}")
            if isinstance(node, ast.ImportFrom):
                private += [f"{path.relative_to(ROOT)}:{node.lineno} import {a.name}"
                            for a in node.names if a.name.startswith("_")
                            and not a.name.startswith("__")]
    assert patched == []
    assert private == []


def test_the_reference_model_never_imports_accel():
    for room in ("nn", "sampling", "training", "evaluation"):
        for path in _python_files(PACKAGE / room):
            text = path.read_text()
            assert "accel" not in [part for line in text.splitlines()
                                   if line.lstrip().startswith(("import", "from"))
                                   for part in line.replace(".", " ").split()], path
