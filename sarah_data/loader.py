"""Training batches filled in place, in batch memory allocated once (as FFCV and DALI do).

torch's DataLoader hands every batch over in fresh memory: a worker builds it in new shared
memory, the main process maps it, and both free it again. For 400-frame windows (4.4 MB each,
70 MB per batch of 16) the page faults of that fresh memory and the shared-memory setup cost
more CPU than computing the windows. `WindowLoader` allocates `slots` batches once, in shared
memory, and has its worker processes write each batch into a free slot with
`WindowDataset.fill`, the same code `WindowDataset.__getitems__` runs: the same indices give
the same bits, whatever the number of workers.

Contract: a yielded batch is a view of a slot. It stays valid until the next batch is
requested from the same loader, which hands its slot back to be refilled; a caller that keeps
a batch (or a tensor of it) longer must clone it. Training consumes each batch (normalizes,
i.e. copies, it, and runs its step) before asking for the next.

A batch is a dict like `collate_windows(dataset.__getitems__(indices))`: one float32 tensor per
field with a leading batch dimension, `sequence` and `agent` as lists of str and `start` as an
int64 tensor.
"""

from __future__ import annotations

import collections
import itertools
import multiprocessing
import multiprocessing.connection
import os
import signal
import time
import traceback
from typing import Any, Iterable, Iterator, Sequence

import torch

_POLL_S = 0.5  # how often a waiting process checks that its peer is still alive


class LoaderError(RuntimeError):
    """A worker of a WindowLoader failed (its traceback is in the message) or died."""


