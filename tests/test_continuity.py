"""Root continuity across latent blocks (sampling.continuity.RootInertia) and where it is used."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sarah_bench.naive import NaiveStreamer
from sarah_data.skeleton import MotionLayout
from sarah_models.config import StreamConfig, VAEConfig
from sarah_models.sampling.continuity import RootInertia
from sarah_models.sampling.stream import StreamingGenerator, generate_offline
from sarah_models.testing import random_models

SHELL = 4
S = 4
LAYOUT = MotionLayout.from_width(55 * 36 + 3 * SHELL)


def walking_body(frames: int, seed: int = 0, velocity=(0.03, 0.0, 0.01)) -> np.ndarray:
    """(frames, Dx): a random rigid pose translated at a constant velocity (metres per frame)."""
    rng = np.random.default_rng(seed)
    pose = rng.normal(scale=0.3, size=(LAYOUT.width // 3, 3))
    path = np.arange(frames)[:, None] * np.asarray(velocity)
    return (pose[None] + path[:, None]).reshape(frames, -1)


def pelvis(motion: np.ndarray) -> np.ndarray:
    return LAYOUT.joint_positions(motion, ["pelvis"])[:, 0]


def block_jumps(frames: int, size: float, seed: int = 1) -> np.ndarray:
    """A per-block random translation of the whole body: the decoder's seam between blocks."""
    jumps = np.random.default_rng(seed).normal(scale=size, size=(frames // S, 3))
    return np.repeat(jumps, S, axis=0)


def test_constant_velocity_passes_unchanged_and_zero_retention_is_the_identity():
    motion = walking_body(40)
    np.testing.assert_allclose(RootInertia(LAYOUT, S, 0.9)(motion), motion, atol=1e-12)
    jumpy = motion + np.tile(block_jumps(40, 0.05), LAYOUT.width // 3)
    assert RootInertia(LAYOUT, S, 0.0)(jumpy) is jumpy


def test_it_moves_the_whole_body_alike_and_removes_the_seams():
    frames = 80
    motion = walking_body(frames)
    jumps = block_jumps(frames, 0.03)
    jumpy = motion + np.tile(jumps, LAYOUT.width // 3)
    out = RootInertia(LAYOUT, S, 0.9)(jumpy)
    shift = (out - jumpy).reshape(frames, -1, 3)
    np.testing.assert_allclose(shift, np.broadcast_to(shift[:, :1], shift.shape), atol=1e-12)
    accel = lambda m: np.linalg.norm(np.diff(pelvis(m), 2, axis=0), axis=-1)  # noqa: E731
    seams = np.arange(S - 1, frames - 2, S)  # second differences centred on a block's last frame
    assert accel(jumpy)[seams].mean() > 5 * accel(out)[seams].mean()  # ~1 / (1 - retention)
    # The offset decays: the output stays within one seam's correction of the decoder's root.
    assert np.abs(pelvis(out) - pelvis(jumpy)).max() < 4 * np.abs(jumps).max() + 0.04


@settings(max_examples=25, deadline=None)
@given(chunks=st.lists(st.integers(1, 9), min_size=1, max_size=12), seed=st.integers(0, 100))
def test_any_chunking_gives_the_frames_of_one_call(chunks, seed):
    frames = sum(chunks)
    rng = np.random.default_rng(seed)
    motion = walking_body(frames, seed) + rng.normal(scale=0.02, size=(frames, LAYOUT.width))
    whole = RootInertia(LAYOUT, S, 0.8)(motion)
    inertia, parts, start = RootInertia(LAYOUT, S, 0.8), [], 0
    for n in chunks:
        parts.append(inertia(motion[start:start + n]))
        start += n
    np.testing.assert_array_equal(np.concatenate(parts), whole)


def test_invalid_settings_are_refused():
    with pytest.raises(ValueError, match="boundary_inertia"):
        VAEConfig(boundary_inertia=1.0)
    with pytest.raises(ValueError, match="retention"):
        RootInertia(LAYOUT, S, -0.1)
    with pytest.raises(ValueError, match="stride"):
        RootInertia(LAYOUT, 1, 0.5)


@pytest.fixture(scope="module")
def inert_models():
    vae, flow, normalizer = random_models("tiny", 8, SHELL, 0, motion_std=0.02, init_std=0.05,
                                          latent_mean_std=0.1)
    vae.config = dataclasses.replace(vae.config, boundary_inertia=0.9)
    return vae, flow, normalizer


def test_generators_decode_through_it(inert_models):
    """Streaming, the offline protocol and the naive reference all apply the VAE config's
    inertia: the stream still agrees with offline on its first block and with the naive
    reference everywhere, and it differs from the raw decoder output after the first block."""
    vae, flow, normalizer = inert_models
    rng = np.random.default_rng(0)
    head = rng.normal(size=(24, 2)).astype(np.float32)
    a, b = (rng.normal(size=(24, 8)).astype(np.float32) for _ in range(2))
    config = StreamConfig(decoder_blocks=100)
    gen, naive = StreamingGenerator(vae, flow, normalizer, config), NaiveStreamer(vae, flow, normalizer, config)
    streamed = np.concatenate([gen.step(head[i:i + S], a[i:i + S], b[i:i + S]) for i in range(0, 24, S)])
    reference = np.concatenate([naive.step(head[i:i + S], a[i:i + S], b[i:i + S]) for i in range(0, 24, S)])
    np.testing.assert_allclose(reference, streamed, atol=1e-4)
    offline = generate_offline(vae, flow, normalizer, head, a, b, config)
    np.testing.assert_allclose(offline[:S], streamed[:S], atol=1e-5)

    vae.config = dataclasses.replace(vae.config, boundary_inertia=0.0)
    try:
        plain = StreamingGenerator(vae, flow, normalizer, config)
        raw = np.concatenate([plain.step(head[i:i + S], a[i:i + S], b[i:i + S]) for i in range(0, 24, S)])
    finally:
        vae.config = dataclasses.replace(vae.config, boundary_inertia=0.9)
    np.testing.assert_allclose(raw[:S], streamed[:S], atol=1e-6)
    assert np.abs(raw[S:] - streamed[S:]).max() > 1e-5
    np.testing.assert_allclose(RootInertia(LAYOUT, S, 0.9)(raw.astype(np.float64)), streamed, atol=1e-6)


def test_the_evaluation_vae_row_decodes_like_the_generators(inert_models):
    """sarah-eval's VAE row is the best a flow sample can decode to, so it decodes through the
    same inertia as the generators."""
    import torch

    from sarah_models.evaluation.runner import _vae_producer
    from sarah_models.training.checkpoint import LoadedModels

    vae, flow, normalizer = inert_models
    models = LoadedModels(vae, flow, normalizer, None, {}, "logmel", 0, "flow")
    rng = np.random.default_rng(5)
    item = {"motion": torch.from_numpy(walking_body(24, 5) + rng.normal(scale=0.01, size=(24, LAYOUT.width))).float()}
    with torch.inference_mode():
        inert = _vae_producer(models)(item, 0)
        vae.config = dataclasses.replace(vae.config, boundary_inertia=0.0)
        try:
            raw = _vae_producer(models)(item, 0)
        finally:
            vae.config = dataclasses.replace(vae.config, boundary_inertia=0.9)
    assert np.abs(inert[S:] - raw[S:]).max() > 1e-6
    np.testing.assert_allclose(inert, RootInertia(LAYOUT, S, 0.9)(raw.astype(np.float64)), atol=1e-6)
