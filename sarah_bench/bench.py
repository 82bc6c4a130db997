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
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from sarah_data.constants import FPS, SAMPLES_PER_FRAME
from sarah_models.accel import (
    cpu_identity,
    cpu_info,
    optimize_for_inference,
    resolve_decoder,
    vector_isa,
    warm_up,
)
from sarah_models.accel.threads import ThreadPolicy, stream_probe
from sarah_models.config import STRIDE, StreamConfig
from sarah_models.sampling.stream import (StreamingGenerator, StreamingSession, generate_offline,
                                          push_together)
from sarah_models.testing import random_models, stream_deviation, synthetic_inputs, without_foot_lock

from .config import CHUNK_FRAMES, SHIPPED_MODEL, BenchConfig
from .data import bench_hubert_windows, bench_loader, bench_prep, write_random_hubert
from .kernels import chunk_weight_bytes, read_floor_ms, total_bytes
from .naive import NaiveStreamer
from .load import BackgroundLoad
from .report import check_goals
from .timing import ChunkClock, StageHooks, percentiles, torch_threads

# --------------------------------------------------------------------------- model benchmarks


def bench_offline(models, frames: int, inputs: dict[str, np.ndarray], features: np.ndarray,
                  config: StreamConfig = StreamConfig(), repeats: int = 3,
                  policy: ThreadPolicy | None = None) -> float:
    """Frames per second of ``generate_offline`` on ``frames`` frames at once (paper 4:
    T / time), the best of ``repeats`` runs (one run lasts about a second: a busy neighbour
    process would otherwise decide the figure). ``policy`` picks the threads before each run."""
    vae, flow, normalizer = models
    head = inputs["user_head"][:frames]
    a = b = features[:frames]
    generate_offline(vae, flow, normalizer, head[:8], a[:8], b[:8], config)  # warm-up
    best = float("inf")
    for _ in range(repeats):
        if policy is not None:
            policy.apply()
        tick = time.perf_counter()
        generate_offline(vae, flow, normalizer, head, a, b, config)
        best = min(best, time.perf_counter() - tick)
    return frames / best


def model_parts(models) -> tuple:
    """(vae, flow, normalizer) of a ``LoadedModels`` (what ``load_model_file`` gives) or of such
    a tuple, which is what the bench's measurements take."""
    if hasattr(models, "vae"):
        return models.vae, models.flow, models.normalizer
    return tuple(models)


def bench_streaming(models, frames: int, inputs: dict[str, np.ndarray], extractor,
                    config: StreamConfig = StreamConfig(),
                    max_seconds: float = float("inf"),
                    policy: ThreadPolicy | None = None) -> dict[str, Any]:
    """Stream ``frames`` frames chunk by chunk from raw audio through the extractor's causal
    mode and ``StreamingGenerator``; fps, per-chunk latency and its split by stage. Stops
    early once ``max_seconds`` have passed (``frames`` then says how many were streamed).
    ``policy`` picks the threads before each chunk (its cost counts in the chunk's time)."""
    vae, flow, normalizer = model_parts(models)
    generator = StreamingGenerator(vae, flow, normalizer, config)
    s = generator.stride
    n = s * SAMPLES_PER_FRAME
    hooks = StageHooks(vae, flow)
    threads_used: list[int] = []
    try:
        for phase in ("warm-up", "measure"):
            generator.reset()
            streams = (extractor.stream(), extractor.stream())
            count = 3 * s if phase == "warm-up" else frames
            clock = ChunkClock()
            hooks.take()
            threads_used.clear()
            started = time.perf_counter()
            for i in range(0, count, s):
                k = i * SAMPLES_PER_FRAME
                tick = time.perf_counter()
                threads_used.append(policy.apply() if policy is not None else torch.get_num_threads())
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
    return {**clock.summary(s, total), "threads_used": threads_share(threads_used)}


def threads_share(threads: list[int]) -> dict[str, float]:
    """{"2": 0.97, "1": 0.03}: the share of chunks run with each thread count."""
    counts = np.bincount(np.asarray(threads, dtype=np.int64)) if threads else np.zeros(0)
    return {str(n): float(c) / len(threads) for n, c in enumerate(counts) if c}


