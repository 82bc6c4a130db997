"""How many intra-op threads generation uses, chosen from what the other processes leave free.

Why a policy and not ``torch.get_num_threads()``: a streamed chunk runs some 130 parallel
kernels (the flow's int8 Linears, the decoder's GEMMs), each only ~0.1-0.4 ms long, and each
ends at a barrier where every intra-op thread must arrive. On an idle machine two threads on two
cores finish each kernel sooner. When another process keeps a core busy, the scheduler shares
that core between the busy process and our second thread in slices of milliseconds, so nearly
every kernel waits at its barrier for a thread that is not running: on the 2-core VMs a chunk
went from ~50 ms to ~250-1100 ms (p50), while one thread on the free core was barely slower than
idle (docs/performance.md has the figures). So: use every core we may run on, minus the cores
other processes are keeping busy.

``ThreadPolicy`` samples ``/proc/stat`` (busy and steal time of the CPUs this process may run
on) and this process's own CPU time at most every ``interval_s`` seconds, from the caller's loop
(no thread of its own); "others' load" is the busy CPU time that was not ours, in cores. It
gives up one thread per core of others' load beyond ``tolerance``. A fixed ``threads`` (the
``--threads`` flags) turns it off. Without ``/proc/stat`` (not Linux) it keeps every core.

``torch.set_num_threads`` applies to the calling thread's parallel regions (OpenMP keeps the
thread count per thread), so ``apply()`` is called by the thread that computes: the streaming
loop of ``sarah-generate`` and the bench, each compute thread of ``sarah-serve``.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from typing import Callable

import torch

# Others' load (cores) ignored before a thread is given up: short bursts of system daemons
# and the interpreter's own helper threads stay below it; a second process streaming or
# rendering does not. sarah-bench --background-load measures the two sides of it.
TOLERANCE_CORES = 0.3
INTERVAL_S = 0.5


def usable_cpus() -> list[int]:
    """The CPUs this process may run on (its affinity), or all of them."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


def read_cpu_seconds(cpus: list[int], path: str = "/proc/stat") -> float | None:
    """Busy seconds (user, nice, system, irq, softirq and steal; not idle or iowait) summed
    over ``cpus`` since boot, or None where ``/proc/stat`` cannot be read."""
    wanted = {f"cpu{i}" for i in cpus}
    busy_ticks = 0
    try:
        with open(path, encoding="ascii") as stat:
            for line in stat:
                name, _, rest = line.partition(" ")
                if name in wanted:
                    values = [int(v) for v in rest.split()]
                    # user nice system idle iowait irq softirq steal (guest is inside user)
                    busy_ticks += sum(values[:3]) + sum(values[5:8])
    except (OSError, ValueError):
        return None
    return busy_ticks / os.sysconf("SC_CLK_TCK")


@dataclass
class LoadSample:
    wall: float
    busy: float  # all processes' busy CPU seconds on our CPUs
    ours: float  # this process's CPU seconds


