"""Causal generation of the agent's motion: streaming with imputation, and the offline protocol.

The flow model generates standardized VAE latents, one token per block of s frames (paper 3.3),
by integrating the flow (``solver.py``) under classifier-free guidance (``guidance.py``).

Streaming vs offline. ``generate_offline`` denoises all K tokens jointly under the causal mask
(the paper's fps = T / time protocol) with the same per-token noise and guidance. Causality
makes token 1 identical in both. For later tokens, offline history tokens follow their own
solver trajectories while streaming with the paper's imputation (``StreamConfig.imputation =
"final"``) substitutes tau z_final + (1 - tau) eps: the two coincide exactly when those
trajectories are straight, which holds (a) for a single token, (b) for one Euler step (the only
evaluation is at tau = 0, where both are the noise eps) and (c) whenever the network's x1
prediction is constant along the path. In general they differ. With ``imputation =
"trajectory"`` a stream keeps each history token's own trajectory (the state at every solver
time) and replays it, and keeps as many history tokens as the flow's attention reaches
(``FlowModel.context_tokens`` - 1; ``history_tokens`` when attention is unbounded): a stream is
then the offline joint solve computed causally, equal to it up to float rounding, for streams
of any length when the flow's attention is windowed (the tiny preset) and, with unbounded
attention, while the stream is within ``history_tokens`` + 1 tokens. A flow that reads where
its agent stands (``flow.user_relative``, ``nn/user_offset.py``) takes each block's place from
the stream's decoded frames, so its offline protocol is that stream, block by block.

Many streams. ``step_together`` (and ``push_together`` for sessions) takes one block of each
of several streams and solves all of them in one network call per evaluation, as a server does
per round; each stream gets what its own ``step`` gives it (see ``nn/streams.py`` for the one
layer that has to know).

Frames and anchor. The model was trained on windows normalized to the agent's pelvis at the
window's first frame (origin, facing +z). Latents encode motion in that frame, so a history latent
is only valid under the anchor it was generated in; re-anchoring while streaming would mean
re-encoding the history. We use one fixed anchor for the whole stream: the agent's initial pose
(``anchor``, a WindowTransform from world to the generation frame; identity = agent starts at
the world origin facing +z). The user's head trajectory is mapped into that frame, the decoded
motion is mapped back to world. This matches training while the agent stays within the range of
motion seen in T = 400-frame windows (the paper's setting: conversing agents step and turn but
stay near their start); streams that wander far from the anchor leave the training distribution.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from sarah_data.frames import WindowTransform
from sarah_data.skeleton import MotionLayout

from ..config import HISTORY_TOKENS, HISTORY_WINDOW, StreamConfig, check_gaze
from ..nn.flow import FlowModel
from ..nn.head_travel import TravelState
from ..nn.normalizer import Normalizer
from ..nn.stance import RECEPTIVE_TOKENS
from ..nn.streams import independent_streams
from ..nn.user_offset import pelvis_floor, user_offset
from ..nn.vae import CausalVAE, detail_generator
from .decoding import (StreamDecoding, decoded_stance, decoder_frames, reads_stance,
                       stream_decoding)
from .guidance import branches_run, combine, drop_masks, scale_at
from .path import velocity_from_x1
from .rigid_skeleton import check_lengths
from .solver import imputer, integrate, replayer, token_noise

IDENTITY = WindowTransform(0.0, 0.0, 0.0)


def solve(flow: FlowModel, cond_tokens: Tensor, noise: Tensor, known: Tensor | None,
          config: StreamConfig, trace: list[Tensor] | None = None) -> Tensor:
    """Integrate tau 0 -> 1 for L tokens of one stream, or of G streams at once.

    One stream: cond_tokens (B, L, hidden) with B = 1, or 2 for (conditional, unconditional)
    with guidance, run as one batch; noise (L, Dz) each token's eps; known None or the first m
    tokens' history: with ``config.imputation`` "final" their final latents (m, Dz), imputed as
    tau * known + (1 - tau) * eps before every evaluation, with "trajectory" their recorded
    states (m, len(replay_times), Dz); returns z (L, Dz). G streams: a leading stream axis on all
    three, cond_tokens (G, B, L, hidden); one network call per evaluation serves every stream's
    branches. ``trace`` receives the state of all L tokens at every time of ``replay_times``."""
    if noise.dim() == 2:
        inner = None if trace is None else []
        z = solve(flow, cond_tokens[None], noise[None], None if known is None else known[None],
                  config, inner)[0]
        if trace is not None:
            trace.extend(state[0] for state in inner)
        return z
    streams, branches = cond_tokens.shape[:2]
    # rows of every branch, and of the conditional one alone (branches_run)
    rows = {branches: cond_tokens.flatten(0, 1), 1: cond_tokens[:, :1].flatten(0, 1)}

    def velocity(z: Tensor, tau: float) -> Tensor:
        w = scale_at(tau, config.cfg_scale, config.guidance_interval)
        live = branches_run(branches, w)
        x = z[:, None].expand(-1, live, -1, -1).flatten(0, 1)
        x1 = flow(x, tau, cond_tokens=rows[live]).unflatten(0, (streams, live))
        return velocity_from_x1(combine(x1, w), z, tau, flow.config.min_denominator)

    impute = replayer(known, config) if config.imputation == "trajectory" else imputer(noise, known)
    with independent_streams(streams):
        return integrate(velocity, noise, impute, config, trace)


def window_history(flow: FlowModel) -> int:
    """The history HISTORY_WINDOW stands for: what one layer of the flow attends to beside the
    new token (its attention window less one), the paper's 2 for a flow without a window."""
    window = flow.config.attention_window
    return HISTORY_TOKENS if window is None else window - 1