def bench_kernel(thread_counts: tuple[int, ...], calls: int = 300) -> dict[str, Any]:
    """Why thread counts matter under load: one paper-size int8 Linear (1024 -> 4096, the 6 rows
    of a streamed evaluation) timed call by call with each thread count. A chunk runs ~130 such
    parallel kernels, each ending at a barrier that waits for every thread."""
    from torch import nn

    from sarah_models.accel.linears import Int8Linear

    torch.manual_seed(0)
    layer = Int8Linear(nn.Linear(1024, 4096))
    x = torch.randn(6, 1024)
    out: dict[str, Any] = {}
    with torch_threads(1):
        for threads in thread_counts:
            torch.set_num_threads(threads)
            for _ in range(20):
                layer(x)
            times = []
            for _ in range(calls):
                tick = time.perf_counter()
                layer(x)
                times.append(time.perf_counter() - tick)
            out[str(threads)] = percentiles(times)
    return out


def bench_memory_floor(models, thread_counts: tuple[int, ...],
                       config: StreamConfig = StreamConfig()) -> dict[str, Any]:
    """The floor under a streamed chunk (``kernels.read_floor_ms``): its weight bytes, and per
    thread count the ms to read them once in a chunk's order and the fps that allows. A stream
    far above it is bound by its kernels and the operations between them; one near it, by the
    machine's memory."""
    weights = chunk_weight_bytes(models, config)
    out: dict[str, Any] = {"megabytes": total_bytes(weights) / 2**20, "weights": weights, "threads": {}}
    for threads, ms in read_floor_ms(weights, thread_counts).items():
        out["threads"][str(threads)] = {"ms": ms, "fps": 1000.0 * CHUNK_FRAMES / ms}
    return out


def bench_concurrent(models, counts: tuple[int, ...], inputs: dict[str, np.ndarray], extractor,
                     seconds: float, policy: ThreadPolicy | None = None,
                     config: StreamConfig = StreamConfig(), together: bool = True) -> dict[str, Any]:
    """K streams in one process on one compute thread, as one ``sarah-serve`` worker serves K
    sessions: each round pushes every stream's next chunk (raw audio and the user's positions)
    into its ``StreamingSession``, all of them at once (``push_together``: one flow solve for
    the round, the server's way) or with ``together=False`` one after another (round robin, the
    server's way until 2026-11-27). A stream holds real time when it gets >= 30 fps and the p99
    round (the longest a chunk can wait) is at most one chunk period (133 ms). Counts are tried
    in order until one fails; ``fit`` is the most streams that held, and ``every_count_held``
    says that the largest count tried held too (more might fit)."""
    s = STRIDE
    n = s * SAMPLES_PER_FRAME
    period_ms = 1000.0 * s / FPS
    total_frames = inputs["user_head"].shape[0]
    rows = []
    for count in counts:
        sessions = [StreamingSession(StreamingGenerator(*models, replace(config, seed=i)),
                                     extractor, keep_features=False) for i in range(count)]
        rounds: list[float] = []
        started = time.perf_counter()
        i = 0
        while time.perf_counter() - started < seconds:
            tick = time.perf_counter()
            if policy is not None:
                policy.apply()
            j = i % (total_frames - total_frames % s)  # the inputs again from the start
            k = j * SAMPLES_PER_FRAME
            chunk = (inputs["user_head"][j:j + s], inputs["agent_wave"][k:k + n],
                     inputs["user_wave"][k:k + n])
            if together:
                push_together(sessions, [chunk] * count)
            else:
                for session in sessions:
                    session.push(*chunk)
            rounds.append(time.perf_counter() - tick)
            i += s
        elapsed = time.perf_counter() - started
        fps_each = len(rounds) * s / elapsed
        round_ms = percentiles(rounds)
        held = fps_each >= FPS and round_ms["p99"] <= period_ms
        rows.append({"streams": count, "fps_each": fps_each, "round_ms": round_ms,
                     "real_time": bool(held)})
        if not held:
            break
    fit = max((row["streams"] for row in rows if row["real_time"]), default=0)
    return {"rows": rows, "fit": fit, "every_count_held": all(r["real_time"] for r in rows),
            "seconds_per_count": seconds,
            "schedule": "together" if together else "round robin"}


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


