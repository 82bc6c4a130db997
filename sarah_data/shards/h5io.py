"""HDF5 files whose bytes depend only on what is written into them, written atomically."""

from __future__ import annotations

import contextlib
import hashlib
import os
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from sarah_data.atomic import atomic_path
from sarah_data.chunks import LEVEL as COMPRESSION_LEVEL
from sarah_data.chunks import write_chunks

from .schema import CHUNK_FRAMES


def create_h5(path: Path | str, in_memory: bool = False) -> h5py.File:
    """A new HDF5 file (truncating) whose bytes depend only on what is written into it.

    `in_memory`: a scratch file that never touches the disk (`path` only has to be unique among
    this process's open files).
    """
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    # Pinned format range: every object in the oldest encoding that can hold it, never one newer
    # than HDF5 1.10's, so a library upgrade cannot change the bytes written.
    fapl.set_libver_bounds(h5py.h5f.LIBVER_EARLIEST, h5py.h5f.LIBVER_V110)
    if in_memory:
        fapl.set_fapl_core(block_size=1 << 20, backing_store=False)
    fcpl = h5py.h5p.create(h5py.h5p.FILE_CREATE)
    fcpl.set_obj_track_times(False)
    fid = h5py.h5f.create(os.fsencode(path), h5py.h5f.ACC_TRUNC, fcpl=fcpl, fapl=fapl)
    return h5py.File(fid)


def create_group(parent: h5py.Group, name: str) -> h5py.Group:
    gcpl = h5py.h5p.create(h5py.h5p.GROUP_CREATE)
    gcpl.set_obj_track_times(False)
    return h5py.Group(h5py.h5g.create(parent.id, name.encode("utf-8"), gcpl=gcpl))


def create_dataset(group: h5py.Group, name: str, data: np.ndarray) -> h5py.Dataset:
    """A time-chunked, gzip+shuffle compressed, fletcher32-checksummed dataset (axis 0 = time).

    The chunks are encoded by `chunks.write_chunks` (same filters, cheaper choices inside deflate).
    """
    data = np.ascontiguousarray(data, dtype=np.asarray(data).dtype.newbyteorder("="))
    chunks = (max(1, min(CHUNK_FRAMES, data.shape[0])),) + data.shape[1:]
    dataset = group.create_dataset(name, shape=data.shape, dtype=data.dtype, chunks=chunks,
                                   compression="gzip", compression_opts=COMPRESSION_LEVEL,
                                   shuffle=True, fletcher32=True, track_times=False)
    write_chunks(dataset, data)
    return dataset


@contextlib.contextmanager
def atomic_h5(path: Path | str) -> Iterator[h5py.File]:
    """Write an HDF5 file under a temporary name; rename it into place (fsynced) only if the
    block succeeds."""
    with atomic_path(path, durable=True, mkdir=False) as tmp:
        handle = create_h5(tmp)
        try:
            yield handle
        finally:
            handle.close()


def file_sha256(path: Path | str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()

