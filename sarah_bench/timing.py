"""Clocks of the bench: per-chunk latency split by stage, percentiles, torch's thread count."""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Any, Iterator

import numpy as np
import torch

from sarah_models.nn.flow import FlowModel
from sarah_models.nn.vae import CausalVAE


class ChunkClock:
    """Per-chunk latency split into audio features / flow solver / VAE decode / the rest, and the
    summary both streaming benchmarks report."""

    def __init__(self) -> None:
        self.latencies: list[float] = []
        self.stages: dict[str, list[float]] = {"audio": [], "flow": [], "decode": [], "other": []}

    def add(self, tick: float, heard: float, done: float, flow: float, decode: float) -> None:
        """One chunk: started at ``tick``, audio features ready at ``heard``, done at ``done``."""
        self.latencies.append(done - tick)
        for stage, value in (("audio", heard - tick), ("flow", flow), ("decode", decode),
                             ("other", done - heard - flow - decode)):
            self.stages[stage].append(value)

    def summary(self, stride: int, total_s: float) -> dict[str, Any]:
        streamed = len(self.latencies) * stride
        return {"frames": streamed, "fps": streamed / total_s,
                "latency_ms": percentiles(self.latencies),
                "stages_ms": {k: percentiles(v) for k, v in self.stages.items()}}


CONFIDENCE = 0.95  # of the intervals every latency percentile carries


def quantile_interval(values: np.ndarray, q: float,
                      confidence: float = CONFIDENCE) -> tuple[float | None, float | None]:
    """Distribution-free ``confidence`` interval of the ``q``-quantile of what ``values`` were
    drawn from: the order statistics X_(l) <= X_(u) with P(l <= B < u) >= confidence, B ~
    Binomial(n, q) the count of draws below the quantile. A tail percentile needs many draws:
    below about -ln((1 - confidence) / 2) / (1 - q) of them (368 for p99 at 95 %) no order
    statistic bounds it from above, and that end is None (open)."""
    from scipy.stats import binom

    n = len(values)
    if n == 0:
        return None, None
    ordered = np.sort(np.asarray(values, dtype=np.float64))
    alpha = 1.0 - confidence
    # 1-based ranks: l = the largest with P(B < l) <= alpha / 2 (ppf is the smallest k with
    # P(B <= k) >= alpha / 2), u = the smallest with P(B >= u) <= alpha / 2: each tail gets half
    # of what the interval may miss.
    low = int(binom.ppf(alpha / 2, n, q))
    high = int(binom.ppf(1.0 - alpha / 2, n, q)) + 1
    return (float(ordered[low - 1]) if low >= 1 else None,
            float(ordered[high - 1]) if high <= n else None)


def percentiles(values_s: list[float]) -> dict[str, Any]:
    """p50, p99 and mean in ms, with ``CONFIDENCE`` intervals of p50 and p99 (``*_interval``:
    [low, high], None where the sample is too small to bound that end) and the sample size."""
    ms = np.asarray(values_s, dtype=np.float64) * 1000.0
    if ms.size == 0:
        return {"p50": float("nan"), "p99": float("nan"), "mean": float("nan"), "n": 0,
                "p50_interval": [None, None], "p99_interval": [None, None]}
    return {"p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
            "mean": float(ms.mean()), "n": int(ms.size),
            "p50_interval": list(quantile_interval(ms, 0.50)),
            "p99_interval": list(quantile_interval(ms, 0.99))}


class StageHooks:
    """Seconds spent inside FlowModel.forward and inside the VAE decoder step, via module hooks
    (flow: around its forward; decoder: from ``latent_in`` to ``frame_out``)."""

    def __init__(self, vae: CausalVAE, flow: FlowModel) -> None:
        self.seconds = {"flow": 0.0, "decode": 0.0}
        self._open: dict[str, float] = {}
        self._handles = [
            flow.register_forward_pre_hook(lambda *_: self._start("flow")),
            flow.register_forward_hook(lambda *_: self._stop("flow")),
            vae.latent_in.register_forward_pre_hook(lambda *_: self._start("decode")),
            vae.frame_out.register_forward_hook(lambda *_: self._stop("decode")),
        ]

    def _start(self, stage: str) -> None:
        self._open[stage] = time.perf_counter()

    def _stop(self, stage: str) -> None:
        self.seconds[stage] += time.perf_counter() - self._open.pop(stage)

    def take(self) -> dict[str, float]:
        out, self.seconds = self.seconds, {"flow": 0.0, "decode": 0.0}
        return out

    def remove(self) -> None:
        for handle in self._handles:
            handle.remove()


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run with ``n`` intra-op threads (prep's in-process tasks set 1; this puts it back)."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
