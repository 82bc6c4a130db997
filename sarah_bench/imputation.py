"""What trajectory imputation costs a streamed chunk: sarah-bench's streaming measurement
(``bench_streaming``: raw audio through causal log-mel, int8 fast path) with the paper's
imputation and with trajectory imputation, rounds alternating, for the shipped fixture-tiny and
a random paper-size model (docs/performance.md, 2026-11-28).

    python -m sarah_bench.imputation [THREADS] [ROUNDS]

Prints each imputation's chunk p50 / p99 in ms (the median over rounds) and the ratio of the
rounds' p50s (median and range).
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from sarah_data.features import get_extractor
from sarah_models.accel import optimize_for_inference
from sarah_models.config import IMPUTATIONS, StreamConfig
from sarah_models.testing import random_models, synthetic_inputs

from .bench import bench_streaming, load_shipped

FRAMES = 400  # 100 chunks per stream: one window of T frames


def main(threads: int, rounds: int) -> None:
    torch.set_num_threads(threads)
    extractor = get_extractor("logmel")
    inputs = synthetic_inputs(FRAMES, 0)
    models = {"shipped fixture-tiny": load_shipped(),
              "paper size (random weights)": random_models("paper", audio_dim=extractor.dim)}
    for name, plain in models.items():
        fast = optimize_for_inference(plain, "int8")
        latency = {imputation: [] for imputation in IMPUTATIONS}
        for round_ in range(rounds):
            for imputation in IMPUTATIONS:
                config = StreamConfig(imputation=imputation, seed=round_)
                figures = bench_streaming(fast, FRAMES, inputs, extractor, config)
                latency[imputation].append(figures["latency_ms"])
        p50, p99 = ({i: np.array([r[q] for r in latency[i]]) for i in IMPUTATIONS}
                    for q in ("p50", "p99"))
        ratios = p50["trajectory"] / p50["final"]
        print(f"{name}, {threads} thread(s), {rounds} rounds of {FRAMES // 4} chunks: "
              + "; ".join(f"{i} p50 {np.median(p50[i]):.2f} ms, p99 {np.median(p99[i]):.2f}"
                          for i in IMPUTATIONS)
              + f"; p50 ratio {np.median(ratios):.3f} ({ratios.min():.3f}-{ratios.max():.3f})",
              flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1, int(sys.argv[2]) if len(sys.argv) > 2 else 6)
