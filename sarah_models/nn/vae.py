"""Causal transformer VAE with latent tokens interleaved at stride s (paper 3.2, eq. 2-3).

Shapes: motion x (B, T, Dx) with T = K*s; latents mu, logvar, z (B, K, Dz).

Encoder sequence, K*(s+2) tokens in this order (eq. 2)::

    x_1 .. x_s, mu_1, sigma_1, x_s+1 .. x_2s, mu_2, sigma_2, ...

Decoder sequence, K*(s+1) tokens: block k is the latent token z_k followed by s learned
query tokens whose outputs are the frames of block k::

    z_1, q_1 .. q_s, z_2, q_1 .. q_s, ...

Both masks are the plain lower triangle over that interleaved order (token i attends to tokens
j <= i). Picture for s = 2, K = 2 (# = attend, . = masked)::

    encoder   x1 x2 m1 s1 x3 x4 m2 s2        decoder   z1 q1 q2 z2 q3 q4
         x1   #  .  .  .  .  .  .  .              z1   #  .  .  .  .  .
         x2   #  #  .  .  .  .  .  .              q1   #  #  .  .  .  .
         m1   #  #  #  .  .  .  .  .              q2   #  #  #  .  .  .
         s1   #  #  #  #  .  .  .  .              z2   #  #  #  #  .  .
         x3   #  #  #  #  #  .  .  .              q3   #  #  #  #  #  .
         x4   #  #  #  #  #  #  .  .              q4   #  #  #  #  #  #
         m2   #  #  #  #  #  #  #  .
         s2   #  #  #  #  #  #  #  #

So a frame token sees past and current frames and the latent tokens of earlier blocks; mu_k and
sigma_k see every frame up to the end of block k and the earlier latent tokens (sigma_k also sees
mu_k); decoded frames of block k depend on z_1..z_k only. The posterior of block k therefore
depends on x_1..x_ks: encoding then decoding looks ahead at most s-1 frames, the streaming
latency of one block.

Positions: RoPE over the index of each token in its interleaved sequence. The loss is the mean
squared error per motion element plus beta times the KL per latent element (both means, so
beta = 1e-4 keeps its paper meaning of "a small KL weight" independent of T, Dx and Dz), plus
``velocity_weight`` times the mean squared error of frame-to-frame differences and
``acceleration_weight`` times that of second differences (both 0 in the paper).
``latent_noise`` > 0 adds noise to the decoder's input latents in training (0 in the paper).
``detail_dim`` > 0 makes the decoder stochastic (not in the paper): each latent token comes with
that many standard normal draws (``detail``); training decodes twice with independent draws and
adds ``energy_weight`` times the energy score of the two samples' accelerations
(``energy_score``) to their mean MSE terms.
``block_code`` adds a linear code of each block beside both transformers (``nn.block_code``;
not in the paper).
``recon_units="metres"`` weights each channel's squared error by its variance (the objective
passes ``channel_weight``), so the loss counts a millimetre the same on every axis.
The planted-foot term (``contact_weight``) and the head-facing term (``head_weight``) need the
motion layout and metres, so the training objective adds them (``training.objectives.VAEObjective``).
``stance_weight`` > 0 gives the VAE a stance head (``nn.stance``, not in the paper): which foot is
planted, per frame, read from the latent tokens the decoder reads; the objective adds its
cross-entropy against the data's stance, and the foot lock steps by it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from ..config import VAEConfig
from .block_code import BlockCode
from .layers import KVCache, TransformerBlock, causal_mask
from .stance import StanceHead

BLOCK_CODE_LOGVAR = -5.0  # the posterior's initial log-variance with ``vae.block_code``
DETAIL_INIT_STD = 0.01  # the detail input's initial weights (vae.detail_dim)
DETAIL_SEED_OFFSET = 0x5EED_DE7A  # detail draws' seed = the generation seed + this


def encoder_layout(num_blocks: int, stride: int) -> list[tuple[str, int, int]]:
    """(kind, block, frame) for every encoder token; kind is 'x', 'mu' or 'sigma', frame is -1
    for latent tokens. Used by the tests to check the mask semantics."""
    layout = []
    for k in range(num_blocks):
        layout += [("x", k, k * stride + i) for i in range(stride)]
        layout += [("mu", k, -1), ("sigma", k, -1)]
    return layout


def decoder_layout(num_blocks: int, stride: int) -> list[tuple[str, int, int]]:
    """(kind, block, frame) for every decoder token; kind is 'z' or 'q'."""
    layout = []
    for k in range(num_blocks):
        layout += [("z", k, -1)] + [("q", k, k * stride + i) for i in range(stride)]
    return layout


@dataclass
class DecoderCache:
    """State of the incremental decoder: one KV cache per layer and the next token position."""

    layers: list[KVCache]
    position: int = 0
    blocks: int = field(default=0)


class CausalVAE(nn.Module):
    def __init__(self, config: VAEConfig, motion_dim: int) -> None:
        super().__init__()
        self.config = config
        self.motion_dim = motion_dim
        h, s = config.hidden, config.stride

        def blocks(n: int) -> nn.ModuleList:
            return nn.ModuleList(TransformerBlock(h, config.heads, config.mlp_ratio,
                                                  config.rope_base) for _ in range(n))

        self.frame_in = nn.Linear(motion_dim, h)
        self.mu_token = nn.Parameter(torch.randn(h) * 0.02)
        self.sigma_token = nn.Parameter(torch.randn(h) * 0.02)
        self.encoder = blocks(config.encoder_layers)
        self.encoder_norm = nn.LayerNorm(h)
        self.mu_out = nn.Linear(h, config.latent_dim)
        self.logvar_out = nn.Linear(h, config.latent_dim)

        self.latent_in = nn.Linear(config.latent_dim, h)
        # ``vae.detail_dim``: what the latent leaves open, drawn per token (None: deterministic)
        self.detail_in = nn.Linear(config.detail_dim, h) if config.detail_dim else None
        if self.detail_in is not None:
            # Small at first: a trained deterministic decoder (--init-from) starts where it was
            nn.init.normal_(self.detail_in.weight, std=DETAIL_INIT_STD)
            nn.init.zeros_(self.detail_in.bias)
        self.queries = nn.Parameter(torch.randn(s, h) * 0.02)
        self.decoder = blocks(config.decoder_layers)
        self.decoder_norm = nn.LayerNorm(h)
        self.frame_out = nn.Linear(h, motion_dim)
        # Not in the paper (``vae.block_code``): a linear code of each block beside the
        # transformers, fitted before training (``BlockCode.fit``); their outputs start at zero,
        # so the untrained VAE is that code and training learns what it misses.
        self.block_code = None
        if config.block_code:
            self.block_code = BlockCode(motion_dim, s, config.latent_dim, rank=h)
            for layer in (self.mu_out, self.frame_out, self.logvar_out):
                nn.init.zeros_(layer.weight)
                nn.init.zeros_(layer.bias)
            # The code's latents are whitened: a posterior std of 1 would bury the code in noise
            # at the first step; start where trained VAEs of this kind end (~0.08 of the spread)
            nn.init.constant_(self.logvar_out.bias, BLOCK_CODE_LOGVAR)
        # Built last: a VAE without it draws every other weight as before
        self.stance = StanceHead(config.latent_dim, s) if config.stance_weight > 0 else None

    @property
    def stride(self) -> int:
        return self.config.stride

    def num_blocks(self, num_frames: int) -> int:
        if num_frames % self.stride:
            raise ValueError(f"motion length {num_frames} is not a multiple of the stride "
                             f"{self.stride}")
        return num_frames // self.stride

    def encode(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """x (B, T, Dx) standardized motion -> mu, logvar (B, K, Dz)."""
        b, t, _ = x.shape
        k, s, h = self.num_blocks(t), self.stride, self.config.hidden
        frames = self.frame_in(x).view(b, k, s, h)
        latent = torch.stack((self.mu_token, self.sigma_token)).to(frames.dtype)
        tokens = torch.cat((frames, latent.expand(b, k, 2, h)), dim=2).reshape(b, k * (s + 2), h)
        n = tokens.shape[1]
        positions = torch.arange(n, device=x.device)
        for block in self.encoder:
            tokens = block(tokens, None, positions)  # None: the lower triangle, as SDPA's flag
        out = self.encoder_norm(tokens).view(b, k, s + 2, h)
        logvar = self.logvar_out(out[:, :, s + 1]).clamp(-30.0, 20.0)
        mu = self.mu_out(out[:, :, s])
        if self.block_code is not None:
            mu = mu + self.block_code.encode(x.reshape(b, k, s, -1))
        return mu, logvar

    def encoder_modules(self) -> list[nn.Module | nn.Parameter]:
        """Everything ``encode`` uses (frozen by ``train.freeze_encoder``)."""
        code = [] if self.block_code is None else self.block_code.encoder_modules()
        return [self.frame_in, self.mu_token, self.sigma_token, self.encoder, self.encoder_norm,
                self.mu_out, self.logvar_out, *code]

    def encoder_parameter_names(self) -> list[str]:
        """The state-dict names of ``encoder_modules``' parameters: what fixes the latents."""
        owned = {id(p) for m in self.encoder_modules()
                 for p in (m.parameters() if isinstance(m, nn.Module) else [m])}
        return [name for name, p in self.named_parameters() if id(p) in owned]

    def detail_noise(self, batch: int, blocks: int, generator: torch.Generator | None = None,
                     device: torch.device | str | None = None) -> Tensor | None:
        """Generation's standard normal detail draws (batch, blocks, detail_dim) for ``decode``
        from a CPU ``generator`` (``detail_generator``), one token at a time, so a stream
        drawing one token per step gets the offline solve's values whatever ``detail_dim`` is
        (one call rounds several tokens' draws alike only for multiples of 16); None for a
        deterministic decoder."""
        if self.detail_in is None:
            return None
        d = self.config.detail_dim
        draws = [torch.randn(d, generator=generator) for _ in range(batch * blocks)]
        return torch.stack(draws).view(batch, blocks, d).to(device)

    def _decoder_tokens(self, z: Tensor, detail: Tensor | None = None) -> Tensor:
        b, k, _ = z.shape
        s, h = self.stride, self.config.hidden
        latent = self.latent_in(z)
        if self.detail_in is not None:
            # No draw given: the draws' mean, zero (a deterministic decode of a stochastic decoder)
            latent = latent + (self.detail_in.bias if detail is None
                               else self.detail_in(detail.to(latent.dtype)))
        latent = latent[:, :, None]
        queries = self.queries.to(latent.dtype).expand(b, k, s, h)
        return torch.cat((latent, queries), dim=2).reshape(b, k * (s + 1), h)

    def _decoder_frames(self, tokens: Tensor, z: Tensor) -> Tensor:
        b, n, h = tokens.shape
        s = self.stride
        out = self.frame_out(self.decoder_norm(tokens).view(b, n // (s + 1), s + 1, h)[:, :, 1:])
        if self.block_code is not None:
            out = out + self.block_code.decode(z).to(out.dtype)
        return out.reshape(b, -1, self.motion_dim)

    def decode(self, z: Tensor, detail: Tensor | None = None) -> Tensor:
        """z (B, K, Dz) -> x_hat (B, K*s, Dx); ``detail`` (B, K, detail_dim): the stochastic
        decoder's draws (``detail_noise``; None: zero draws)."""
        tokens = self._decoder_tokens(z, detail)
        n = tokens.shape[1]
        positions = torch.arange(n, device=z.device)
        for block in self.decoder:
            tokens = block(tokens, None, positions)  # None: the lower triangle, as SDPA's flag
        return self._decoder_frames(tokens, z)

    def new_decoder_cache(self, max_blocks: int | None = None) -> DecoderCache:
        """A fresh streaming-decoder state. ``max_blocks`` bounds memory by attending only to the
        latest blocks (outputs then differ from ``decode`` once older blocks are dropped)."""
        max_tokens = None if max_blocks is None else max_blocks * (self.stride + 1)
        return DecoderCache([KVCache(max_tokens) for _ in self.decoder])

    def decoder_step(self, z_k: Tensor, cache: DecoderCache, detail: Tensor | None = None
                     ) -> Tensor:
        """Decode one block: z_k (B, Dz) -> its s frames (B, s, Dx); updates ``cache``;
        ``detail`` (B, detail_dim) as ``decode``'s for this block.

        Calling this for k = 1..K reproduces ``decode(z, detail)`` (without ``max_blocks``)."""
        tokens = self._decoder_tokens(z_k[:, None], None if detail is None else detail[:, None])
        n = tokens.shape[1]
        positions = torch.arange(cache.position, cache.position + n, device=z_k.device)
        mask = causal_mask(n, len(cache.layers[0]) + n, device=z_k.device)
        for block, layer_cache in zip(self.decoder, cache.layers):
            tokens = block(tokens, mask, positions, layer_cache)
        cache.position += n
        cache.blocks += 1
        return self._decoder_frames(tokens, z_k[:, None])

    @staticmethod
    def kl(mu: Tensor, logvar: Tensor) -> Tensor:
        """KL(N(mu, exp(logvar)) || N(0, I)) per latent element, averaged."""
        return 0.5 * (mu.square() + logvar.exp() - 1.0 - logvar).mean()

    def forward(self, x: Tensor, generator: torch.Generator | None = None,
                channel_weight: Tensor | None = None) -> dict[str, Tensor]:
        """Reconstruct x through a sampled latent; returns loss, recon, kl, x_hat, mu, logvar and
        z (the latents decoded, which the stance head reads).
        ``channel_weight`` (Dx,) weights each channel's squared error (see ``loss_terms``)."""
        mu, logvar = self.encode(x)
        noise = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
        z = mu + noise * (0.5 * logvar).exp()
        if self.config.latent_noise > 0:
            spread = mu.detach().flatten(0, 1).std(0)
            z = z + self.config.latent_noise * spread * torch.randn(
                mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
        cfg = self.config
        kl = self.kl(mu.float(), logvar.float())
        if self.detail_in is None:
            x_hat = self.decode(z)
            terms = self.loss_terms(x_hat, x, channel_weight)
        else:  # two samples of the decoder for the same latents, drawn on the training device
            shape = (*z.shape[:-1], cfg.detail_dim)
            x_hat, twin = (self.decode(z, torch.randn(shape, generator=generator, device=z.device,
                                                      dtype=z.dtype)) for _ in range(2))
            pair = [self.loss_terms(sample, x, channel_weight) for sample in (x_hat, twin)]
            terms = {name: (pair[0][name] + pair[1][name]) / 2 for name in pair[0]}
            # What the MSEs smooth away, sampled: the energy score of the accelerations
            terms["energy"] = energy_score(x_hat, twin, x, cfg.energy_frames, self.stride,
                                           channel_weight, (0.0, 0.0, 1.0), cfg.energy_per_point)
        loss = (terms["recon"] + cfg.beta * kl + cfg.velocity_weight * terms["velocity"]
                + cfg.acceleration_weight * terms["acceleration"])
        if "energy" in terms:
            loss = loss + cfg.energy_weight * terms["energy"]
        return {"loss": loss, **terms, "kl": kl, "x_hat": x_hat, "mu": mu, "logvar": logvar, "z": z}

    @staticmethod
    def loss_terms(x_hat: Tensor, x: Tensor, channel_weight: Tensor | None = None
                   ) -> dict[str, Tensor]:
        """Reconstruction MSE and the MSEs of the error's first and second frame differences
        (velocity and acceleration errors), each channel's squared error times ``channel_weight``
        when given (mean 1 keeps the scale)."""
        error = x_hat.float() - x.float()
        step = error[:, 1:] - error[:, :-1]
        bend = step[:, 1:] - step[:, :-1]
        weight = 1.0 if channel_weight is None else channel_weight
        return {name: (value.square() * weight).mean()
                for name, value in (("recon", error), ("velocity", step), ("acceleration", bend))}


def detail_generator(seed: int) -> torch.Generator:
    """The generator of a stream's (or an offline solve's) detail draws for seed ``seed``: its
    own stream of numbers, apart from the flow's noise (which a generator seeded ``seed``
    draws), so a deterministic decoder's outputs are what they were before detail existed."""
    return torch.Generator().manual_seed(seed + DETAIL_SEED_OFFSET)


def energy_score(sample: Tensor, twin: Tensor, x: Tensor, frames: int, hop: int,
                 channel_weight: Tensor | None = None,
                 orders: tuple[float, float, float] = (1.0, 0.0, 0.0),
                 per_point: bool = False) -> Tensor:
    """The energy score E|Y - x| - E|Y - Y'| / 2 of the decoder's distribution at the data x,
    estimated from two independent samples (B, T, Dx), over units of ``frames`` consecutive
    frames every ``hop`` frames (a unit holds the motion's velocities and accelerations across
    its blocks' seams). A unit's distance is the root mean square of its positions' errors,
    its frame-to-frame differences' and second differences', squared errors weighted by
    ``orders`` (as the deterministic VAE weighs its recon, velocity and acceleration MSEs) and
    each channel's by ``channel_weight``; with ``per_point`` every point (3 channels) of a unit
    is scored on its own. A strictly proper score: its expectation is least
    when the samples are drawn as the data are, where an MSE is least at their mean."""
    if x.shape[1] < frames:
        raise ValueError(f"the energy score's units span vae.energy_frames = {frames} frames; "
                         f"the windows have {x.shape[1]}")
    weight = 1.0 if channel_weight is None else channel_weight

    def distance(a: Tensor, b: Tensor) -> Tensor:  # (B, U, points or 1): weighted RMS
        # Per-frame sums first, then per unit: no copy of the overlapping units' motion
        error, total, count = a.float() - b.float(), 0.0, 0
        for order, scale in enumerate(orders):
            if scale > 0:
                per_frame = error.square() * weight  # (B, T - order, Dx)
                per_frame = (per_frame.unflatten(-1, (-1, 3)).sum(-1) if per_point
                             else per_frame.sum(-1, keepdim=True))  # (B, T - order, units)
                total = total + scale * per_frame.unfold(1, frames - order, hop).sum(-1)
                count += (frames - order) * (3 if per_point else error.shape[-1])
            error = error.diff(dim=1)
        return (total / count).clamp_min(1e-12).sqrt()

    return (0.5 * (distance(sample, x) + distance(twin, x)) - 0.5 * distance(sample, twin)).mean()
