"""Continuity across latent blocks (sampling.continuity.SeamInertia) and where it is used."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sarah_bench.naive import NaiveStreamer
from sarah_data.skeleton import MotionLayout
from sarah_models.config import StreamConfig, VAEConfig
from sarah_models.sampling.continuity import SeamInertia
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


def block_seams(frames: int, size: float, seed: int = 1) -> np.ndarray:
    """(frames, Dx): every point of every block offset and drifting on its own, the decoder's
    seams between tokens that disagree on where each point is and how it moves."""
    rng = np.random.default_rng(seed)
    shape = (frames // S, 1, LAYOUT.width)
    offsets, drifts = rng.normal(scale=size, size=shape), rng.normal(scale=size / 4, size=shape)
    k = np.arange(S)[None, :, None]
    return (offsets + drifts * k).reshape(frames, -1)


def acceleration(motion: np.ndarray) -> np.ndarray:
    p = motion.reshape(len(motion), -1, 3)
    return np.linalg.norm(p[2:] - 2 * p[1:-1] + p[:-2], axis=-1).mean(axis=1)


def test_smooth_motion_passes_unchanged_and_zero_decay_is_the_identity():
    motion = walking_body(40)
    np.testing.assert_allclose(SeamInertia(S, 0.8)(motion), motion, atol=1e-12)
    jumpy = motion + block_seams(40, 0.05)
    assert SeamInertia(S, 0.0)(jumpy) is jumpy


def test_it_removes_the_seams_and_stays_near_the_decoder():
    frames = 80
    motion = walking_body(frames)
    seams = block_seams(frames, 0.03)
    out = SeamInertia(S, 0.8)(motion + seams)
    centre = np.arange(1, frames - 1)
    at_seam = (centre % S == S - 1) | (centre % S == 0)
    raw, smooth = acceleration(motion + seams), acceleration(out)
    assert raw[at_seam].mean() > 4 * smooth[at_seam].mean()
    # Position and velocity continue at every seam: the acceleration across it is the spring's,
    # no larger than inside a block.
    assert smooth[at_seam].max() < 2 * smooth[~at_seam].max() + 1e-9
    # The offset decays: the output stays within a few seams' size of the decoder's output.
    assert np.abs(out - (motion + seams)).max() < 10 * np.abs(seams).max()
    np.testing.assert_array_equal(out[:S], (motion + seams)[:S])  # the first block has no seam


def accelerating_body(frames: int, seed: int = 0) -> np.ndarray:
    """(frames, Dx): a random rigid pose at constant acceleration, each point its own."""
    rng = np.random.default_rng(seed)
    pose = rng.normal(scale=0.3, size=(LAYOUT.width // 3, 3))
    accel = rng.normal(scale=0.002, size=(LAYOUT.width // 3, 3))
    t = np.arange(frames)[:, None, None]
    return (pose[None] + 0.01 * t + 0.5 * accel[None] * t**2).reshape(frames, -1)


def test_the_position_mode_lets_accelerating_motion_pass_and_removes_jumps():
    """The velocity mode damps every acceleration at a seam, real ones too (the fixtures' ground
    truth through it alone: FGD_acc 194, docs/results.md, fortieth run); the position mode reads
    the jump against both sides' velocities, so motion without one passes as it came, and a
    jump is sprung out with the block's own velocity kept."""
    frames = 80
    motion = accelerating_body(frames)
    np.testing.assert_allclose(SeamInertia(S, 0.8, mode="position")(motion), motion, atol=1e-12)
    assert np.abs(SeamInertia(S, 0.8)(motion) - motion).max() > 1e-3
    jumps = np.zeros((frames // S, 1, LAYOUT.width))
    jumps[:] = np.random.default_rng(3).normal(scale=0.03, size=jumps.shape)
    jumpy = motion + np.broadcast_to(jumps, (frames // S, S, LAYOUT.width)).reshape(frames, -1)
    out = SeamInertia(S, 0.8, mode="position")(jumpy)
    centre = np.arange(1, frames - 1)
    at_seam = (centre % S == S - 1) | (centre % S == 0)
    assert acceleration(jumpy)[at_seam].mean() > 4 * acceleration(out)[at_seam].mean()
    # the first frame of every block continues the last position
    p = out.reshape(frames, -1, 3)
    gap = np.linalg.norm(p[S::S] - p[S - 1:-1:S], axis=-1).mean()
    step = np.linalg.norm(motion.reshape(frames, -1, 3)[1:] - motion.reshape(frames, -1, 3)[:-1],
                          axis=-1).mean()
    assert gap < 1.5 * step
    with pytest.raises(ValueError, match="mode"):
        SeamInertia(S, 0.8, mode="jerk")
    with pytest.raises(ValueError, match="seam_mode"):
        VAEConfig(seam_mode="jerk")


def test_the_root_has_its_own_spring():
    """vae.root_inertia acts on what the whole body shares (the root's translation) and
    vae.boundary_inertia on the rest: seams that only move the whole body follow the root's
    spring, seams that leave the root in place follow the pose's."""
    frames, root = 80, LAYOUT.joint_slice("pelvis")
    points = slice(root.start // 3, root.stop // 3)
    motion = walking_body(frames)
    rigid = np.tile(block_seams(frames, 0.03)[:, :3], LAYOUT.width // 3)  # one offset for all
    split = SeamInertia(S, 0.6, 0.9, points)
    np.testing.assert_allclose(split(motion + rigid), SeamInertia(S, 0.9)(motion + rigid), atol=1e-12)
    pose = block_seams(frames, 0.03, seed=2)
    pose[:, root] = 0.0
    pose.reshape(frames, -1, 3)[:] -= pose.reshape(frames, -1, 3)[:, points].mean(axis=1, keepdims=True)
    split = SeamInertia(S, 0.6, 0.9, points)
    np.testing.assert_allclose(split(motion + pose), SeamInertia(S, 0.6)(motion + pose), atol=1e-12)
    with pytest.raises(ValueError, match="root's points"):
        SeamInertia(S, 0.6, 0.9)


def test_still_hands_keep_their_decoded_points_and_the_rest_is_sprung_as_before():
    """vae.seam_skips_hands: the hands' icosahedra and the shell points nearest them pass as the
    decoder put them, every other point is sprung as without it; streamed in blocks as at once."""
    frames = 40
    jumpy = walking_body(frames) + block_seams(frames, 0.03)
    hands = LAYOUT.group_points(jumpy[0], ("hands",))
    finger = LAYOUT.joint("left_index1") * 12
    assert finger in hands and LAYOUT.joint("left_wrist") * 12 not in hands
    rest = np.setdiff1d(np.arange(LAYOUT.width // 3), hands)
    sprung = SeamInertia(S, 0.8, mode="position")(jumpy).reshape(frames, -1, 3)
    still = SeamInertia(S, 0.8, mode="position", layout=LAYOUT, still=("hands",))
    out = still(jumpy).reshape(frames, -1, 3)
    np.testing.assert_array_equal(out[:, hands], jumpy.reshape(frames, -1, 3)[:, hands])
    np.testing.assert_allclose(out[:, rest], sprung[:, rest], atol=1e-12)
    assert np.abs(out[:, rest] - jumpy.reshape(frames, -1, 3)[:, rest]).max() > 1e-3
    still.reset()
    blocks = np.concatenate([still(jumpy[i:i + 2 * S]) for i in range(0, frames, 2 * S)])
    np.testing.assert_array_equal(blocks.reshape(frames, -1, 3), out)
    with pytest.raises(ValueError, match="layout"):
        SeamInertia(S, 0.8, still=("hands",))


@settings(max_examples=25, deadline=None)
@given(chunks=st.lists(st.integers(1, 4), min_size=1, max_size=10), seed=st.integers(0, 100))
def test_any_chunking_in_blocks_gives_the_frames_of_one_call(chunks, seed):
    frames = S * sum(chunks)
    rng = np.random.default_rng(seed)
    motion = walking_body(frames, seed) + rng.normal(scale=0.02, size=(frames, LAYOUT.width))
    whole = SeamInertia(S, 0.7)(motion)
    inertia, parts, start = SeamInertia(S, 0.7), [], 0
    for n in chunks:
        parts.append(inertia(motion[start:start + S * n]))
        start += S * n
    np.testing.assert_array_equal(np.concatenate(parts), whole)


def test_invalid_settings_are_refused():
    with pytest.raises(ValueError, match="boundary_inertia"):
        VAEConfig(boundary_inertia=1.0)
    with pytest.raises(ValueError, match="root_inertia"):
        VAEConfig(root_inertia=-0.5)
    with pytest.raises(ValueError, match="decay"):
        SeamInertia(S, -0.1)
    with pytest.raises(ValueError, match="stride"):
        SeamInertia(1, 0.5)
    with pytest.raises(ValueError, match="whole blocks"):
        SeamInertia(S, 0.5)(walking_body(S + 1))


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
    config = StreamConfig(decoder_frames=400)
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
    np.testing.assert_allclose(SeamInertia(S, 0.9)(raw.astype(np.float64)), streamed, atol=1e-6)


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
    np.testing.assert_allclose(inert, SeamInertia(S, 0.9)(raw.astype(np.float64)), atol=1e-6)


def test_the_chain_leaves_the_hands_still_when_the_model_says_so(inert_models):
    """vae.seam_skips_hands reaches the stream's seam spring, and is a decoding setting."""
    from sarah_models.config import DECODING_FIELDS
    from sarah_models.sampling.decoding import stream_decoding

    vae, _, normalizer = inert_models
    assert "seam_skips_hands" in DECODING_FIELDS["vae"]
    assert stream_decoding(vae, normalizer).filters[0].still == ()
    vae.config = dataclasses.replace(vae.config, seam_skips_hands=True)
    try:
        spring = stream_decoding(vae, normalizer).filters[0]
    finally:
        vae.config = dataclasses.replace(vae.config, seam_skips_hands=False)
    assert isinstance(spring, SeamInertia) and spring.still == ("hands",)
