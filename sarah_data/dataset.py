"""Training and evaluation windows over a shards folder, as a torch Dataset.

Each item is one window of T frames in which both persons are tracked, with one person as the
agent (whose motion is generated) and the other as the user (whose head trajectory and audio
condition it). Everything spatial is put in the window frame: the agent's pelvis at the window's
first frame at the origin, facing +z (sarah_data/frames.py). Items follow the contract in
docs/architecture.md.

Two ways to choose windows (paper A.2):
- random (training): item i is the (sequence, agent) pair i mod P, P = the number of pairs (so
  every sequence is drawn equally often, whatever its length), at a start drawn uniformly from
  that pair's all-tracked window starts by `default_rng((seed, epoch, i))` -- reproducible, new
  windows each epoch via `set_epoch`.
- sliding (evaluation, `WindowDataset.sliding` or `deterministic=True`): non-overlapping windows
  tiled from the start of every run of both-tracked frames, each with either person as agent.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from sarah_data.frames import window_transform
from sarah_data.shards import ShardSet

log = logging.getLogger(__name__)

DEFAULT_WINDOW = 400  # frames (paper: T = 400 at 30 fps)
DEFAULT_CACHE_BYTES = 2 << 30  # per process; a split that fits is read once, then sliced
_PER_PERSON = ("icosahedra", "shell", "head", "gaze", "speaking", "root_position", "root_rotation")


def motion_vector(icosahedra: np.ndarray, shell: np.ndarray) -> np.ndarray:
    """(T,J,12,3) icosahedra and (T,V,3) shell -> (T, J*12*3 + V*3), the flattened motion."""
    frames = icosahedra.shape[0]
    return np.concatenate([icosahedra.reshape(frames, -1), shell.reshape(frames, -1)], axis=1)


def normalize_window(icosahedra: np.ndarray, shell: np.ndarray, user_head: np.ndarray,
                     root_position: np.ndarray, root_rotation: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Agent motion and user head trajectory in the frame of the agent's root at frame 0.

    `root_position (3,)` and `root_rotation (3,3)` are the agent's pelvis at the window's first
    frame. Returns motion (T, D) float32, user_head (T, 2) float32 and the transform (4,)
    [yaw, x, z, 0] that maps world to window coordinates.
    """
    transform = window_transform(root_position, root_rotation)
    frames, joint_points = icosahedra.shape[0], icosahedra.shape[1] * icosahedra.shape[2]
    # Both rotate straight into one (T, J*12 + V, 3) buffer whose flat view is the motion vector.
    points = np.empty((frames, joint_points + shell.shape[1], 3), np.float32)
    transform.apply_points(icosahedra.reshape(frames, joint_points, 3), out=points[:, :joint_points])
    transform.apply_points(shell, out=points[:, joint_points:])
    return (points.reshape(frames, -1), transform.apply_floor(user_head).astype(np.float32),
            transform.as_array())


