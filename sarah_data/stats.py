"""Normalization statistics of the training split, in `shards/stats.h5`.

Per channel mean and standard deviation of what models see: the flattened window-normalized
agent motion (the Dataset's `motion`), the window-normalized user head trajectory, and each audio
extractor's features; and of every bone's length (`bone_length`, metres, in
`MotionLayout.bones` order), the skeleton a rigid decoding holds generated bones to
(`sarah_models.sampling.rigid_skeleton`). Computed from the train split only, over every frame where both persons are
tracked (the frames training windows are drawn from):

- sequences in name order, each person as agent in turn (the partner as user);
- window normalization relative to deterministic window starts: each run of both-tracked frames
  is cut into consecutive windows of `window` frames from the run's first frame (the last one
  shorter), each normalized to the agent's root at its own first frame;
- audio features of each person over the same frames, pooled per extractor (they serve as both
  agent and user audio);
- population statistics accumulated in float64 (Chan's pairwise update): window by window
  within a sequence (`sequence_moments`, which prep runs in its workers), then sequence by
  sequence in name order (`merge_moments`); std floored at `epsilon` so constant channels
  standardize to 0 instead of dividing by zero.

The same shards give byte-identical `stats.h5`.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path

import h5py
import numpy as np

from sarah_data.constants import JOINT_NAMES, READABLE_SCHEMA_VERSIONS, SHARD_SCHEMA_VERSION
from sarah_data.moments import Moments
from sarah_data.dataset import DEFAULT_WINDOW, normalize_window, tracked_runs
from sarah_data.skeleton import MotionLayout, bone_lengths
from sarah_data.shards import (MANIFEST_NAME, STATS_NAME, ShardError, ShardSet, atomic_h5, create_dataset,
                               create_group, read_manifest)

log = logging.getLogger(__name__)

STD_EPSILON = 1e-4  # metres for motion and head; feature units for audio
STATS_SPLIT = "train"


def sequence_moments(persons: list[Mapping], extractors: list[str], window: int = DEFAULT_WINDOW,
                     joint_names: Sequence[str] = JOINT_NAMES) -> dict[str, Moments]:
    """One sequence's contribution to the statistics: `persons` are its two persons' arrays
    (`icosahedra`, `shell`, `head`, `valid`, `root_position`, `root_rotation`, and `audio`, a
    mapping extractor -> (T, D)), as numpy arrays or h5py datasets; `joint_names` those of the
    icosahedra (the shards' attribute)."""
    moments = {"motion": Moments(), "user_head": Moments(), "bone_length": Moments()}
    moments.update({f"audio/{name}": Moments() for name in extractors})
    bones = MotionLayout(tuple(joint_names)).bones
    runs = tracked_runs(np.logical_and(*(np.asarray(p["valid"][()], bool) for p in persons)))
    for agent, user in ((persons[0], persons[1]), (persons[1], persons[0])):
        for run_start, run_stop in runs:
            for start in range(run_start, run_stop, window):
                frames = slice(start, min(start + window, run_stop))
                motion, head, _ = normalize_window(
                    agent["icosahedra"][frames], agent["shell"][frames], user["head"][frames],
                    agent["root_position"][start], agent["root_rotation"][start])
                moments["motion"].add(motion)
                moments["user_head"].add(head)
            if bones:
                joints = np.asarray(agent["icosahedra"][run_start:run_stop], np.float64).mean(axis=-2)
                moments["bone_length"].add(bone_lengths(joints, bones))
            audio = agent.get("audio", {})
            for extractor in extractors:
                if extractor in audio:
                    moments[f"audio/{extractor}"].add(audio[extractor][run_start:run_stop])
    return moments


def merge_moments(parts: list[dict[str, Moments]], extractors: list[str]) -> dict[str, Moments]:
    """The sequences' moments combined in the order given (prep and compute_stats: name order)."""
    total = {"motion": Moments(), "user_head": Moments(), "bone_length": Moments()}
    total.update({f"audio/{name}": Moments() for name in extractors})
    for part in parts:
        for key, value in part.items():
            total[key].merge(value)
    return total


def write_moments(group: h5py.Group, moments: dict[str, Moments]) -> None:
    """Moments as plain float64 datasets (a work file's, exact), for `read_moments`."""
    for key, value in moments.items():
        if value.count:
            sub = group.create_group(key)
            sub.attrs["count"] = np.int64(value.count)
            sub["mean"], sub["m2"] = value.mean, value.scatter


def read_moments(group: h5py.Group) -> dict[str, Moments]:
    found: dict[str, Moments] = {}
    group.visititems(lambda key, obj: found.__setitem__(key, Moments(
        int(obj.attrs["count"]), obj["mean"][()], obj["m2"][()])) if "count" in obj.attrs else None)
    return found


def compute_stats(shards_dir: Path | str, window: int = DEFAULT_WINDOW,
                  epsilon: float = STD_EPSILON) -> dict[str, np.ndarray]:
    """Compute the train-split statistics, write `<shards_dir>/stats.h5`, return `load_stats`'s dict.

    Needs the manifest (prep writes stats after the shards and the manifest).
    """
    shards = ShardSet(shards_dir)
    try:
        extractors = sorted(shards.attrs.extractors) if shards.manifest.shards else []
        names = shards.sequences(STATS_SPLIT)
        parts = [sequence_moments(_persons(shards.group(name)), extractors, window,
                                  shards.attrs.joint_names) for name in names]
    finally:
        shards.close()
    return write_stats(shards_dir, merge_moments(parts, extractors), len(names), window, epsilon)


def _persons(group: h5py.Group) -> list[dict]:
    persons = [group[str(p)] for p in group.attrs["persons"]]
    return [{**{key: p[key][()] for key in p if key != "audio"},
             "audio": {k: v[()] for k, v in p["audio"].items()} if "audio" in p else {}}
            for p in persons]


def write_stats(shards_dir: Path | str, moments: dict[str, Moments], sequences: int,
                window: int = DEFAULT_WINDOW, epsilon: float = STD_EPSILON) -> dict[str, np.ndarray]:
    """Write `<shards_dir>/stats.h5` from the train split's merged moments (the manifest lists the
    train files recorded in it); returns `load_stats`'s dict."""
    if moments["motion"].count == 0:
        raise ShardError(Path(shards_dir), f"no tracked frames in the {STATS_SPLIT} split to "
                                           "compute normalization statistics from")
    manifest = read_manifest(Path(shards_dir) / MANIFEST_NAME)
    train_files = sorted((s.file, s.sha256) for s in manifest.shards if s.split == STATS_SPLIT)
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
            mean, std = acc.mean_std(epsilon)
            create_dataset(group, "mean", mean)
            create_dataset(group, "std", std)
    return load_stats(shards_dir)


def load_stats(shards_dir: Path | str) -> dict[str, np.ndarray]:
    """`{"motion/mean", "motion/std", "user_head/mean", "user_head/std",
    "audio/<extractor>/mean", "audio/<extractor>/std", "bone_length/mean", "bone_length/std"}`
    -> float32 (D,) arrays (no bone lengths in files written before they were added)."""
    path = Path(shards_dir) / STATS_NAME
    if not path.is_file():
        raise ShardError(path, "no normalization statistics (run sarah-prep, which writes them)")
    stats: dict[str, np.ndarray] = {}
    try:
        with h5py.File(path, "r") as handle:
            if int(handle.attrs.get("schema_version", -1)) not in READABLE_SCHEMA_VERSIONS:
                raise ShardError(path, f"schema version {handle.attrs.get('schema_version')}, "
                                       f"expected one of {READABLE_SCHEMA_VERSIONS}")
            handle.visititems(lambda key, obj: stats.__setitem__(key, obj[()])
                              if isinstance(obj, h5py.Dataset) else None)
    except OSError as error:
        raise ShardError(path, f"unreadable statistics file: {error}") from None
    for key in ("motion/mean", "motion/std", "user_head/mean", "user_head/std"):
        if key not in stats:
            raise ShardError(path, f"missing dataset {key}")
    return dict(sorted(stats.items()))
