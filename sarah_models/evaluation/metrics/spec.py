"""What a metric is, the registry of them, and the evaluation settings they read.

A metric is one ``Metric`` in one file of this folder (its module sets ``METRIC``); the registry
finds them all, in ``order``. Two kinds:

* ``"frechet"``: ``function(clip, config)`` returns per-frame samples (N, D) in metres; the
  score is a Fréchet distance between generated and ground-truth samples (``table.py``).
* ``"clip"``: ``function(clip, config)`` returns one value per generated clip; the score is
  their mean (Avg) and the means over speaking (S) and non-speaking (NS) clips.

Raw values are in metres and seconds; ``length_power`` says how a value scales with the length
unit (FGD: m^2 -> cm^2 is a factor 1e4), and tables show ``raw / scale`` with ``decimals``.
"""

from __future__ import annotations

import functools
import importlib
import pkgutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

from sarah_data.skeleton import FEET, HEAD, ROOT, WRISTS

from ...config import STRIDE


ARROWS = {"lower": "↓", "higher": "↑", "gt": "≈GT"}
FOOT_MAX_HEIGHT = 0.05  # m: "near the ground (<5 cm)" (paper, foot slide)
FOOT_MIN_SPEED = 0.03  # m/s: "moving horizontally (>3 cm/s)"


@dataclass(frozen=True)
class Metric:
    name: str  # key in tables and JSON ("fgd")
    label: str  # column header ("FGD")
    kind: str  # "frechet" or "clip"
    function: Callable[[Any, "MetricsConfig"], Any]
    order: int  # column position
    unit: str  # with "{u}" for the length unit: "{u}^2", "{u}/s", "fraction of frame steps"
    length_power: int = 0  # raw value ~ length^power
    scale: float = 1.0  # tables show raw / scale ("FGD (x10^1)")
    decimals: int = 2
    better: str = "lower"  # "lower", "higher" or "gt" (closest to GT's): the table's arrow
    value_range: str = ""  # shown in the header, e.g. " ∈ [0, 1]"
    window_frame: bool = False  # defined for clips in their window frame only (not world clips)
    # A per-clip magnitude that reads as a share of GT's ("wrists at 1.2x GT's speed"); others
    # are compared to GT by difference only (GT's bone-length error or frame-0 offset is ~0).
    ratio_to_gt: bool = False

    def __post_init__(self) -> None:
        if self.kind not in ("frechet", "clip"):
            raise ValueError(f"metric {self.name}: kind must be 'frechet' or 'clip', got {self.kind!r}")
        if self.better not in ARROWS:
            raise ValueError(f"metric {self.name}: better must be one of {sorted(ARROWS)}")

    @property
    def arrow(self) -> str:
        return ARROWS[self.better]


@functools.cache
def registered() -> tuple[Metric, ...]:
    """Every metric of this folder (a module with a ``METRIC``), in ``order``."""
    found = []
    for info in pkgutil.iter_modules([str(Path(__file__).parent)]):
        metric = getattr(importlib.import_module(f"{__package__}.{info.name}"), "METRIC", None)
        if isinstance(metric, Metric):
            found.append(metric)
    return tuple(sorted(found, key=lambda m: m.order))


def unit_name(report_unit: float) -> str:
    return {0.01: "cm", 1.0: "m", 0.001: "mm"}.get(report_unit, f"{report_unit} m")


@dataclass(frozen=True)
class MetricsConfig:
    """Evaluation settings; defaults are the paper's values where it states them."""

    # Clips per batch for the FGD / FGD_acc Avg column. The paper does not state it; 16 is its
    # per-GPU batch size, and its remark that a batch may hold "too few clips of one category"
    # implies batches of this order.
    batch_clips: int = 16
    foot_max_height: float = FOOT_MAX_HEIGHT
    foot_min_speed: float = FOOT_MIN_SPEED
    foot_joints: tuple[str, ...] = FEET
    wrist_joints: tuple[str, ...] = WRISTS
    head_joint: str = HEAD
    root_joint: str = ROOT
    # Frames per latent block, where the seam share looks for seams: the VAE's stride.
    block_frames: int = STRIDE
    # Re-normalize every clip to its window frame (agent's pelvis at frame 0 at the origin facing
    # +z) before FGD, so world-frame clips score like window-frame ones. Idempotent on clips that
    # are already in the window frame.
    normalize_window: bool = True
    report_unit: float = 0.01  # metres per reported length unit: centimetres
    fd_ridge: float = 1e-6  # relative ridge for ill-conditioned covariances (frechet.py)
    # The pooled Fréchet distances' 95 % interval: a delete-one-group jackknife over this many
    # groups of consecutive clips (windows of one sequence stay together), one more distance
    # per group and metric. 0: no interval. A bootstrap would need a distance per draw, and at
    # 768 dimensions each takes ~0.8 s. Each group keeps a full covariance per metric and side:
    # ~0.57 GB at 20 groups of 768-dimensional samples, whatever the number of clips.
    pooled_groups: int = 20
    # FGD_acc by body part as well (``body_parts``): each part's shell point indices, e.g.
    # ``body_parts.shell_parts`` of one ground-truth frame. None: the whole shell only.
    shell_parts: Mapping[str, tuple[int, ...]] | None = None
    display_scale: dict[str, float] = field(
        default_factory=lambda: {m.name: m.scale for m in registered()})