def kept_history(flow: FlowModel, config: StreamConfig) -> int | None:
    """How many history tokens a stream keeps (None: all). With trajectory imputation and
    windowed attention exactly what the flow's attention reaches, so that the stream equals the
    offline solve at a bounded cost; otherwise ``config.history_tokens``, where HISTORY_WINDOW
    is what one layer of the flow attends to beside the new token (the paper's 2 without a
    window): the context the flow was trained to read."""
    if config.imputation == "trajectory" and flow.context_tokens is not None:
        return flow.context_tokens - 1
    if config.history_tokens == HISTORY_WINDOW:
        return window_history(flow)
    return config.history_tokens


def _as_tensor(x, shape_tail: tuple[int, ...], name: str, frames: int | None) -> Tensor:
    t = torch.as_tensor(np.asarray(x, dtype=np.float32))
    if t.dim() != 1 + len(shape_tail) or tuple(t.shape[1:]) != shape_tail or (
            frames is not None and t.shape[0] != frames):
        want = ("T" if frames is None else str(frames),) + tuple(map(str, shape_tail))
        raise ValueError(f"{name} has shape {tuple(t.shape)}, expected ({', '.join(want)})")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} contains non-finite values")
    return t


class _Models:
    """The three modules plus the conversions between world inputs/outputs and model space."""

    def __init__(self, vae: CausalVAE, flow: FlowModel, normalizer: Normalizer,
                 config: StreamConfig, anchor: WindowTransform | None,
                 bone_lengths=None) -> None:
        if flow.stride != vae.stride or flow.latent_dim != vae.config.latent_dim:
            raise ValueError(f"flow (stride {flow.stride}, Dz {flow.latent_dim}) does not match "
                             f"the VAE (stride {vae.stride}, Dz {vae.config.latent_dim})")
        if "latent" not in normalizer.keys:
            raise ValueError("the normalizer has no 'latent' statistics: generation needs a "
                             "flow-stage checkpoint")
        layout = MotionLayout.from_width(vae.motion_dim)  # ValueError naming a width not ours
        self.vae, self.flow, self.normalizer, self.config = vae, flow, normalizer, config
        self.anchor = IDENTITY if anchor is None else anchor
        self.bone_lengths = bone_lengths  # the agent's own skeleton, or None: the training data's
        if bone_lengths is not None:  # ValueError now, not after an offline solve
            check_lengths(layout, bone_lengths, "the agent's ")
        self.device = next(flow.parameters()).device
        self.stride, self.audio_dim = vae.stride, flow.audio_dim
        self.audio_keys = {k: normalizer.stats_key(k) for k in ("agent_audio", "user_audio")}

    def user_floor(self, user_head, frames: int | None) -> np.ndarray:
        """World-frame user head (T, 2), which it checks (``frames`` of them unless None) ->
        the generation frame (T, 2) float64: what the flow reads (``condition``) and a root hold
        that turns (``vae.root_hold_turn``) turns the body by."""
        head = _as_tensor(user_head, (2,), "user_head", frames)
        return self.anchor.apply_floor(head.numpy().astype(np.float64))

    def condition(self, floor: np.ndarray, agent_audio, user_audio, gaze: float | None,
                  place: Tensor | None = None) -> dict[str, Tensor]:
        """Standardized model inputs (1, T, .) from the user's head in the generation frame
        (``user_floor``) and raw features; with ``flow.user_relative`` also user_offset, the head
        less ``place`` (2,), where the agent stands in the generation frame as these frames
        begin (one block of them)."""
        t = floor.shape[0]
        a = _as_tensor(agent_audio, (self.audio_dim,), "agent_audio", t)
        b = _as_tensor(user_audio, (self.audio_dim,), "user_audio", t)
        head = torch.from_numpy(floor.astype(np.float32))
        nz = self.normalizer
        cond = {"user_head": nz.normalize("user_head", head.to(self.device)),
                "agent_audio": nz.normalize(self.audio_keys["agent_audio"], a.to(self.device)),
                "user_audio": nz.normalize(self.audio_keys["user_audio"], b.to(self.device)),
                "gaze": torch.full((t, 1), 0.0 if gaze is None else float(gaze),
                                   device=self.device)}
        if self.flow.config.user_relative:
            if place is None or t != self.stride:
                raise ValueError("a flow that reads where its agent stands (flow.user_relative) "
                                 "takes one block at a time, with the agent's place")
            starts = place.reshape(1, 1, 2).to(self.device)
            cond["user_offset"] = user_offset(head.to(self.device)[None], starts, self.stride)[0]
        return {k: v[None] for k, v in cond.items()}

    def cond_tokens(self, cond: Mapping[str, Tensor], gaze: float | None,
                    first_token: int = 0) -> Tensor:
        masks = drop_masks(gaze, self.config.guide, self.config.cfg_scale).to(self.device)
        batch = {k: v.expand(masks.shape[0], -1, -1) for k, v in cond.items()}
        return self.flow.encode_condition(batch, masks, first_token=first_token)

    def decoding(self) -> StreamDecoding:
        """A new stream's decoding (seams, skeleton, feet: as the VAE config asks)."""
        return stream_decoding(self.vae, self.normalizer, self.bone_lengths)

    def decode(self, motion: Tensor, decoding: StreamDecoding, stance: np.ndarray | None,
               user: np.ndarray) -> np.ndarray:
        """The decoder's next T frames in metres (T, Dx) -> motion in the generation frame
        (T, Dx) float64, through the stream's ``decoding``; ``stance`` (T, feet): the frames'
        decoded stance (``decoding.decoded_stance``), for the foot lock; ``user`` (T, 2): the
        user's floor path in the generation frame (``user_floor``)."""
        return decoding(motion.double().cpu().numpy(), stance, user)

    def to_world(self, x: np.ndarray) -> np.ndarray:
        """Generation-frame motion (T, Dx) -> world-frame motion vector (T, Dx) float32."""
        points = self.anchor.invert_points(x.reshape(x.shape[0], -1, 3))
        return points.reshape(x.shape).astype(np.float32)

    def latent_for_decoder(self, z: Tensor) -> Tensor:
        return self.normalizer.denormalize("latent", z)


