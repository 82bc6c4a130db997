"""Chunk time of a stream with the paper's imputation and with trajectory imputation, side by
side (four rounds, the two alternating), for the shipped fixture-tiny and a random paper-size
model through the int8 fast path (sarah-bench's default). Prints p50 / p99 per chunk in ms and
the ratio of the medians with a 95 % bootstrap interval (docs/performance.md, 2026-11-28 12:52).

    python scripts/imputation_chunk_time.py [THREADS]
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

from sarah_models.accel import optimize_for_inference
from sarah_models.config import IMPUTATIONS, StreamConfig
from sarah_models.pretrained import model_path
from sarah_models.sampling.stream import StreamingGenerator
from sarah_models.testing import random_models
from sarah_models.training.model_file import load_model_file

CHUNKS, WARM_UP, ROUNDS = 100, 5, 4


def chunk_ms(models, config: StreamConfig, rng: np.random.Generator) -> np.ndarray:
    """Milliseconds of each of CHUNKS streamed chunks after the first WARM_UP."""
    vae, flow, normalizer = (models.vae, models.flow, models.normalizer) \
        if hasattr(models, "vae") else models
    generator = StreamingGenerator(vae, flow, normalizer, config)
    frames = CHUNKS * generator.stride
    head = rng.normal(0.0, 1.0, (frames, 2)).astype(np.float32)
    agent, user = (rng.normal(-8.0, 4.0, (frames, generator.audio_dim)).astype(np.float32)
                   for _ in range(2))
    times = []
    for start in range(0, frames, generator.stride):
        block = slice(start, start + generator.stride)
        begin = time.perf_counter()
        generator.step(head[block], agent[block], user[block])
        times.append(time.perf_counter() - begin)
    return 1000.0 * np.array(times[WARM_UP:])


def main(threads: int) -> None:
    torch.set_num_threads(threads)
    rng = np.random.default_rng(0)
    named = {"fixture-tiny": lambda: load_model_file(model_path("fixture-tiny")),
             "paper (random weights)": lambda: random_models("paper")}
    for name, load in named.items():
        models = optimize_for_inference(load(), "int8")
        times = {imputation: [] for imputation in IMPUTATIONS}
        for round_ in range(ROUNDS):
            for imputation in IMPUTATIONS:
                config = StreamConfig(imputation=imputation, seed=round_)
                times[imputation].append(chunk_ms(models, config, rng))
        final, trajectory = (np.concatenate(times[i]) for i in ("final", "trajectory"))
        ratios = [np.median(rng.choice(trajectory, trajectory.size))
                  / np.median(rng.choice(final, final.size)) for _ in range(2000)]
        print(f"{name}, {threads} thread(s), {final.size} chunks each: final p50 "
              f"{np.median(final):.2f} ms, p99 {np.percentile(final, 99):.2f}; trajectory p50 "
              f"{np.median(trajectory):.2f} ms, p99 {np.percentile(trajectory, 99):.2f}; "
              f"p50 ratio {np.median(trajectory) / np.median(final):.3f} "
              f"({np.percentile(ratios, 2.5):.3f}-{np.percentile(ratios, 97.5):.3f})", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1)
