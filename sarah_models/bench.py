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
import json
import os
import platform
import shutil
import tempfile
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch

from sarah_data import icosahedron
from sarah_data.constants import AUDIO_SAMPLE_RATE, FPS, NUM_JOINTS, SAMPLES_PER_FRAME

from .checkpoint import build_models
from .config import RunConfig
from .fast import (MODES, cpu_info, optimize_for_inference, resolve_decoder, stream_deviation,
                   warm_time_grid)
from .flow import FlowModel
from .normalizer import Normalizer
from .stream import (StreamConfig, StreamingGenerator, drop_masks, generate_offline, imputer, integrate,
                     token_noise)
from .vae import CausalVAE

CHUNK_FRAMES = 4  # paper A.3: chunks of s = 4 frames
GOALS = (  # (key, description, target, "min" = at least / "max" = below)
    ("streaming.paper.fps", "streaming fps, paper size, logmel (real time)", 30.0, "min"),
    ("streaming.paper.fps@60", "streaming fps, paper size (paper's 60 fps)", 60.0, "min"),
    ("streaming.paper.latency_ms.p99", "chunk latency p99, paper size (ms)", 33.0, "max"),
    # The brief allows fewer solver steps; they change the output (quality: docs/results.md).
    ("streaming.paper.fewer_steps.latency_ms.p99",
     "chunk latency p99, paper size, fewer solver steps (ms)", 33.0, "max"),
    ("offline.paper.fps", "offline fps, paper size (paper: 600)", 600.0, "min"),
    ("prep.logmel.rtf", "prep real-time factor, logmel, -j 2", 100.0, "min"),
    ("loader.workers_2.windows_per_s", "loader windows/s, 2 workers", 1000.0, "min"),
)


@dataclass(frozen=True)
class BenchConfig:
    """What ``sarah-bench`` runs; ``quick()`` is the CI smoke run (tiny model, small inputs)."""

    threads: int = 2
    mode: str = "int8"  # the optimized path (fast.MODES)
    decoder: str = "auto"  # the VAE decoder's precision in that path (fast.DECODER_PRECISIONS)
    sizes: tuple[str, ...] = ("paper", "tiny")
    stream_frames: int = 400  # streamed by the optimized generator
    naive_frames: int = 64  # streamed by the naive reference (its cost grows per chunk)
    max_stream_seconds: float = 60.0  # a stream stops early past this (slow or loaded machine)
    fewer_steps: int | None = 2  # also stream with this many midpoint steps (None: skip)
    offline_frames: int = 400  # the paper's T
    deviation_frames: int = 64  # tolerance check: optimized vs plain fp32
    prep: bool = True
    prep_sessions: int = 4  # the fixture corpus the loader section reads (as shards)
    prep_sequences_per_session: int = 2
    prep_seconds: float = 60.0
    prep_jobs: int = 2
    # The prep benchmark's own corpus (sessions, sequences per session, seconds): 12 dyads of 4
    # min, 40 dyad-minutes with audio, so that fixed start-up (workers that import torch and load
    # the body model) weighs about as little as in a real corpus. None: the loader's corpus.
    prep_corpus: tuple[int, int, float] | None = (6, 2, 240.0)
    loader: bool = True
    loader_windows: int = 1024  # 64 batches: start-up (fork, slot mapping) paid once, as in training
    loader_batch: int = 16
    hubert: bool = True
    hubert_prep_seconds: float = 6.0
    hubert_windows_s: tuple[float, ...] = (1.0, 2.0, 4.0, 13.2)  # 13.2 s = T = 396 + 4 frames
    seed: int = 0

    def __post_init__(self) -> None:
        if self.threads < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")
        if self.mode not in MODES:
            raise ValueError(f"unknown mode {self.mode!r}; choose from {MODES}")
        resolve_decoder(self.decoder, self.mode, torch.device("cpu"))  # raises on a bad pair
        unknown = [s for s in self.sizes if s not in ("paper", "tiny")]
        if unknown:
            raise ValueError(f"unknown model sizes {unknown}; choose from paper, tiny")
        for name in ("stream_frames", "naive_frames", "offline_frames", "deviation_frames"):
            if getattr(self, name) < CHUNK_FRAMES or getattr(self, name) % CHUNK_FRAMES:
                raise ValueError(f"{name} must be a positive multiple of {CHUNK_FRAMES}")

    @classmethod
    def quick(cls, **overrides: Any) -> "BenchConfig":
        base = cls(sizes=("tiny",), stream_frames=32, naive_frames=16, offline_frames=64,
                   fewer_steps=1,
                   deviation_frames=16, prep_sessions=1, prep_sequences_per_session=2,
                   prep_seconds=14.0, prep_corpus=None, loader_windows=32, loader_batch=8,
                   hubert=False)
        return replace(base, **overrides)


