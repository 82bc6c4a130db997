"""Where per-sequence work runs: in this process, a local process pool, or a Ray cluster.

Every executor is a `concurrent.futures.Executor`, so the pipeline is written once against
`submit`/`Future` and the choice is a flag (`-j N`, `--executor ray`).
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Executor, Future, ProcessPoolExecutor


class SerialExecutor(Executor):
    """Runs each task at submission, in this process: the reference `-j 1` path, easy to debug."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as error:  # noqa: BLE001 - handed to the caller through the future
            future.set_exception(error)
        return future


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
    """`process` with jobs > 1 is a spawn-context pool (no forked torch or HDF5 state)."""
    if kind == "ray":
        return RayExecutor(max_workers=jobs, address=address)
    if kind != "process":
        raise ValueError(f"unknown executor {kind!r}: expected 'process' or 'ray'")
    if jobs <= 1:
        return SerialExecutor()
    return ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"))
