"""Speaking labels: exact on constructed signals, accurate on synthesized dyads with crosstalk."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sarah_data.fixtures.audio import synthesize_dyad_audio
from sarah_data.speaking import (
    SpeakingConfig,
    _hysteresis,
    clip_is_speaking,
    frame_energy_db,
    labels_from_levels,
    speaking_fraction,
    speaking_labels,
)

RATE = 48_000
SPF = 1600
CFG = SpeakingConfig()


def tone(num_frames: int, level_db: float, freq: float = 300.0, rate: int = RATE) -> np.ndarray:
    """A sine of RMS ``level_db`` dBFS; 300 Hz fits whole periods in every 1/30 s frame."""
    n = num_frames * rate // 30
    amplitude = math.sqrt(2) * 10 ** (level_db / 20)
    return (amplitude * np.sin(2 * np.pi * freq * np.arange(n) / rate)).astype(np.float32)


def silence(num_frames: int, rate: int = RATE) -> np.ndarray:
    return np.zeros(num_frames * rate // 30, dtype=np.float32)


def frames(mask_ranges: list[tuple[int, int]], total: int) -> np.ndarray:
    out = np.zeros(total, dtype=bool)
    for a, b in mask_ranges:
        out[a:b] = True
    return out


def test_frame_energy_is_rms_dbfs_per_whole_frame():
    wave = np.concatenate([silence(2), tone(3, -20.0), np.ones(SPF, dtype=np.float32), np.ones(5, np.float32)])
    level = frame_energy_db(wave)
    assert level.shape == (6,)  # the 5-sample tail is not a frame
    np.testing.assert_allclose(level[:2], -120.0)  # the floor on digital silence
    np.testing.assert_allclose(level[2:5], -20.0, atol=1e-4)
    np.testing.assert_allclose(level[5], 0.0, atol=1e-9)


def test_labels_from_levels_equal_labels_from_waves():
    """prep computes each track's levels once and labels both persons from them."""
    own, partner = synthesize_dyad_audio_pair()
    for a, b in ((own, partner), (partner, own)):
        expected = speaking_labels(a, b, CFG)
        np.testing.assert_array_equal(labels_from_levels(frame_energy_db(a), frame_energy_db(b), CFG), expected)
    levels = frame_energy_db(own)
    exact = [10 * np.log10(max(np.mean(own[t * SPF:(t + 1) * SPF].astype(np.float64) ** 2), 1e-12))
             for t in range(len(levels))]
    np.testing.assert_allclose(levels, exact, atol=1e-9)


def synthesize_dyad_audio_pair() -> tuple[np.ndarray, np.ndarray]:
    parts = [tone(20, -30.0), silence(7), tone(11, -45.0, 440.0), tone(9, -60.0), silence(3)]
    own = np.concatenate(parts) + np.random.default_rng(0).normal(0, 1e-4, 50 * SPF).astype(np.float32)
    return own.astype(np.float32), np.roll(own, 17 * SPF) * np.float32(0.3)


def test_frame_energy_with_fractional_samples_per_frame():
    # 16 kHz: 533 1/3 samples per frame; frame t is [floor(533.33 t), floor(533.33 (t + 1))).
    wave = np.arange(1601, dtype=np.float64) / 1600
    level = frame_energy_db(wave, 16000 / 30)
    bounds = [0, 533, 1066, 1600]
    expected = [10 * np.log10(np.mean(wave[a:b] ** 2)) for a, b in zip(bounds, bounds[1:])]
    np.testing.assert_allclose(level, expected, rtol=1e-12)


def test_tone_between_silences_is_labelled_exactly():
    own = np.concatenate([silence(30), tone(30, -25.0), silence(30)])
    labels = speaking_labels(own, np.zeros_like(own))
    assert labels.dtype == bool and labels.shape == (90,)
    np.testing.assert_array_equal(labels, frames([(30, 60)], 90))


def test_hysteresis_continues_but_does_not_start_between_thresholds():
    # on -42, off -50: -46 dB continues a run started at -30 dB but cannot start one by itself.
    own = np.concatenate([tone(10, -30.0), tone(10, -46.0), silence(20), tone(10, -46.0), silence(10)])
    labels = speaking_labels(own, None)
    np.testing.assert_array_equal(labels, frames([(0, 20)], 60))


def test_short_gaps_are_filled_and_short_bursts_dropped():
    # min_gap 0.3 s = 9 frames, min_burst 0.1 s = 3 frames.
    parts = [tone(20, -25.0), silence(8), tone(20, -25.0), silence(10), tone(20, -25.0),
             silence(20), tone(2, -25.0), silence(20), tone(3, -25.0), silence(10)]
    labels = speaking_labels(np.concatenate(parts), None)
    expected = frames([(0, 48), (58, 78), (120, 123)], 133)
    np.testing.assert_array_equal(labels, expected)


