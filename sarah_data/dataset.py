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

import contextlib
import functools
import logging
import math
import weakref
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import default_collate

from sarah_data.frames import WindowTransform, window_transform
from sarah_data.shards import ShardSet
from sarah_data.skeleton import MotionLayout

log = logging.getLogger(__name__)

DEFAULT_WINDOW = 400  # frames (paper: T = 400 at 30 fps)
DEFAULT_CACHE_BYTES = 2 << 30  # per process; a split that fits is read once, then sliced
_PER_PERSON = ("icosahedra", "shell", "head", "gaze", "speaking", "root_position", "root_rotation")
_BATCH_BUFFERS: "weakref.WeakValueDictionary[int, torch.Tensor]" = weakref.WeakValueDictionary()


def homogeneous_points(icosahedra: np.ndarray, shell: np.ndarray) -> np.ndarray:
    """(T,J,12,3) icosahedra and (T,V,3) shell -> (T, J*12 + V, 4) float32 points [x, y, z, 1]:
    flattened per frame, the first three columns are the motion vector's layout, and the 1s let
    `WindowTransform.matrix()` rotate and translate a whole window in one matmul."""
    frames = icosahedra.shape[0]
    points = np.empty((frames, icosahedra.shape[1] * icosahedra.shape[2] + shell.shape[1], 4),
                      np.float32)
    points[:, :-shell.shape[1], :3] = icosahedra.reshape(frames, -1, 3)
    points[:, -shell.shape[1]:, :3] = shell
    points[..., 3] = 1.0
    return points


def window_motion(points: np.ndarray, transform: WindowTransform,
                  out: torch.Tensor | None = None) -> torch.Tensor:
    """Homogeneous world points (T, N, 4) -> the motion (T, N*3) float32 in the window frame.

    One float32 matmul writes the result straight into `out` (e.g. a row of a batch buffer): the
    window is the loader's biggest array, and every extra pass over it costs about a millisecond.
    The matmul is numpy's (OpenBLAS) on one thread: for this (N, 4) x (4, 3) shape torch's MKL
    sgemm took 3x as long on an AMD EPYC (2.4 against 0.8 ms per 400-frame window), and
    OpenBLAS's own threads, next to torch's or in forked loader workers, made it up to 10x slower
    (docs/performance.md).
    """
    frames = points.shape[0]
    out = torch.empty((frames, points.shape[1] * 3)) if out is None else out
    if not out.is_contiguous():
        raise ValueError("window_motion writes into a contiguous tensor only")
    matrix = transform.matrix().astype(np.float32)
    with _blas_threads().limit(limits=1, user_api="blas"):
        np.matmul(points.reshape(-1, 4), matrix, out=out.numpy().reshape(-1, 3))
    return out


