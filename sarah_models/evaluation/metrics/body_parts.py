"""FGD_acc by body part: the Fréchet distance of the shell's accelerations over the points of one
part of the body at a time, and each part's acceleration energy against the ground truth's.

FGD_acc scores the whole shell at once. On the fixture benchmark three quarters of a model's
distance sat in its legs (docs/results.md, fifty-fifth run), which the whole-shell figure cannot
say, and a part's distance means little without Random's and the real-vs-real floor's for the
same part beside it. ``table.evaluate`` scores the parts with FGD_acc's own samples, batches,
pooling and intervals; this module names their values and slices their samples.

A shell point belongs to the joint group (``sarah_data.skeleton.JOINT_GROUPS``) of the joint it
lies nearest to in one reference frame (``sarah_data.skeleton.shell_parts``): ``sarah-eval``
takes the first test window's ground truth, so every method scored against the same windows
splits the shell alike (a Fréchet distance needs the same points in every clip).
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

SCORED_METRIC = "fgd_acc"  # the registered Fréchet metric whose per-point samples parts slice


def part_key(part: str) -> str:
    """The key of a part's values in a ``MetricsTable`` ("fgd_acc@legs")."""
    return f"{SCORED_METRIC}@{part}"


def part_samples(samples: np.ndarray, parts: Mapping[str, Sequence[int]]) -> dict[str, np.ndarray]:
    """Per-frame samples of every shell point (N, V*3) -> each part's columns (N, 3 * points)."""
    points = samples.reshape(len(samples), -1, 3)
    return {part: points[:, list(indices)].reshape(len(samples), -1)
            for part, indices in parts.items()}


def energy(samples: np.ndarray) -> float:
    """Mean squared magnitude per frame of (N, D) samples: a part's acceleration energy."""
    return float(np.sum(samples ** 2) / len(samples))
