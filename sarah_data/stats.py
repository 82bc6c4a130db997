"""Normalization statistics of the training split, in `shards/stats.h5`.

Per channel mean and standard deviation of what models see: the flattened window-normalized
agent motion (the Dataset's `motion`), the window-normalized user head trajectory, and each audio
extractor's features. Computed from the train split only, over every frame where both persons are
tracked (the frames training windows are drawn from):

- sequences in name order, each person as agent in turn (the partner as user);
- window normalization relative to deterministic window starts: each run of both-tracked frames
  is cut into consecutive windows of `window` frames from the run's first frame (the last one
  shorter), each normalized to the agent's root at its own first frame;
- audio features of each person over the same frames, pooled per extractor (they serve as both
  agent and user audio);
- population statistics accumulated in float64 (Chan's pairwise update), std floored at
  `epsilon` so constant channels standardize to 0 instead of dividing by zero.

The same shards give byte-identical `stats.h5`.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import h5py
import numpy as np

from sarah_data.constants import SHARD_SCHEMA_VERSION
from sarah_data.dataset import DEFAULT_WINDOW, normalize_window, tracked_runs
from sarah_data.shards import STATS_NAME, ShardError, ShardSet, atomic_h5, create_dataset, create_group

log = logging.getLogger(__name__)

STD_EPSILON = 1e-4  # metres for motion and head; feature units for audio
STATS_SPLIT = "train"


class _Moments:
    """Running per-channel count, mean and sum of squared deviations."""

    def __init__(self) -> None:
        self.count = 0
        self.mean: np.ndarray | None = None
        self.m2: np.ndarray | None = None

    def add(self, x: np.ndarray) -> None:
        x = np.asarray(x, np.float64).reshape(len(x), -1)
        if len(x) == 0:
            return
        batch_mean = x.mean(axis=0)
        batch_m2 = ((x - batch_mean) ** 2).sum(axis=0)
        if self.mean is None:
            self.count, self.mean, self.m2 = len(x), batch_mean, batch_m2
            return
        if x.shape[1] != self.mean.shape[0]:
            raise ValueError(f"channel count changed from {self.mean.shape[0]} to {x.shape[1]}")
        total = self.count + len(x)
        delta = batch_mean - self.mean
        self.mean = self.mean + delta * (len(x) / total)
        self.m2 = self.m2 + batch_m2 + delta ** 2 * (self.count * len(x) / total)
        self.count = total

    def result(self, epsilon: float) -> tuple[np.ndarray, np.ndarray]:
        std = np.sqrt(self.m2 / self.count)
        return self.mean.astype(np.float32), np.maximum(std, epsilon).astype(np.float32)


def compute_stats(shards_dir: Path | str, window: int = DEFAULT_WINDOW,
                  epsilon: float = STD_EPSILON) -> dict[str, np.ndarray]:
    """Compute the train-split statistics, write `<shards_dir>/stats.h5`, return `load_stats`'s dict.

    Needs the manifest (prep writes stats after the shards and the manifest).
    """
    shards = ShardSet(shards_dir)
    try:
        moments, sequences = _accumulate(shards, window)
        train_files = sorted((s.file, s.sha256) for s in shards.manifest.shards
                             if s.split == STATS_SPLIT)
    finally:
        shards.close()
    if moments["motion"].count == 0:
        raise ShardError(Path(shards_dir), f"no tracked frames in the {STATS_SPLIT} split to "
                                           "compute normalization statistics from")
    path = Path(shards_dir) / STATS_NAME
    with atomic_h5(path) as handle:
        handle.attrs["schema_version"] = np.int64(SHARD_SCHEMA_VERSION)
        handle.attrs["split"] = STATS_SPLIT
        handle.attrs["window"] = np.int64(window)
        handle.attrs["epsilon"] = np.float64(epsilon)
        handle.attrs["sequences"] = np.int64(sequences)
        handle.attrs["shards"] = json.dumps([{"file": f, "sha256": h} for f, h in train_files])
        for key, acc in moments.items():
            if acc.count == 0:
                log.warning("no %s split frames with %s: no statistics for it", STATS_SPLIT, key)
                continue
            group = handle
            for part in key.split("/"):
                group = group[part] if part in group else create_group(group, part)
            group.attrs["count"] = np.int64(acc.count)
            mean, std = acc.result(epsilon)
            create_dataset(group, "mean", mean)
            create_dataset(group, "std", std)
    return load_stats(shards_dir)


def _accumulate(shards: ShardSet, window: int) -> tuple[dict[str, _Moments], int]:
    extractors = sorted(shards.attrs.extractors) if shards.manifest.shards else []
    moments = {"motion": _Moments(), "user_head": _Moments()}
    moments.update({f"audio/{name}": _Moments() for name in extractors})
    names = shards.sequences(STATS_SPLIT)
    for name in names:
        group = shards.group(name)
        persons = [group[str(p)] for p in group.attrs["persons"]]
        both = np.logical_and(*(p["valid"][()].astype(bool) for p in persons))
        runs = tracked_runs(both)
        for agent, user in ((persons[0], persons[1]), (persons[1], persons[0])):
            for run_start, run_stop in runs:
                for start in range(run_start, run_stop, window):
                    frames = slice(start, min(start + window, run_stop))
                    motion, head, _ = normalize_window(
                        agent["icosahedra"][frames], agent["shell"][frames], user["head"][frames],
                        agent["root_position"][start], agent["root_rotation"][start])
                    moments["motion"].add(motion)
                    moments["user_head"].add(head)
                for extractor in extractors:
                    if "audio" in agent and extractor in agent["audio"]:
                        moments[f"audio/{extractor}"].add(agent["audio"][extractor][run_start:run_stop])
    return moments, len(names)


def load_stats(shards_dir: Path | str) -> dict[str, np.ndarray]:
    """`{"motion/mean", "motion/std", "user_head/mean", "user_head/std",
    "audio/<extractor>/mean", "audio/<extractor>/std"}` -> float32 (D,) arrays."""
    path = Path(shards_dir) / STATS_NAME
    if not path.is_file():
        raise ShardError(path, "no normalization statistics (run sarah-prep, which writes them)")
    stats: dict[str, np.ndarray] = {}
    try:
        with h5py.File(path, "r") as handle:
            if int(handle.attrs.get("schema_version", -1)) != SHARD_SCHEMA_VERSION:
                raise ShardError(path, f"schema version {handle.attrs.get('schema_version')}, "
                                       f"expected {SHARD_SCHEMA_VERSION}")
            handle.visititems(lambda key, obj: stats.__setitem__(key, obj[()])
                              if isinstance(obj, h5py.Dataset) else None)
    except OSError as error:
        raise ShardError(path, f"unreadable statistics file: {error}") from None
    for key in ("motion/mean", "motion/std", "user_head/mean", "user_head/std"):
        if key not in stats:
            raise ShardError(path, f"missing dataset {key}")
    return dict(sorted(stats.items()))
