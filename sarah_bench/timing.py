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


def percentiles(values_s: list[float]) -> dict[str, float]:
    ms = np.asarray(values_s, dtype=np.float64) * 1000.0
    if ms.size == 0:
        return {"p50": float("nan"), "p99": float("nan"), "mean": float("nan")}
    return {"p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
            "mean": float(ms.mean())}


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
