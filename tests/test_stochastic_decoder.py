"""The stochastic decoder (``vae.detail_dim``): the energy score it trains with, its draws
decoded incrementally as at once, streams that decode the offline solve's draws, and a trained
deterministic VAE fine-tuned into one."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from sarah_models.config import StreamConfig, VAEConfig
from sarah_models.nn.vae import CausalVAE, energy_score
from sarah_models.sampling.stream import StreamingGenerator, offline_with_latents
from sarah_models.testing import random_models

DX = 30
CFG = replace(VAEConfig.tiny(), latent_dim=8, hidden=16, heads=2, detail_dim=4)


def unit_distance(a, b, frames, hop, weight, orders, per_point=False):
    """The energy score's unit distance written out: every unit's positions, differences and
    second differences (of each point alone, or of all) stacked into one vector, its weighted
    root mean square."""
    error = (a - b) * weight.sqrt()
    groups = error.unflatten(-1, (-1, 3)).unbind(-2) if per_point else (error,)
    out = []
    for start in range(0, a.shape[1] - frames + 1, hop):
        for group in groups:
            unit, parts = group[:, start:start + frames], []
            for scale in orders:
                if scale > 0:
                    parts.append(scale ** 0.5 * unit.flatten(1))
                unit = unit.diff(dim=1)
            out.append(torch.cat(parts, 1).square().mean(1).sqrt())
    return torch.stack(out, 1)


def test_energy_score_is_each_units_distance_as_written():
    g = torch.Generator().manual_seed(0)
    sample, twin, x = (torch.randn(2, 21, DX, generator=g) for _ in range(3))
    weight = torch.rand(DX, generator=g) + 0.5
    orders = (1.0, 10.0, 3.0)
    expected = (0.5 * (unit_distance(sample, x, 8, 4, weight, orders)
                       + unit_distance(twin, x, 8, 4, weight, orders))
                - 0.5 * unit_distance(sample, twin, 8, 4, weight, orders)).mean()
    torch.testing.assert_close(energy_score(sample, twin, x, 8, 4, weight, orders), expected)
    per_point = (0.5 * (unit_distance(sample, x, 8, 4, weight, orders, True)
                        + unit_distance(twin, x, 8, 4, weight, orders, True))
                 - 0.5 * unit_distance(sample, twin, 8, 4, weight, orders, True)).mean()
    torch.testing.assert_close(energy_score(sample, twin, x, 8, 4, weight, orders, True), per_point)
    with pytest.raises(ValueError, match="energy_frames = 8"):
        energy_score(sample[:, :6], twin[:, :6], x[:, :6], 8, 4)


def test_energy_score_is_least_for_samples_drawn_as_the_data_are():
    """A proper score: samples from the data's distribution score below its mean (what an MSE
    prefers) and below samples of twice its spread; the MSE ranks the mean first."""
    g = torch.Generator().manual_seed(1)
    x = torch.randn(4, 400, DX, generator=g)

    def score(spread):
        sample, twin = (spread * torch.randn(x.shape, generator=g) for _ in range(2))
        return float(energy_score(sample, twin, x, 8, 4)), float((sample - x).square().mean())

    (right, right_mse), (mean, mean_mse), (wide, _) = score(1.0), score(0.0), score(2.0)
    assert right < wide < mean
    assert right == pytest.approx(0.5 * 2 ** 0.5, rel=0.02)  # E|Y - x| - E|Y - Y'| / 2, unit normals
    assert mean_mse < right_mse


def test_draws_decode_incrementally_as_at_once_and_change_the_motion():
    torch.manual_seed(0)
    vae = CausalVAE(CFG, DX).eval()
    z = torch.randn(2, 5, CFG.latent_dim)
    detail = vae.detail_noise(2, 5, torch.Generator().manual_seed(3))
    assert detail.shape == (2, 5, CFG.detail_dim)
    with torch.no_grad():
        full = vae.decode(z, detail)
        cache = vae.new_decoder_cache()
        steps = torch.cat([vae.decoder_step(z[:, k], cache, detail[:, k]) for k in range(5)], 1)
        torch.testing.assert_close(steps, full, atol=1e-5, rtol=0)
        # one token drawn at a time gives the same draws as the whole window at once
        g = torch.Generator().manual_seed(3)
        one_by_one = torch.cat([vae.detail_noise(1, 1, g) for _ in range(10)], 1).view(2, 5, -1)
        torch.testing.assert_close(one_by_one, detail)
        assert (vae.decode(z, torch.randn(detail.shape)) - full).abs().max() > 1e-4
        torch.testing.assert_close(vae.decode(z), vae.decode(z, torch.zeros_like(detail)))
    # a deterministic decoder has no draws and no detail input
    plain = CausalVAE(replace(CFG, detail_dim=0), DX)
    assert plain.detail_in is None and plain.detail_noise(2, 5) is None


def test_the_loss_adds_the_energy_of_the_accelerations_and_trains_the_detail_input():
    """Two samples' mean MSE terms (as a deterministic VAE's) plus the energy score of their
    second differences; the draws' input gets gradients."""
    torch.manual_seed(0)
    vae = CausalVAE(CFG, DX)
    x = torch.randn(2, 16, DX)
    out = vae(x, torch.Generator().manual_seed(0))
    assert set(out) >= {"loss", "energy", "recon", "kl", "x_hat"}
    torch.testing.assert_close(out["loss"], out["recon"] + CFG.beta * out["kl"]
                               + CFG.velocity_weight * out["velocity"]
                               + CFG.acceleration_weight * out["acceleration"]
                               + CFG.energy_weight * out["energy"])
    out["loss"].backward()
    assert vae.detail_in.weight.grad.abs().sum() > 0
    again = vae(x, torch.Generator().manual_seed(0))  # seeded: the same draws
    torch.testing.assert_close(again["x_hat"], out["x_hat"])


def test_a_stream_decodes_the_offline_solves_draws():
    """Trajectory imputation makes a stream the offline solve (test_stream); with a stochastic
    decoder both draw the same detail per token, so the frames agree too; without the draws'
    effect the frames are others."""
    models = random_models("tiny", 8, 4, 0, motion_std=0.02, init_std=0.05,
                           latent_mean_std=0.1, overrides=("vae.detail_dim=4",))
    vae = models[0]
    with torch.no_grad():  # a detail input that moves the motion visibly
        vae.detail_in.weight.normal_(0, 0.5)
    rng = np.random.default_rng(0)
    frames = 4 * 10
    head = np.stack([np.cos(np.linspace(0, 2, frames)), np.sin(np.linspace(0, 2, frames))], 1)
    inputs = (head.astype(np.float32), rng.normal(size=(frames, 8)).astype(np.float32),
              rng.normal(size=(frames, 8)).astype(np.float32))
    config = StreamConfig(imputation="trajectory", noise_scale=0.6)
    gen = StreamingGenerator(*models, config)
    streamed = np.concatenate([gen.step(*(x[i:i + 4] for x in inputs))
                               for i in range(0, frames, 4)])
    offline, _ = offline_with_latents(*models, *inputs, config)
    np.testing.assert_allclose(streamed, offline, atol=1e-5)
    with torch.no_grad():
        vae.detail_in.weight.zero_()
    without, _ = offline_with_latents(*models, *inputs, config)
    assert np.abs(without - offline).max() > 1e-4