# --------------------------------------------------------------------------- models and inputs


def random_models(size: str = "paper", audio_dim: int = 80, shell_points: int = 256,
                  seed: int = 0, motion_std: float = 0.1, *, init_std: float = 0.02,
                  audio_mean: float = -5.0, audio_std: float = 3.0, latent_mean_std: float = 0.0
                  ) -> tuple[CausalVAE, FlowModel, Normalizer]:
    """VAE + flow of the ``size`` preset with random weights, in eval mode, with a normalizer.

    AdaLN-Zero starts every block and the output at zero, which would make the flow predict
    x1 = 0 whatever its input; those parameters are drawn N(0, init_std) so that conditioning,
    noise and history all matter, as in a trained model. The normalizer: a standing pose as the
    motion mean with per-coordinate std ``motion_std`` m, constant audio statistics, and latent
    means drawn N(0, latent_mean_std) with unit std."""
    config = RunConfig.preset(size)
    dims = {"motion": NUM_JOINTS * 36 + 3 * shell_points, "audio": audio_dim}
    torch.manual_seed(seed)
    vae, flow = build_models(config, dims)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in flow.parameters():
            if not p.any():
                p.copy_(torch.randn(p.shape, generator=g) * init_std)
    rng = np.random.default_rng(seed)
    positions = np.stack([np.zeros(NUM_JOINTS), np.linspace(0.1, 1.7, NUM_JOINTS),
                          np.zeros(NUM_JOINTS)], 1)
    ico = icosahedron.encode(positions, np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3)))
    shell = rng.normal(0, 0.2, (shell_points, 3)) + [0, 1, 0]
    dz = config.vae.latent_dim
    normalizer = Normalizer({
        "motion": (np.concatenate([ico.reshape(-1), shell.reshape(-1)]),
                   np.full(dims["motion"], motion_std)),
        "user_head": (np.zeros(2), np.full(2, 1.5)),
        "audio": (np.full(audio_dim, audio_mean), np.full(audio_dim, audio_std)),
        "latent": (rng.normal(0, latent_mean_std, dz) if latent_mean_std else np.zeros(dz), np.ones(dz)),
    })
    return vae.eval(), flow.eval(), normalizer


