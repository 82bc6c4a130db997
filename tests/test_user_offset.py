"""flow.user_relative: the user's head as seen from where the agent stands, in training (the
data's agent) and in generation (the stream's own decoded agent), offline as streamed."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from sarah_data.frames import WindowTransform
from sarah_models.config import StreamConfig
from sarah_models.nn.user_offset import block_starts, pelvis_floor, user_offset
from sarah_models.sampling.guidance import drop_masks
from sarah_models.sampling.stream import StreamingGenerator, offline_with_latents
from sarah_models.testing import random_models
from sarah_models.training.objectives import FlowObjective

S = 4
AUDIO = 8


@pytest.fixture(scope="module")
def models():
    return random_models("tiny", AUDIO, 4, 0, motion_std=0.02, init_std=0.05, audio_mean=0.0,
                         audio_std=1.0, latent_mean_std=0.1, overrides=("flow.user_relative=true",))


def inputs(frames: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    angle = np.linspace(0.3, 2.0, frames)
    head = np.stack([1.8 * np.sin(angle), 1.8 * np.cos(angle)], 1).astype(np.float32)
    return (head, rng.normal(size=(frames, AUDIO)).astype(np.float32),
            rng.normal(size=(frames, AUDIO)).astype(np.float32))


@settings(max_examples=20, deadline=None)
@given(blocks=st.integers(1, 6), stride=st.integers(1, 5), seed=st.integers(0, 10_000))
def test_each_block_starts_where_the_previous_one_ended(blocks, stride, seed):
    floor = torch.from_numpy(np.random.default_rng(seed).normal(size=(2, blocks * stride, 2)))
    head = torch.from_numpy(np.random.default_rng(seed + 1).normal(size=(2, blocks * stride, 2)))
    starts = block_starts(floor, stride)
    assert starts.shape == (2, blocks, 2)
    assert torch.equal(starts[:, 0], torch.zeros(2, 2))  # every window's agent starts there
    for k in range(1, blocks):
        assert torch.equal(starts[:, k], floor[:, k * stride - 1])
    offset = user_offset(head, starts, stride)
    for t in range(blocks * stride):
        assert torch.equal(offset[:, t], head[:, t] - starts[:, t // stride])


def test_a_bad_floor_path_or_starts_are_refused():
    with pytest.raises(ValueError, match="not whole blocks of 4"):
        block_starts(torch.zeros(1, 10, 2), 4)
    with pytest.raises(ValueError, match=r"expected \(1, 3, 2\)"):
        user_offset(torch.zeros(1, 12, 2), torch.zeros(1, 2, 2), 4)


def test_training_reads_where_the_data_agent_stands(models):
    """The flow stage's batch carries the head less the data agent's pelvis at each previous
    block's last frame: a stiff body walking a known path, in metres."""
    vae, flow, normalizer = models
    frames = 5 * S
    path = np.stack([np.linspace(0, 1.2, frames), np.linspace(0, -0.6, frames) ** 2], 1)
    lift = np.stack([path[:, 0], np.zeros(frames), path[:, 1]], 1)
    mean = normalizer.motion_mean.numpy()
    motion = (mean.reshape(-1, 3)[None] + lift[:, None]).reshape(frames, -1)
    head, a, b = inputs(frames)
    batch = {"motion": torch.from_numpy(motion[None]).float(), "user_head": torch.from_numpy(head[None]),
             "agent_audio": torch.from_numpy(a[None]), "user_audio": torch.from_numpy(b[None]),
             "gaze": torch.zeros(1, frames)}
    prepared = FlowObjective(flow, vae, normalizer).prepare(batch)
    np.testing.assert_allclose(pelvis_floor(batch["motion"])[0].numpy(), path, atol=1e-5)
    for t in range(frames):
        stood = path[t // S * S - 1] if t >= S else np.zeros(2)
        np.testing.assert_allclose(prepared["user_offset"][0, t].numpy(), head[t] - stood, atol=1e-5)
    assert torch.isfinite(FlowObjective(flow, vae, normalizer)(prepared)["loss"])


def test_a_stream_reads_where_its_decoded_agent_stands(models):
    """Each block's conditioning takes the user's head less the pelvis of the last frame the
    stream returned, both in the generation frame (the stream's anchor is not the world's)."""
    vae, flow, normalizer = models
    anchor = WindowTransform(0.9, 0.7, -0.4)
    head, a, b = inputs(6 * S)
    config = StreamConfig(cfg_scale=1.3, noise_scale=0.6, gaze=None)
    gen = StreamingGenerator(vae, flow, normalizer, config, anchor)
    masks = drop_masks(None, config.guide, config.cfg_scale)
    last = None
    for k in range(6):
        block = slice(k * S, (k + 1) * S)
        here = anchor.apply_floor(head[block].astype(np.float64))
        stood = np.zeros(2) if last is None else anchor.apply_floor(
            pelvis_floor(torch.from_numpy(last[-1:]).double())[0].numpy())
        cond = {"user_head": normalizer.normalize("user_head", torch.from_numpy(here).float()),
                "agent_audio": normalizer.normalize(normalizer.stats_key("agent_audio"), torch.from_numpy(a[block])),
                "user_audio": normalizer.normalize(normalizer.stats_key("user_audio"), torch.from_numpy(b[block])),
                "gaze": torch.zeros(S, 1),
                "user_offset": torch.from_numpy(here - stood).float()}
        cond = {key: value[None].expand(len(masks), -1, -1) for key, value in cond.items()}
        torch.testing.assert_close(gen.block_condition(head[block], a[block], b[block]).tokens,
                                   flow.encode_condition(cond, masks, first_token=k),
                                   atol=1e-5, rtol=1e-5)
        last = gen.step(head[block], a[block], b[block])
    assert last is not None and np.abs(stood).max() > 1e-3  # it did read a place off the origin


def test_offline_generation_is_the_stream_block_by_block(models):
    """A flow that reads its agent's place cannot solve every block at once: offline runs the
    stream that equals the joint solve (trajectory imputation), whatever imputation is asked."""
    data = inputs(10 * S, seed=3)
    for imputation in ("final", "trajectory"):
        config = StreamConfig(cfg_scale=1.3, noise_scale=0.6, imputation=imputation)
        motion, latents = offline_with_latents(*models, *data, config)
        gen = StreamingGenerator(*models, StreamConfig(cfg_scale=1.3, noise_scale=0.6,
                                                       imputation="trajectory", history_tokens=None))
        streamed, streamed_latents = [], []
        for i in range(0, 10 * S, S):
            streamed.append(gen.step(*(x[i:i + S] for x in data)))
            streamed_latents.append(gen.last_latent)
        np.testing.assert_array_equal(motion, np.concatenate(streamed))
        torch.testing.assert_close(latents, torch.stack(streamed_latents), atol=0, rtol=0)
    with pytest.raises(ValueError, match="positive multiple of 4 frames"):
        offline_with_latents(*models, *(x[:6] for x in data), StreamConfig())


def test_a_flow_without_the_offset_is_told_what_it_misses(models):
    _, flow, _ = models
    head, a, b = (torch.from_numpy(x[None]) for x in inputs(2 * S))
    cond = {"user_head": head, "agent_audio": a, "user_audio": b, "gaze": torch.zeros(1, 2 * S)}
    with pytest.raises(KeyError, match="user_offset"):
        flow.encode_condition(cond)
    with pytest.raises(ValueError, match="user_offset has shape"):
        flow.encode_condition({**cond, "user_offset": head[:, :S]})


def test_the_naive_reference_streamer_reads_the_same_place(models):
    """sarah-bench's reference loop re-encodes its whole window each block: every history
    block keeps the place it was generated from, as the stream's cached conditioning does."""
    from sarah_bench.naive import NaiveStreamer

    data = inputs(8 * S, seed=5)
    config = StreamConfig(decoder_frames=400, cfg_scale=1.3, noise_scale=0.6)
    generator, naive = StreamingGenerator(*models, config), NaiveStreamer(*models, config)
    for i in range(0, 8 * S, S):
        block = [x[i:i + S] for x in data]
        np.testing.assert_allclose(naive.step(*block), generator.step(*block), atol=1e-4)


def test_without_the_absolute_position_only_the_offset_is_read():
    """flow.user_absolute=False: moving the user and the agent's place together changes
    nothing the flow reads (it cannot work out the place); moving the user alone does."""
    vae, flow, normalizer = random_models(
        "tiny", AUDIO, 4, 0, motion_std=0.02, init_std=0.05, audio_mean=0.0, audio_std=1.0,
        latent_mean_std=0.1, overrides=("flow.user_relative=true", "flow.user_absolute=false"))
    head, a, b = (torch.from_numpy(x[None]) for x in inputs(3 * S))
    base = {"user_head": head, "agent_audio": a, "user_audio": b, "gaze": torch.zeros(1, 3 * S),
            "user_offset": head - 0.3}
    moved = {**base, "user_head": head + 1.0}
    torch.testing.assert_close(flow.encode_condition(base), flow.encode_condition(moved))
    assert not torch.allclose(flow.encode_condition(base),
                              flow.encode_condition({**base, "user_offset": head + 0.7}))
    with pytest.raises(ValueError, match="user_relative=True"):
        random_models("tiny", AUDIO, 4, 0, overrides=("flow.user_absolute=false",))
