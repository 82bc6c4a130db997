"""Running moments of (N, D) samples, merged exactly (Chan et al.'s pairwise update).

Used for the shards' normalization statistics (per-channel variance: ``full=False``) and for the
Fréchet distances of the evaluation (the full covariance: ``full=True``). Both accumulate piece
by piece in float64 and merge in a fixed order, so results do not depend on how the work was
split, and no raw sum of squares is formed (which would cancel catastrophically).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Moments:
    """Count, mean and centred scatter: per-channel sums of squared deviations (D,), or with
    ``full`` the (D, D) scatter matrix."""

    count: int = 0
    mean: np.ndarray | None = None
    scatter: np.ndarray | None = None
    full: bool = False

    def add(self, samples: np.ndarray) -> None:
        x = np.array(samples, np.float64).reshape(len(samples), -1)  # a copy: centred in place
        if not len(x):
            return
        mean = x.mean(axis=0)
        x -= mean
        scatter = x.T @ x if self.full else np.einsum("ij,ij->j", x, x)
        self.merge(Moments(len(x), mean, scatter, self.full))

    def merge(self, other: "Moments") -> None:
        """As if ``other``'s samples had been added here."""
        if other.count == 0:
            return
        if self.count == 0:
            self.count, self.mean, self.scatter = other.count, other.mean.copy(), other.scatter.copy()
            return
        if other.mean.shape != self.mean.shape:
            raise ValueError(f"channel count changed from {self.mean.shape[0]} to "
                             f"{other.mean.shape[0]}")
        total = self.count + other.count
        delta = other.mean - self.mean
        self.mean = self.mean + delta * (other.count / total)
        spread = np.outer(delta, delta) if self.full else delta ** 2
        self.scatter = self.scatter + other.scatter + spread * (self.count * other.count / total)
        self.count = total

    @property
    def covariance(self) -> np.ndarray:
        """Sample covariance (N - 1 in the denominator); per channel unless ``full``."""
        return self.scatter / (self.count - 1)

    def mean_std(self, epsilon: float) -> tuple[np.ndarray, np.ndarray]:
        """float32 mean and population standard deviation, the latter floored at ``epsilon``."""
        std = np.sqrt(self.scatter / self.count)
        return self.mean.astype(np.float32), np.maximum(std, epsilon).astype(np.float32)
