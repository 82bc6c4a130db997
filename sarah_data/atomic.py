"""Files that appear whole or not at all: write under a temporary name, rename into place.

Every writer of the toolkit (shards, manifests, checkpoints, plots, tables, motion files) goes
through ``atomic_path``: a crash, a full disk or Ctrl-C leaves the previous file (or none),
never a half-written one, and the temporary is removed on failure. The temporary lives in the
target's folder (a rename is atomic only within one file system) and keeps the target's suffix,
because matplotlib and Pillow pick the format from it. ``durable=True`` also fsyncs the file
before the rename, for files a resumed run trusts (shards, manifests, work files).
"""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path
from typing import Iterator


class OutOfSpace(BaseException):
    """The disk being written is full: a problem of the machine, not of one input, so a long run
    stops with one line instead of reporting every remaining input as failed. A BaseException,
    like KeyboardInterrupt, so that per-task ``except Exception`` reporting lets it through."""


def out_of_space(error: BaseException) -> bool:
    # h5py reports HDF5's failed writes as an OSError without errno, or (copying objects) a
    # RuntimeError: the text carries the OS's words.
    if isinstance(error, OSError) and error.errno == errno.ENOSPC:
        return True
    return isinstance(error, (OSError, RuntimeError)) and "No space left on device" in str(error)


def temporary_name(path: Path) -> Path:
    """The temporary beside ``path``: hidden, unique to this process, same suffix."""
    return path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")


def fsync_file(path: Path | str) -> None:
    with open(path, "rb") as handle:
        os.fsync(handle.fileno())


@contextlib.contextmanager
def atomic_path(path: Path | str, durable: bool = False, mkdir: bool = True) -> Iterator[Path]:
    """Yield a temporary path to write; on success it is renamed to ``path``, on failure removed.

    ``mkdir`` creates the target's folder first; ``durable`` fsyncs the written file first."""
    path = Path(path)
    if mkdir:
        path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    try:
        yield tmp
        if durable:
            fsync_file(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_bytes(path: Path | str, data: bytes, durable: bool = False) -> Path:
    with atomic_path(path, durable) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: Path | str, text: str, durable: bool = False) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"), durable)
