"""The evaluated windows of a split, and every method's clips produced lazily from them."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from sarah_data.constants import FPS
from sarah_data.skeleton import MotionLayout

from .metrics import Clip


def select_windows(available: int, requested: int) -> np.ndarray:
    """Indices of the evaluated windows: all of them, or ``requested`` evenly spaced ones."""
    if available <= requested:
        return np.arange(available, dtype=np.int64)
    return np.unique(np.round(np.linspace(0, available - 1, requested)).astype(np.int64))


class TestWindows:
    """The evaluated windows of a split, read on demand (the last two items are cached: the
    metrics read a method's clip and its ground truth one after the other)."""

    def __init__(self, dataset, indices: np.ndarray) -> None:
        self.dataset, self.indices = dataset, np.asarray(indices, np.int64)
        self._cache: dict[int, dict] = {}

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> dict:
        i = int(i)
        if i not in self._cache:
            if len(self._cache) >= 2:
                self._cache.pop(next(iter(self._cache)))
            self._cache[i] = self.dataset[int(self.indices[i])]
        return self._cache[i]


def motion_clip(motion, user_head) -> Clip:
    """A metrics Clip from a (T, Dx) motion vector (icosahedra then shell) and (T, 2) user head."""
    motion = np.asarray(motion.numpy() if hasattr(motion, "numpy") else motion, np.float32)
    ico, shell = MotionLayout.from_width(motion.shape[-1]).split(motion)
    head = user_head.numpy() if hasattr(user_head, "numpy") else user_head
    return Clip(ico, shell, np.asarray(head, np.float32), fps=FPS)


class MethodClips:
    """Lazily produced clips of one method: clip i = ``produce(window i, i)`` scored against
    window i's user head. Seconds per window are recorded in ``seconds``."""

    def __init__(self, windows: TestWindows, produce: Callable[[dict, int], np.ndarray],
                 progress=None) -> None:
        self.windows, self.produce, self.progress = windows, produce, progress
        self.seconds: list[float] = []
        self._last: tuple[int, Clip] | None = None

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, i: int) -> Clip:
        if self._last is not None and self._last[0] == i:
            return self._last[1]
        item = self.windows[i]
        tick = time.perf_counter()
        motion = self.produce(item, i)
        self.seconds.append(time.perf_counter() - tick)
        clip = motion_clip(motion, item["user_head"])
        self._last = (i, clip)
        if self.progress is not None:
            self.progress.update(1)
        return clip


def gt_clips(windows: TestWindows) -> MethodClips:
    return MethodClips(windows, lambda item, _: item["motion"])
