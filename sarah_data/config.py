"""The configuration of `sarah-prep`: every field is a command-line flag and lands in the manifest."""

from __future__ import annotations

from dataclasses import dataclass, field

from .icosahedron import DEFAULT_RADIUS
from .speaking import SpeakingConfig


@dataclass(frozen=True)
class PrepConfig:
    extractors: tuple[str, ...] = ("logmel",)  # the paper's is "hubert-large" (needs weights)
    hubert_weights: str | None = None  # a local HuBERT-Large weight file; never downloaded
    shell_points: int = 256  # mesh-shell vertices kept per frame
    icosahedron_radius: float = DEFAULT_RADIUS
    speaking: SpeakingConfig = field(default_factory=SpeakingConfig)
    split_seed: int = 0
    split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)  # paper A.2, by session
    max_shard_bytes: int = 1 << 30  # a shard file closes once it holds about this much
    device: str = "cpu"
    body_batch_frames: int = 4096  # frames per body-model batch (bounds memory, not results)

    def extractor_options(self, name: str) -> dict:
        if name == "hubert-large" and self.hubert_weights:
            return {"weights": self.hubert_weights}
        return {}