class SizeBench:
    """One model size's models, inputs and features, for the idle and the loaded sections."""

    def __init__(self, size: str, cfg: BenchConfig) -> None:
        from sarah_data.features import get_extractor

        self.size, self.cfg = size, cfg
        self.extractor = get_extractor("logmel")
        self.plain = random_models(size, audio_dim=self.extractor.dim, seed=cfg.seed)
        self.fast = optimize_for_inference(self.plain, cfg.mode, decoder=cfg.decoder)
        frames = max(cfg.stream_frames, cfg.naive_frames, cfg.offline_frames)
        self.inputs = synthetic_inputs(frames, cfg.seed)
        self.features = self.extractor.extract(self.inputs["agent_wave"], frames)
        # Each size its own policy: a small model's kernels are too short to share threads.
        self.policy = ThreadPolicy(cfg.threads)
        self._shipped = None
        self.calibration = {str(k): 1000.0 * v for k, v in
                            self.policy.calibrate(stream_probe(self.fast)).items()}

    def shipped_fast(self):
        """The shipped trained model, optimized as the random one: what ``sarah-serve
        --pretrained fixture-tiny`` serves, with the decoding chain (seams, root hold, rigid
        skeleton, foot lock) that random weights' configs leave off; built once."""
        if self._shipped is None:
            self._shipped = model_parts(optimize_for_inference(load_shipped(), self.cfg.mode,
                                                               decoder=self.cfg.decoder))
        return self._shipped

    def offline(self, naive: bool) -> dict[str, Any]:
        cfg = self.cfg
        row = {"frames": cfg.offline_frames,
               "fps": bench_offline(self.fast, cfg.offline_frames, self.inputs, self.features,
                                    policy=self.policy)}
        if naive:
            row["naive_fps"] = bench_offline(self.plain, cfg.offline_frames, self.inputs,
                                             self.features, policy=self.policy)
            row["ratio"] = row["fps"] / row["naive_fps"]
        return row

    def stream(self, config: StreamConfig = StreamConfig(), max_seconds: float | None = None,
               policy: ThreadPolicy | None = None) -> dict[str, Any]:
        """The optimized stream, with this size's policy unless ``policy`` is given."""
        cap = self.cfg.max_stream_seconds if max_seconds is None else max_seconds
        return bench_streaming(self.fast, self.cfg.stream_frames, self.inputs, self.extractor,
                               config, max_seconds=cap, policy=policy or self.policy)

    def thread_figures(self, label: str, log: Callable[[str], None]) -> dict[str, Any]:
        """Concurrent streams in one process (tiny) and the per-kernel cost of each thread
        count (paper size)."""
        out: dict[str, Any] = {}
        if self.size == "tiny" and self.cfg.concurrent_streams:
            log(f"[{label}] concurrent streams in one process: {self.cfg.concurrent_streams}")
            out["concurrent"] = bench_concurrent(self.fast, self.cfg.concurrent_streams,
                                                 self.inputs, self.extractor,
                                                 self.cfg.concurrent_seconds, self.policy)
            log(f"[{label}] the same, round robin (one solve per stream), for the ratio")
            out["concurrent"]["round_robin"] = bench_concurrent(
                self.fast, self.cfg.concurrent_streams, self.inputs, self.extractor,
                self.cfg.concurrent_seconds, self.policy, together=False)
            log(f"[{label}] the same with the shipped fixture-tiny (its decoding chain on)")
            out["concurrent"]["shipped"] = bench_concurrent(
                self.shipped_fast(), self.cfg.concurrent_streams, self.inputs, self.extractor,
                self.cfg.concurrent_seconds, self.policy)
        if self.size == "paper":
            out["kernel"] = bench_kernel(tuple(range(1, len(self.policy.cpus) + 1)))
        log(f"[{label}] memory floor: the time to read one streamed chunk's weights")
        out["memory_floor"] = bench_memory_floor(self.fast, tuple(range(1, len(self.policy.cpus) + 1)))
        return out


def load_shipped():
    """The shipped trained model (``SHIPPED_MODEL``), plain, as ``load_model_file`` gives it."""
    from sarah_models.pretrained import model_path
    from sarah_models.training.model_file import load_model_file

    return load_model_file(model_path(SHIPPED_MODEL))


