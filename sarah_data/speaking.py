"""Per-frame and per-clip speaking labels from each person's separated audio track.

Frame t of a sequence covers samples [t * rate / 30, (t + 1) * rate / 30) (1600 samples at 48 kHz).
A frame is the person's speech when

1. their track is loud enough, with hysteresis: a run starts at ``on_db`` and continues while the
   level stays above ``off_db`` (syllable dips inside a word do not end it);
2. their track is not much quieter than the partner's track: the separated tracks leak the partner's
   voice ~15-25 dB below its source, so a frame whose own level is more than ``crosstalk_margin_db``
   below the partner's track is that leakage, not the person talking. Speech of both at once
   (overlaps, backchannels) sits within a few dB and survives;
3. after smoothing: silences shorter than ``min_gap_s`` inside speech are filled (pauses between
   words), then bursts shorter than ``min_burst_s`` are dropped (clicks, breaths).

Levels are dBFS RMS: 10 log10(mean(x^2)) with x in [-1, 1], so a full-scale sine is -3 dBFS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from sarah_data.constants import AUDIO_SAMPLE_RATE, FPS, SAMPLES_PER_FRAME

# Keeps log10 finite on digital silence; -120 dBFS is far below any real noise floor.
_POWER_FLOOR = 1e-12


@dataclass(frozen=True)
class SpeakingConfig:
    """Thresholds of the speaking labeler; every level is in dBFS RMS per 1/30 s frame.

    on_db: a speech run starts when the own track reaches this level.
    off_db: a run continues while the own track stays at or above this level (hysteresis).
    crosstalk_margin_db: own speech needs own_db >= partner_db - crosstalk_margin_db; math.inf turns
        the crosstalk rule off.
    min_gap_s: silences shorter than this between two speech runs are filled.
    min_burst_s: speech runs shorter than this (after gap filling) are dropped.
    clip_speaking_fraction: a clip is speaking (S) when at least this fraction of its frames are
        speaking. Each partner talks roughly half of a conversation, so S means the agent clearly
        holds the floor; S is then the minority class, as in the paper (544 S of 2048 clips, 27%).
        On balanced synthetic conversations 0.6 marks 22% of 400-frame clips S (0.5 would mark 48%).
    """

    on_db: float = -42.0
    off_db: float = -50.0
    crosstalk_margin_db: float = 9.0
    min_gap_s: float = 0.3
    min_burst_s: float = 0.1
    clip_speaking_fraction: float = 0.6

    def __post_init__(self) -> None:
        if self.off_db > self.on_db:
            raise ValueError(f"SpeakingConfig: off_db ({self.off_db}) must not exceed on_db ({self.on_db})")
        if self.crosstalk_margin_db < 0:
            raise ValueError(f"SpeakingConfig: crosstalk_margin_db must be >= 0, got {self.crosstalk_margin_db}")
        if self.min_gap_s < 0 or self.min_burst_s < 0:
            raise ValueError("SpeakingConfig: min_gap_s and min_burst_s must be >= 0")
        if not 0.0 <= self.clip_speaking_fraction <= 1.0:
            raise ValueError(
                f"SpeakingConfig: clip_speaking_fraction must be in [0, 1], got {self.clip_speaking_fraction}"
            )


def as_mono_wave(wave: np.ndarray, what: str) -> np.ndarray:
    """``wave`` checked to be a finite mono float waveform; ``what`` names the caller in errors."""
    wave = np.asarray(wave)
    if wave.ndim != 1:
        raise ValueError(f"{what}: expected a mono waveform of shape (N,), got shape {wave.shape}")
    if not np.issubdtype(wave.dtype, np.floating):
        raise TypeError(f"{what}: expected floating-point samples in [-1, 1], got dtype {wave.dtype}")
    if not np.all(np.isfinite(wave)):
        raise ValueError(f"{what}: waveform contains NaN or infinite samples")
    return wave


def frame_bounds(num_samples: int, samples_per_frame: float | Fraction) -> np.ndarray:
    """Sample index where each whole frame starts, plus the end of the last one: (T + 1,) int64.

    A fractional ``samples_per_frame`` (e.g. 16000/30) gives frames of floor(t * spf) samples exactly.
    """
    spf = Fraction(samples_per_frame).limit_denominator(10_000)
    if spf <= 0:
        raise ValueError(f"samples_per_frame must be positive, got {samples_per_frame}")
    num_frames = int(num_samples * spf.denominator // spf.numerator)
    t = np.arange(num_frames + 1, dtype=np.int64)
    return (t * spf.numerator) // spf.denominator


def frame_energy_db(wave: np.ndarray, samples_per_frame: float | Fraction = SAMPLES_PER_FRAME) -> np.ndarray:
    """RMS level in dBFS of each whole frame: (T,) float64 with T = len(wave) // samples_per_frame.

    A trailing partial frame is ignored, as the motion has no frame for it.
    """
    wave = as_mono_wave(wave, "frame_energy_db")
    bounds = frame_bounds(len(wave), samples_per_frame)
    size = int(bounds[1] - bounds[0]) if len(bounds) > 1 else 0
    if len(bounds) > 1 and bounds[-1] == size * (len(bounds) - 1):
        # Equal frames (48 kHz: 1600 samples): one float64 dot product per frame.
        frames = wave[: bounds[-1]].reshape(-1, size).astype(np.float64)
        power = np.einsum("ij,ij->i", frames, frames) / size
    else:
        # Sums of squares from a float64 running sum: exact enough and independent of frame size.
        cumulative = np.concatenate([[0.0], np.cumsum(np.square(wave, dtype=np.float64))])
        power = (cumulative[bounds[1:]] - cumulative[bounds[:-1]]) / np.diff(bounds)
    return 10.0 * np.log10(np.maximum(power, _POWER_FLOOR))


def _runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) indices of the True runs of a 1-D bool array."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def _hysteresis(level_db: np.ndarray, gate: np.ndarray, on_db: float, off_db: float) -> np.ndarray:
    """Runs of frames above ``off_db`` that reach ``on_db`` somewhere, restricted to ``gate``.

    Equivalent to the on/off state machine: a run of 'above off' frames is speech from its first
    frame at or above ``on_db`` to its end. Vectorized so hour-long tracks label in milliseconds.
    """
    above_off = (level_db >= off_db) & gate
    above_on = (level_db >= on_db) & above_off
    labels = np.zeros(len(level_db), dtype=bool)
    starts, ends = _runs(above_off)
    on_idx = np.flatnonzero(above_on)
    if len(on_idx) == 0:
        return labels
    # First 'on' frame at or after each run start; the run is speech from there if it is inside the run.
    first_on = np.searchsorted(on_idx, starts)
    has_on = first_on < len(on_idx)
    first_on_frame = np.where(has_on, on_idx[np.minimum(first_on, len(on_idx) - 1)], ends)
    for begin, end in zip(first_on_frame[first_on_frame < ends], ends[first_on_frame < ends]):
        labels[begin:end] = True
    return labels


def _fill_gaps(labels: np.ndarray, max_gap: int) -> np.ndarray:
    """Fill False runs shorter than ``max_gap`` frames that lie between two True runs."""
    out = labels.copy()
    starts, ends = _runs(~labels)
    for begin, end in zip(starts, ends):
        if begin > 0 and end < len(labels) and end - begin < max_gap:
            out[begin:end] = True
    return out


def _drop_bursts(labels: np.ndarray, min_len: int) -> np.ndarray:
    """Clear True runs shorter than ``min_len`` frames."""
    out = labels.copy()
    starts, ends = _runs(labels)
    for begin, end in zip(starts, ends):
        if end - begin < min_len:
            out[begin:end] = False
    return out


def speaking_labels(
    own: np.ndarray,
    partner: np.ndarray | None,
    config: SpeakingConfig = SpeakingConfig(),
    sample_rate: int = AUDIO_SAMPLE_RATE,
) -> np.ndarray:
    """Per-frame speaking labels of the person whose separated track is ``own``: (T,) bool.

    T = len(own) // (sample_rate / 30). ``partner`` is the other person's separated track (same rate;
    its frames past T are ignored, missing ones count as silence); None disables the crosstalk rule.
    """
    samples_per_frame = Fraction(sample_rate, FPS)
    partner_db = None
    if partner is not None and math.isfinite(config.crosstalk_margin_db):
        partner_db = frame_energy_db(partner, samples_per_frame)
    return labels_from_levels(frame_energy_db(own, samples_per_frame), partner_db, config)


def labels_from_levels(own_db: np.ndarray, partner_db: np.ndarray | None,
                       config: SpeakingConfig = SpeakingConfig()) -> np.ndarray:
    """`speaking_labels` from the tracks' `frame_energy_db` levels (a dyad needs each track's
    levels twice: once as own, once as partner)."""
    gate = np.ones(len(own_db), dtype=bool)
    if partner_db is not None and math.isfinite(config.crosstalk_margin_db):
        aligned = np.full(len(own_db), 10.0 * np.log10(_POWER_FLOOR))
        n = min(len(own_db), len(partner_db))
        aligned[:n] = partner_db[:n]
        gate = own_db >= aligned - config.crosstalk_margin_db
    labels = _hysteresis(own_db, gate, config.on_db, config.off_db)
    labels = _fill_gaps(labels, max_gap=round(config.min_gap_s * FPS))
    return _drop_bursts(labels, min_len=round(config.min_burst_s * FPS))


def speaking_fraction(labels: np.ndarray) -> float:
    """Fraction of frames labelled speaking (0 for an empty clip)."""
    labels = np.asarray(labels)
    return float(labels.mean()) if labels.size else 0.0


def clip_is_speaking(
    agent_audio_or_labels: np.ndarray,
    config: SpeakingConfig = SpeakingConfig(),
    partner: np.ndarray | None = None,
    sample_rate: int = AUDIO_SAMPLE_RATE,
) -> bool:
    """Whether a clip counts as speaking (S) for evaluation: the agent speaks in at least
    ``config.clip_speaking_fraction`` of its frames.

    Takes per-frame labels (bool array) or the agent's waveform (float array; labelled with
    ``speaking_labels(agent, partner, config, sample_rate)``).
    """
    values = np.asarray(agent_audio_or_labels)
    if values.dtype == bool:
        if values.ndim != 1:
            raise ValueError(f"clip_is_speaking: expected (T,) labels, got shape {values.shape}")
        labels = values
    else:
        labels = speaking_labels(values, partner, config, sample_rate)
    return bool(labels.size) and speaking_fraction(labels) >= config.clip_speaking_fraction
