"""The naive reference streamer every streaming figure is compared with."""

from __future__ import annotations

import time

import numpy as np
import torch

from sarah_models.config import StreamConfig
from sarah_models.nn.flow import FlowModel
from sarah_models.nn.normalizer import Normalizer
from sarah_models.nn.user_offset import pelvis_floor
from sarah_models.nn.vae import CausalVAE, detail_generator
from sarah_models.sampling.decoding import decoded_stance, stream_decoding
from sarah_models.sampling.guidance import branches_run, drop_masks, guided, scale_at
from sarah_models.sampling.path import velocity_from_x1
from sarah_models.sampling.solver import imputer, integrate, token_noise
from sarah_models.sampling.stream import kept_history


class NaiveStreamer:
    """The reference streaming loop: what ``StreamingGenerator`` computes, without its savings.

    Per chunk it re-encodes the conditioning of the whole window (history + new block), runs
    the conditional and the unconditional pass as two separate network calls at every solver
    evaluation (no batched guidance), and decodes the whole latent history (up to
    ``decoder_frames``) from scratch instead of one block through a KV cache. Same noise, same
    imputation, same maths: its frames equal ``StreamingGenerator``'s (identity anchor) up to
    float rounding while the stream is at most ``decoder_frames`` frames long.
    """

    def __init__(self, vae: CausalVAE, flow: FlowModel, normalizer: Normalizer,
                 config: StreamConfig = StreamConfig()) -> None:
        self.vae, self.flow, self.normalizer, self.config = vae, flow, normalizer, config
        self.stride = vae.stride
        self.audio_keys = {k: normalizer.stats_key(k) for k in ("agent_audio", "user_audio")}
        self.reset()

    def reset(self) -> None:
        self._generator = torch.Generator().manual_seed(self.config.seed)
        self._inputs: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._latents: list[torch.Tensor] = []  # final latents of every block so far
        self._noise: list[torch.Tensor] = []
        self._detail = detail_generator(self.config.seed)  # a stochastic decoder's draws
        self._details: list[torch.Tensor] = []
        self._places: list[np.ndarray] = [np.zeros(2)]  # where the agent stands as each block begins
        self._decoding = stream_decoding(self.vae, self.normalizer)
        self._decoded = None  # the decoder's last frame in metres (root steps)

    def _window(self, items: list) -> list:
        keep = kept_history(self.flow, self.config)
        return items if keep is None else items[len(items) - min(len(items), keep):]

    @torch.inference_mode()
    def step(self, user_head: np.ndarray, agent_audio: np.ndarray, user_audio: np.ndarray,
             timings: dict[str, float] | None = None) -> np.ndarray:
        """Raw features (s, Da) and world head (s, 2) -> world motion (s, Dx); adds the seconds
        spent in the flow and the decoder to ``timings`` when given."""
        tick = time.perf_counter()
        cfg, nz, flow = self.config, self.normalizer, self.flow
        history = self._window(list(range(len(self._latents))))
        self._inputs.append((user_head, agent_audio, user_audio))
        blocks = [self._inputs[i] for i in history] + [self._inputs[-1]]
        head, a, b = (torch.from_numpy(np.concatenate([blk[j] for blk in blocks]))
                      for j in range(3))
        frames = head.shape[0]
        cond = {"user_head": nz.normalize("user_head", head)[None],
                "agent_audio": nz.normalize(self.audio_keys["agent_audio"], a)[None],
                "user_audio": nz.normalize(self.audio_keys["user_audio"], b)[None],
                "gaze": torch.full((1, frames, 1), 0.0 if cfg.gaze is None else float(cfg.gaze))}
        if flow.config.user_relative:
            places = [self._places[i] for i in history] + [self._places[-1]]
            cond["user_offset"] = torch.cat([torch.from_numpy(blk[0] - place).float()
                                             for blk, place in zip(blocks, places)])[None]
        masks = drop_masks(cfg.gaze, cfg.guide, cfg.cfg_scale)
        first = len(self._latents) - len(history)  # the stream index of the window's first block
        branches = [flow.encode_condition(cond, masks[i:i + 1], first_token=first)
                    for i in range(masks.shape[0])]
        eps = token_noise(self._generator, flow.latent_dim, cfg.noise_scale)
        noise = torch.stack([self._noise[i] for i in history] + [eps])
        known = torch.stack([self._latents[i] for i in history]) if history else None
        z = self._solve(branches, noise, known)[-1]
        self._latents.append(z)
        self._noise.append(eps)
        solved = time.perf_counter()
        blocks = cfg.decoder_blocks(self.stride)
        context = self._latents if blocks is None else self._latents[-blocks:]
        latents = nz.denormalize("latent", torch.stack(context))[None]
        detail = self.vae.detail_noise(1, 1, self._detail)
        if detail is not None:
            self._details.append(detail[0, 0])
            detail = torch.stack(self._details[-len(context):])[None]
        motion = nz.denormalize("motion", self.vae.decode(latents, detail)[0, -self.stride:],
                                self._decoded)
        self._decoded = motion[-1]
        out = self._decoding(motion.double().numpy(),
                             decoded_stance(self.vae, latents, last=True),
                             np.asarray(user_head, np.float64)).astype(np.float32)
        if flow.config.user_relative:
            self._places.append(pelvis_floor(torch.from_numpy(out[-1:]).double())[0].numpy())
        if timings is not None:
            timings["flow"] = timings.get("flow", 0.0) + solved - tick
            timings["decode"] = timings.get("decode", 0.0) + time.perf_counter() - solved
        return out

    def _solve(self, branches: list[torch.Tensor], noise: torch.Tensor,
               known: torch.Tensor | None) -> torch.Tensor:
        cfg, flow = self.config, self.flow

        def velocity(z: torch.Tensor, tau: float) -> torch.Tensor:
            # naive on purpose: one network call per guidance branch instead of one batch
            w = scale_at(tau, cfg.cfg_scale, cfg.guidance_interval)
            used = branches[:branches_run(len(branches), w)]
            x1 = [flow(z[None], tau, cond_tokens=tokens)[0] for tokens in used]
            x1 = guided(x1[0], x1[1], w) if len(x1) == 2 else x1[0]
            return velocity_from_x1(x1, z, tau, flow.config.min_denominator)

        return integrate(velocity, noise, imputer(noise, known), cfg)
