"""Shards assembled from prep's work files while the tasks still run.

Each split's sequences go into its shards in corpus order, so the bytes do not depend on which
task finishes first (`-j`, executor, resumed run). A sequence is copied as soon as it and every
sequence before it in its split are finished; copying moves compressed chunks (H5Ocopy), cheap
enough for the parent to keep up with its workers, so little is left to do after the last task.
"""

from __future__ import annotations

from pathlib import Path

import h5py

from .config import PrepConfig
from .embody3d import PairRecord
from .process import MOMENTS_GROUP, TaskResult
from .shards import SHARD_FILE_RE, SequenceEntry, ShardAttrs, ShardInfo, ShardWriter
from .splits import SPLITS
from .stats import STATS_SPLIT, Moments, read_moments


class Assembler:
    """`update(results)` after each finished task, `close()` once all are; `abort()` on failure."""

    def __init__(self, out_dir: Path, work_dir: Path, pairs: list[PairRecord],
                 split_of: dict[str, str], config: PrepConfig):
        self.out_dir, self.work_dir, self.config = out_dir, work_dir, config
        self._queues = {name: [p for p in pairs if split_of[p.session] == name] for name in SPLITS}
        self._next = dict.fromkeys(SPLITS, 0)
        self._writers: dict[str, ShardWriter] = {}
        self.attrs: ShardAttrs | None = None  # of the first work file; every one must agree
        self.moments: dict[str, dict[str, Moments]] = {}  # train sequence -> its moments

    def update(self, results: dict[str, TaskResult]) -> None:
        for name in SPLITS:
            queue = self._queues[name]
            while self._next[name] < len(queue) and queue[self._next[name]].sequence in results:
                pair = queue[self._next[name]]
                if results[pair.sequence].status == "ok":
                    self._copy(name, pair)
                self._next[name] += 1

    def _copy(self, split: str, pair: PairRecord) -> None:
        path = self.work_dir / f"{pair.sequence}.h5"
        with h5py.File(path, "r") as handle:
            if self.attrs is None:
                self.attrs = ShardAttrs.read(handle.attrs, path)
                self._writers = {name: ShardWriter(self.out_dir, name, self.attrs,
                                                   max_bytes=self.config.max_shard_bytes)
                                 for name in SPLITS}
            self._writers[split].add_copy(handle[pair.sequence])
            if split == STATS_SPLIT:
                self.moments[pair.sequence] = read_moments(handle[MOMENTS_GROUP])

    def close(self) -> tuple[list[ShardInfo], dict[str, SequenceEntry]]:
        """Finish every split (removing its files left from an earlier run); the files written
        and the sequences' manifest entries (without sources)."""
        if any(self._next[name] < len(queue) for name, queue in self._queues.items()):
            raise RuntimeError("Assembler.close: some sequences have no result yet")
        shards, entries = [], {}
        for name in SPLITS:
            if name in self._writers:
                shards += self._writers[name].close()
                entries.update(self._writers[name].entries)
            else:  # nothing was written at all: no writer to clear the split's old files
                for path in self.out_dir.glob(f"{name}-*.h5"):
                    if SHARD_FILE_RE.match(path.name):
                        path.unlink()
        return shards, entries

    def abort(self) -> None:
        for writer in self._writers.values():
            writer.abort()
