"""Reading shards: a whole file back in memory, or a folder through its manifest."""

from __future__ import annotations

import os
from pathlib import Path

import h5py

from sarah_data.constants import READABLE_SCHEMA_VERSIONS

from .manifest import SequenceEntry, read_manifest
from .schema import (MANIFEST_NAME, PERSON_BODY_DATASETS, PERSON_DATASETS, ProcessedPerson,
                     ProcessedSequence, ShardAttrs, ShardError)


def read_shard(path: Path | str) -> tuple[ShardAttrs, list[ProcessedSequence]]:
    """A whole shard-format file back in memory: root attributes and sequences (name order)."""
    try:
        handle = h5py.File(path, "r")
    except OSError as error:
        raise ShardError(path, f"cannot open shard: {error}") from None
    with handle:
        return ShardAttrs.read(handle.attrs, path), [_read_sequence(handle[name]) for name in handle]


def _read_sequence(group: h5py.Group) -> ProcessedSequence:
    persons = []
    for name in (str(n) for n in group.attrs["persons"]):
        g = group[name]
        arrays = {key: g[key][()] for key in PERSON_DATASETS}
        arrays["speaking"] = arrays["speaking"].astype(bool)
        arrays["valid"] = arrays["valid"].astype(bool)
        audio = {key: g["audio"][key][()] for key in g["audio"]} if "audio" in g else {}
        shape = {key: (g[key][()] if key in g else None) for key in PERSON_BODY_DATASETS}
        persons.append(ProcessedPerson(name=name, audio=audio, gender=str(g.attrs.get("gender", "neutral")),
                                       **shape, **arrays))
    return ProcessedSequence(name=group.name.lstrip("/"), session=str(group.attrs["session"]),
                             split=str(group.attrs["split"]), persons=tuple(persons),
                             fps=int(group.attrs["fps"]))


class ShardSet:
    """Read access to a shards folder through its manifest.

    Picklable: it holds paths, never open files. HDF5 files are opened on first use in each
    process (a handle inherited through fork is left alone, not reused), so a DataLoader worker
    opens its own.
    """

    def __init__(self, shards_dir: Path | str):
        self.root = Path(shards_dir)
        self.manifest = read_manifest(self.root / MANIFEST_NAME)
        if self.manifest.schema_version not in READABLE_SCHEMA_VERSIONS:
            raise ShardError(self.root / MANIFEST_NAME,
                             f"schema version {self.manifest.schema_version}, this toolkit reads "
                             f"{', '.join(map(str, READABLE_SCHEMA_VERSIONS))}: prepare the shards again")
        self._attrs: ShardAttrs | None = None
        self._handles: dict[str, h5py.File] = {}
        self._pid = os.getpid()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_handles"] = {}
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._pid = os.getpid()

    def sequences(self, split: str | None = None) -> list[str]:
        """Sequence names (sorted), of one split or all."""
        return sorted(name for name, entry in self.manifest.sequences.items()
                      if split is None or entry.split == split)

    def entry(self, sequence: str) -> SequenceEntry:
        try:
            return self.manifest.sequences[sequence]
        except KeyError:
            raise ShardError(self.root / MANIFEST_NAME, f"no sequence {sequence!r}") from None

    @property
    def attrs(self) -> ShardAttrs:
        """Root attributes, as stored in the first shard file (verify checks they all agree)."""
        if self._attrs is None:
            if not self.manifest.shards:
                raise ShardError(self.root / MANIFEST_NAME, "lists no shard files")
            first = sorted(info.file for info in self.manifest.shards)[0]
            self._attrs = ShardAttrs.read(self._open(first).attrs, self.root / first)
        return self._attrs

    def _open(self, file: str) -> h5py.File:
        if os.getpid() != self._pid:
            # Forked from a process that had files open: HDF5 handles must not be shared
            # between processes, so the inherited ones are abandoned and this one opens its own.
            self._handles = {}
            self._pid = os.getpid()
        handle = self._handles.get(file)
        if handle is None:
            path = self.root / file
            try:
                handle = h5py.File(path, "r")
            except OSError as error:
                raise ShardError(path, f"cannot open shard: {error}") from None
            self._handles[file] = handle
        return handle

    def group(self, sequence: str) -> h5py.Group:
        """The sequence's HDF5 group (`/<sequence>`), from its file opened in this process."""
        entry = self.entry(sequence)
        handle = self._open(entry.file)
        if sequence not in handle:
            raise ShardError(self.root / entry.file, f"has no sequence {sequence!r}")
        return handle[sequence]

    def read_sequence(self, sequence: str) -> ProcessedSequence:
        """The whole sequence, back in memory as written."""
        return _read_sequence(self.group(sequence))

    def close(self) -> None:
        if os.getpid() == self._pid:
            for handle in self._handles.values():
                handle.close()
        self._handles = {}


def open_shards(shards_dir: Path | str) -> ShardSet:
    return ShardSet(shards_dir)
