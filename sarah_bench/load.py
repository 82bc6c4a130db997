"""Busy processes beside the bench: the load a VR host's renderer or a server's other sessions
put on the cores, so that contended figures are measured side by side with idle ones."""

from __future__ import annotations

import subprocess
import sys
import time

# Each process spins until its own deadline, so a bench that dies (kill -9 included) never
# leaves a core busy for longer than the deadline.
_SPIN = "import time, sys\nend = time.monotonic() + float(sys.argv[1])\nwhile time.monotonic() < end:\n    pass\n"


class BackgroundLoad:
    """``processes`` single-threaded busy loops for at most ``max_seconds``; a context manager
    that starts them on entry (and waits ``settle_s`` for the scheduler to spread them) and
    ends them on exit."""

    def __init__(self, processes: int, max_seconds: float = 900.0, settle_s: float = 0.5) -> None:
        if processes < 0:
            raise ValueError(f"background load must be >= 0 processes, got {processes}")
        self.processes, self.max_seconds, self.settle_s = processes, max_seconds, settle_s
        self._procs: list[subprocess.Popen] = []

    def __enter__(self) -> "BackgroundLoad":
        for _ in range(self.processes):
            self._procs.append(subprocess.Popen(
                [sys.executable, "-c", _SPIN, str(self.max_seconds)],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        if self._procs:
            time.sleep(self.settle_s)
        return self

    def running(self) -> int:
        return sum(p.poll() is None for p in self._procs)

    def __exit__(self, *exc) -> None:
        for proc in self._procs:
            proc.kill()
        for proc in self._procs:
            proc.wait()
        self._procs.clear()
