"""Writing shards: one sequence into an open file, one whole file, or a split's files."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Mapping
from pathlib import Path

import h5py
import numpy as np

from sarah_data.atomic import fsync_file, temporary_name
from sarah_data.splits import SPLITS

from .h5io import atomic_h5, create_dataset, create_group, create_h5, file_sha256
from .manifest import SequenceEntry, ShardInfo
from .schema import (DEFAULT_MAX_BYTES, SEQUENCE_OVERHEAD_BYTES, SHARD_FILE_RE, ProcessedSequence,
                     ShardAttrs, ShardError, sequence_arrays, shard_name)


def _write_sequence(handle: h5py.File, seq: ProcessedSequence,
                    persons: list[tuple[str, dict[str, np.ndarray]]]) -> None:
    """Build the sequence in a scratch file and copy it in: a group copied (H5Ocopy) is laid out
    differently from one built in place, and prep copies sequences from work files, so every
    writer copies and the same sequence gives the same bytes whichever way it arrives."""
    with create_h5(f"scratch-{os.getpid()}-{id(seq)}", in_memory=True) as scratch:
        _build_sequence(scratch, seq, persons)
        scratch.copy(scratch[seq.name], handle, name=seq.name)


def _build_sequence(handle: h5py.File, seq: ProcessedSequence,
                    persons: list[tuple[str, dict[str, np.ndarray]]]) -> None:
    group = create_group(handle, seq.name)
    group.attrs["session"] = seq.session
    group.attrs["split"] = seq.split
    group.attrs["frames"] = np.int64(seq.frames)
    group.attrs["fps"] = np.int64(seq.fps)
    group.attrs["persons"] = [name for name, _ in persons]
    for person, (name, arrays) in zip(seq.persons, persons):
        person_group = create_group(group, name)
        if "betas" in arrays:
            person_group.attrs["gender"] = person.gender
        if any(key.startswith("audio/") for key in arrays):
            create_group(person_group, "audio")
        for key, array in arrays.items():
            create_dataset(person_group, key, array)


def write_sequence(handle: h5py.File, seq: ProcessedSequence, attrs: ShardAttrs
                   ) -> list[tuple[str, dict[str, np.ndarray]]]:
    """Check one sequence against the schema (ShardError, nothing written) and write it into an
    open shard-format file whose root attributes are `attrs`; returns each person's arrays as
    stored (`{dataset or "audio/<extractor>": array}`)."""
    persons = sequence_arrays(seq, attrs, seq.split)
    _write_sequence(handle, seq, persons)
    return persons


def write_shard(path: Path | str, sequences: list[ProcessedSequence], attrs: ShardAttrs | Mapping
                ) -> None:
    """Write `sequences` (all of one split) into one shard-format file at `path`, atomically.

    No size budget and no manifest entry: for a single file such as a per-sequence cache that
    `read_shard` reads back; a shards folder is written with `ShardWriter`.
    """
    path = Path(path)
    splits = {seq.split for seq in sequences}
    if len(splits) != 1:
        raise ShardError(path, f"a shard holds sequences of one split, got {sorted(splits)}")
    names = [seq.name for seq in sequences]
    if len(set(names)) != len(names):
        raise ShardError(path, f"duplicate sequence names in {names}")
    split = splits.pop()
    attrs = ShardAttrs.coerce(attrs)
    checked = [(seq, sequence_arrays(seq, attrs, split)) for seq in sequences]
    with atomic_h5(path) as handle:
        attrs.write(handle.attrs, split)
        for seq, persons in checked:
            _write_sequence(handle, seq, persons)


class ShardWriter:
    """Writes one split's sequences into `<split>-NNNNN.h5` files of at most `max_bytes` each.

    A sequence is never split across files. A new file is started when the current file's size
    plus the next sequence's uncompressed array bytes plus SEQUENCE_OVERHEAD_BYTES would exceed
    `max_bytes` (so only a file holding one sequence larger than the budget can exceed it).
    Files are written under a temporary dot-name and renamed into place when complete; `close`
    then removes this split's files left over from an earlier, larger run. Used as a context
    manager, an exception discards the unfinished file (files already completed stay).

    `add` raises ShardError for a sequence that does not fit the schema before writing anything,
    so the caller may skip it and go on; any other failure during a write aborts the writer.
    """

    def __init__(self, out_dir: Path | str, split: str, attrs: ShardAttrs | Mapping,
                 max_bytes: int = DEFAULT_MAX_BYTES):
        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; expected one of {SPLITS}")
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be positive, got {max_bytes}")
        self.out_dir = Path(out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.split = split
        self.attrs = ShardAttrs.coerce(attrs)
        self.max_bytes = int(max_bytes)
        self.entries: dict[str, SequenceEntry] = {}  # sequence -> entry (without sources)
        self._infos: list[ShardInfo] = []
        self._file: h5py.File | None = None
        self._file_sequences: list[str] = []
        self._file_bytes = 0
        self._state = "open"

    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    @property
    def _current_name(self) -> str:
        return shard_name(self.split, len(self._infos))

    def add(self, seq: ProcessedSequence) -> str:
        """Append a sequence; returns the name of the shard file it goes to."""
        if self._state != "open":
            raise RuntimeError(f"ShardWriter for {self.split!r} is {self._state}")
        if seq.name in self.entries:
            raise ShardError(f"sequence {seq.name}", "added twice")
        persons = sequence_arrays(seq, self.attrs, self.split)
        size = sum(a.nbytes for _, arrays in persons for a in arrays.values())
        self._append(seq.name, size, lambda handle: _write_sequence(handle, seq, persons))
        return self._entry(seq.name, seq.session, tuple(name for name, _ in persons),
                           seq.frames, seq.fps)

    def add_copy(self, source: h5py.Group) -> str:
        """Append a sequence group of another file in this format with these root attributes
        (prep's per-sequence work files, written by `write_shard`): its chunks are copied as
        stored, nothing is decoded. The same bytes as `add` of that sequence."""
        if self._state != "open":
            raise RuntimeError(f"ShardWriter for {self.split!r} is {self._state}")
        name = source.name.lstrip("/")
        where = f"{source.file.filename}: sequence {name}"
        if name in self.entries:
            raise ShardError(f"sequence {name}", "added twice")
        if ShardAttrs.read(source.file.attrs, source.file.filename).to_json() != self.attrs.to_json():
            raise ShardError(where, "root attributes differ from this writer's")
        if str(source.attrs["split"]) != self.split:
            raise ShardError(where, f"belongs to split {source.attrs['split']!r}, this writer "
                                    f"writes {self.split!r}")
        sizes: list[int] = []
        source.visititems(lambda _, obj: sizes.append(obj.size * obj.dtype.itemsize)
                          if isinstance(obj, h5py.Dataset) else None)
        self._append(name, sum(sizes), lambda handle: source.file.copy(source, handle, name=name))
        return self._entry(name, str(source.attrs["session"]),
                           tuple(str(p) for p in source.attrs["persons"]),
                           int(source.attrs["frames"]), int(source.attrs["fps"]))

    def _append(self, name: str, array_bytes: int, write) -> None:
        size = array_bytes + SEQUENCE_OVERHEAD_BYTES
        try:
            if self._file is not None and self._file_bytes + size > self.max_bytes:
                self._finish_file()
            if self._file is None:
                self._file = create_h5(temporary_name(self.out_dir / self._current_name))
                self.attrs.write(self._file.attrs, self.split)
            write(self._file)
            self._file.flush()
            self._file_bytes = os.path.getsize(self._file.filename)
        except BaseException:
            self.abort()
            raise
        self._file_sequences.append(name)

    def _entry(self, name: str, session: str, persons: tuple[str, ...], frames: int, fps: int) -> str:
        self.entries[name] = SequenceEntry(session=session, split=self.split, file=self._current_name,
                                           persons=persons, frames=frames, seconds=frames / fps)
        return self._current_name

    def _finish_file(self) -> None:
        final = self.out_dir / self._current_name
        tmp = Path(self._file.filename)
        self._file.close()
        self._file = None
        fsync_file(tmp)
        sha256, size = file_sha256(tmp), os.path.getsize(tmp)
        os.replace(tmp, final)
        self._infos.append(ShardInfo(final.name, self.split, tuple(self._file_sequences), size, sha256))
        self._file_sequences = []
        self._file_bytes = 0

    def close(self) -> list[ShardInfo]:
        """Finish the last file, remove stale files of this split, return the files written."""
        if self._state == "closed":
            return list(self._infos)
        if self._state != "open":
            raise RuntimeError(f"ShardWriter for {self.split!r} is {self._state}")
        if self._file is not None:
            self._finish_file()
        written = {info.file for info in self._infos}
        for path in self.out_dir.iterdir():
            match = SHARD_FILE_RE.match(path.name)
            if match and match["split"] == self.split and path.name not in written:
                path.unlink()
        self._state = "closed"
        return list(self._infos)

    def abort(self) -> None:
        """Discard the unfinished file; the writer cannot be used afterwards."""
        if self._file is not None:
            tmp = Path(self._file.filename)
            with contextlib.suppress(Exception):
                self._file.close()
            self._file = None
            tmp.unlink(missing_ok=True)
        if self._state == "open":
            self._state = "aborted"