class StreamingGenerator:
    """Generates the agent's motion causally, one block of s frames per ``step``.

    Only past and current inputs are used: ``step`` sees the chunk it is given and what earlier
    calls gave. The flow's context is the last ``kept_history(flow, config)`` latents plus the new one.
    ``anchor`` puts the generation frame in the world; ``bone_lengths`` is the agent's own
    skeleton, which the decoding puts the motion on (``decoding.stream_decoding``).
    """

    def __init__(self, vae: CausalVAE, flow: FlowModel, normalizer: Normalizer,
                 config: StreamConfig = StreamConfig(),
                 anchor: WindowTransform | None = None, bone_lengths=None) -> None:
        self._m = _Models(vae, flow, normalizer, config, anchor, bone_lengths)
        self.config = config
        self.gaze = config.gaze
        self.reset()

    @property
    def stride(self) -> int:
        return self._m.stride

    @property
    def audio_dim(self) -> int:
        return self._m.audio_dim

    @property
    def motion_dim(self) -> int:
        return self._m.vae.motion_dim

    @property
    def anchor(self) -> WindowTransform:
        return self._m.anchor

    def reset(self) -> None:
        """Start a new stream (same seed: the same noise again)."""
        cfg = self.config
        self._generator = torch.Generator().manual_seed(cfg.seed)
        self._detail = detail_generator(cfg.seed)  # a stochastic decoder's draws (vae.detail_dim)
        keep = kept_history(self._m.flow, cfg)
        self._latents: deque[Tensor] = deque(maxlen=keep)  # final z of history tokens
        self._noise: deque[Tensor] = deque(maxlen=keep)  # their eps
        self._states: deque[Tensor] = deque(maxlen=keep)  # their trajectories ("trajectory")
        window = None if keep is None else keep + 1
        self._cond: deque[Tensor] = deque(maxlen=window)  # per block (2, 1, hidden), padded
        self._carried: TravelState | None = None  # what the flow carries across blocks
        self._place = torch.zeros(2)  # the decoded pelvis's floor (x, z) in the generation frame
        self._decoder = self._m.vae.new_decoder_cache(cfg.decoder_blocks(self._m.vae.stride))
        self._decoded: Tensor | None = None  # the decoder's last frame in metres (root steps)
        self._decoding = self._m.decoding()
        # the decoder's latest latent tokens, all the stance head reads (vae.foot_lock_reads);
        # None for a decoding that does not step by it
        self._stance_tokens: deque[Tensor] | None = (
            deque(maxlen=RECEPTIVE_TOKENS) if reads_stance(self._m.vae) else None)
        self.frames_generated = 0
        self.last_latent: Tensor | None = None  # the latest block's standardized latent (Dz,)

    def set_gaze(self, gaze: float | None) -> None:
        """Change the target gaze score for the blocks that follow (live control)."""
        check_gaze(gaze)
        self.gaze = gaze

    def step(self, user_head, agent_audio, user_audio) -> np.ndarray:
        """user_head (s, 2) world floor (x, z); agent_audio, user_audio (s, Da) raw features ->
        the agent's next s frames (s, Dx) as a world-frame motion vector (icosahedra, shell):
        ``step_together`` with this stream alone."""
        return step_together([self], [(user_head, agent_audio, user_audio)])[0]

    def block_condition(self, user_head, agent_audio, user_audio) -> BlockCondition:
        """The next block's conditioning from its inputs, which it checks (ValueError naming
        the input); the stream's state is left as it was."""
        m = self._m
        floor = m.user_floor(user_head, m.stride)
        cond, carried = m.flow.carry_condition(
            m.condition(floor, agent_audio, user_audio, self.gaze, self._place), self._carried)
        return BlockCondition(
            m.cond_tokens(cond, self.gaze, first_token=self.frames_generated // m.stride), carried,
            floor)

    def begin_step(self, condition: BlockCondition) -> PendingBlock:
        """``step`` up to the flow's solve: the block's conditioning (``block_condition``)
        enters the window and its noise is drawn. The caller solves the block, alone or batched
        with other streams' (``step_together``), and hands the new latent to ``end_step``."""
        m = self._m
        self._cond.append(condition.tokens)
        self._carried = condition.carried
        window = list(self._cond)
        if any(t.shape[0] == 2 for t in window):  # guidance active somewhere in the window
            window = [t if t.shape[0] == 2 else t.expand(2, -1, -1) for t in window]
        eps = token_noise(self._generator, m.flow.latent_dim, self.config.noise_scale).to(m.device)
        history = self._states if self.config.imputation == "trajectory" else self._latents
        return PendingBlock(m.flow, self.config, torch.cat(window, dim=1),
                            torch.stack([*self._noise, eps]),
                            torch.stack(list(history)) if history else None, eps, condition.user)

    def end_step(self, block: PendingBlock, z: Tensor, states: Tensor | None = None) -> np.ndarray:
        """``step`` after the solve: the new token's latent z (Dz,) joins the history and is
        decoded; returns its s frames. ``states`` (len(replay_times), Dz): the token's
        trajectory, which trajectory imputation needs."""
        m = self._m
        self.last_latent = z
        self._latents.append(z)  # a deque of maxlen 0 keeps nothing: no history
        self._noise.append(block.eps)
        if self.config.imputation == "trajectory":
            if states is None:
                raise ValueError("trajectory imputation needs the new token's solver states")
            self._states.append(states)
        detail = m.vae.detail_noise(1, 1, self._detail, m.device)
        token = m.latent_for_decoder(z)[None]
        stance = None
        if self._stance_tokens is not None:
            self._stance_tokens.append(token)
            stance = decoded_stance(m.vae, torch.stack(list(self._stance_tokens), dim=1), last=True)
        decoded = m.normalizer.denormalize(
            "motion", m.vae.decoder_step(token, self._decoder,
                                         None if detail is None else detail[:, 0])[0],
            self._decoded)
        self._decoded = decoded[-1]
        frames = m.decode(decoded, self._decoding, stance, block.user)
        if m.flow.config.user_relative:  # where the next block's offset is taken from
            self._place = pelvis_floor(torch.from_numpy(frames[-1:]))[0].float()
        self.frames_generated += m.stride
        return m.to_world(frames)


@dataclass(frozen=True)
class BlockCondition:
    """One stream's next block's conditioning: its tokens (B, 1, hidden), and what the flow
    carries to the next block (``FlowModel.carry_condition``; None when it carries nothing)."""

    tokens: Tensor
    carried: TravelState | None
    user: np.ndarray  # (s, 2): the user's floor path in the generation frame, for the decoding


@dataclass
class PendingBlock:
    """One stream's next block as the solver takes it (``solve``'s single-stream shapes)."""

    flow: FlowModel
    config: StreamConfig
    cond_tokens: Tensor  # (B, L, hidden)
    noise: Tensor  # (L, Dz): the history tokens' eps, then the new one's
    known: Tensor | None  # the history: final latents (m, Dz) or trajectories (m, E + 1, Dz)
    eps: Tensor  # (Dz,): the new token's noise
    user: np.ndarray  # (s, 2): the user's floor path in the generation frame, for the decoding

    def batch_key(self) -> tuple:
        """Blocks with equal keys can be solved as one batch: the same flow, solver and
        guidance weight, and the same window shape (branches, tokens, history)."""
        c = self.config
        return (id(self.flow), tuple(self.cond_tokens.shape),
                0 if self.known is None else self.known.shape[0], c.steps, c.solver, c.cfg_scale,
                c.imputation)


@torch.inference_mode()
def step_together(generators: Sequence[StreamingGenerator],
                  inputs: Sequence[tuple]) -> list[np.ndarray]:
    """``generators[i].step(*inputs[i])`` for every i, with one flow solve for all the streams
    whose blocks share a ``batch_key``: what a server with many sessions runs per round. Each
    network call then serves every stream's rows, so its fixed cost (weight reads, some 30
    small operations per block) is paid once per round instead of once per stream."""
    if len(generators) != len(inputs):
        raise ValueError(f"{len(generators)} generators but {len(inputs)} inputs")
    if len({id(g) for g in generators}) != len(generators):
        raise ValueError("a generator appears twice: a stream takes one block per round")
    # Every stream's inputs are checked before any stream's state changes.
    conditions = [g.block_condition(*x) for g, x in zip(generators, inputs)]
    blocks = [g.begin_step(c) for g, c in zip(generators, conditions)]
    groups: dict[tuple, list[PendingBlock]] = {}
    for block in blocks:
        groups.setdefault(block.batch_key(), []).append(block)
    solved: dict[int, tuple[Tensor, Tensor | None]] = {}
    for members in groups.values():
        lead = members[0]
        trace = [] if lead.config.imputation == "trajectory" else None
        z = solve(lead.flow, torch.stack([b.cond_tokens for b in members]),
                  torch.stack([b.noise for b in members]),
                  None if lead.known is None else torch.stack([b.known for b in members]),
                  lead.config, trace)
        states = None if trace is None else torch.stack([t[:, -1] for t in trace], dim=1)
        solved.update((id(b), (z[row, -1], None if states is None else states[row]))
                      for row, b in enumerate(members))
    return [g.end_step(b, *solved[id(b)]) for g, b in zip(generators, blocks)]


@torch.inference_mode()
def generate_offline(vae: CausalVAE, flow: FlowModel, normalizer: Normalizer,
                     user_head, agent_audio, user_audio, config: StreamConfig = StreamConfig(),
                     anchor: WindowTransform | None = None, bone_lengths=None) -> np.ndarray:
    """The paper's offline protocol: all K = T/s tokens denoised jointly (causal mask, same
    solver, guidance and per-token noise as streaming); returns world motion (T, Dx)."""
    return offline_with_latents(vae, flow, normalizer, user_head, agent_audio, user_audio,
                                config, anchor, bone_lengths)[0]


@torch.inference_mode()
def offline_with_latents(vae: CausalVAE, flow: FlowModel, normalizer: Normalizer,
                         user_head, agent_audio, user_audio, config: StreamConfig = StreamConfig(),
                         anchor: WindowTransform | None = None,
                         bone_lengths=None) -> tuple[np.ndarray, Tensor]:
    """``generate_offline``'s motion and the standardized latents it decoded (K, Dz)."""
    t = len(user_head)
    if t == 0 or t % vae.stride:
        raise ValueError(f"offline generation needs a positive multiple of {vae.stride} frames, "
                         f"got {t}")
    if flow.config.user_relative:
        return _offline_by_blocks(vae, flow, normalizer, user_head, agent_audio, user_audio,
                                  config, anchor, bone_lengths)
    m = _Models(vae, flow, normalizer, config, anchor, bone_lengths)
    floor = m.user_floor(user_head, None)
    cond = m.condition(floor, agent_audio, user_audio, config.gaze)
    generator = torch.Generator().manual_seed(config.seed)
    noise = torch.stack([token_noise(generator, flow.latent_dim, config.noise_scale)
                         for _ in range(t // m.stride)]).to(m.device)
    z = solve(flow, m.cond_tokens(cond, config.gaze), noise, None, config)
    frames, stance = decoder_frames(vae, normalizer, m.latent_for_decoder(z)[None], config.seed)
    return m.to_world(m.decoding()(frames, stance, floor)), z


def _offline_by_blocks(vae: CausalVAE, flow: FlowModel, normalizer: Normalizer, user_head,
                       agent_audio, user_audio, config: StreamConfig,
                       anchor: WindowTransform | None, bone_lengths) -> tuple[np.ndarray, Tensor]:
    """The offline protocol for a flow that reads where its agent stands: each block needs the
    decoded frames before it, so the joint solve runs as the stream that equals it, trajectory
    imputation over everything the flow's attention reaches."""
    s = vae.stride
    stream = StreamingGenerator(vae, flow, normalizer,
                                replace(config, imputation="trajectory", history_tokens=None),
                                anchor, bone_lengths)
    motion, latents = [], []
    for i in range(0, len(user_head), s):
        motion.append(stream.step(user_head[i:i + s], agent_audio[i:i + s], user_audio[i:i + s]))
        latents.append(stream.last_latent)
    return np.concatenate(motion), torch.stack(latents)


class StreamingSession:
    """A StreamingGenerator fed with raw 48 kHz audio, chunk by chunk.

    Audio goes through the extractors' causal ``.stream()`` mode (features for completed frames,
    past audio only); user head positions arrive per frame. Whenever s frames of all three
    inputs are available, one block is generated. ``keep_features=False`` keeps only the last
    push's features (``last_features``): a session that runs for hours must not keep them all.
    """

    def __init__(self, generator: StreamingGenerator, extractor, keep_features: bool = True) -> None:
        if extractor.dim != generator.audio_dim:
            raise ValueError(f"audio extractor {extractor.name!r} gives {extractor.dim} channels, "
                             f"the model expects {generator.audio_dim}")
        self.generator = generator
        self._agent = extractor.stream()
        self._user = extractor.stream()
        self._buffers: dict[str, list[np.ndarray]] = {"head": [], "agent": [], "user": []}
        self._used: dict[str, list[np.ndarray]] = {"agent": [], "user": []}
        self._pushed: dict[str, list[np.ndarray]] = {"agent": [], "user": []}  # this push's
        self.keep_features = keep_features
        self._no_features = np.zeros((0, generator.audio_dim), np.float32)
        self.last_features: dict[str, np.ndarray] = {"agent": self._no_features,
                                                     "user": self._no_features}

    def _available(self, key: str) -> int:
        return sum(len(b) for b in self._buffers[key])

    def _take(self, key: str, n: int) -> np.ndarray:
        data = np.concatenate(self._buffers[key], axis=0)
        self._buffers[key] = [data[n:]]
        return data[:n]

    def features(self, person: str) -> np.ndarray:
        """The audio features of ``person`` ("agent" or "user") used so far, (frames, Da)
        (with ``keep_features``)."""
        used = self._used[person]
        return np.concatenate(used) if used else self._no_features

    def push(self, user_head, agent_samples, user_samples) -> np.ndarray:
        """Feed new inputs (any lengths); returns the frames generated now, (k*s, Dx)."""
        return push_together([self], [(user_head, agent_samples, user_samples)])[0]

    def feed(self, user_head, agent_samples, user_samples) -> None:
        """``push``'s first part: buffer the inputs and their audio features. Then take every
        block that is complete (``next_block``), generate it, and call ``end_push``."""
        self._pushed = {"agent": [], "user": []}
        head = np.asarray(user_head, dtype=np.float32).reshape(-1, 2)
        self._buffers["head"].append(head)
        for key, stream, samples in (("agent", self._agent, agent_samples),
                                     ("user", self._user, user_samples)):
            feats = np.asarray(stream.push(np.asarray(samples, dtype=np.float32)), np.float32)
            self._buffers[key].append(feats.reshape(-1, self.generator.audio_dim))

    def next_block(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The next s frames of user head, agent and user features for ``generator.step``, or
        None until all three have them."""
        if min(self._available(k) for k in self._buffers) < self.generator.stride:
            return None
        head, a, b = (self._take(k, self.generator.stride) for k in ("head", "agent", "user"))
        self._pushed["agent"].append(a)
        self._pushed["user"].append(b)
        return head, a, b

    def end_push(self) -> None:
        """``push``'s last part: the features its blocks used become ``last_features``."""
        for person, blocks in self._pushed.items():
            self.last_features[person] = np.concatenate(blocks) if blocks else self._no_features
            if self.keep_features:
                self._used[person] += blocks
        self._pushed = {"agent": [], "user": []}

    def frames_of(self, blocks: list[np.ndarray]) -> np.ndarray:
        """Blocks of frames from ``step`` as one (k*s, Dx) array (none: (0, Dx))."""
        if blocks:
            return np.concatenate(blocks)
        return np.zeros((0, self.generator.motion_dim), np.float32)


def push_together(sessions: Sequence[StreamingSession], pushes: Sequence[tuple]) -> list[np.ndarray]:
    """``sessions[i].push(*pushes[i])`` for every i, the blocks of a round generated together
    (``step_together``): a server's round over its sessions. Returns each session's frames."""
    if len(sessions) != len(pushes):
        raise ValueError(f"{len(sessions)} sessions but {len(pushes)} pushes")
    for session, inputs in zip(sessions, pushes):
        session.feed(*inputs)
    frames: list[list[np.ndarray]] = [[] for _ in sessions]
    while True:
        ready = [(i, block) for i, session in enumerate(sessions)
                 if (block := session.next_block()) is not None]
        if not ready:
            break
        blocks = step_together([sessions[i].generator for i, _ in ready], [b for _, b in ready])
        for (i, _), out in zip(ready, blocks):
            frames[i].append(out)
    for session in sessions:
        session.end_push()
    return [session.frames_of(out) for session, out in zip(sessions, frames)]
