"""The library behind ``sarah-bench``: speed of prep, loading and generation, in one process.

Every figure is measured against a naive reference in the same run, with the thread count fixed
(``torch.set_num_threads``), and reported as a ratio:

    section     measured                                        naive reference
    prep        dyad-seconds per wall-second, ``-j 2``          the same prep with ``-j 1``
    loader      400-frame windows per second, 2 workers         0 workers
    offline     frames / time for 400 frames at once (paper 4)  plain fp32 models
    streaming   frames / time, chunks of s = 4 (paper A.3),      ``NaiveStreamer``: plain fp32,
                per-chunk latency by stage                       recomputes the context per chunk
    hubert      one causal HuBERT-Large pass per chunk, by window length (random weights)

Models have random weights (paper and tiny sizes); speed does not depend on the values. The
zero-initialised AdaLN-Zero parameters get small random values so that the tolerance figures
(``fast.stream_deviation``) compare motions that depend on noise, history and conditioning.
The machine's load average is recorded before and after: other processes on the same cores make
every figure (and 2-thread runs most of all) slower.
"""

from __future__ import annotations

import datetime
import os
import platform
import shutil
import tempfile
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from sarah_data.constants import SAMPLES_PER_FRAME
from sarah_models.accel import (
    cpu_info,
    optimize_for_inference,
    resolve_decoder,
    warm_up,
)
from sarah_models.config import StreamConfig
from sarah_models.sampling.stream import StreamingGenerator, generate_offline
from sarah_models.testing import random_models, stream_deviation, synthetic_inputs

from .config import CHUNK_FRAMES, BenchConfig
from .data import bench_hubert_windows, bench_loader, bench_prep, write_random_hubert
from .naive import NaiveStreamer
from .report import check_goals
from .timing import ChunkClock, StageHooks, torch_threads

# --------------------------------------------------------------------------- model benchmarks


def bench_offline(models, frames: int, inputs: dict[str, np.ndarray], features: np.ndarray,
                  config: StreamConfig = StreamConfig(), repeats: int = 3) -> float:
    """Frames per second of ``generate_offline`` on ``frames`` frames at once (paper 4:
    T / time), the best of ``repeats`` runs (one run lasts about a second: a busy neighbour
    process would otherwise decide the figure)."""
    vae, flow, normalizer = models
    head = inputs["user_head"][:frames]
    a = b = features[:frames]
    generate_offline(vae, flow, normalizer, head[:8], a[:8], b[:8], config)  # warm-up
    best = float("inf")
    for _ in range(repeats):
        tick = time.perf_counter()
        generate_offline(vae, flow, normalizer, head, a, b, config)
        best = min(best, time.perf_counter() - tick)
    return frames / best


def bench_streaming(models, frames: int, inputs: dict[str, np.ndarray], extractor,
                    config: StreamConfig = StreamConfig(),
                    max_seconds: float = float("inf")) -> dict[str, Any]:
    """Stream ``frames`` frames chunk by chunk from raw audio through the extractor's causal
    mode and ``StreamingGenerator``; fps, per-chunk latency and its split by stage. Stops
    early once ``max_seconds`` have passed (``frames`` then says how many were streamed)."""
    vae, flow, normalizer = models
    generator = StreamingGenerator(vae, flow, normalizer, config)
    s = generator.stride
    n = s * SAMPLES_PER_FRAME
    hooks = StageHooks(vae, flow)
    try:
        for phase in ("warm-up", "measure"):
            generator.reset()
            streams = (extractor.stream(), extractor.stream())
            count = 3 * s if phase == "warm-up" else frames
            clock = ChunkClock()
            hooks.take()
            started = time.perf_counter()
            for i in range(0, count, s):
                k = i * SAMPLES_PER_FRAME
                tick = time.perf_counter()
                a = streams[0].push(inputs["agent_wave"][k:k + n])
                b = streams[1].push(inputs["user_wave"][k:k + n])
                heard = time.perf_counter()
                generator.step(inputs["user_head"][i:i + s], a, b)
                done = time.perf_counter()
                clock.add(tick, heard, done, **hooks.take())
                if done - started > max_seconds:
                    break
            total = time.perf_counter() - started
    finally:
        hooks.remove()
    return clock.summary(s, total)