def test_crosstalk_rule_rejects_leakage_and_keeps_overlaps():
    partner = np.concatenate([tone(30, -20.0), silence(30), tone(30, -22.0, freq=450.0)])
    leak = 10 ** (-18 / 20) * partner  # the partner's voice in my track: -38 dBFS, above on_db
    own = leak + np.concatenate([silence(60), tone(30, -24.0)])  # I speak only in the last second
    labels = speaking_labels(own, partner)
    np.testing.assert_array_equal(labels, frames([(60, 90)], 90))
    naive = speaking_labels(own, partner, replace(CFG, crosstalk_margin_db=math.inf))
    np.testing.assert_array_equal(naive, frames([(0, 30), (60, 90)], 90))


def test_partner_track_shorter_than_own_counts_as_silence():
    own = tone(20, -25.0)
    labels = speaking_labels(own, tone(10, -10.0))
    np.testing.assert_array_equal(labels, frames([(10, 20)], 20))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_synthesized_dyads_are_labelled_accurately_and_need_the_crosstalk_rule(seed):
    dyad = synthesize_dyad_audio(1800, seed)  # one minute
    no_crosstalk = replace(CFG, crosstalk_margin_db=math.inf)
    accuracy, naive_accuracy = [], []
    for own, partner, truth in ((dyad.track_a, dyad.track_b, dyad.speaking_a),
                                (dyad.track_b, dyad.track_a, dyad.speaking_b)):
        labels = speaking_labels(own, partner, CFG)
        assert labels.shape == truth.shape
        accuracy.append(np.mean(labels == truth))
        naive_accuracy.append(np.mean(speaking_labels(own, partner, no_crosstalk) == truth))
    assert min(accuracy) >= 0.95, accuracy
    # Without the rule the partner's louder turns leak in: clearly worse.
    assert np.mean(naive_accuracy) <= np.mean(accuracy) - 0.03, (accuracy, naive_accuracy)


@pytest.mark.parametrize("rate", [16_000, 44_100])
def test_other_sample_rates(rate):
    dyad = synthesize_dyad_audio(900, seed=7, sample_rate=rate)
    labels = speaking_labels(dyad.track_a, dyad.track_b, CFG, sample_rate=rate)
    assert labels.shape == (900,)
    assert np.mean(labels == dyad.speaking_a) >= 0.95


def _reference_hysteresis(level, gate, on, off):
    state, out = False, []
    for value, ok in zip(level, gate):
        state = ok and (value >= on or (state and value >= off))
        out.append(state)
    return np.array(out, dtype=bool)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(-70, -20), st.booleans()), max_size=60))
def test_vectorized_hysteresis_equals_the_state_machine(samples):
    level = np.array([s[0] for s in samples], dtype=float)
    gate = np.array([s[1] for s in samples], dtype=bool)
    np.testing.assert_array_equal(_hysteresis(level, gate, -42.0, -50.0),
                                  _reference_hysteresis(level, gate, -42.0, -50.0))


@settings(max_examples=100, deadline=None)
@given(st.lists(st.booleans(), max_size=50), st.floats(0.0, 1.0))
def test_clip_rule_is_the_speaking_fraction_threshold(labels, threshold):
    labels = np.array(labels, dtype=bool)
    config = replace(CFG, clip_speaking_fraction=threshold)
    expected = labels.size > 0 and labels.mean() >= threshold
    assert clip_is_speaking(labels, config) == expected


def test_clip_rule_on_labels_and_on_audio():
    assert CFG.clip_speaking_fraction == 0.6
    assert clip_is_speaking(frames([(0, 240)], 400))  # exactly 60%: speaking
    assert not clip_is_speaking(frames([(0, 239)], 400))
    assert not clip_is_speaking(np.zeros(0, dtype=bool))
    own = np.concatenate([tone(250, -25.0), silence(150)])
    assert clip_is_speaking(own, CFG, partner=np.zeros_like(own))
    assert not clip_is_speaking(own, CFG, partner=np.concatenate([tone(150, -10.0), silence(250)]))
    assert not clip_is_speaking(np.concatenate([tone(230, -25.0), silence(170)]))
    assert speaking_fraction(speaking_labels(own, None)) == pytest.approx(250 / 400)


def test_bad_input_and_config_are_rejected():
    with pytest.raises(ValueError, match="off_db"):
        SpeakingConfig(on_db=-50.0, off_db=-40.0)
    with pytest.raises(ValueError, match="shape"):
        speaking_labels(np.zeros((2, 1600), np.float32), None)
    with pytest.raises(TypeError, match="dtype"):
        speaking_labels(np.zeros(1600, np.int16), None)
    with pytest.raises(ValueError, match="NaN"):
        speaking_labels(np.full(1600, np.nan, np.float32), None)
