"""The limb low-pass (sampling.limb_lowpass) on a prepared fixture body: the arms' jitter goes,
their slow motion and everything else stay, a walking body's arms do not lag, and a stream
decoded in chunks is the same as decoded at once."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sarah_data.constants import FPS, JOINT
from sarah_data.dataset import WindowDataset
from sarah_data.skeleton import JOINT_GROUPS, MotionLayout, shell_parts
from sarah_models.sampling.limb_lowpass import LIMBS, LimbLowpass, butterworth

T = 240


@pytest.fixture(scope="module")
def body(prepared_shards):
    """A real fixture frame held still for T frames, its layout, and which points are limbs."""
    data = WindowDataset.sliding(prepared_shards, "train", extractor=None, window=64)
    frame = data[0]["motion"].numpy().astype(np.float64)[0]
    layout = MotionLayout.from_width(len(frame))
    icosahedra, shell = layout.split(frame)
    parts = shell_parts(icosahedra, shell, layout.joint_names)
    limb_joints = [layout.joint(n) for g in LIMBS for n in JOINT_GROUPS[g]]
    limb_shell = [p for g in LIMBS for p in parts.get(g, ())]
    return np.repeat(frame[None], T, axis=0), layout, limb_joints, limb_shell


def moved(motion, layout, joints, shell, offset):
    """``motion`` with the icosahedra of ``joints`` and the ``shell`` points moved by (T, 3)."""
    icosahedra, points = layout.split(motion.copy())
    icosahedra[:, joints] += offset[:, None, None]
    points[:, shell] += offset[:, None]
    return np.concatenate([icosahedra.reshape(T, -1), points.reshape(T, -1)], axis=1)


def amplitude(signal: np.ndarray, hz: float) -> float:
    """The amplitude of ``signal``'s ``hz`` sine over the second half (past the start)."""
    t = np.arange(T)[T // 2:] / FPS
    basis = np.stack([np.sin(2 * np.pi * hz * t), np.cos(2 * np.pi * hz * t), np.ones_like(t)], 1)
    coef = np.linalg.lstsq(basis, signal[T // 2:], rcond=None)[0]
    return float(np.hypot(*coef[:2]))


def test_a_still_or_walking_body_passes_unchanged(body):
    still, layout, *_ = body
    np.testing.assert_allclose(LimbLowpass(layout, 6.0)(still), still, atol=1e-12)
    walk = still.reshape(T, -1, 3).copy()
    walk[..., 2] += 1.2 * np.arange(T)[:, None] / FPS  # 1.2 m/s, arms carried along
    walk[..., 0] += 0.3 * np.sin(np.arange(T) / FPS)[:, None]
    walk = walk.reshape(T, -1)
    np.testing.assert_allclose(LimbLowpass(layout, 6.0)(walk), walk, atol=1e-9)


def test_limb_jitter_goes_slow_motion_stays_and_the_rest_is_untouched(body):
    still, layout, limb_joints, limb_shell = body
    t = np.arange(T) / FPS
    wobble = np.zeros((T, 3))
    wobble[:, 0] = 0.05 * np.sin(2 * np.pi * 2.0 * t) + 0.01 * np.sin(2 * np.pi * 12.0 * t)
    arms = moved(still, layout, limb_joints, limb_shell, wobble)
    others = [j for j in range(layout.num_joints) if j not in limb_joints]
    # the rest but the pelvis (the frame the arms are filtered in) jitters too, unfiltered
    legs_head = [j for j in others if j != JOINT["pelvis"]]
    both = moved(arms, layout, legs_head, [], 0.01 * np.sin(2 * np.pi * 12.0 * t)[:, None] * np.ones(3))
    out = LimbLowpass(layout, 6.0)(both)
    ico_in, shell_in = layout.split(both)
    ico_out, shell_out = layout.split(out)
    elbow = JOINT["left_elbow"]
    x_in, x_out = ico_in[:, elbow, 0, 0], ico_out[:, elbow, 0, 0]
    gain = butterworth(6.0)
    assert amplitude(x_out, 12.0) < 0.2 * amplitude(x_in, 12.0)  # -14 dB at twice the cutoff
    assert amplitude(x_out, 2.0) > 0.95 * amplitude(x_in, 2.0)
    if limb_shell:
        assert amplitude(shell_out[:, limb_shell[0], 0], 12.0) < 0.2 * amplitude(
            shell_in[:, limb_shell[0], 0], 12.0)
    np.testing.assert_array_equal(ico_out[:, others], ico_in[:, others])  # legs, trunk, head
    rest = [p for p in range(layout.shell_points) if p not in limb_shell]
    np.testing.assert_array_equal(shell_out[:, rest], shell_in[:, rest])
    assert np.isclose(gain[0].sum(), gain[1].sum())  # unit gain at 0 Hz


def test_chunks_and_a_whole_window_filter_alike(body):
    still, layout, limb_joints, limb_shell = body
    rng = np.random.default_rng(0)
    noisy = moved(still, layout, limb_joints, limb_shell, rng.normal(scale=0.01, size=(T, 3)))
    whole = LimbLowpass(layout, 6.0)
    expected = whole(noisy)
    streamed = LimbLowpass(layout, 6.0)
    chunks = np.concatenate([streamed(noisy[i:i + 4]) for i in range(0, T, 4)])
    np.testing.assert_allclose(chunks, expected, atol=1e-12)
    whole.reset()
    np.testing.assert_allclose(whole(noisy), expected, atol=1e-12)


def test_the_decoding_chain_runs_it_where_the_config_asks():
    from sarah_models.config import VAEConfig
    from sarah_models.sampling.decoding import stream_decoding
    from sarah_models.testing import random_models

    vae, _, normalizer = random_models("tiny")
    vae.config = dataclasses.replace(vae.config, limb_lowpass=6.0)
    assert [type(f).__name__ for f in stream_decoding(vae, normalizer).filters] == [
        "SeamInertia", "LimbLowpass"]
    for bad in (-1.0, FPS / 2):
        with pytest.raises(ValueError, match="limb_lowpass"):
            VAEConfig(limb_lowpass=bad)
