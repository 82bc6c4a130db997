"""The synthetic dyad: shapes, determinism, turn-taking, speech-like sound and crosstalk."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sarah_data.fixtures.audio import synthesize_dyad_audio
from sarah_data.speaking import SpeakingConfig, frame_energy_db, speaking_labels


@pytest.fixture(scope="module")
def dyad():
    return synthesize_dyad_audio(9000, seed=1)  # five minutes


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    edges = np.diff(np.concatenate([[0], mask.astype(int), [0]]))
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def test_shapes_and_types():
    d = synthesize_dyad_audio(31, seed=0)
    for track in (d.track_a, d.track_b):
        assert track.dtype == np.float32 and track.shape == (31 * 1600,)
        assert np.all(np.abs(track) <= 1.0)
    assert d.speaking_a.dtype == bool and d.speaking_a.shape == (31,) and d.speaking_b.shape == (31,)
    assert d.sample_rate == 48_000
    low = synthesize_dyad_audio(31, seed=0, sample_rate=16_000)
    assert low.track_a.shape == (31 * 16_000 // 30,)
    empty = synthesize_dyad_audio(0, seed=0)
    assert empty.track_a.shape == (0,) and empty.speaking_a.shape == (0,)


def test_same_seed_same_bytes_other_seed_other_audio():
    a, b, c = (synthesize_dyad_audio(300, seed=s) for s in (4, 4, 5))
    assert a.track_a.tobytes() == b.track_a.tobytes() and a.track_b.tobytes() == b.track_b.tobytes()
    np.testing.assert_array_equal(a.speaking_a, b.speaking_a)
    assert not np.array_equal(a.track_a, c.track_a)


def test_turn_taking(dyad):
    a, b = dyad.speaking_a, dyad.speaking_b
    for own in (a, b):
        assert 0.3 <= own.mean() <= 0.65
    assert 0.0 < (a & b).mean() < 0.1  # some overlap and backchannels, mostly one at a time
    assert 0.0 < (~a & ~b).mean() < 0.2  # short gaps between turns
    lengths = np.concatenate([np.subtract(*_runs(m)[::-1]) for m in (a, b)]) / 30
    turns, short = lengths[lengths >= 1.0], lengths[lengths < 1.0]
    assert len(turns) > 30 and turns.min() >= 1.4 and np.median(turns) < 6.0
    assert len(short) >= 3 and short.min() >= 0.25  # backchannels


def _longest_solo_segment(dyad) -> np.ndarray:
    starts, ends = _runs(dyad.speaking_a & ~dyad.speaking_b)
    k = int(np.argmax(ends - starts))
    return dyad.track_a[starts[k] * 1600: ends[k] * 1600].astype(np.float64)


def test_sound_is_speech_like(dyad):
    segment = _longest_solo_segment(dyad)
    assert len(segment) >= 2 * 48_000
    # Syllabic rhythm: the 10 ms RMS envelope is modulated at ~4-5 Hz.
    envelope = np.sqrt(np.mean(segment[: len(segment) // 480 * 480].reshape(-1, 480) ** 2, axis=1))
    spectrum = np.abs(np.fft.rfft(envelope - envelope.mean(), 4096))
    freqs = np.fft.rfftfreq(4096, 0.01)
    band = (freqs > 1.0) & (freqs < 10.0)
    assert 3.0 <= freqs[band][np.argmax(spectrum[band])] <= 6.0
    # Voiced: an autocorrelation pitch within the speakers' 90-250 Hz in most 40 ms blocks.
    pitches = []
    for start in range(0, len(segment) - 1920, 4800):
        block = segment[start: start + 1920] - segment[start: start + 1920].mean()
        ac = np.correlate(block, block, "full")[len(block) - 1:]
        lags = np.arange(48_000 // 300, 48_000 // 70)
        pitches.append(48_000 / lags[np.argmax(ac[lags])])
    assert np.mean((np.array(pitches) >= 85) & (np.array(pitches) <= 260)) >= 0.7
    # Formant-filtered: the energy sits below 4 kHz.
    power = np.abs(np.fft.rfft(segment)) ** 2
    assert power[np.fft.rfftfreq(len(segment), 1 / 48_000) < 4000].sum() / power.sum() > 0.95


@pytest.mark.parametrize("crosstalk_db", [-18.0, -26.0])
def test_tracks_leak_the_partner_at_the_crosstalk_level(crosstalk_db):
    d = synthesize_dyad_audio(1800, seed=1, crosstalk_db=crosstalk_db)
    level_a, level_b = frame_energy_db(d.track_a), frame_energy_db(d.track_b)
    # Frames where only B talks, loudly enough that the leak stands well above the noise floor.
    loud_b = d.speaking_b & ~d.speaking_a & (level_b > -32.0)
    assert loud_b.sum() > 100
    assert abs(np.median(level_a[loud_b] - level_b[loud_b]) - crosstalk_db) < 1.0


def test_a_plain_level_threshold_mislabels_the_leak(dyad):
    naive = speaking_labels(dyad.track_a, None, replace(SpeakingConfig(), crosstalk_margin_db=math.inf))
    only_b = dyad.speaking_b & ~dyad.speaking_a
    assert naive[only_b].mean() > 0.1  # the partner's loud turns cross the level threshold
    silent = ~dyad.speaking_a & ~dyad.speaking_b
    assert np.median(frame_energy_db(dyad.track_a)[silent]) < -55  # a low noise floor in the gaps