def bench_naive_streaming(models, frames: int, inputs: dict[str, np.ndarray], extractor,
                          config: StreamConfig = StreamConfig(), window: int = 400,
                          max_seconds: float = float("inf")) -> dict[str, Any]:
    """``NaiveStreamer`` fed with features re-extracted per chunk from the last ``window``
    frames of audio (offline extraction of the context, no streaming state)."""
    naive = NaiveStreamer(*models, config=config)
    s = naive.stride
    clock = ChunkClock()
    started = time.perf_counter()
    for i in range(0, frames, s):
        tick = time.perf_counter()
        first = max(0, i + s - window)
        span = slice(first * SAMPLES_PER_FRAME, (i + s) * SAMPLES_PER_FRAME)
        a = extractor.extract(inputs["agent_wave"][span], i + s - first)[-s:]
        b = extractor.extract(inputs["user_wave"][span], i + s - first)[-s:]
        heard = time.perf_counter()
        timings: dict[str, float] = {}
        naive.step(inputs["user_head"][i:i + s], a, b, timings)
        done = time.perf_counter()
        clock.add(tick, heard, done, flow=timings["flow"], decode=timings["decode"])
        if done - started > max_seconds:
            break
    return clock.summary(s, time.perf_counter() - started)


def bench_model_size(size: str, cfg: BenchConfig, log: Callable[[str], None]) -> dict[str, Any]:
    """Offline and streaming, optimized vs naive, and the optimized mode's deviation."""
    from sarah_data.features import get_extractor

    extractor = get_extractor("logmel")
    plain = random_models(size, audio_dim=extractor.dim, seed=cfg.seed)
    fast = optimize_for_inference(plain, cfg.mode, decoder=cfg.decoder)
    frames = max(cfg.stream_frames, cfg.naive_frames, cfg.offline_frames)
    inputs = synthetic_inputs(frames, cfg.seed)
    features = extractor.extract(inputs["agent_wave"], frames)
    out: dict[str, Any] = {}
    log(f"[{size}] offline generation, {cfg.offline_frames} frames at once")
    offline = {"frames": cfg.offline_frames,
               "fps": bench_offline(fast, cfg.offline_frames, inputs, features),
               "naive_fps": bench_offline(plain, cfg.offline_frames, inputs, features)}
    offline["ratio"] = offline["fps"] / offline["naive_fps"]
    out["offline"] = offline
    log(f"[{size}] streaming, {cfg.stream_frames} frames in chunks of {CHUNK_FRAMES} "
        f"(naive reference: {cfg.naive_frames} frames)")
    cap = cfg.max_stream_seconds
    streaming = bench_streaming(fast, cfg.stream_frames, inputs, extractor, max_seconds=cap)
    streaming["naive"] = bench_naive_streaming(plain, cfg.naive_frames, inputs, extractor,
                                               max_seconds=cap / 2)
    streaming["ratio"] = streaming["fps"] / streaming["naive"]["fps"]
    if cfg.fewer_steps is not None:
        fewer = StreamConfig(steps=cfg.fewer_steps)
        warm_up(fast[1], fewer)
        log(f"[{size}] streaming with {cfg.fewer_steps} midpoint steps "
            f"({2 * cfg.fewer_steps} NFE; changes the output, not an exact optimization)")
        streaming["fewer_steps"] = {"steps": cfg.fewer_steps, **bench_streaming(
            fast, cfg.stream_frames, inputs, extractor, fewer, max_seconds=cap / 2)}
        log(f"[{size}] deviation: {2 * cfg.fewer_steps} NFE {cfg.mode} vs the paper's 8 NFE fp32")
        streaming["fewer_steps"]["deviation"] = stream_deviation(
            plain, fast, frames=cfg.deviation_frames, seed=cfg.seed,
            optimized_config=fewer).as_dict()
    log(f"[{size}] tolerance: {cfg.mode} vs plain fp32 over {cfg.deviation_frames} frames")
    streaming["deviation"] = stream_deviation(plain, fast, frames=cfg.deviation_frames,
                                              seed=cfg.seed).as_dict()
    out["streaming"] = streaming
    return out


# --------------------------------------------------------------------------- the whole run


def environment(threads: int) -> dict[str, Any]:
    cpu = cpu_info("model name") or platform.processor() or "unknown"
    return {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "cpu": cpu, "cores": os.cpu_count(), "threads": threads, "torch": torch.__version__,
            "numpy": np.__version__, "python": platform.python_version(),
            "load_before": list(os.getloadavg())}


