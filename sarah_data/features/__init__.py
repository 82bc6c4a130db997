"""Audio features per motion frame: a registry of named extractors (see ``base``).

``logmel`` (default, no weights) and ``hubert-large`` (the paper's; local weights only).
"""

from sarah_data.features.base import (
    AudioFeatureExtractor,
    FeatureStream,
    available_extractors,
    fit_to_frames,
    get_extractor,
    register_extractor,
)
from sarah_data.features.hubert import HubertConfig, HubertExtractor, MissingWeightsError
from sarah_data.features.logmel import LogMelConfig, LogMelExtractor

__all__ = [
    "AudioFeatureExtractor",
    "FeatureStream",
    "HubertConfig",
    "HubertExtractor",
    "LogMelConfig",
    "LogMelExtractor",
    "MissingWeightsError",
    "available_extractors",
    "fit_to_frames",
    "get_extractor",
    "register_extractor",
]