class ThreadPolicy:
    """Intra-op threads for the work that follows; see the module docstring."""

    def __init__(self, threads: int | None = None, tolerance: float = TOLERANCE_CORES,
                 interval_s: float = INTERVAL_S, settle_s: float = 0.1,
                 stat_path: str = "/proc/stat") -> None:
        if threads is not None and threads < 1:
            raise ValueError(f"threads must be >= 1 or None (automatic), got {threads}")
        self.fixed = threads
        self.tolerance, self.interval_s, self.stat_path = tolerance, interval_s, stat_path
        self.cpus = usable_cpus()
        self.others_cores = 0.0  # the last measured load of other processes, in cores
        self.threads = threads if threads is not None else len(self.cpus)
        self.ceiling: int | None = None  # the most threads worth using (``calibrate``)
        self._lock = threading.Lock()  # sarah-serve's compute threads share one policy
        self._last = self._sample()
        if self.automatic and settle_s > 0:
            self.measure(settle_s)

    @property
    def automatic(self) -> bool:
        return self.fixed is None

    def _sample(self) -> LoadSample | None:
        busy = read_cpu_seconds(self.cpus, self.stat_path)
        return None if busy is None else LoadSample(time.monotonic(), busy, time.process_time())

    def measure(self, seconds: float) -> int:
        """Measure others' load over the next ``seconds`` (sleeping) and decide from that alone:
        at start-up, or when the load is known to have just changed."""
        if self.automatic:
            self._last = self._sample()
            time.sleep(seconds)
            self._decide()
        return self.threads

    def update(self) -> int:
        """Re-measure others' load when ``interval_s`` has passed; the thread count to use."""
        if (self.automatic and self._last is not None
                and time.monotonic() - self._last.wall >= self.interval_s):
            self._decide()
        return self.threads

    def _decide(self) -> None:
        with self._lock:
            sample = self._sample()
            if sample is None or self._last is None:
                return
            elapsed = sample.wall - self._last.wall
            others = (sample.busy - self._last.busy) - (sample.ours - self._last.ours)
            self._last = sample
            if elapsed > 0:
                self.others_cores = max(0.0, others / elapsed)
                self.threads = self.threads_for(self.others_cores)

    def threads_for(self, others_cores: float) -> int:
        """Every usable core but one per core of others' load beyond the tolerance, and never
        more than ``calibrate`` found useful."""
        taken = max(0, int(-(-(others_cores - self.tolerance) // 1)))  # ceil, never negative
        return max(1, min(self.ceiling or len(self.cpus), len(self.cpus) - taken))

    def calibrate(self, chunk: Callable[[], object], calls: int = 6, warm: int = 2) -> dict[int, float]:
        """Time ``chunk()`` (one streamed chunk, say) with 1, 2, ... threads up to what the
        other processes leave free now: the median of ``calls`` calls after ``warm``. More
        threads than the fastest count are never used after: a small model's kernels are too
        short to share (the tiny preset streamed 1.5x faster on one thread than on two of an
        idle 2-core VM; the paper size 1.2x faster on two). The counts take turns, call by call,
        so that a machine whose speed drifts while it calibrates (a shared VM's does by a third
        within minutes) slows each count alike instead of the one measured last.
        Returns {threads: median seconds}."""
        if not self.automatic:
            return {}
        before = torch.get_num_threads()
        counts = range(1, self.update() + 1)
        times: dict[int, list[float]] = {threads: [] for threads in counts}
        try:
            for i in range(warm + calls):
                for threads in counts:
                    torch.set_num_threads(threads)
                    tick = time.perf_counter()
                    chunk()
                    if i >= warm:
                        times[threads].append(time.perf_counter() - tick)
        finally:
            torch.set_num_threads(before)
        medians = {threads: sorted(t)[len(t) // 2] for threads, t in times.items()}
        if len(medians) == len(self.cpus):  # measured on a machine nobody else was using
            self.ceiling = min(medians, key=medians.get)
            self.threads = min(self.threads, self.ceiling)
        return medians

    def apply(self) -> int:
        """``update()``, and set this thread's torch intra-op threads to the answer."""
        threads = self.update()
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)
        return threads

    def describe(self) -> str:
        if self.fixed is not None:
            return f"{self.fixed} threads (fixed)"
        ceiling = "" if self.ceiling is None else f", at most {self.ceiling} (calibrated)"
        return (f"automatic: {self.threads} of {len(self.cpus)} cores{ceiling}, other processes "
                f"{self.others_cores:.2f} cores busy")


def stream_probe(models, config=None) -> Callable[[], object]:
    """One streamed chunk of silence and a standing user on a fresh ``StreamingGenerator`` of
    ``models`` (vae, flow, normalizer, or LoadedModels): what ``ThreadPolicy.calibrate`` times."""
    import numpy as np

    from ..config import StreamConfig
    from ..sampling.stream import StreamingGenerator
    from ..training.checkpoint import unpack_models

    vae, flow, normalizer = unpack_models(models)
    generator = StreamingGenerator(vae, flow, normalizer, config or StreamConfig())
    s = generator.stride
    head = np.zeros((s, 2), np.float32)
    audio = np.zeros((s, generator.audio_dim), np.float32)
    return lambda: generator.step(head, audio, audio)
