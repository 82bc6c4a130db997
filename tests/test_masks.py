"""Attention masks: their structure, and causality of the VAE and flow model end to end."""

import pytest
import torch
from helpers import randomize
from hypothesis import given, settings
from hypothesis import strategies as st

from sarah_models.config import FlowConfig, VAEConfig
from sarah_models.nn.flow import MODALITIES, FlowModel, build_block_mask
from sarah_models.nn.layers import AdaLNZeroBlock, Attention, KVCache, TransformerBlock, causal_mask
from sarah_models.nn.vae import CausalVAE, decoder_layout, encoder_layout

S, K, DX, DA = 4, 5, 18, 6
T = S * K


def _randomize(model: torch.nn.Module, seed: int) -> torch.nn.Module:
    return randomize(model, seed, 0.2)


@pytest.fixture(scope="module")
def vae():
    torch.manual_seed(0)
    return _randomize(CausalVAE(VAEConfig.tiny(), DX), 1)


@pytest.fixture(scope="module")
def flow():
    torch.manual_seed(0)
    return _randomize(FlowModel(FlowConfig.tiny(), VAEConfig.tiny().latent_dim, S, DA), 2)


def test_causal_mask_is_lower_right_aligned():
    assert torch.equal(causal_mask(5), torch.ones(5, 5, dtype=torch.bool).tril())
    m = causal_mask(2, 5)  # two new queries after three cached keys
    assert m.tolist() == [[True, True, True, True, False], [True, True, True, True, True]]
    w = causal_mask(4, window=2)
    assert w.tolist() == [[True, False, False, False], [True, True, False, False],
                          [False, True, True, False], [False, False, True, True]]
    assert torch.equal(build_block_mask(3, 7), causal_mask(3, 7))
    with pytest.raises(ValueError):
        causal_mask(4, 3)


def test_encoder_mask_semantics():
    layout = encoder_layout(K, S)
    mask = causal_mask(len(layout))
    for i, (kind_i, block_i, frame_i) in enumerate(layout):
        for j, (kind_j, block_j, frame_j) in enumerate(layout):
            allowed = bool(mask[i, j])
            if kind_i == "x" and kind_j == "x":  # frames see past and current frames
                assert allowed == (frame_j <= frame_i)
            elif kind_i == "x":  # frames see only the latent tokens of earlier blocks
                assert allowed == (block_j < block_i)
            elif kind_j == "x":  # mu/sigma see frames up to the end of their block
                assert allowed == (frame_j < (block_i + 1) * S)
            else:  # latents see earlier latents; sigma_k also sees mu_k
                expected = block_j < block_i or (block_j == block_i and
                                                 (kind_j == kind_i or kind_i == "sigma"))
                assert allowed == expected


def test_decoder_mask_semantics():
    layout = decoder_layout(K, S)
    mask = causal_mask(len(layout))
    for i, (kind_i, block_i, frame_i) in enumerate(layout):
        for j, (kind_j, block_j, frame_j) in enumerate(layout):
            if kind_j == "z":  # every token of block k sees z_1..z_k only
                assert bool(mask[i, j]) == (block_j <= block_i)
            if kind_i == "q" and kind_j == "q":
                assert bool(mask[i, j]) == (frame_j <= frame_i)


@settings(max_examples=12, deadline=None)
@given(t=st.integers(0, T - 2), seed=st.integers(0, 2**16))
def test_encoder_is_causal(vae, t, seed):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(2, T, DX, generator=g)
    y = x.clone()
    y[:, t + 1:] += torch.randn(y[:, t + 1:].shape, generator=g)
    with torch.no_grad():
        (mu_x, lv_x), (mu_y, lv_y) = vae.encode(x), vae.encode(y)
    done = (t + 1) // S  # blocks whose frames all lie at or before t
    if done:
        assert (mu_x[:, :done] - mu_y[:, :done]).abs().max().item() < 1e-6
        assert (lv_x[:, :done] - lv_y[:, :done]).abs().max().item() < 1e-6
    assert (mu_x[:, done:] - mu_y[:, done:]).abs().max().item() > 1e-4  # the rest does change


@settings(max_examples=12, deadline=None)
@given(k=st.integers(0, K - 2), seed=st.integers(0, 2**16))
def test_decoder_is_causal(vae, k, seed):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(2, K, VAEConfig.tiny().latent_dim, generator=g)
    w = z.clone()
    w[:, k + 1:] += torch.randn(w[:, k + 1:].shape, generator=g)
    with torch.no_grad():
        a, b = vae.decode(z), vae.decode(w)
    end = (k + 1) * S
    assert (a[:, :end] - b[:, :end]).abs().max().item() < 1e-6
    assert (a[:, end:] - b[:, end:]).abs().max().item() > 1e-4


