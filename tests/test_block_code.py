"""The VAE's linear block code (``vae.block_code``): fitted to the data's principal components,
the untrained VAE reconstructs what a linear code of one block can, causally, and the training
stage fits it from the shards."""

from dataclasses import replace

import pytest
import torch

from sarah_models.config import VAEConfig
from sarah_models.nn.block_code import BlockCode
from sarah_models.nn.vae import CausalVAE

DX = 30
CFG = replace(VAEConfig.tiny(), latent_dim=8, hidden=16, heads=2, block_code=True)


def low_rank_motion(batches: int, blocks: int, rank: int, seed: int = 0,
                    frame_rank: int = 6) -> torch.Tensor:
    """(batches, blocks * s, DX) motion whose frames lie in one ``frame_rank``-dim subspace and
    whose blocks' coefficients there lie in one ``rank``-dim subspace."""
    g = torch.Generator().manual_seed(seed)
    s = CFG.stride
    frame_basis = torch.randn(frame_rank, DX, generator=g)
    block_basis = torch.randn(rank, s * frame_rank, generator=g)
    coefficients = torch.randn(batches, blocks, rank, generator=g) * torch.linspace(3, 0.5, rank)
    frames = (coefficients @ block_basis).reshape(batches, blocks * s, frame_rank)
    return frames @ frame_basis


def fitted_vae(motion: torch.Tensor, weight: torch.Tensor | None = None) -> CausalVAE:
    torch.manual_seed(0)
    vae = CausalVAE(CFG, DX).eval()
    vae.block_code.fit(lambda: iter(motion.split(2)), weight)
    return vae


def test_fitted_untrained_vae_reconstructs_motion_a_block_code_can_carry():
    """Blocks of rank <= Dz come back exactly through encode -> decode of the fresh VAE (its
    transformers' outputs start at zero), with or without channel weights; rank above Dz
    does not (the code is what it claims, not an identity)."""
    motion = low_rank_motion(6, 10, rank=CFG.latent_dim)
    weight = torch.rand(DX, generator=torch.Generator().manual_seed(1)) + 0.1
    for w in (None, weight):
        vae = fitted_vae(motion, w)
        with torch.no_grad():
            mu, logvar = vae.encode(motion)
            decoded = vae.decode(mu)
        torch.testing.assert_close(decoded, motion, atol=1e-3, rtol=1e-3)
        # whitened: each latent channel has unit mean square over the fitted data
        torch.testing.assert_close(mu.square().mean((0, 1)), torch.ones(CFG.latent_dim),
                                   atol=1e-3, rtol=1e-3)
        assert torch.all(logvar < -4)  # the posterior starts narrow, not at the prior's width
    wider = low_rank_motion(6, 10, rank=3 * CFG.latent_dim, seed=2, frame_rank=12)
    vae = fitted_vae(wider)
    with torch.no_grad():
        error = (vae.decode(vae.encode(wider)[0]) - wider).square().mean()
    assert error > 0.05 * wider.square().mean()


def test_fit_is_deterministic_and_refuses_what_it_cannot_fit():
    motion = low_rank_motion(4, 6, rank=12)
    first, second = fitted_vae(motion), fitted_vae(motion.clone())
    for a, b in zip(first.block_code.state_dict().values(), second.block_code.state_dict().values()):
        assert torch.equal(a, b)
    code = BlockCode(DX, CFG.stride, CFG.latent_dim, rank=16)
    with pytest.raises(ValueError, match="multiples of 4 frames"):
        code.fit(lambda: iter([torch.zeros(1, 6, DX)]))
    with pytest.raises(ValueError, match="no motion"):
        code.fit(lambda: iter([]))


