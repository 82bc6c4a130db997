"""The causal VAE: shapes, KL, streaming decode, and that it learns."""

from dataclasses import replace

import pytest
import torch
from torch.distributions import Normal, kl_divergence

from sarah_models.config import VAEConfig
from sarah_models.nn.vae import CausalVAE

CFG = VAEConfig.tiny()
DX = 30


@pytest.fixture(scope="module")
def vae():
    torch.manual_seed(0)
    return CausalVAE(CFG, DX).eval()


def test_shapes(vae):
    x = torch.randn(3, 8 * CFG.stride, DX)
    mu, logvar = vae.encode(x)
    assert mu.shape == logvar.shape == (3, 8, CFG.latent_dim)
    assert vae.decode(mu).shape == x.shape
    out = vae(x, torch.Generator().manual_seed(0))
    assert set(out) >= {"loss", "recon", "velocity", "acceleration", "kl", "x_hat"}
    assert out["x_hat"].shape == x.shape and out["loss"].dim() == 0
    torch.testing.assert_close(out["loss"], out["recon"] + CFG.beta * out["kl"]
                               + CFG.velocity_weight * out["velocity"]
                               + CFG.acceleration_weight * out["acceleration"])


def test_velocity_term_is_the_error_of_frame_differences():
    """The extra term (not in the paper, on in the tiny preset) is the MSE of the error's
    frame-to-frame change, so a constant offset costs nothing there."""
    torch.manual_seed(0)
    vae = CausalVAE(VAEConfig.tiny(), DX).eval()
    x = torch.randn(1, 4 * CFG.stride, DX)
    x_hat = vae(x, torch.Generator().manual_seed(0))["x_hat"].detach()
    error = x_hat - x
    out = vae(x, torch.Generator().manual_seed(0))
    torch.testing.assert_close(out["velocity"], (error[:, 1:] - error[:, :-1]).square().mean())
    # the same prediction against a target shifted by a constant: position error grows,
    # the velocity term does not move
    torch.testing.assert_close(vae.loss_terms(x_hat, x - 0.5)["velocity"], out["velocity"])
    assert vae.loss_terms(x_hat, x - 0.5)["recon"] > out["recon"] + 0.2
    assert VAEConfig.paper().velocity_weight == 0.0  # eq. 3 of the paper has no such term
    assert VAEConfig.tiny().velocity_weight > 0


def test_acceleration_term_is_the_error_of_second_differences():
    """Not in the paper: the MSE of the error's second difference, so a target moved by any
    straight line in time (offset plus drift) costs nothing there; weighted into the loss."""
    torch.manual_seed(0)
    config = replace(VAEConfig.tiny(), acceleration_weight=30.0)
    vae = CausalVAE(config, DX).eval()
    x = torch.randn(1, 4 * CFG.stride, DX)
    out = vae(x, torch.Generator().manual_seed(0))
    error = out["x_hat"].detach() - x
    bend = error[:, 2:] - 2 * error[:, 1:-1] + error[:, :-2]
    torch.testing.assert_close(out["acceleration"], bend.square().mean())
    drift = 0.5 + 0.1 * torch.arange(x.shape[1], dtype=x.dtype)[None, :, None]
    moved = vae.loss_terms(out["x_hat"].detach(), x - drift)
    torch.testing.assert_close(moved["acceleration"], out["acceleration"])
    assert moved["velocity"] > out["velocity"] + 0.005
    torch.testing.assert_close(out["loss"], out["recon"] + config.beta * out["kl"]
                               + config.velocity_weight * out["velocity"]
                               + 30.0 * out["acceleration"])
    assert VAEConfig.paper().acceleration_weight == 0.0


def test_rejects_length_not_multiple_of_stride(vae):
    with pytest.raises(ValueError, match="stride"):
        vae.encode(torch.randn(1, CFG.stride * 3 + 1, DX))


