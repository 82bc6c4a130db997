"""The configuration of `sarah-prep`: every field is a command-line flag and lands in the manifest."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from .icosahedron import DEFAULT_RADIUS
from .speaking import SpeakingConfig


@dataclass(frozen=True)
class PrepConfig:
    extractors: tuple[str, ...] = ("logmel",)  # the paper's is "hubert-large" (needs weights)
    hubert_weights: str | None = None  # a local HuBERT-Large weight file; never downloaded
    hubert_architecture: str = "large"  # "base" for HuBERT-Base weights (the paper: large)
    shell_points: int = 256  # mesh-shell vertices kept per frame
    icosahedron_radius: float = DEFAULT_RADIUS
    speaking: SpeakingConfig = field(default_factory=SpeakingConfig)
    split_seed: int = 0
    split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)  # paper A.2, by session
    max_shard_bytes: int = 1 << 30  # a shard file closes once it holds about this much
    device: str = "cpu"
    body_batch_frames: int = 4096  # frames per body-model batch (bounds memory, not results)

    def problems(self) -> list[str]:
        """What makes this configuration unusable, one line each, checked before any work
        starts (a bad setting used to surface per sequence, after all the work)."""
        from .features import available_extractors
        from .features.hubert import MissingWeightsError, default_weights_path, weight_file

        found = []
        known = available_extractors()
        if not self.extractors:
            found.append(f"--extractors: none given; choose from {', '.join(known)}")
        for name in self.extractors:
            if name not in known:
                found.append(f"--extractors: unknown extractor {name!r}; choose from "
                             f"{', '.join(known)}")
        if "hubert-large" in self.extractors:
            weights = Path(self.hubert_weights).expanduser() if self.hubert_weights else \
                default_weights_path(self.hubert_architecture)
            try:
                weights = weight_file(weights)
            except MissingWeightsError:
                pass
            if not weights.is_file():
                found.append(f"--hubert-weights: {weights}: no such file (hubert-large needs a "
                             f"local HuBERT checkpoint: torchaudio's .pth, fairseq's .pt or a "
                             f"Hugging Face folder; nothing is ever downloaded)")
            if self.hubert_architecture not in ("large", "base"):
                found.append(f"--hubert-architecture must be large or base, got {self.hubert_architecture!r}")
        if self.shell_points < 1:
            found.append(f"--shell-points must be at least 1, got {self.shell_points}")
        if self.max_shard_bytes <= 0:
            found.append(f"--max-shard-mb must be positive, got {self.max_shard_bytes / 2**20:g}")
        if len(self.split_fractions) != 3 or min(self.split_fractions) < 0 or \
                abs(sum(self.split_fractions) - 1.0) > 1e-9:
            found.append(f"split fractions must be three non-negative numbers summing to 1, got "
                         f"{self.split_fractions}")
        found += device_problems(self.device)
        return found

    def extractor_options(self, name: str) -> dict:
        if name != "hubert-large":
            return {}
        options = {"weights": self.hubert_weights} if self.hubert_weights else {}
        if self.hubert_architecture != "large":
            options["architecture"] = self.hubert_architecture
        return options


def device_problems(device: str) -> list[str]:
    """Why ``device`` cannot be used here ("cpu", "cuda" or "cuda:N"), or nothing."""
    import torch

    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError):
        return [f"--device: {device!r} is not a device; use cpu, cuda or cuda:N"]
    if parsed.type == "cuda":
        if not torch.cuda.is_available():
            return [f"--device {device}: no CUDA GPU is available here; use --device cpu"]
        if parsed.index is not None and parsed.index >= torch.cuda.device_count():
            return [f"--device {device}: this machine has {torch.cuda.device_count()} GPU(s)"]
    elif parsed.type != "cpu":
        return [f"--device {device}: use cpu, cuda or cuda:N"]
    return []
