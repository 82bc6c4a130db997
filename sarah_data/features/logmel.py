"""Causal log-mel features at 30 fps: the default extractor, needing no weights.

Pipeline for a 48 kHz track:

1. Resample to 16 kHz with torchaudio's windowed-sinc filter, made causal by delaying the input by
   the filter's lookahead (21 samples at 48 kHz, 0.44 ms): 16 kHz sample j then depends on 48 kHz
   samples up to 3 j only.
2. Mel power spectrogram (torchaudio MelSpectrogram's window and filterbank, power as re^2 + im^2;
   Hann window of 25 ms, hop 10 ms, 80 bands
   from 0 to 8 kHz, ``center=False``) over the resampled audio left-padded with zeros, so mel frame
   m is the window that *ends* at 16 kHz sample 160 (m + 1).
3. Natural log of max(power, ``log_floor``).
4. Motion frame t (samples [1600 t, 1600 (t + 1)) at 48 kHz) is the mean of the log-mel frames
   whose windows end inside (t / 30, (t + 1) / 30] s: three or four frames (ends at 10, 20, 30 ms go
   to frame 0; 40, 50, 60 ms to frame 1; 70 ... 100 ms to frame 2; and so on).

Every step reads only audio before the end of the frame it serves, so the offline features equal
the streaming ones, whatever the chunk sizes.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
import torchaudio

from sarah_data.constants import AUDIO_SAMPLE_RATE, SAMPLES_PER_FRAME
from sarah_data.features.base import AudioFeatureExtractor, FeatureStream, fit_to_frames, register_extractor

# torchaudio.functional.resample's defaults, pinned: the causal delay below is measured for them.
_LOWPASS_FILTER_WIDTH = 6
_ROLLOFF = 0.99


@dataclass(frozen=True)
class LogMelConfig:
    """Log-mel filterbank settings (at ``sample_rate``, after resampling from 48 kHz)."""

    sample_rate: int = 16_000
    n_mels: int = 80
    win_length_ms: float = 25.0
    hop_length_ms: float = 10.0
    f_min: float = 0.0
    f_max: float = 8_000.0
    log_floor: float = 1e-6  # power floor before the log: ~100 dB below a full-scale sine's peak bin

    def __post_init__(self) -> None:
        if AUDIO_SAMPLE_RATE % self.sample_rate:
            raise ValueError(f"logmel: sample_rate must divide {AUDIO_SAMPLE_RATE}, got {self.sample_rate}")
        for name in ("win_length_ms", "hop_length_ms"):
            samples = getattr(self, name) * self.sample_rate / 1000
            if samples != int(samples) or samples <= 0:
                raise ValueError(f"logmel: {name} must be a positive whole number of samples at {self.sample_rate} Hz")
        if self.hop_length_ms > self.win_length_ms:
            raise ValueError("logmel: hop_length_ms must not exceed win_length_ms")
        if not 0 <= self.f_min < self.f_max <= self.sample_rate / 2:
            raise ValueError(f"logmel: need 0 <= f_min < f_max <= {self.sample_rate / 2}")
        if self.log_floor <= 0:
            raise ValueError("logmel: log_floor must be positive")


@functools.cache
def _causal_resampling_taps(orig: int, new: int) -> torch.Tensor:
    """FIR taps g (float32) with resampled[j] = sum_m g[m] * x[r j - m], r = orig / new, m >= 0.

    torchaudio's resampling kernel, read off by resampling impulses (so it follows torchaudio rather
    than restating it), shifted by its lookahead so that sample j reads no input past r j.
    """
    ratio = orig // new
    base = 64 * ratio
    by_offset: dict[int, float] = {}  # d -> h[d] with resampled[j] = sum_d h[d] x[r j - d]
    for phase in range(ratio):
        impulse = torch.zeros(2 * base, dtype=torch.float64)
        impulse[base + phase] = 1.0
        out = torchaudio.functional.resample(impulse, orig, new, lowpass_filter_width=_LOWPASS_FILTER_WIDTH,
                                             rolloff=_ROLLOFF)
        for j in torch.nonzero(out).flatten().tolist():
            by_offset[ratio * j - base - phase] = float(out[j])
    lookahead = -min(by_offset)
    taps = torch.zeros(max(by_offset) + lookahead + 1, dtype=torch.float64)
    for offset, value in by_offset.items():
        taps[offset + lookahead] = value
    return taps.to(torch.float32)


_RESAMPLE_BLOCK = 32_768  # outputs per block on the CPU: its arrays stay in the L2 cache


def _causal_resample(x: torch.Tensor, ratio: int, taps: torch.Tensor) -> torch.Tensor:
    """Downsample by ``ratio``: output j reads x[: ratio * j + 1] only.

    Summed tap by tap in a fixed order with separately rounded products and sums (no conv kernel,
    no fused multiply-add), so each output is bitwise the same however long the input is: this is
    what makes streaming features identical to offline ones. On the CPU the same sums run block
    by block in numpy (IEEE float32 like torch's, so the same bits; ~2x faster, cache-resident).
    """
    count = (len(x) - 1) // ratio + 1 if len(x) else 0
    # Left padding to a whole number of `ratio` blocks; each phase then is one contiguous row.
    left = -(-(len(taps) - 1) // ratio) * ratio
    padded = torch.nn.functional.pad(x, (left, ratio - len(x) % ratio if len(x) % ratio else 0))
    phases = padded.view(-1, ratio).T.contiguous()  # phases[p, q] = padded[ratio * q + p]
    # x[ratio j - m] = padded[ratio (j + block) + phase]
    plan = [(*divmod(left - m, ratio), tap) for m, tap in enumerate(taps.tolist())]
    if x.device.type == "cpu":
        return torch.from_numpy(_resample_blocks(phases.numpy(), count, plan))
    y = torch.zeros(count, dtype=x.dtype, device=x.device)
    product = torch.empty_like(y)
    for block, phase, tap in plan:
        torch.mul(phases[phase, block: block + count], tap, out=product)
        y += product
    return y


def _resample_blocks(phases: np.ndarray, count: int, plan: list[tuple[int, int, float]]) -> np.ndarray:
    y = np.zeros(count, dtype=phases.dtype)
    product = np.empty(min(count, _RESAMPLE_BLOCK), dtype=phases.dtype)
    plan = [(block, phase, phases.dtype.type(tap)) for block, phase, tap in plan]
    for start in range(0, count, _RESAMPLE_BLOCK):
        stop = min(start + _RESAMPLE_BLOCK, count)
        out, prod = y[start:stop], product[: stop - start]
        for block, phase, tap in plan:
            np.multiply(phases[phase, block + start: block + stop], tap, out=prod)
            np.add(out, prod, out=out)
    return y


class _LogMel:
    """The computation shared by the offline and the streaming paths."""

    def __init__(self, config: LogMelConfig, device: torch.device) -> None:
        self.config = config
        self.ratio = AUDIO_SAMPLE_RATE // config.sample_rate
        self.hop = round(config.hop_length_ms * config.sample_rate / 1000)
        self.win = round(config.win_length_ms * config.sample_rate / 1000)
        self.taps = _causal_resampling_taps(AUDIO_SAMPLE_RATE, config.sample_rate).to(device)
        # Segment starts on this grid keep the 16 kHz samples, the mel hops and the motion frames
        # in the same phase as offline, so a segment reproduces the offline numbers.
        self.period = math.lcm(self.hop * self.ratio, SAMPLES_PER_FRAME)
        # Audio before a frame that its features can read: one window plus the resampling filter.
        self.context = self.ratio * self.win + len(self.taps)
        self.device = device
        self.mel = torchaudio.transforms.MelSpectrogram(
            sample_rate=config.sample_rate, n_fft=self.win, win_length=self.win, hop_length=self.hop,
            f_min=config.f_min, f_max=config.f_max, n_mels=config.n_mels, center=False, power=2.0,
        ).to(device, torch.float64)

    def move_to(self, device: torch.device) -> None:
        self.taps = self.taps.to(device)
        self.mel = self.mel.to(device)
        self.device = device

    def segment_start(self, first_frame: int) -> int:
        """Where a segment that serves frames >= ``first_frame`` starts (48 kHz sample index)."""
        wanted = first_frame * SAMPLES_PER_FRAME - self.context
        return max(0, wanted // self.period * self.period)

    def _mel_power(self, z: torch.Tensor) -> torch.Tensor:
        """(num_mel, n_mels): torchaudio's MelSpectrogram (its window and filterbank) with the
        power taken as re^2 + im^2; its |X|.pow(2) goes through hypot, ~40 % of this step."""
        spectrogram = self.mel.spectrogram
        spec = torch.stft(z, n_fft=spectrogram.n_fft, hop_length=spectrogram.hop_length,
                          win_length=spectrogram.win_length, window=spectrogram.window, center=False,
                          normalized=False, onesided=True, return_complex=True)
        power = spec.real.square() + spec.imag.square()  # (freq, num_mel)
        return power.T @ self.mel.mel_scale.fb

    @torch.inference_mode()
    def features(self, segment: np.ndarray, start: int, first_frame: int, end_frame: int) -> np.ndarray:
        """Features of frames [first_frame, end_frame) from samples [start, end_frame * 1600)."""
        count = end_frame - first_frame
        if count <= 0:
            return np.zeros((0, self.config.n_mels), dtype=np.float32)
        assert start % self.period == 0 and len(segment) == end_frame * SAMPLES_PER_FRAME - start
        x = torch.from_numpy(np.ascontiguousarray(segment)).to(self.device, torch.float32)
        y = _causal_resample(x, self.ratio, self.taps)
        # Spectra in float64: FFT and filterbank kernels may round differently for different numbers
        # of frames; in double precision that can no longer show in the float32 result.
        z = torch.nn.functional.pad(y.double(), (self.win - self.hop, 0))
        num_mel = len(y) // self.hop
        log_mel = self._mel_power(z[: (num_mel - 1) * self.hop + self.win]).clamp_min(self.config.log_floor).log()
        # Mel frame m ends at 48 kHz sample `ends[m]`; it belongs to the motion frame whose end is
        # the first at or after it.
        ends = start + self.ratio * self.hop * torch.arange(1, num_mel + 1, device=self.device)
        frame = torch.div(ends + SAMPLES_PER_FRAME - 1, SAMPLES_PER_FRAME, rounding_mode="floor") - 1
        keep = frame >= first_frame
        index = frame[keep] - first_frame
        sums = torch.zeros(count, self.config.n_mels, dtype=torch.float64, device=self.device)
        sums.index_add_(0, index, log_mel[keep])
        counts = torch.bincount(index, minlength=count).clamp_min(1)
        return (sums / counts[:, None]).to(torch.float32).cpu().numpy()


class LogMelStream(FeatureStream):
    def __init__(self, logmel: _LogMel) -> None:
        self._logmel = logmel
        super().__init__(logmel.config.n_mels)

    def _keep_from(self, next_frame: int) -> int:
        return self._logmel.segment_start(next_frame)

    def _frames(self, first: int, end: int) -> np.ndarray:
        start = self._logmel.segment_start(first)
        return self._logmel.features(self._audio(start, end * SAMPLES_PER_FRAME), start, first, end)


@register_extractor
class LogMelExtractor(AudioFeatureExtractor):
    """Causal 80-band log-mel at 16 kHz, averaged to 30 fps; streaming equals offline."""

    name = "logmel"
    config_type = LogMelConfig

    def __init__(self, config: LogMelConfig | None = None) -> None:
        super().__init__(config)
        self._logmel = _LogMel(self.config, torch.device("cpu"))

    @property
    def dim(self) -> int:
        return self.config.n_mels

    def to(self, device: str | None) -> "LogMelExtractor":
        if device is None:
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self._logmel.move_to(torch.device(device))  # in place: open streams follow
        return self

    def extract(self, wave: np.ndarray, num_frames: int) -> np.ndarray:
        wave = fit_to_frames(wave, num_frames)
        return self._logmel.features(wave, 0, 0, num_frames)

    def stream(self) -> LogMelStream:
        return LogMelStream(self._logmel)
