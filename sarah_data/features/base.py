"""The audio-feature extractor interface and its registry of named extractors.

An extractor turns a person's 48 kHz track into one feature vector per motion frame: frame t covers
[t / 30, (t + 1) / 30) s, i.e. samples [1600 t, 1600 (t + 1)). Offline, ``extract`` first fits the
track to exactly ``num_frames * 1600`` samples: a longer track is cut at the end, a shorter one is
padded at the end with zeros (silence), so frames past the audio describe silence.

Streaming, ``stream()`` returns a causal extractor: ``push(samples)`` appends audio and returns the
features of every frame completed by it, computed from audio up to that frame's end only.
"""

from __future__ import annotations

import abc
from dataclasses import fields, is_dataclass
from typing import Any, ClassVar, TypeVar

import numpy as np

from sarah_data.constants import SAMPLES_PER_FRAME
from sarah_data.speaking import as_mono_wave

_REGISTRY: dict[str, type["AudioFeatureExtractor"]] = {}

E = TypeVar("E", bound=type["AudioFeatureExtractor"])


def fit_to_frames(wave: np.ndarray, num_frames: int) -> np.ndarray:
    """``wave`` as float32 of exactly ``num_frames * 1600`` samples (cut or zero-padded at the end)."""
    wave = as_mono_wave(wave, "audio features").astype(np.float32, copy=False)
    if num_frames < 0:
        raise ValueError(f"audio features: num_frames must be >= 0, got {num_frames}")
    target = num_frames * SAMPLES_PER_FRAME
    if len(wave) >= target:
        return wave[:target]
    return np.concatenate([wave, np.zeros(target - len(wave), dtype=np.float32)])


class FeatureStream(abc.ABC):
    """A causal extractor over one growing track; never looks at audio past a frame's end."""

    def __init__(self, dim: int) -> None:
        self.dim = dim
        self.reset()

    def reset(self) -> None:
        """Forget all audio: the next push starts frame 0 of a new track."""
        self._buffer = np.zeros(0, dtype=np.float32)
        self._buffer_start = 0  # absolute sample index of _buffer[0]
        self.frames_done = 0  # frames already returned
        self.samples_seen = 0

    def push(self, samples: np.ndarray) -> np.ndarray:
        """Append 48 kHz samples; return (k, dim) float32 features of the k frames they complete."""
        samples = np.asarray(samples)
        if samples.ndim != 1 or not np.issubdtype(samples.dtype, np.floating):
            raise ValueError(f"stream.push: expected float samples of shape (n,), got {samples.dtype} {samples.shape}")
        samples = samples.astype(np.float32, copy=False)
        if not np.all(np.isfinite(samples)):
            raise ValueError("stream.push: samples contain NaN or infinite values")
        self._buffer = np.concatenate([self._buffer, samples])
        self.samples_seen += len(samples)
        complete = self.samples_seen // SAMPLES_PER_FRAME
        if complete == self.frames_done:
            return np.zeros((0, self.dim), dtype=np.float32)
        features = self._frames(self.frames_done, complete)
        self.frames_done = complete
        keep_from = min(self._keep_from(complete), complete * SAMPLES_PER_FRAME)
        if keep_from > self._buffer_start:
            self._buffer = self._buffer[keep_from - self._buffer_start:]
            self._buffer_start = keep_from
        return features

    def _audio(self, start: int, end: int) -> np.ndarray:
        """Buffered samples [start, end) by absolute index; ``start`` must still be buffered."""
        assert self._buffer_start <= start <= end <= self.samples_seen, (start, end, self._buffer_start)
        return self._buffer[start - self._buffer_start: end - self._buffer_start]

    @abc.abstractmethod
    def _frames(self, first: int, end: int) -> np.ndarray:
        """Features of frames [first, end), from samples before ``end * 1600`` only."""

    @abc.abstractmethod
    def _keep_from(self, next_frame: int) -> int:
        """Earliest absolute sample the features of frames >= ``next_frame`` will read."""


class AudioFeatureExtractor(abc.ABC):
    """A named audio-feature extractor configured by a dataclass (stored in shards via ``asdict``)."""

    name: ClassVar[str]
    config_type: ClassVar[type]

    def __init__(self, config: Any = None) -> None:
        self.config = self.config_type() if config is None else config
        if not isinstance(self.config, self.config_type):
            raise TypeError(f"{self.name}: config must be a {self.config_type.__name__}, got {type(self.config)}")

    @property
    @abc.abstractmethod
    def dim(self) -> int:
        """Feature width D."""

    @abc.abstractmethod
    def extract(self, wave: np.ndarray, num_frames: int) -> np.ndarray:
        """(num_frames, D) float32 features of a 48 kHz mono track, one row per motion frame."""

    def record(self) -> dict[str, Any]:
        """What shards record of this extractor: its configuration (JSON-able), with anything
        that names a local file replaced by what identifies its content."""
        from dataclasses import asdict

        return asdict(self.config)

    @abc.abstractmethod
    def stream(self) -> FeatureStream:
        """A fresh causal streaming extractor sharing this extractor's configuration and model."""

    def to(self, device: str | None) -> "AudioFeatureExtractor":
        """Move any model to ``device`` (None: CUDA when available); returns self."""
        return self

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.config!r})"


def register_extractor(cls: E) -> E:
    """Class decorator: make ``cls`` available by ``cls.name`` to ``get_extractor``."""
    if not (isinstance(cls, type) and issubclass(cls, AudioFeatureExtractor)):
        raise TypeError(f"register_extractor: {cls!r} is not an AudioFeatureExtractor subclass")
    if not is_dataclass(getattr(cls, "config_type", None)):
        raise TypeError(f"register_extractor: {cls.__name__}.config_type must be a dataclass")
    existing = _REGISTRY.get(cls.name)
    if existing is not None and existing is not cls:
        raise ValueError(f"register_extractor: the name {cls.name!r} is already taken by {existing.__name__}")
    _REGISTRY[cls.name] = cls
    return cls


def available_extractors() -> tuple[str, ...]:
    """Names accepted by ``get_extractor``, sorted."""
    return tuple(sorted(_REGISTRY))


def get_extractor(name: str, **overrides: Any) -> AudioFeatureExtractor:
    """The extractor registered as ``name``, its config's defaults replaced by ``overrides``."""
    if name not in _REGISTRY:
        raise KeyError(f"unknown audio feature extractor {name!r}; available: {', '.join(available_extractors())}")
    cls = _REGISTRY[name]
    known = {f.name for f in fields(cls.config_type)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise TypeError(f"{name}: unknown config option(s) {unknown}; known: {sorted(known)}")
    return cls(cls.config_type(**overrides))