def run_bench(cfg: BenchConfig = BenchConfig(), workdir: Path | None = None,
              log: Callable[[str], None] = print) -> dict[str, Any]:
    """Every section of ``cfg`` in this process; returns the results as a JSON-able dict."""
    from sarah_data.config import PrepConfig
    from sarah_data.fixtures.dyads import make_fixtures

    threads_before = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)
    results: dict[str, Any] = {"environment": environment(cfg.threads), "config": asdict(cfg)}
    results["config"]["decoder_precision"] = resolve_decoder(cfg.decoder, cfg.mode,
                                                             torch.device("cpu"))
    started = time.perf_counter()
    own_dir = workdir is None
    work = Path(tempfile.mkdtemp(prefix="sarah-bench-")) if own_dir else Path(workdir)
    work.mkdir(parents=True, exist_ok=True)
    try:
        if cfg.prep or cfg.loader:
            log(f"fixtures: {cfg.prep_sessions} x {cfg.prep_sequences_per_session} dyads of "
                f"{cfg.prep_seconds:g} s")
            make_fixtures(work / "raw", sessions=cfg.prep_sessions, seconds=cfg.prep_seconds,
                          sequences_per_session=cfg.prep_sequences_per_session, seed=cfg.seed)
            raw, shards = work / "raw", work / "shards"
            if cfg.prep and cfg.prep_corpus is not None:
                sessions, per_session, seconds = cfg.prep_corpus
                log(f"prep fixtures: {sessions} x {per_session} dyads of {seconds:g} s")
                raw, shards = work / "raw_prep", work / "shards_prep"
                make_fixtures(raw, sessions=sessions, seconds=seconds, sequences_per_session=per_session,
                              seed=cfg.seed, body_model=next((work / "raw" / "body_models").glob("*.npz")))
            if cfg.prep:
                log(f"prep (logmel): -j 1 and -j {cfg.prep_jobs}")
                results["prep"] = {"logmel": bench_prep(raw, shards, PrepConfig(), cfg.prep_jobs,
                                                        cfg.threads)}
            if cfg.loader and not (work / "shards" / "manifest.json").exists():
                from sarah_data.prep import prepare

                with torch_threads(cfg.threads):
                    prepare([work / "raw"], work / "shards", PrepConfig(), jobs=cfg.prep_jobs,
                            progress=False, log=lambda *_: None)
            shutil.rmtree(work / "raw_prep", ignore_errors=True)
            shutil.rmtree(work / "shards_prep", ignore_errors=True)
        if cfg.loader:
            results["loader"] = {}
            for workers in (0, 2):
                log(f"loader: {cfg.loader_windows} windows, {workers} workers")
                results["loader"][f"workers_{workers}"] = bench_loader(
                    work / "shards", cfg.loader_windows, cfg.loader_batch, workers, cfg.seed)
            loader = results["loader"]
            loader["ratio"] = (loader["workers_2"]["windows_per_s"]
                               / loader["workers_0"]["windows_per_s"])
        for size in cfg.sizes:
            sized = bench_model_size(size, cfg, log)
            for section, values in sized.items():
                results.setdefault(section, {})[size] = values
        if cfg.hubert:
            weights = work / "hubert_large_random.pt"
            log("HuBERT-Large: random weights")
            write_random_hubert(weights, cfg.seed)
            if cfg.prep:
                log(f"prep (hubert-large): 2 dyads of {cfg.hubert_prep_seconds:g} s, -j 1 and -j 2")
                make_fixtures(work / "raw_hubert", sessions=1, sequences_per_session=2,
                              seconds=cfg.hubert_prep_seconds, seed=cfg.seed + 1)
                hubert_prep = PrepConfig(extractors=("hubert-large",), hubert_weights=str(weights))
                results["prep"]["hubert-large"] = bench_prep(
                    work / "raw_hubert", work / "shards_hubert", hubert_prep, 2, cfg.threads)
            log(f"HuBERT-Large streaming cost per chunk, windows {cfg.hubert_windows_s} s")
            with torch_threads(cfg.threads):
                results["hubert_streaming"] = bench_hubert_windows(weights, cfg.hubert_windows_s)
    finally:
        if own_dir:
            shutil.rmtree(work, ignore_errors=True)
        torch.set_num_threads(threads_before)
    results["environment"]["load_after"] = list(os.getloadavg())
    results["environment"]["bench_seconds"] = time.perf_counter() - started
    results["goals"] = check_goals(results)
    return results