def tracked_runs(valid: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of every maximal run of True in a boolean mask."""
    padded = np.concatenate([[False], np.asarray(valid, bool), [False]])
    edges = np.flatnonzero(padded[1:] != padded[:-1])
    return [(int(a), int(b)) for a, b in zip(edges[0::2], edges[1::2])]


def valid_starts(valid: np.ndarray, window: int) -> np.ndarray:
    """Every start s with valid[s:s+window] all True (int64, ascending)."""
    valid = np.asarray(valid, bool)
    if valid.size < window:
        return np.zeros(0, np.int64)
    counts = np.concatenate([[0], np.cumsum(valid, dtype=np.int64)])
    sums = counts[window:] - counts[:-window]
    return np.flatnonzero(sums == window).astype(np.int64)


def sliding_starts(valid: np.ndarray, window: int) -> np.ndarray:
    """Non-overlapping full windows tiled from the start of each tracked run."""
    starts = [np.arange(a, b - window + 1, window) for a, b in tracked_runs(valid)]
    return np.concatenate(starts).astype(np.int64) if starts else np.zeros(0, np.int64)


class WindowDataset(torch.utils.data.Dataset):
    """Windows of `window` frames from one split of a shards folder; see the module docstring.

    `extractor` names the audio features returned as `agent_audio`/`user_audio`; sequences
    without them are skipped (None returns no audio and keeps them, e.g. for the motion VAE).
    `length` sets the number of items per epoch in random mode (default: one per pair).
    Sequences without a single all-tracked window are skipped; `skipped` lists (sequence, reason).
    `motion_dim` (J*12*3 + V*3) and `audio_dim` (D, None without audio) size the models.

    When the split's arrays fit in `cache_bytes` (decompressed), each process reads every
    sequence once and serves windows as slices of memory; a larger split is read window by window
    from the compressed chunks (a cache smaller than the data would thrash on random windows).
    """

    def __init__(self, shards_dir: Path | str, split: str, extractor: str | None = "logmel",
                 window: int = DEFAULT_WINDOW, seed: int = 0, length: int | None = None,
                 deterministic: bool = False, cache_bytes: int = DEFAULT_CACHE_BYTES):
        if window < 1:
            raise ValueError(f"window must be positive, got {window}")
        self.shards = ShardSet(shards_dir)
        self.split = split
        self.extractor = extractor
        self.window = int(window)
        self.seed = int(seed)
        self.deterministic = deterministic
        self.epoch = 0
        self.skipped: list[tuple[str, str]] = []
        self.audio_dim: int | None = None
        # (sequence, agent person index, valid window starts) per usable pair
        self.pairs: list[tuple[str, int, np.ndarray]] = []
        self._split_bytes = 0
        self._cache: dict[str, dict[str, dict[str, np.ndarray]]] = {}
        try:
            self._index_sequences()
            attrs = self.shards.attrs if self.shards.manifest.shards else None
            self.motion_dim = (len(attrs.joint_names) * 12 * 3 + len(attrs.shell_vertex_ids) * 3
                               if attrs else None)
        finally:
            self.shards.close()  # no open file may cross into DataLoader workers
        if deterministic:
            if length is not None:
                raise ValueError("length applies to random windows, not to sliding windows")
            # (pair index, start) per item, ordered by sequence, then start, then agent
            items = [(p, int(s)) for p, (_, _, starts) in enumerate(self.pairs) for s in starts]
            self.items = sorted(items, key=lambda item: (self.pairs[item[0]][0], item[1],
                                                         self.pairs[item[0]][1]))
            self.length = len(self.items)
        else:
            self.length = len(self.pairs) if length is None else int(length)
            if self.length and not self.pairs:
                raise ValueError(f"split {split!r} of {shards_dir} has no usable window of "
                                 f"{window} frames: {self.skipped}")
        if not self.pairs:
            log.warning("split %r of %s has no usable window of %d frames", split, shards_dir, window)
        self.in_memory = self._split_bytes <= cache_bytes

    @classmethod
    def sliding(cls, shards_dir: Path | str, split: str, extractor: str | None = "logmel",
                window: int = DEFAULT_WINDOW) -> "WindowDataset":
        """Evaluation windows: non-overlapping, fixed, every agent (paper A.2)."""
        return cls(shards_dir, split, extractor=extractor, window=window, deterministic=True)

    def _index_sequences(self) -> None:
        for name in self.shards.sequences(self.split):
            group = self.shards.group(name)
            persons = [str(p) for p in group.attrs["persons"]]
            reason = None
            if self.extractor is not None and any(
                    "audio" not in group[p] or self.extractor not in group[p]["audio"] for p in persons):
                reason = f"no audio features {self.extractor!r}"
            else:
                both = np.logical_and(*(group[p]["valid"][()].astype(bool) for p in persons))
                starts = (sliding_starts if self.deterministic else valid_starts)(both, self.window)
                if starts.size == 0:
                    longest = max((b - a for a, b in tracked_runs(both)), default=0)
                    reason = (f"no window of {self.window} frames with both persons tracked "
                              f"(longest tracked run {longest} of {both.size} frames)")
            if reason is not None:
                log.warning("skipping sequence %s: %s", name, reason)
                self.skipped.append((name, reason))
                continue
            if self.extractor is not None:
                self.audio_dim = int(group[persons[0]]["audio"][self.extractor].shape[1])
            self._split_bytes += sum(group[p][key].size * group[p][key].dtype.itemsize
                                     for p in persons for key in self._keys())
            for agent in range(len(persons)):
                self.pairs.append((name, agent, starts))

    def set_epoch(self, epoch: int) -> None:
        """Draw new random windows (set before creating the DataLoader iterator of the epoch)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.length

    def locate(self, index: int) -> tuple[str, int, int]:
        """(sequence, agent person index, start frame) of item `index`."""
        if not 0 <= index < self.length:
            raise IndexError(f"index {index} out of range for {self.length} windows")
        if self.deterministic:
            pair, start = self.items[index]
            return self.pairs[pair][0], self.pairs[pair][1], start
        name, agent, starts = self.pairs[index % len(self.pairs)]
        rng = np.random.default_rng((self.seed, self.epoch, index))
        return name, agent, int(starts[rng.integers(starts.size)])

    def _keys(self) -> tuple[str, ...]:
        return _PER_PERSON + ((f"audio/{self.extractor}",) if self.extractor is not None else ())

    def _arrays(self, name: str) -> dict[str, dict]:
        """The sequence's per-person datasets: h5py datasets, or arrays read once into memory."""
        group = self.shards.group(name)
        if not self.in_memory:
            return {p: {key: group[p][key] for key in self._keys()} for p in group.attrs["persons"]}
        if name not in self._cache:
            self._cache[name] = {p: {key: group[p][key][()] for key in self._keys()}
                                 for p in group.attrs["persons"]}
        return self._cache[name]

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_cache"] = {}  # each worker fills its own
        return state

    def __getitem__(self, index: int) -> dict:
        name, agent, start = self.locate(int(index))
        persons = self.shards.entry(name).persons  # verify checks they match the file's
        arrays = self._arrays(name)
        a, u = arrays[persons[agent]], arrays[persons[1 - agent]]
        frames = slice(start, start + self.window)
        motion, user_head, transform = normalize_window(
            a["icosahedra"][frames], a["shell"][frames], u["head"][frames],
            a["root_position"][start], a["root_rotation"][start])
        item = {
            "motion": torch.from_numpy(motion),
            "user_head": torch.from_numpy(user_head),
            "gaze": torch.from_numpy(a["gaze"][frames].astype(np.float32)),
            "agent_speaking": torch.from_numpy(a["speaking"][frames].astype(np.float32)),
            "user_speaking": torch.from_numpy(u["speaking"][frames].astype(np.float32)),
            "transform": torch.from_numpy(transform),
            "sequence": name,
            "agent": persons[agent],
            "start": start,
        }
        if self.extractor is not None:
            key = f"audio/{self.extractor}"
            item["agent_audio"] = torch.from_numpy(a[key][frames].astype(np.float32))
            item["user_audio"] = torch.from_numpy(u[key][frames].astype(np.float32))
        return item