class WindowLoader:
    """Batches of a `WindowDataset` (anything with `batch_buffers(size, shared)` and
    `fill(indices, out)`), filled by `workers` processes into `slots` reused batches.

    `batches`: a batch size (consecutive indices 0..len(dataset)-1, the last batch shorter
    unless `drop_last`), or an iterable of index batches (e.g. one epoch of one rank's
    sampler, cut into batches); slots hold the largest of them. `iter_batches(other)` serves
    another list of index batches (of at most `batch_size` indices) with the same workers and
    slots, as training does once per epoch.

    `workers=0` fills each batch in this process when it is requested. Otherwise the workers
    are started here (forked by default on Linux, `context` picks another multiprocessing start
    method) after `dataset.load()`, so that a split read into memory is shared, not read again.
    Each iteration takes the dataset's `epoch` as it is when the iteration starts (call
    `set_epoch` first, as with a DataLoader) and sends it with every batch.
    `slots` defaults to 2 * workers + 1 (each worker one batch ahead and one queued, plus the
    batch in use) and to 1 without workers.

    A failing batch raises `LoaderError` with the worker's traceback; a worker that dies raises
    `LoaderError` (and closes the loader) instead of waiting forever; `timeout` (seconds, None:
    no limit) bounds the wait for any one batch from live workers. `close()` (also on `with`
    exit, on deletion, and on a KeyboardInterrupt while iterating) stops the workers and frees
    the slots. See the module docstring for how long a yielded batch stays valid.
    """

    def __init__(self, dataset: Any, batches: int | Iterable[Sequence[int]], workers: int = 0,
                 slots: int | None = None, *, drop_last: bool = False,
                 context: str | multiprocessing.context.BaseContext | None = None,
                 timeout: float | None = None) -> None:
        if workers < 0:
            raise ValueError(f"workers must be >= 0, got {workers}")
        self.dataset = dataset
        self.workers = int(workers)
        self.timeout = timeout
        self.drop_last = drop_last  # (of batches cut here from a batch size)
        self._closed = True  # until the slots exist: close() and __del__ have nothing to do
        self._procs: list = []
        self._conns: list = []
        if isinstance(batches, int):
            if batches < 1:
                raise ValueError(f"batch size must be positive, got {batches}")
            self.batch_size, self._batches = int(batches), None
        else:
            self._batches = [[int(i) for i in batch] for batch in batches]
            self.batch_size = max((len(batch) for batch in self._batches), default=0)
        self.slots = int(slots) if slots is not None else (2 * self.workers + 1 if self.workers else 1)
        if self.slots < 1:
            raise ValueError(f"slots must be >= 1, got {slots}")
        shared = self.workers > 0
        self._slots = [dataset.batch_buffers(self.batch_size, shared=shared)
                       for _ in range(self.slots)]
        if shared:
            _touch(self._slots, write=True)  # allocated once here, before the workers map them
        self._closed = False
        self._generation = 0  # the running iteration; an older one may not continue
        self._pending: dict[tuple[int, int], int] = {}  # (generation, batch) -> worker
        self._done: dict[tuple[int, int], tuple[bool, Any]] = {}  # -> (ok, names or traceback)
        if self.workers:
            self._start(context)

    # ----------------------------------------------------------------------- processes

    def _start(self, context) -> None:
        if context is None:
            context = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
        ctx = multiprocessing.get_context(context) if isinstance(context, str) else context
        if hasattr(self.dataset, "load"):
            self.dataset.load()  # before forking: the workers share the split in memory
        try:
            for rank in range(self.workers):
                ours, theirs = ctx.Pipe(duplex=True)
                proc = ctx.Process(target=_worker, name=f"WindowLoader-{rank}", daemon=True,
                                   args=(self.dataset, self._slots, theirs, os.getpid()))
                proc.start()
                theirs.close()
                self._procs.append(proc)
                self._conns.append(ours)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Stop the workers (terminate them if they do not stop within a second or two) and
        release the slots' shared memory. Idempotent; the loader cannot be iterated after."""
        if self._closed:
            return
        self._closed = True
        self._generation += 1
        for conn in self._conns:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
        deadline = time.monotonic() + 2.0
        for proc in self._procs:
            proc.join(max(0.0, deadline - time.monotonic()))
        for proc in self._procs:
            if proc.is_alive():
                proc.terminate()
                proc.join(1.0)
            if proc.is_alive():
                proc.kill()
                proc.join()
        for conn in self._conns:
            conn.close()
        for proc in self._procs:
            proc.close()
        self._procs, self._conns, self._slots = [], [], []
        self._pending.clear()
        self._done.clear()

    def __enter__(self) -> "WindowLoader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: the daemonic workers are terminated anyway
            pass

    @property
    def pids(self) -> list[int]:
        """Process ids of the workers (empty without workers or once closed)."""
        return [proc.pid for proc in self._procs]

    # ----------------------------------------------------------------------- iteration

    def __len__(self) -> int:
        if self._batches is not None:
            return len(self._batches)
        full, rest = divmod(len(self.dataset), self.batch_size)
        return full + (1 if rest and not self.drop_last else 0)

    def __iter__(self) -> Iterator[dict]:
        if self._batches is not None:
            return self.iter_batches(self._batches)
        size, length = self.batch_size, len(self.dataset)
        stop = length - length % size if self.drop_last else length
        return self.iter_batches(list(range(start, min(start + size, length)))
                                 for start in range(0, stop, size))

    def iter_batches(self, batches: Iterable[Sequence[int]]) -> Iterator[dict]:
        """The batches of `batches` (index lists of at most `batch_size`), in order. Starting
        an iteration ends the previous one of this loader (which then raises if resumed)."""
        if self._closed:
            raise RuntimeError("this WindowLoader is closed")
        self._drain()  # an abandoned iteration's batches may still be filling slots
        self._generation += 1
        epoch = getattr(self.dataset, "epoch", None)
        batches = ([int(i) for i in batch] for batch in batches)
        if self.workers == 0:
            return self._in_process(self._generation, batches)
        return self._from_workers(self._generation, batches, epoch)

    def _in_process(self, generation: int, batches: Iterator[list[int]]) -> Iterator[dict]:
        for number, indices in enumerate(batches):
            self._check(generation, indices)
            slot = self._slots[number % self.slots]
            yield self._batch(slot, len(indices), self.dataset.fill(indices, slot))

    def _from_workers(self, generation: int, batches: Iterator[list[int]],
                      epoch: int | None) -> Iterator[dict]:
        queued: collections.deque[tuple[int, int]] = collections.deque()  # (batch, rows)
        numbers = itertools.count()

        def send_next() -> None:
            indices = next(batches, None)
            if indices is None:
                return
            self._check(generation, indices)
            number = next(numbers)
            key = (generation, number)
            loads = [0] * self.workers
            for worker in self._pending.values():
                loads[worker] += 1
            worker = loads.index(min(loads))
            self._send(worker, (key, number % self.slots, epoch, indices))
            self._pending[key] = worker
            queued.append((number, len(indices)))

        try:
            for _ in range(self.slots):
                send_next()
            while queued:
                number, rows = queued[0]
                ok, value = self._wait((generation, number))
                queued.popleft()
                if not ok:
                    raise LoaderError(f"a WindowLoader worker failed on batch {number}:\n{value}")
                yield self._batch(self._slots[number % self.slots], rows, value)
                self._check(generation, ())
                send_next()  # into the slot just handed back
        except GeneratorExit:  # stopped early, or garbage: no slot may stay half-filled
            if not self._closed:
                try:
                    self._drain(generation)
                except LoaderError:  # a dead worker (closed the loader): nothing to wait for
                    pass
            raise
        except Exception:
            if not self._closed:
                self._drain(generation)
            raise
        except BaseException:  # KeyboardInterrupt: do not wait for anything
            self.close()
            raise

    def _check(self, generation: int, indices: Sequence[int]) -> None:
        if self._closed:
            raise RuntimeError("this WindowLoader is closed")
        if generation != self._generation:
            raise RuntimeError("a newer iteration of this WindowLoader has started; its slots "
                               "are no longer this iteration's")
        if len(indices) > self.batch_size:
            raise ValueError(f"a batch of {len(indices)} indices does not fit the loader's "
                             f"slots of {self.batch_size}")

    @staticmethod
    def _batch(slot: dict[str, torch.Tensor], rows: int, names: dict[str, list]) -> dict:
        batch: dict[str, Any] = {key: value[:rows] for key, value in slot.items()}
        batch["sequence"], batch["agent"] = list(names["sequence"]), list(names["agent"])
        batch["start"] = torch.tensor(names["start"], dtype=torch.int64)
        return batch

    # ----------------------------------------------------------------------- messages

    def _send(self, worker: int, job: tuple) -> None:
        try:
            self._conns[worker].send(job)
        except (OSError, ValueError):
            self._dead(worker)

    def _wait(self, key: tuple[int, int]) -> tuple[bool, Any]:
        """The result of batch `key`, receiving others meanwhile."""
        self._wait_for(lambda: key in self._done)
        return self._done.pop(key)

    def _wait_for(self, done) -> None:
        """Receive results until `done()`; raises LoaderError (after closing the loader) when a
        worker dies or `timeout` passes without any result."""
        last = time.monotonic()
        while not done():
            if self._receive():
                last = time.monotonic()
            elif self.timeout is not None and time.monotonic() - last > self.timeout:
                pids = self.pids
                self.close()
                raise LoaderError(f"no batch from the WindowLoader workers {pids} within "
                                  f"{self.timeout:g} s")

    def _receive(self) -> bool:
        """Wait up to _POLL_S for messages; True when one arrived. A worker's exit (it stops
        only when closed) is an error."""
        sentinels = {proc.sentinel: rank for rank, proc in enumerate(self._procs)}
        ready = multiprocessing.connection.wait(self._conns + list(sentinels), _POLL_S)
        received = False
        for rank, conn in enumerate(self._conns):
            if conn in ready:
                try:
                    key, ok, value = conn.recv()
                except (EOFError, OSError):
                    self._dead(rank)
                if self._pending.pop(key, None) is not None:
                    self._done[key] = (ok, value)
                received = True
        for sentinel, rank in sentinels.items():
            if sentinel in ready and not received:
                self._dead(rank)
        return received

    def _dead(self, rank: int) -> None:
        proc = self._procs[rank]
        proc.join(0.1)
        pid, code = proc.pid, proc.exitcode
        how = (f"was killed by signal {-code}" if code is not None and code < 0
               else f"exited with code {code}" if code is not None else "closed its pipe")
        self.close()
        raise LoaderError(f"WindowLoader worker {rank} (pid {pid}) {how} while the loader "
                          f"was running; the loader is closed")

    def _drain(self, generation: int | None = None) -> None:
        """Wait for every batch still being filled (of `generation`, default: any)."""
        self._wait_for(lambda: not any(generation is None or key[0] == generation
                                       for key in self._pending))
        for key in [key for key in self._done if generation is None or key[0] == generation]:
            del self._done[key]