def test_block_code_vae_stays_causal_and_streams_as_it_decodes():
    """With every weight set (not the zeros a fresh code's transformers start from): a latent
    does not see later blocks' frames, a decoded block does not see later latents, and the
    decoder fed one latent at a time gives the full decode."""
    vae = fitted_vae(low_rank_motion(4, 6, rank=12))
    with torch.no_grad():
        for p in vae.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    s = CFG.stride
    x = torch.randn(1, 8 * s, DX)
    later = x.clone()
    later[:, 5 * s:] += torch.randn(1, 3 * s, DX)
    with torch.no_grad():
        mu, _ = vae.encode(x)
        mu_later, _ = vae.encode(later)
        torch.testing.assert_close(mu[:, :5], mu_later[:, :5])
        assert not torch.allclose(mu[:, 5:], mu_later[:, 5:])
        z_later = mu.clone()
        z_later[:, 5:] += 1.0
        full, full_later = vae.decode(mu), vae.decode(z_later)
        torch.testing.assert_close(full[:, :5 * s], full_later[:, :5 * s])
        assert not torch.allclose(full[:, 5 * s:], full_later[:, 5 * s:])
        cache = vae.new_decoder_cache()
        steps = [vae.decoder_step(mu[:, k], cache) for k in range(8)]
    torch.testing.assert_close(torch.cat(steps, 1), full, atol=1e-5, rtol=1e-5)


def test_freezing_the_encoder_freezes_the_code_s_encoding_half():
    vae = CausalVAE(CFG, DX)
    frozen = {id(p) for part in vae.encoder_modules()
              for p in (part.parameters() if isinstance(part, torch.nn.Module) else [part])}
    code = vae.block_code
    assert {id(code.frame_in.weight), id(code.block_in.weight)} <= frozen
    assert not {id(code.frame_out.weight), id(code.block_out.weight)} & frozen


def test_training_stage_fits_the_code_from_the_shards(prepared_shards, tmp_path):
    """``vae.block_code`` through the training stage: the code is fitted before the first step
    (the run says how much it keeps), so the VAE starts from a reconstruction the paper's
    VAE reaches only after training, and a fine-tune keeps the trained code instead of refitting."""
    from sarah_data.dataset import WindowDataset
    from sarah_models.config import RunConfig
    from sarah_models.training.checkpoint import load_models
    from sarah_models.training.objectives import VAEObjective
    from sarah_models.training.stages import train

    def config(steps: int, *extra: str) -> RunConfig:
        return RunConfig.preset("tiny").with_overrides([
            "vae.hidden=32", "vae.heads=2", "vae.latent_dim=16", "vae.encoder_layers=1",
            "vae.decoder_layers=1", "train.window=16", "train.batch_size=2", f"train.vae_steps={steps}",
            "train.num_workers=0", "train.latent_stats_batches=4", "train.log_every=1",
            "vae.root_relative=true", "vae.recon_units=metres", "flow.position_tokens=4", *extra])

    said = []
    common = dict(device="cpu", progress=False)
    with_code = train("vae", config(1, "vae.block_code=true"), prepared_shards,
                      tmp_path / "code", echo=said.append, **common)
    without = train("vae", config(1), prepared_shards, tmp_path / "plain",
                    echo=lambda _: None, **common)
    assert any("block code fitted" in line for line in said)
    windows = WindowDataset.sliding(prepared_shards, "train", extractor=None, window=16)
    motion = torch.stack([windows[i]["motion"] for i in range(len(windows))])

    def error(path) -> float:
        """Squared error as the loss counts it (in metres, root weighted)."""
        models = load_models(path, device="cpu")
        nz, vae = models.normalizer, models.vae
        weight = VAEObjective(vae, nz).channel_weight
        with torch.no_grad():
            x = nz.normalize("motion", motion)
            return float(((vae.decode(vae.encode(x)[0]) - x).square() * weight).mean())

    assert error(with_code) < 0.2 * error(without)
    said.clear()
    train("vae", config(1, "vae.block_code=true"), prepared_shards, tmp_path / "tuned",
          init_from=with_code, echo=said.append, **common)
    assert not any("block code fitted" in line for line in said)


def test_block_code_model_streams_through_the_fast_path():
    """The inference fast path runs the VAE's own decoder_step with swapped modules, so the code
    decodes there too: exact in fp32, within #20's 1 mm with the int8 flow."""
    from sarah_models.accel import optimize_for_inference
    from sarah_models.testing import random_models, stream_deviation

    models = random_models("tiny", audio_dim=8, shell_points=4, seed=0,
                           overrides=("vae.block_code=true",))
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in models[0].block_code.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.1)
    assert stream_deviation(models, optimize_for_inference(models, "fp32"), frames=24).max_joint_mm == 0.0
    deviation = stream_deviation(models, optimize_for_inference(models, "int8"), frames=24)
    assert 0.0 < deviation.max_joint_mm <= 1.0, deviation