def test_kl_matches_torch_distributions():
    g = torch.Generator().manual_seed(0)
    mu, logvar = torch.randn(2, 5, 7, generator=g), torch.randn(2, 5, 7, generator=g)
    ref = kl_divergence(Normal(mu, (0.5 * logvar).exp()), Normal(0.0, 1.0)).mean()
    torch.testing.assert_close(CausalVAE.kl(mu, logvar), ref)
    assert CausalVAE.kl(torch.zeros(3), torch.zeros(3)).item() == 0.0


def test_forward_is_reproducible_with_a_generator(vae):
    x = torch.randn(2, 4 * CFG.stride, DX)
    a = vae(x, torch.Generator().manual_seed(5))["loss"]
    b = vae(x, torch.Generator().manual_seed(5))["loss"]
    c = vae(x, torch.Generator().manual_seed(6))["loss"]
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_incremental_decode_equals_full_decode(vae):
    z = torch.randn(2, 9, CFG.latent_dim, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        full = vae.decode(z)
        cache = vae.new_decoder_cache()
        steps = [vae.decoder_step(z[:, k], cache) for k in range(z.shape[1])]
    assert all(s.shape == (2, CFG.stride, DX) for s in steps)
    torch.testing.assert_close(torch.cat(steps, 1), full, atol=1e-5, rtol=1e-5)
    assert cache.blocks == 9 and cache.position == 9 * (CFG.stride + 1)


def test_two_frame_tokens_encode_causally_and_decode_incrementally():
    """At stride 2 a token is 2 frames: its latent does not see later frames, and the decoder
    fed one token at a time gives the full decode."""
    torch.manual_seed(0)
    vae = CausalVAE(replace(CFG, stride=2), DX).eval()
    x = torch.randn(1, 2 * 9, DX)
    later = x.clone()
    later[:, 10:] += torch.randn(1, 8, DX)
    with torch.no_grad():
        mu, _ = vae.encode(x)
        mu_later, _ = vae.encode(later)
        assert mu.shape == (1, 9, CFG.latent_dim)
        torch.testing.assert_close(mu[:, :5], mu_later[:, :5])
        assert not torch.allclose(mu[:, 5:], mu_later[:, 5:])
        cache = vae.new_decoder_cache()
        steps = [vae.decoder_step(mu[:, k], cache) for k in range(9)]
        full = vae.decode(mu)
    assert all(s.shape == (1, 2, DX) for s in steps)
    torch.testing.assert_close(torch.cat(steps, 1), full, atol=1e-5, rtol=1e-5)


def test_windowed_decoder_cache_stays_bounded(vae):
    z = torch.randn(1, 12, CFG.latent_dim)
    cache = vae.new_decoder_cache(max_blocks=3)
    with torch.no_grad():
        first = [vae.decoder_step(z[:, k], cache) for k in range(12)]
    assert all(len(c) == 3 * (CFG.stride + 1) for c in cache.layers)
    # Until the window is full the windowed decoder still equals the full decode.
    with torch.no_grad():
        full = vae.decode(z[:, :3])
    torch.testing.assert_close(torch.cat(first[:3], 1), full, atol=1e-5, rtol=1e-5)


def test_tiny_vae_overfits_a_small_batch():
    torch.manual_seed(0)
    model = CausalVAE(CFG, DX)
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 6.28, 16)
    # Smooth, structured synthetic motion: sinusoids with random phases and frequencies.
    freq, phase = torch.rand(2, 1, DX, generator=g) * 3, torch.rand(2, 1, DX, generator=g) * 6
    x = torch.sin(t[None, :, None] * freq + phase)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for step in range(120):
        out = model(x, torch.Generator().manual_seed(step))
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(out["recon"].item())
    assert losses[-1] < losses[0] / 20, (losses[0], losses[-1])