def _cond(g: torch.Generator) -> dict:
    return {"user_head": torch.randn(2, T, 2, generator=g),
            "agent_audio": torch.randn(2, T, DA, generator=g),
            "user_audio": torch.randn(2, T, DA, generator=g),
            "gaze": torch.rand(2, T, generator=g) * 2 - 1}


@settings(max_examples=12, deadline=None)
@given(t=st.integers(0, T - 2), name=st.sampled_from(MODALITIES + ("z_tau",)),
       seed=st.integers(0, 2**16))
def test_flow_is_causal(flow, t, name, seed):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(2, K, flow.latent_dim, generator=g)
    cond = _cond(g)
    tau = torch.rand(2, generator=g)
    z2, cond2 = z.clone(), {k: v.clone() for k, v in cond.items()}
    first_block = (t + 1) // S  # first block holding a frame after t
    if name == "z_tau":
        z2[:, first_block:] += 1.0
    else:
        cond2[name][:, t + 1:] += 1.0
    with torch.no_grad():
        a, b = flow(z, tau, cond), flow(z2, tau, cond2)
    if first_block:
        assert (a[:, :first_block] - b[:, :first_block]).abs().max().item() < 1e-6
    assert (a[:, first_block:] - b[:, first_block:]).abs().max().item() > 1e-5


def test_adaln_zero_block_is_identity_at_init():
    torch.manual_seed(0)
    block = AdaLNZeroBlock(32, 4, cond_dim=16)
    x, c = torch.randn(2, 7, 32), torch.randn(2, 16)
    out = block(x, c, causal_mask(7), torch.arange(7))
    assert torch.equal(out, x)
    # Per-token conditioning too, and gradients still reach the modulation.
    out = block(x, torch.randn(2, 7, 16, requires_grad=True), causal_mask(7), torch.arange(7))
    out.square().sum().backward()
    assert block.modulation[1].weight.grad.abs().sum() > 0


@pytest.mark.parametrize("adaln", [False, True])
def test_kv_cache_matches_full_pass(adaln):
    torch.manual_seed(0)
    block = (AdaLNZeroBlock(32, 4, 8) if adaln else TransformerBlock(32, 4))
    _randomize(block, 3)
    x, c = torch.randn(1, 9, 32), torch.randn(1, 9, 8)
    args = (lambda lo, hi: (c[:, lo:hi],)) if adaln else (lambda lo, hi: ())
    full = block(x, *args(0, 9), causal_mask(9), torch.arange(9))
    cache, parts = KVCache(), []
    for lo, hi in ((0, 4), (4, 5), (5, 9)):
        parts.append(block(x[:, lo:hi], *args(lo, hi), causal_mask(hi - lo, hi),
                           torch.arange(lo, hi), cache))
    assert len(cache) == 9
    torch.testing.assert_close(torch.cat(parts, 1), full, atol=1e-5, rtol=1e-5)
    # commit=False peeks without growing; max_tokens keeps a sliding window.
    block(x[:, :1], *args(0, 1), causal_mask(1, 10), torch.arange(9, 10), cache, commit=False)
    assert len(cache) == 9
    windowed = KVCache(max_tokens=3)
    block(x, *args(0, 9), causal_mask(9), torch.arange(9), windowed)
    assert len(windowed) == 3


def test_attention_rejects_bad_masks():
    attn = Attention(16, 2)
    x = torch.randn(1, 4, 16)
    with pytest.raises(TypeError):
        attn(x, causal_mask(4).float(), torch.arange(4))
    with pytest.raises(ValueError):
        attn(x, causal_mask(3), torch.arange(4))


@pytest.mark.parametrize("tokens", [1, 9, 37])
def test_no_mask_is_the_lower_triangle_to_the_bit(tokens):
    """``mask=None`` over a square window runs SDPA's causal flag, which skips the masked half of
    the scores; outputs and every gradient are the explicit triangle's, bit for bit."""
    attn = _randomize(Attention(32, 4), 4)
    x = torch.randn(3, tokens, 32)
    results = []
    for mask in (causal_mask(tokens), None):
        attn.zero_grad()
        inputs = x.clone().requires_grad_()
        out = attn(inputs, mask, torch.arange(tokens))
        out.mul(torch.linspace(-1, 1, 32)).sum().backward()
        results.append([out.detach(), inputs.grad, attn.qkv.weight.grad.clone()])
    for flag, explicit in zip(results[1], results[0]):
        assert torch.equal(flag, explicit)