def normalize_window(icosahedra: np.ndarray, shell: np.ndarray, user_head: np.ndarray,
                     root_position: np.ndarray, root_rotation: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Agent motion and user head trajectory in the frame of the agent's root at frame 0.

    `root_position (3,)` and `root_rotation (3,3)` are the agent's pelvis at the window's first
    frame. Returns motion (T, D) float32, user_head (T, 2) float32 and the transform (4,)
    [yaw, x, z, 0] that maps world to window coordinates. `WindowDataset` items equal this.
    """
    transform = window_transform(root_position, root_rotation)
    motion = window_motion(homogeneous_points(icosahedra, shell), transform)
    return (motion.numpy(), transform.apply_floor(user_head).astype(np.float32),
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

    When the split's arrays fit in `cache_bytes` (decompressed), the first item read in a process
    reads them all and windows are then served from memory (DataLoader workers forked after that
    share the parent's pages; a pickled copy, as spawned workers get, reads its own); a larger
    split is read window by window from the compressed chunks (a cache smaller than the data
    would thrash on random windows).

    A DataLoader fetches a batch with `__getitems__`, which writes the windows into one tensor
    per field; give it `collate_fn=collate_windows` to receive those tensors without a copy.
    Training uses `sarah_data.loader.WindowLoader` instead, whose workers refill a few batches
    allocated once with `fill`, the code `__getitems__` runs.
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
            self.motion_dim = MotionLayout.of_shards(attrs).width if attrs else None
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
            self._split_bytes += sum(_cached_bytes(group[p], self._keys()) for p in persons)
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
        """The sequence's per-person arrays: h5py datasets, or, when the split fits in memory,
        arrays read once, icosahedra and shell stored as one `homogeneous_points` array."""
        if name in self._cache:
            return self._cache[name]
        if not self.in_memory:
            group = self.shards.group(name)
            return {p: {key: group[p][key] for key in self._keys()} for p in group.attrs["persons"]}
        # The first window read reads the whole split: DataLoader workers forked after it (training
        # reads an item first) share these pages instead of each reading the split every epoch.
        for other in dict.fromkeys(other for other, _, _ in self.pairs):
            group = self.shards.group(other)
            self._cache[other] = {p: _read_person(group[p], self._keys())
                                  for p in group.attrs["persons"]}
        self.shards.close()  # no longer needed, and no open file may cross into forked workers
        return self._cache[name]

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_cache"] = {}  # up to cache_bytes: a spawned worker reads its own, not a pickle
        return state

    def __getitem__(self, index: int) -> dict:
        return self.__getitems__([index])[0]

    def __getitems__(self, indices: list[int]) -> list[dict]:
        """The items of `indices` (a DataLoader calls this with a batch's indices), written
        straight into one batch buffer per field by `fill`: each item's tensors are rows of those
        buffers, which `collate_windows` hands on without another copy."""
        batch = self._batch_buffers(len(indices))
        names = self.fill(indices, batch)
        return [{**{key: value[row] for key, value in batch.items()},
                 **{key: values[row] for key, values in names.items()}}
                for row in range(len(indices))]

    def batch_buffers(self, size: int, shared: bool = False) -> dict[str, torch.Tensor]:
        """Empty float32 tensors, one per tensor field, for a batch of `size` windows (what
        `fill` writes into); `shared`: in shared memory, for worker processes to fill."""
        frames = self.window
        shapes = {"motion": (frames, self.motion_dim), "user_head": (frames, 2),
                  "gaze": (frames,), "agent_speaking": (frames,), "user_speaking": (frames,),
                  "transform": (4,)}
        if self.extractor is not None:
            shapes.update(agent_audio=(frames, self.audio_dim), user_audio=(frames, self.audio_dim))
        return {key: _empty_float32((size,) + shape, shared) for key, shape in shapes.items()}

    def fill(self, indices: list[int], out: dict[str, torch.Tensor]) -> dict[str, list]:
        """Write the windows of `indices` into rows 0..len(indices)-1 of the tensors `out` (as
        made by `batch_buffers`, at least that many rows) and return the other fields:
        {"sequence": [...], "agent": [...], "start": [...]}, one entry per index.

        The one code path of every batch: `__getitems__` fills new buffers with it, and
        `sarah_data.loader.WindowLoader` refills the same shared buffers, in its workers."""
        located = [self.locate(int(index)) for index in indices]
        for key, value in out.items():
            if value.shape[0] < len(located):
                raise ValueError(f"{key} has {value.shape[0]} rows for {len(located)} windows")
        with _one_thread():
            return self._fill(located, out)

    def load(self) -> None:
        """Read the split into memory now when it fits (otherwise the first window does): a
        process forked after this shares the pages instead of reading the split again."""
        if self.in_memory and self.pairs and not self._cache:
            self._arrays(self.pairs[0][0])

    def _fill(self, located: list[tuple[str, int, int]], batch: dict[str, torch.Tensor]
              ) -> dict[str, list]:
        rows = {key: value.numpy() for key, value in batch.items()}
        names: dict[str, list] = {"sequence": [], "agent": [], "start": []}
        for row, (name, agent, start) in enumerate(located):
            persons = self.shards.entry(name).persons  # verify checks they match the file's
            arrays = self._arrays(name)
            a, u = arrays[persons[agent]], arrays[persons[1 - agent]]
            frames = slice(start, start + self.window)
            transform = window_transform(a["root_position"][start], a["root_rotation"][start])
            window_motion(_window_points(a, frames), transform, out=batch["motion"][row])
            rows["user_head"][row] = transform.apply_floor(u["head"][frames])
            rows["transform"][row] = transform.as_array()
            # numpy assignment casts (speaking is bool) without an intermediate copy
            rows["gaze"][row] = a["gaze"][frames]
            rows["agent_speaking"][row] = a["speaking"][frames]
            rows["user_speaking"][row] = u["speaking"][frames]
            if self.extractor is not None:
                key = f"audio/{self.extractor}"
                rows["agent_audio"][row] = a[key][frames]
                rows["user_audio"][row] = u[key][frames]
            names["sequence"].append(name)
            names["agent"].append(persons[agent])
            names["start"].append(start)
        return names

    def _batch_buffers(self, size: int) -> dict[str, torch.Tensor]:
        """`batch_buffers` registered for `collate_windows` (in shared memory inside a
        DataLoader worker, which sends the batch to the main process)."""
        buffers = self.batch_buffers(size, shared=torch.utils.data.get_worker_info() is not None)
        _BATCH_BUFFERS.update((id(buffer), buffer) for buffer in buffers.values())
        return buffers


def collate_windows(items: list[dict]) -> dict:
    """`default_collate` for WindowDataset items, except that a field whose tensors are, in
    order, the rows of one tensor (as `WindowDataset.__getitems__` writes them) is that tensor:
    a batch of 400-frame windows is 70 MB, and copying it again costs as much as making it.
    Pass it as a DataLoader's `collate_fn`; any other items are collated as usual."""
    batch = {}
    for key in items[0]:
        values = [item[key] for item in items]
        rows_of = _rows_of(values)
        batch[key] = rows_of if rows_of is not None else default_collate(values)
    return batch


def _rows_of(values: list) -> torch.Tensor | None:
    """The batch buffer whose rows 0..n-1 are exactly `values`, or None. Only buffers made by
    `_batch_buffers` qualify: rows of any other tensor, say a dataset's own, would otherwise
    come back as that tensor itself, and changing the batch in place would change the dataset."""
    base = getattr(values[0], "_base", None)
    if base is None or _BATCH_BUFFERS.get(id(base)) is not base or base.shape[0] != len(values):
        return None
    row_bytes = base.stride(0) * base.element_size()
    for row, value in enumerate(values):
        if (getattr(value, "_base", None) is not base or value.shape != base.shape[1:]
                or value.stride() != base.stride()[1:]
                or value.data_ptr() != base.data_ptr() + row * row_bytes):
            return None
    return base


@contextlib.contextmanager
def _one_thread():
    """Filling a batch is memory-bound: in the main process (num_workers=0) a second intra-op
    thread doubled its CPU time and, on a busy machine, tripled its wall time. DataLoader workers
    already run with one thread."""
    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


@functools.cache
def _blas_threads():
    """This process's BLAS thread pools (scanned once, ~1 ms; a limit then costs ~10 us)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def _empty_float32(shape: tuple[int, ...], shared: bool = False) -> torch.Tensor:
    """An empty float32 tensor; `shared`: in shared memory (as `default_collate` makes a batch
    in a DataLoader worker, so that sending it to the main process does not copy it again)."""
    if not shared:
        return torch.empty(shape)
    # torch's private allocator of shared storage (checked with torch 2.14.1): the public
    # share_memory_() would first allocate and then copy 70 MB per batch.
    storage = torch.UntypedStorage._new_shared(math.prod(shape) * 4)
    return torch.empty(0).set_(storage, 0, shape)  # not a view: its rows' `_base` is this tensor


def _read_person(group, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    arrays = {key: group[key][()] for key in keys if key not in ("icosahedra", "shell")}
    arrays["points"] = homogeneous_points(group["icosahedra"][()], group["shell"][()])
    return arrays


def _cached_bytes(group, keys: tuple[str, ...]) -> int:
    """What `_read_person` keeps of one person: 4 floats per icosahedron and shell point."""
    points = sum(math.prod(group[key].shape[:-1]) for key in ("icosahedra", "shell"))
    return points * 4 * 4 + sum(group[key].size * group[key].dtype.itemsize
                                for key in keys if key not in ("icosahedra", "shell"))


def _window_points(arrays: dict, frames: slice) -> np.ndarray:
    if "points" in arrays:
        return arrays["points"][frames]
    return homogeneous_points(arrays["icosahedra"][frames], arrays["shell"][frames])
