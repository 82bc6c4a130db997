"""The fused inference forwards compute what the modules compute.

Flow: the fused forward equals the model's own forward to float32 rounding (relative 1e-5) for
any solver call (1 or 2 guidance branches, 1 to 3 tokens, any tau), and every other call goes to
the model's own forward unchanged. Decoder: table lookups of rotary angles are bit-identical,
and the fused decoder step streams the module step's joints to within 1e-3 mm."""

from __future__ import annotations

import copy

import pytest
import torch
from hypothesis import given, settings, strategies as st

from sarah_models.bench import random_models
from sarah_models.fast import optimize_for_inference, stream_deviation
from sarah_models.fused import (FusedDecoderStep, FusedFlowForward, RopeTable, fuse_decoder,
                                fuse_flow)
from sarah_models.layers import RopeAngles
from sarah_models.stream import StreamConfig

AUDIO_DIM = 8


@pytest.fixture(scope="module")
def models():
    vae, flow, normalizer = random_models("tiny", audio_dim=AUDIO_DIM, shell_points=4, seed=3,
                                          init_std=0.05)
    return vae.eval(), flow.eval(), normalizer


@settings(max_examples=30, deadline=None)
@given(branches=st.integers(1, 2), tokens=st.integers(1, 3),
       tau=st.floats(0.0, 0.999, allow_nan=False), seed=st.integers(0, 2**16))
def test_fused_flow_equals_the_module_forward(models, branches, tokens, tau, seed):
    _, flow, _ = models
    fused = fuse_flow(copy.deepcopy(flow))
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(branches, tokens, flow.latent_dim, generator=g)
    cond = torch.randn(branches, tokens, flow.config.hidden, generator=g)
    with torch.inference_mode():
        want = flow(z, tau, cond_tokens=cond)
        got = fused(z, tau, cond_tokens=cond)
    assert fused.forward.fused_calls == 1
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-5 * want.abs().max().item())


def test_other_calls_use_the_module_forward(models):
    _, flow, _ = models
    fused = fuse_flow(copy.deepcopy(flow))
    forward = fused.forward
    assert isinstance(forward, FusedFlowForward) and fuse_flow(fused).forward is forward
    z = torch.randn(2, 3, flow.latent_dim)
    cond = torch.randn(2, 3, flow.config.hidden)
    tau = torch.tensor([0.25, 0.5])
    with torch.inference_mode():
        assert torch.equal(fused(z, tau, cond_tokens=cond), flow(z, tau, cond_tokens=cond))
        positions = torch.tensor([4, 5, 6])
        assert torch.equal(fused(z, 0.25, cond_tokens=cond, positions=positions),
                           flow(z, 0.25, cond_tokens=cond, positions=positions))
    with torch.no_grad():  # autograd off but not inference mode: still fused
        fused(z, 0.25, cond_tokens=cond)
    assert forward.fused_calls == 1
    out = fused(z, 0.25, cond_tokens=cond)  # autograd on (training): the module forward
    assert out.requires_grad and forward.fused_calls == 1


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


def test_fused_decoder_streams_identical_frames(models):
    vae, flow, normalizer = models
    fast = (fuse_decoder(copy.deepcopy(vae)), flow, normalizer)
    assert all(isinstance(b.attn.rope.angles, RopeTable) for b in fast[0].decoder)
    assert stream_deviation(models, fast, frames=24).max_joint_mm == 0.0


def test_fused_decoder_step_matches_the_module_step(models):
    vae, flow, normalizer = models
    fused_vae = fuse_decoder(copy.deepcopy(vae), steps=True)
    assert isinstance(fused_vae.decoder_step, FusedDecoderStep)
    assert fuse_decoder(fused_vae, steps=True).decoder_step is fused_vae.decoder_step
    # a stream long enough for the decoder's sliding window (decoder_blocks) to drop blocks
    config = StreamConfig(decoder_blocks=3)
    deviation = stream_deviation(models, (fused_vae, flow, normalizer), frames=40, config=config)
    assert deviation.max_joint_mm < 1e-3
    z = torch.randn(1, vae.config.latent_dim)
    cache = fused_vae.new_decoder_cache()
    assert fused_vae.decoder_step(z, cache).requires_grad  # autograd on: the module step


def test_int8_mode_uses_the_fused_forward(models):
    fast = optimize_for_inference(models, "int8")
    forward = fast[1].forward
    assert isinstance(forward, FusedFlowForward)
    assert isinstance(fast[0].decoder_step, FusedDecoderStep)
    stream_deviation(models, fast, frames=8)
    assert forward.fused_calls > 0