def shipped_deviation(cfg: BenchConfig) -> dict[str, Any]:
    """The optimized mode against fp32 on the shipped trained model (``--pretrained
    fixture-tiny``): random weights give small, smooth activations and once hid a decoder
    precision that moved a trained model's joints by centimetres (docs/performance.md)."""
    shipped = without_foot_lock(load_shipped())
    fast = optimize_for_inference(shipped, cfg.mode, decoder=cfg.decoder)
    return stream_deviation(shipped, fast, frames=cfg.deviation_frames, seed=cfg.seed).as_dict()


def bench_model_size(bench: SizeBench, log: Callable[[str], None]) -> dict[str, Any]:
    """Offline and streaming, optimized vs naive, and the optimized mode's deviation."""
    cfg, size, policy = bench.cfg, bench.size, bench.policy
    out: dict[str, Any] = {}
    log(f"[{size}] offline generation, {cfg.offline_frames} frames at once")
    out["offline"] = bench.offline(naive=True)
    log(f"[{size}] streaming, {cfg.stream_frames} frames in chunks of {CHUNK_FRAMES} "
        f"(naive reference: {cfg.naive_frames} frames)")
    cap = cfg.max_stream_seconds
    streaming = bench.stream()
    streaming["calibration_ms"] = bench.calibration
    policy.apply()
    streaming["naive"] = bench_naive_streaming(bench.plain, cfg.naive_frames, bench.inputs,
                                               bench.extractor, max_seconds=cap / 2)
    streaming["ratio"] = streaming["fps"] / streaming["naive"]["fps"]
    if cfg.fewer_steps is not None:
        fewer = StreamConfig(steps=cfg.fewer_steps)
        warm_up(bench.fast[1], fewer)
        log(f"[{size}] streaming with {cfg.fewer_steps} midpoint steps "
            f"({2 * cfg.fewer_steps} NFE; changes the output, not an exact optimization)")
        streaming["fewer_steps"] = {"steps": cfg.fewer_steps,
                                    **bench.stream(fewer, cap / 2)}
        log(f"[{size}] deviation: {2 * cfg.fewer_steps} NFE {cfg.mode} vs the paper's 8 NFE fp32")
        streaming["fewer_steps"]["deviation"] = stream_deviation(
            bench.plain, bench.fast, frames=cfg.deviation_frames, seed=cfg.seed,
            optimized_config=fewer).as_dict()
    log(f"[{size}] tolerance: {cfg.mode} vs plain fp32 over {cfg.deviation_frames} frames")
    streaming["deviation"] = stream_deviation(bench.plain, bench.fast, frames=cfg.deviation_frames,
                                              seed=cfg.seed).as_dict()
    if size == "tiny":
        log(f"[{size}] tolerance on trained weights: {cfg.mode} vs fp32, the shipped fixture-tiny")
        streaming["deviation_shipped"] = shipped_deviation(cfg)
    out["streaming"] = streaming
    out.update(bench.thread_figures(size, log))
    return out


def bench_loaded_size(bench: SizeBench, log: Callable[[str], None]) -> dict[str, Any]:
    """The timed figures of ``bench_model_size`` again, while the background load runs, plus
    the stream with a fixed thread count of every core (what the default was before the
    thread policy) for comparison."""
    cfg, size, policy = bench.cfg, bench.size, bench.policy
    policy.measure(0.3)  # the load just changed: decide from it, not from before
    out: dict[str, Any] = {}
    log(f"[{size}, loaded] offline generation")
    out["offline"] = bench.offline(naive=False)
    log(f"[{size}, loaded] streaming")
    out["streaming"] = bench.stream()
    if cfg.fewer_steps is not None:
        out["streaming"]["fewer_steps"] = {"steps": cfg.fewer_steps, **bench.stream(
            StreamConfig(steps=cfg.fewer_steps), cfg.max_stream_seconds / 2)}
    if policy.automatic:
        every_core = ThreadPolicy(threads=len(policy.cpus))
        log(f"[{size}, loaded] streaming with a fixed {len(policy.cpus)} threads (at most "
            f"{cfg.loaded_fixed_seconds:g} s)")
        out["streaming"]["fixed_threads"] = {
            "threads": len(policy.cpus),
            **bench.stream(max_seconds=cfg.loaded_fixed_seconds, policy=every_core)}
    out.update(bench.thread_figures(f"{size}, loaded", log))
    return out


