"""Where per-sequence work runs: in this process, a local process pool, or a Ray cluster.

Every executor is a `concurrent.futures.Executor`, so the pipeline is written once against
`submit`/`Future` and the choice is a flag (`-j N`, `--executor ray`).
"""

from __future__ import annotations

import multiprocessing
import threading
from collections import deque
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from functools import partial


class SerialExecutor(Executor):
    """Runs each task at submission, in this process: the reference `-j 1` path, easy to debug."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as error:  # noqa: BLE001 - handed to the caller through the future
            future.set_exception(error)
        # Anything else (Ctrl-C, a full disk) propagates now: caught here, every later task
        # would still run before the caller saw it.
        return future


class LocalPool(Executor):
    """`jobs` tasks at a time: `jobs - 1` spawned worker processes and one thread of this process.

    A spawned worker spends seconds importing torch and loading the body model before its first
    task; this process has done that already (or does it once), so it takes a share of the work
    instead of idling until the workers are done. Tasks go to whichever slot is free first.
    """

    def __init__(self, jobs: int):
        self._processes = ProcessPoolExecutor(max_workers=jobs - 1,
                                              mp_context=multiprocessing.get_context("spawn"))
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="sarah-task")
        self._free = {self._thread: 1, self._processes: jobs - 1}
        self._pending: deque = deque()
        self._lock = threading.Lock()

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        with self._lock:
            self._pending.append((future, fn, args, kwargs))
        self._dispatch()
        return future

    def _dispatch(self) -> None:
        started = []
        with self._lock:
            while self._pending:
                pool = next((p for p in (self._thread, self._processes) if self._free[p]), None)
                if pool is None:
                    break
                future, fn, args, kwargs = self._pending.popleft()
                if future.set_running_or_notify_cancel():
                    self._free[pool] -= 1
                    started.append((pool, future, fn, args, kwargs))
        # Outside the lock: a task that is already done runs its callback right here.
        for pool, future, fn, args, kwargs in started:
            pool.submit(fn, *args, **kwargs).add_done_callback(partial(self._finished, pool, future))

    def _finished(self, pool: Executor, future: Future, inner: Future) -> None:
        with self._lock:
            self._free[pool] += 1
        if inner.exception() is not None:
            future.set_exception(inner.exception())
        else:
            future.set_result(inner.result())
        self._dispatch()

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        with self._lock:
            if cancel_futures:
                while self._pending:
                    self._pending.popleft()[0].cancel()
        self._processes.shutdown(wait=wait, cancel_futures=cancel_futures)
        self._thread.shutdown(wait=wait, cancel_futures=cancel_futures)


class RayExecutor(Executor):
    """Submits tasks to Ray: a local instance, or a cluster given by `address` ("auto" joins one).

    Workers must see the raw data and the output folder at the same paths (a shared filesystem).
    """

    def __init__(self, max_workers: int | None = None, address: str | None = None):
        try:
            import ray
        except ImportError as error:
            raise RuntimeError("--executor ray needs Ray: pip install 'sarah-toolkit[ray]'") from error
        self._ray = ray
        self._started_here = not ray.is_initialized()
        if self._started_here:
            ray.init(address=address, num_cpus=None if address else max_workers,
                     include_dashboard=False, log_to_driver=False, configure_logging=False)
        self._remote = ray.remote(num_cpus=1)(_call)

    def submit(self, fn, /, *args, **kwargs) -> Future:
        return self._remote.remote(fn, args, kwargs).future()

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        if self._started_here and self._ray.is_initialized():
            self._ray.shutdown()


def _call(fn, args, kwargs):
    return fn(*args, **kwargs)


def make_executor(kind: str = "process", jobs: int = 1, address: str | None = None) -> Executor:
    """`process` with jobs > 1 is this process plus a spawn-context pool of jobs - 1 (no forked
    torch or HDF5 state)."""
    if kind == "ray":
        return RayExecutor(max_workers=jobs, address=address)
    if kind != "process":
        raise ValueError(f"unknown executor {kind!r}: expected 'process' or 'ray'")
    if jobs <= 1:
        return SerialExecutor()
    return LocalPool(jobs)