def synthetic_inputs(frames: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A user walking an arc (frames, 2) and two 48 kHz tracks of amplitude-modulated noise."""
    rng = np.random.default_rng(seed)
    angle = np.linspace(-0.8, 0.8, frames)
    n = frames * SAMPLES_PER_FRAME
    envelope = 0.5 + 0.5 * np.sin(2 * np.pi * 4.5 * np.arange(n) / AUDIO_SAMPLE_RATE)
    return {
        "user_head": np.stack([1.6 * np.sin(angle), 1.6 * np.cos(angle)], 1).astype(np.float32),
        "agent_wave": (0.1 * envelope * rng.standard_normal(n)).astype(np.float32),
        "user_wave": (0.05 * rng.standard_normal(n)).astype(np.float32),
    }


# --------------------------------------------------------------------------- naive reference


class NaiveStreamer:
    """The reference streaming loop: what ``StreamingGenerator`` computes, without its savings.

    Per chunk it re-encodes the conditioning of the whole window (history + new block), runs
    the conditional and the unconditional pass as two separate network calls at every solver
    evaluation (no batched guidance), and decodes the whole latent history (up to
    ``decoder_blocks``) from scratch instead of one block through a KV cache. Same noise, same
    imputation, same maths: its frames equal ``StreamingGenerator``'s (identity anchor) up to
    float rounding while the stream is at most ``decoder_blocks`` blocks long.
    """

    def __init__(self, vae: CausalVAE, flow: FlowModel, normalizer: Normalizer,
                 config: StreamConfig = StreamConfig()) -> None:
        self.vae, self.flow, self.normalizer, self.config = vae, flow, normalizer, config
        self.stride = vae.stride
        self.audio_keys = {k: normalizer.stats_key(k) for k in ("agent_audio", "user_audio")}
        self.reset()

    def reset(self) -> None:
        self._generator = torch.Generator().manual_seed(self.config.seed)
        self._inputs: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._latents: list[torch.Tensor] = []  # final latents of every block so far
        self._noise: list[torch.Tensor] = []

    def _window(self, items: list) -> list:
        keep = self.config.history_tokens
        return items if keep is None else items[len(items) - min(len(items), keep):]

    @torch.inference_mode()
    def step(self, user_head: np.ndarray, agent_audio: np.ndarray, user_audio: np.ndarray,
             timings: dict[str, float] | None = None) -> np.ndarray:
        """Raw features (s, Da) and world head (s, 2) -> world motion (s, Dx); adds the seconds
        spent in the flow and the decoder to ``timings`` when given."""
        tick = time.perf_counter()
        cfg, nz, flow = self.config, self.normalizer, self.flow
        history = self._window(list(range(len(self._latents))))
        self._inputs.append((user_head, agent_audio, user_audio))
        blocks = [self._inputs[i] for i in history] + [self._inputs[-1]]
        head, a, b = (torch.from_numpy(np.concatenate([blk[j] for blk in blocks]))
                      for j in range(3))
        frames = head.shape[0]
        cond = {"user_head": nz.normalize("user_head", head)[None],
                "agent_audio": nz.normalize(self.audio_keys["agent_audio"], a)[None],
                "user_audio": nz.normalize(self.audio_keys["user_audio"], b)[None],
                "gaze": torch.full((1, frames, 1), 0.0 if cfg.gaze is None else float(cfg.gaze))}
        masks = drop_masks(cfg.gaze, cfg.guide, cfg.cfg_scale)
        branches = [flow.encode_condition(cond, masks[i:i + 1]) for i in range(masks.shape[0])]
        eps = token_noise(self._generator, flow.latent_dim)
        noise = torch.stack([self._noise[i] for i in history] + [eps])
        known = torch.stack([self._latents[i] for i in history]) if history else None
        z = self._solve(branches, noise, known)[-1]
        self._latents.append(z)
        self._noise.append(eps)
        solved = time.perf_counter()
        context = self._latents if cfg.decoder_blocks is None else self._latents[-cfg.decoder_blocks:]
        latents = nz.denormalize("latent", torch.stack(context))[None]
        motion = self.vae.decode(latents)[0, -self.stride:]
        out = nz.denormalize("motion", motion).numpy()
        if timings is not None:
            timings["flow"] = timings.get("flow", 0.0) + solved - tick
            timings["decode"] = timings.get("decode", 0.0) + time.perf_counter() - solved
        return out

    def _solve(self, branches: list[torch.Tensor], noise: torch.Tensor,
               known: torch.Tensor | None) -> torch.Tensor:
        cfg, flow = self.config, self.flow

        def velocity(z: torch.Tensor, tau: float) -> torch.Tensor:
            # naive on purpose: one network call per guidance branch instead of one batch
            x1 = [flow(z[None], tau, cond_tokens=tokens)[0] for tokens in branches]
            if len(x1) == 2:
                x1 = [x1[1] + cfg.cfg_scale * (x1[0] - x1[1])]
            return flow.velocity(x1[0], z, tau)

        return integrate(velocity, noise, imputer(noise, known), cfg)


# --------------------------------------------------------------------------- timing helpers


class _ChunkClock:
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
                "latency_ms": _percentiles(self.latencies),
                "stages_ms": {k: _percentiles(v) for k, v in self.stages.items()}}


def _percentiles(values_s: list[float]) -> dict[str, float]:
    ms = np.asarray(values_s, dtype=np.float64) * 1000.0
    if ms.size == 0:
        return {"p50": float("nan"), "p99": float("nan"), "mean": float("nan")}
    return {"p50": float(np.percentile(ms, 50)), "p99": float(np.percentile(ms, 99)),
            "mean": float(ms.mean())}


class _StageHooks:
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
def _threads(n: int) -> Iterator[None]:
    """Run with ``n`` intra-op threads (prep's in-process tasks set 1; this puts it back)."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


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
    hooks = _StageHooks(vae, flow)
    try:
        for phase in ("warm-up", "measure"):
            generator.reset()
            streams = (extractor.stream(), extractor.stream())
            count = 3 * s if phase == "warm-up" else frames
            clock = _ChunkClock()
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
    clock = _ChunkClock()
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
        warm_time_grid(fast[1], fewer)
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


# --------------------------------------------------------------------------- HuBERT


def write_random_hubert(path: Path, seed: int = 0) -> Path:
    """HuBERT-Large with random weights, saved as a state dict the extractor's ``weights=`` reads."""
    import torchaudio

    torch.manual_seed(seed)
    model = torchaudio.models.hubert_large()
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    torch.save(model.state_dict(), tmp)
    os.replace(tmp, path)
    return path


def bench_hubert_windows(weights: Path, windows_s: tuple[float, ...]) -> list[dict[str, float]]:
    """Cost of one causal HuBERT-Large pass (what each streamed chunk runs) per window length."""
    from sarah_data.features import get_extractor

    extractor = get_extractor("hubert-large", weights=str(weights), device="cpu")
    rng = np.random.default_rng(0)
    chunk_s = CHUNK_FRAMES / FPS
    rows = []
    extractor.extract((0.1 * rng.standard_normal(AUDIO_SAMPLE_RATE // 2)).astype(np.float32), 15)
    for seconds in windows_s:
        frames = max(CHUNK_FRAMES, int(round(seconds * FPS)))
        wave = (0.1 * rng.standard_normal(frames * SAMPLES_PER_FRAME)).astype(np.float32)
        tick = time.perf_counter()
        extractor.extract(wave, frames)
        cost = time.perf_counter() - tick
        rows.append({"window_s": frames / FPS, "ms_per_chunk": cost * 1000.0,
                     "realtime_factor": chunk_s / cost, "fps": CHUNK_FRAMES / cost})
    return rows


# --------------------------------------------------------------------------- prep and loader


def bench_prep(raw: Path, out: Path, config, jobs: int, threads: int) -> dict[str, float]:
    """Prep of ``raw`` with ``jobs`` workers and with ``-j 1`` (the naive reference)."""
    import resource

    from sarah_data.prep import prepare

    def cpu() -> float:  # a finished pool has joined its workers: they count as children
        return sum(getattr(resource.getrusage(who), field) for who in (resource.RUSAGE_SELF,
                   resource.RUSAGE_CHILDREN) for field in ("ru_utime", "ru_stime"))

    result: dict[str, float] = {"jobs": jobs}
    for key, j in (("naive", 1), ("fast", jobs)):
        shutil.rmtree(out, ignore_errors=True)
        cpu_before = cpu()
        with _threads(threads):
            done = prepare([raw], out, config, jobs=j, progress=False, log=lambda *_: None)
        # CPU per dyad-second: the figure that other processes on the machine disturb least
        result[f"{key}_cpu_ms_per_dyad_s"] = 1000 * (cpu() - cpu_before) / max(done.dyad_seconds, 1e-9)
        result[f"{key}_wall_s"] = done.wall_seconds
        result[f"{key}_rtf"] = done.dyad_seconds / max(done.wall_seconds, 1e-9)
        result["dyad_seconds"] = done.dyad_seconds
        result["sequences"] = len(done.written)
    result["rtf"] = result.pop("fast_rtf")
    result["wall_s"] = result.pop("fast_wall_s")
    result["ratio"] = result["rtf"] / result["naive_rtf"]
    return result


def bench_loader(shards: Path, windows: int, batch: int, workers: int, seed: int = 0
                 ) -> dict[str, Any]:
    """400-frame training windows per second through the loader training uses, a WindowLoader
    (`workers` processes filling reused shared-memory batches), with its figures for torch's
    DataLoader (`collate_windows`, fresh memory per batch) as the reference under `dataloader`.
    The first batch (worker start-up) is timed separately. `cpu_ms_per_window` is the CPU time
    of this process and its workers over the whole loop, start-up included, a figure that
    depends far less on other load than the rates do."""
    import resource

    from sarah_data.dataset import WindowDataset, collate_windows
    from sarah_data.loader import WindowLoader

    def cpu() -> float:  # a closed loader has joined its workers: they count as children
        usages = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
        return sum(usage.ru_utime + usage.ru_stime for usage in usages)

    def measure(make: Callable[[], Any]) -> dict[str, float]:
        cpu_before = cpu()
        started = time.perf_counter()
        loader = make()
        first, count, batch_items = None, 0, None
        for batch_items in loader:
            if first is None:
                first = time.perf_counter()
            else:
                count += batch_items["motion"].shape[0]
        del batch_items  # a WindowLoader's batch is a view of its slots
        if isinstance(loader, WindowLoader):
            loader.close()
        total = time.perf_counter() - started
        steady = time.perf_counter() - first if first is not None else float("nan")
        return {"workers": workers, "windows": windows, "startup_s": (first or started) - started,
                "windows_per_s": count / steady if count else float("nan"),
                "windows_per_s_with_startup": windows / total,
                "cpu_ms_per_window": (cpu() - cpu_before) / windows * 1e3}

    dataset = WindowDataset(shards, "train", extractor="logmel", window=400, seed=seed,
                            length=windows)
    dataset.load()  # as training does before its loaders: the split is read once, workers share it
    results: dict[str, Any] = measure(lambda: WindowLoader(dataset, batch, workers))
    results["dataloader"] = measure(lambda: torch.utils.data.DataLoader(
        dataset, batch_size=batch, num_workers=workers, shuffle=False, collate_fn=collate_windows))
    return results


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

                with _threads(cfg.threads):
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
            with _threads(cfg.threads):
                results["hubert_streaming"] = bench_hubert_windows(weights, cfg.hubert_windows_s)
    finally:
        if own_dir:
            shutil.rmtree(work, ignore_errors=True)
        torch.set_num_threads(threads_before)
    results["environment"]["load_after"] = list(os.getloadavg())
    results["environment"]["bench_seconds"] = time.perf_counter() - started
    results["goals"] = check_goals(results)
    return results


def _lookup(results: dict[str, Any], key: str) -> float | None:
    node: Any = results
    for part in key.split("@")[0].split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return float(node)


def check_goals(results: dict[str, Any]) -> list[dict[str, Any]]:
    """Each goal of ``GOALS`` with its measured value (None when not measured) and verdict."""
    rows = []
    for key, text, target, kind in GOALS:
        value = _lookup(results, key)
        met = None if value is None else (value >= target if kind == "min" else value < target)
        rows.append({"goal": key, "description": text, "target": target, "kind": kind,
                     "value": value, "met": met})
    return rows


# --------------------------------------------------------------------------- report


def _deviation_text(label: str, dev: dict[str, float], reference: str = "fp32") -> str:
    return (f"{label} vs {reference} over {dev['frames']} frames: max joint {dev['max_joint_mm']:.3f} mm, "
            f"mean {dev['mean_joint_mm']:.3f} mm (motion scale {dev['motion_scale_mm']:.1f} mm), "
            f"head-angle delta {dev['head_angle_delta']:.4f}")


def _f(value: float | None, digits: int = 1) -> str:
    return "-" if value is None or value != value else f"{value:,.{digits}f}"


def format_report(results: dict[str, Any]) -> str:
    """The results as plain-text tables."""
    env = results["environment"]
    lines = [f"sarah-bench  {env['date']}  {env['cpu']}, {env['cores']} cores, "
             f"{env['threads']} threads, torch {env['torch']}",
             f"load average before {env['load_before'][0]:.2f}, after "
             f"{env.get('load_after', [float('nan')])[0]:.2f} "
             f"(other processes on these cores slow every figure down)", ""]
    prep = results.get("prep", {})
    if prep:
        lines += ["prep (dyad-seconds per wall-second)      fast    naive(-j 1)   ratio   "
                  "CPU ms per dyad-s, fast / naive"]
        for name, row in prep.items():
            lines.append(f"  {name:<14} -j {int(row['jobs'])}, {row['dyad_seconds']:.0f} dyad-s "
                         f"{_f(row['rtf']):>9}x {_f(row['naive_rtf']):>9}x   {_f(row['ratio'], 2)}"
                         f"    {_f(row.get('fast_cpu_ms_per_dyad_s'), 2)} / "
                         f"{_f(row.get('naive_cpu_ms_per_dyad_s'), 2)}")
    loader = results.get("loader")
    if loader:
        lines += ["", "loader (400-frame windows per second)   steady   with start-up   CPU ms/window"]
        rows = [(f"WindowLoader, {key.replace('_', ' ')}", loader[key]) for key in ("workers_0", "workers_2")]
        rows += [(f"DataLoader, {key.replace('_', ' ')} (reference)", loader[key]["dataloader"])
                 for key in ("workers_0", "workers_2") if "dataloader" in loader[key]]
        for label, row in rows:
            lines.append(f"  {label:<38}{_f(row['windows_per_s']):>8}  "
                         f"{_f(row['windows_per_s_with_startup']):>8}   "
                         f"{_f(row.get('cpu_ms_per_window'), 2):>13}")
        lines.append(f"  ratio 2 workers / 0 workers: {_f(loader['ratio'], 2)}")
    offline = results.get("offline", {})
    if offline:
        lines += ["", f"offline generation (fps = T / time, best of 3)   {results['config']['mode']}"
                      f"     fp32 plain   ratio"]
        for size, row in offline.items():
            lines.append(f"  {size:<44}{_f(row['fps']):>8}  {_f(row['naive_fps']):>10}   "
                         f"{_f(row['ratio'], 2)}")
    streaming = results.get("streaming", {})
    if streaming:
        cfg = results["config"]
        lines += ["", "streaming (chunks of 4 frames, midpoint x 4 = 8 NFE, cfg 1.3, logmel audio; "
                      f"fast = {cfg['mode']} flow, {cfg.get('decoder_precision', 'fp32')} decoder)"]
        header = (f"  {'':<16}{'fps':>8}  {'p50 ms':>8}  {'p99 ms':>8}   "
                  f"stage p50/p99 ms: audio | flow | decode | other")
        lines.append(header)
        for size, row in streaming.items():
            variants = [(f"{size} fast", row), (f"{size} naive", row["naive"])]
            if "fewer_steps" in row:
                variants.append((f"{size} fast {2 * row['fewer_steps']['steps']} NFE",
                                 row["fewer_steps"]))
            for label, r in variants:
                st = r["stages_ms"]
                stage_text = " | ".join(f"{_f(st[k]['p50'])}/{_f(st[k]['p99'])}"
                                        for k in ("audio", "flow", "decode", "other"))
                lines.append(f"  {label:<16}{_f(r['fps']):>8}  {_f(r['latency_ms']['p50']):>8}  "
                             f"{_f(r['latency_ms']['p99']):>8}   {stage_text}")
            lines.append(f"  {size} ratio fast/naive {_f(row['ratio'], 2)}; "
                         f"{_deviation_text(results['config']['mode'], row['deviation'])}")
            if "deviation" in row.get("fewer_steps", {}):
                nfe = 2 * row["fewer_steps"]["steps"]
                text = _deviation_text(f"{nfe} NFE {results['config']['mode']}",
                                       row["fewer_steps"]["deviation"], "8 NFE fp32")
                lines.append(f"  {size} {text}"
                             f" (fewer steps change the output: quality in docs/results.md)")
    hubert = results.get("hubert_streaming")
    if hubert:
        lines += ["", "HuBERT-Large causal streaming: one pass per 4-frame chunk (133 ms of audio)",
                  "  window s   ms per chunk   x real time   fps"]
        for row in hubert:
            lines.append(f"  {row['window_s']:>8.1f}   {row['ms_per_chunk']:>12,.0f}   "
                         f"{row['realtime_factor']:>11.3f}   {row['fps']:>5.2f}")
    lines += ["", "goals"]
    for goal in results.get("goals", []):
        verdict = {True: "MET", False: "MISSED", None: "not measured"}[goal["met"]]
        sign = ">=" if goal["kind"] == "min" else "<"
        lines.append(f"  {goal['description']:<48} {_f(goal['value']):>9}  {sign} "
                     f"{goal['target']:g}  {verdict}")
    lines.append(f"\nbench time {results['environment'].get('bench_seconds', 0):.0f} s")
    return "\n".join(lines)


def history_row(results: dict[str, Any]) -> str:
    """One line for the history table of docs/performance.md."""
    env = results["environment"]

    def get(key: str) -> str:
        value = _lookup(results, key)
        return _f(value)

    mode = results["config"]["mode"]
    if results["config"].get("decoder_precision") == "bf16":
        mode += ", bf16 decoder"
    return (f"| {env['date'][:10]} | {env['cpu']} | {env['threads']} | {env['torch']} | "
            f"{mode} | {get('streaming.paper.fps')} | "
            f"{get('streaming.paper.latency_ms.p99')} | "
            f"{get('streaming.paper.fewer_steps.latency_ms.p99')} | {get('offline.paper.fps')} | "
            f"{get('streaming.tiny.fps')} | {get('prep.logmel.rtf')} | "
            f"{get('loader.workers_2.windows_per_s')} | {env['load_before'][0]:.1f} |")


def write_json(path: Path, results: dict[str, Any]) -> None:
    """Write ``results`` to ``path`` via a temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(json.dumps(results, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, path)