def _worker(dataset: Any, slots: list[dict[str, torch.Tensor]],
            conn: multiprocessing.connection.Connection, parent: int) -> None:
    """Fill slots until told to stop (None) or the parent is gone; errors go back as text."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle
    torch.set_num_threads(1)
    _touch(slots)  # map every page now, not during the first batches
    while True:
        while not conn.poll(_POLL_S):
            if os.getppid() != parent:
                return
        try:
            job = conn.recv()
        except EOFError:
            return
        if job is None:
            return
        key, slot, epoch, indices = job
        try:
            if epoch is not None and getattr(dataset, "epoch", None) != epoch:
                dataset.set_epoch(epoch)
            result = (key, True, dataset.fill(indices, slots[slot]))
        except Exception:
            result = (key, False, traceback.format_exc())
        try:
            conn.send(result)
        except OSError:  # the main process closed the pipe: it is gone or closing
            return


def _touch(slots: list[dict[str, torch.Tensor]], write: bool = False) -> None:
    """Touch one float per 4 KiB page of every slot, so that the page faults of fresh memory
    (about 2 us a page here, 2-3 ms a window) are paid once per process, at start-up. Only the
    main process writes (zeros, before any job): a worker may start while another one is
    already filling a slot, so workers read (which maps shared memory writable as well)."""
    for slot in slots:
        for value in slot.values():
            pages = value.view(-1)[::1024]
            if write:
                pages.zero_()
            else:
                pages.sum()
