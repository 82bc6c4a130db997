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