def bench_rounds(bench: SizeBench, processes: int, rounds: int,
                 log: Callable[[str], None]) -> dict[str, Any]:
    """The optimized stream ``rounds`` more times, idle and then beside ``processes`` busy
    processes in each round: per side, every round's fps and p50/p99 chunk latency and their
    median, min and max. One run's figures move with what else the host runs; the median of
    several pairs, taken minutes apart, is the figure to hold a goal to."""
    sides: dict[str, dict[str, list[float]]] = {
        side: {"fps": [], "p50_ms": [], "p99_ms": []} for side in ("idle", "loaded")}
    for i in range(rounds):
        for side in ("idle", "loaded"):
            log(f"[{bench.size}] round {i + 1} of {rounds}, {side}")
            with BackgroundLoad(processes if side == "loaded" else 0):
                bench.policy.measure(0.3)  # the load just changed: decide from it
                row = bench.stream()
            for key, value in (("fps", row["fps"]), ("p50_ms", row["latency_ms"]["p50"]),
                               ("p99_ms", row["latency_ms"]["p99"])):
                sides[side][key].append(value)
    return {side: {key: {"rounds": values, "median": float(np.median(values)),
                         "min": min(values), "max": max(values)}
                   for key, values in figures.items()}
            for side, figures in sides.items()}


# --------------------------------------------------------------------------- the whole run


def environment(threads: int | str) -> dict[str, Any]:
    cpu = cpu_info("model name") or platform.processor() or "unknown"
    isa = vector_isa()
    return {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "cpu": f"{cpu} ({isa})" if isa else cpu, "cpu_identity": cpu_identity(),
            "cores": os.cpu_count(),
            "threads": threads, "torch": torch.__version__,
            "numpy": np.__version__, "python": platform.python_version(),
            "load_before": list(os.getloadavg())}


def run_bench(cfg: BenchConfig = BenchConfig(), workdir: Path | None = None,
              log: Callable[[str], None] = print) -> dict[str, Any]:
    """Every section of ``cfg`` in this process; returns the results as a JSON-able dict."""
    from sarah_data.config import PrepConfig
    from sarah_data.fixtures.dyads import make_fixtures

    threads_before = torch.get_num_threads()
    policy = ThreadPolicy(cfg.threads)
    fixed_threads = policy.apply()  # prep and the loader run with this count throughout
    results: dict[str, Any] = {"environment": environment(cfg.threads or "auto"), "config": asdict(cfg)}
    results["config"]["decoder_precision"] = resolve_decoder(cfg.decoder, cfg.mode)
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
                                                        fixed_threads)}
            if cfg.loader and not (work / "shards" / "manifest.json").exists():
                from sarah_data.prep import prepare

                with torch_threads(fixed_threads):
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
        benches = [SizeBench(size, cfg) for size in cfg.sizes]
        for bench in benches:
            for section, values in bench_model_size(bench, log).items():
                results.setdefault(section, {})[bench.size] = values
        if cfg.background_load:
            log(f"background load: {cfg.background_load} busy processes")
            loaded: dict[str, Any] = {"processes": cfg.background_load}
            with BackgroundLoad(cfg.background_load):
                for bench in benches:
                    for section, values in bench_loaded_size(bench, log).items():
                        loaded.setdefault(section, {})[bench.size] = values
            results["loaded"] = loaded
        if cfg.rounds:
            results["rounds"] = {"processes": cfg.background_load, "count": cfg.rounds}
            for bench in benches:
                results["rounds"][bench.size] = bench_rounds(bench, cfg.background_load,
                                                             cfg.rounds, log)
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
                    work / "raw_hubert", work / "shards_hubert", hubert_prep, 2, fixed_threads)
            log(f"HuBERT-Large streaming cost per chunk, windows {cfg.hubert_windows_s} s")
            with torch_threads(fixed_threads):
                results["hubert_streaming"] = bench_hubert_windows(weights, cfg.hubert_windows_s)
    finally:
        if own_dir:
            shutil.rmtree(work, ignore_errors=True)
        torch.set_num_threads(threads_before)
    results["environment"]["load_after"] = list(os.getloadavg())
    results["environment"]["bench_seconds"] = time.perf_counter() - started
    results["goals"] = check_goals(results)
    return results