def test_quintic_hermite_meets_its_end_conditions():
    """Each basis function is 1 in its own end value (position, velocity or acceleration at
    t = 0 or 1) and 0 in the five others, and the position weights sum to 1 everywhere."""
    from sarah_models.nn.vae import quintic_hermite

    t = torch.tensor([0.0, 1.0], dtype=torch.float64, requires_grad=True)
    basis = quintic_hermite(t)  # (2, 6)
    values, slopes, bends = [], [], []
    for j in range(6):
        (d1,) = torch.autograd.grad(basis[:, j].sum(), t, create_graph=True)
        (d2,) = torch.autograd.grad(d1.sum(), t)
        values.append(basis[:, j].detach()), slopes.append(d1.detach()), bends.append(d2)
    ends = torch.stack([torch.stack((v[0], s[0], b[0], v[1], s[1], b[1]))
                        for v, s, b in zip(values, slopes, bends)])
    torch.testing.assert_close(ends, torch.eye(6, dtype=torch.float64))
    inside = quintic_hermite(torch.linspace(0, 1, 11, dtype=torch.float64))
    torch.testing.assert_close(inside[:, 0] + inside[:, 3], torch.ones(11, dtype=torch.float64))


@pytest.fixture(scope="module")
def curve_vae():
    torch.manual_seed(0)
    vae = CausalVAE(replace(CFG, frame_curve="quintic"), DX).eval()
    with torch.no_grad():  # trained weights: derivatives that are not zero
        vae.frame_out.weight.normal_(0, 0.05)
    return vae


def test_quintic_frames_are_smooth_across_seams(curve_vae):
    """Decoded with frame_curve="quintic", block k's frames are the quintic Hermite curve from
    block k-1's end state to its own (so, by the basis's end conditions, consecutive blocks
    meet in position, velocity and acceleration), and its last frame is its end position."""
    from sarah_models.nn.layers import causal_mask
    from sarah_models.nn.vae import quintic_hermite

    s, k = CFG.stride, 5
    z = torch.randn(2, 12, CFG.latent_dim, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        curve = curve_vae.decode(z)
        tokens = curve_vae._decoder_tokens(z)
        n = tokens.shape[1]
        for block in curve_vae.decoder:
            tokens = block(tokens, causal_mask(n), torch.arange(n))
        states = curve_vae.frame_out(curve_vae.decoder_norm(tokens).view(2, 12, s + 1, -1)[:, :, 1:])
    ends = states.unflatten(-1, (3, DX))[:, :, -1]  # (B, K, position/velocity/acceleration, Dx)
    basis = quintic_hermite(torch.arange(1, s + 1, dtype=torch.float32) / s)
    expected = torch.einsum("sc,bcd->bsd", basis, torch.cat((ends[:, k - 1], ends[:, k]), dim=1))
    torch.testing.assert_close(curve[:, k * s:(k + 1) * s], expected, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(curve[:, (k + 1) * s - 1], ends[:, k, 0], atol=1e-5, rtol=1e-5)
    # the derivatives are the network's (not zero), so the curve between ends is not a plain ease
    eased = torch.einsum("sc,bcd->bsd", basis, torch.cat(
        (ends[:, k - 1] * torch.tensor([1.0, 0, 0])[:, None],
         ends[:, k] * torch.tensor([1.0, 0, 0])[:, None]), dim=1))
    assert (curve[:, k * s:(k + 1) * s - 1] - eased[:, :-1]).abs().max() > 1e-3


def test_quintic_decoder_streams_and_stays_causal(curve_vae):
    """One block at a time (the stream's decoder) gives the full decode, and a later latent
    changes no earlier frame."""
    z = torch.randn(2, 9, CFG.latent_dim, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        full = curve_vae.decode(z)
        cache = curve_vae.new_decoder_cache()
        steps = [curve_vae.decoder_step(z[:, k], cache) for k in range(9)]
        later = z.clone()
        later[:, 6:] += 1.0
        changed = curve_vae.decode(later)
    torch.testing.assert_close(torch.cat(steps, 1), full, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(changed[:, :6 * CFG.stride], full[:, :6 * CFG.stride])
    assert not torch.allclose(changed[:, 6 * CFG.stride:], full[:, 6 * CFG.stride:])


def test_quintic_curve_rejects_a_block_code():
    with pytest.raises(ValueError, match="block_code"):
        replace(CFG, frame_curve="quintic", block_code=True)
    with pytest.raises(ValueError, match="frame_curve"):
        replace(CFG, frame_curve="spline")
