"""The live server under load (``sarah-bench --serve``): how many concurrent sessions hold real
time on this machine, at tiny and paper size, and whether a long run loses, reorders or leaks.

A ``sarah-serve`` process serves random-weight models of each size (int8 path, as deployed), or
for ``fixture-tiny`` the shipped trained model (``--pretrained``), whose decoding chain (seams,
root hold, rigid skeleton, foot lock) random weights' configs leave off;
this process plays N clients over loopback, each sending a 4-frame chunk every 133 ms on the
clock (two voices as s16le PCM, a walking user) and checking every answer's sequence number. A
level holds real time when every session's p99 round trip (send to frames received, queueing
included) is at most ``p99_goal_ms`` and nothing is lost: then each receives 30 frames/s. The
session count doubles until a level fails. The soak then runs the largest count that held, at
tiny size, for ``soak_seconds``, sampling the server's resident memory.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from sarah_data.constants import FPS, SAMPLES_PER_FRAME

from .config import SHIPPED_MODEL
from .load import BackgroundLoad
from .report import interval_text
from .timing import quantile_interval

CHUNK = 4
SIZES = ("tiny", "paper", SHIPPED_MODEL)  # a "size" that is the shipped trained model too


@dataclass
class ServeBenchConfig:
    sizes: tuple[str, ...] = ("tiny", "paper")
    session_counts: tuple[int, ...] = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32)
    level_seconds: float = 15.0
    soak_seconds: float = 600.0  # at least; longer when needed for soak_min_chunks
    soak_min_chunks: int = 10_000
    p99_goal_ms: float = 100.0
    mode: str = "int8"
    steps: int = 4  # solver steps per chunk (the paper's)
    threads: int | None = None  # the server's --threads (None: its automatic policy)
    background_load: int = 0  # busy processes of the bench's own beside every level and the soak
    seed: int = 0


@dataclass
class Level:
    size: str
    sessions: int
    seconds: float
    chunks: int
    lost: int
    reordered: int
    p50_ms: float
    p99_ms: float  # worst session's p99
    min_fps: float  # slowest session's frames received per second of its run
    holds: bool


@dataclass
class ServeBenchResult:
    config: dict
    levels: list[Level] = field(default_factory=list)
    capacity: dict[str, int] = field(default_factory=dict)  # size -> sessions that held
    soak: dict[str, Any] | None = None
    environment: dict[str, Any] = field(default_factory=dict)


def _save_random_run(folder: Path, size: str, seed: int) -> Path:
    from sarah_models.config import RunConfig
    from sarah_models.testing import random_models
    from sarah_models.training.checkpoint import save_checkpoint

    vae, flow, normalizer = random_models(size, seed=seed)
    folder.mkdir(parents=True, exist_ok=True)
    dims = {"motion": vae.motion_dim, "audio": flow.audio_dim}
    save_checkpoint(folder / "flow.pt", {
        "stage": "flow", "step": 0, "total_steps": 0, "config": RunConfig.preset(size).to_dict(),
        "dims": dims, "features": "logmel", "normalizer": normalizer.state_dict(),
        "vae": vae.state_dict(), "flow": flow.state_dict()})
    return folder


class ServerProcess:
    def __init__(self, model: list[str], cfg: ServeBenchConfig):
        """``model``: sarah-serve's model arguments (``--run PATH`` or ``--pretrained NAME``)."""
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        threads = [] if cfg.threads is None else ["--threads", str(cfg.threads)]
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sarah_cli.serve", *model, "--port", "0", "--device",
             "cpu", "--speed", cfg.mode, "--steps", str(cfg.steps), "--max-sessions", "256",
             *threads],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        line = self.proc.stdout.readline()
        match = re.search(r"ws://127\.0\.0\.1:(\d+)/", line)
        if not match:
            self.proc.kill()
            raise RuntimeError(f"sarah-serve did not start: {line}{self.proc.stdout.read()[-2000:]}")
        self.url = f"ws://127.0.0.1:{match.group(1)}/"

    def rss_mb(self) -> float:
        with open(f"/proc/{self.proc.pid}/status") as handle:
            for line in handle:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
        return float("nan")

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()


async def _client(url: str, seconds: float, seed: int, stats: dict) -> None:
    """One session: a chunk every 133 ms on the clock, at most two in flight."""
    from websockets.asyncio.client import connect

    from sarah_models.serving.client import read_frames
    from sarah_models.serving.protocol import encode_pcm, pack

    rng = np.random.default_rng(seed)
    n = CHUNK * SAMPLES_PER_FRAME
    voices = [encode_pcm(0.1 * rng.standard_normal(n).astype(np.float32), "s16le") for _ in range(8)]
    sent: dict[int, float] = {}
    rtts, expected, frames = [], 0, 0
    async with connect(url, max_size=None, compression=None) as ws:
        await ws.send(json.dumps({"type": "open", "version": 1, "gaze": 0.8, "seed": seed}))
        json.loads(await ws.recv())
        in_flight = asyncio.Semaphore(2)
        total = int(seconds * FPS / CHUNK)

        async def receive() -> None:
            nonlocal expected, frames
            async for message in ws:
                if isinstance(message, str):
                    raise RuntimeError(f"server error: {message}")
                header, _ = read_frames(message)
                now = time.perf_counter()
                if header["seq"] != expected:
                    stats["reordered"] += 1
                expected = header["seq"] + 1
                rtts.append(now - sent.pop(header["seq"]))
                frames += header["frames"]
                in_flight.release()
                if header["seq"] == total - 1:
                    return

        receiver = asyncio.create_task(receive())
        start = time.perf_counter()
        for seq in range(total):
            delay = start + seq * CHUNK / FPS - time.perf_counter()
            if delay > 0:
                await asyncio.sleep(delay)
            await in_flight.acquire()
            angle = 0.3 * (seq * CHUNK / FPS)
            head = [[2 * np.sin(angle), 2 * np.cos(angle)]] * CHUNK
            sent[seq] = time.perf_counter()
            await ws.send(pack({"type": "chunk", "seq": seq, "frames": CHUNK, "head": head})
                          + voices[seq % 8] + voices[(seq + 3) % 8])
        try:
            await asyncio.wait_for(receiver, timeout=30)
        except asyncio.TimeoutError:
            receiver.cancel()
        elapsed = time.perf_counter() - start
        await ws.send(json.dumps({"type": "close"}))
    stats["chunks"] += total
    stats["lost"] += len(sent)
    stats["rtts"].append(np.asarray(rtts))
    stats["fps"].append(frames / elapsed)


async def _level(url: str, sessions: int, seconds: float, seed: int) -> dict:
    stats = {"chunks": 0, "lost": 0, "reordered": 0, "rtts": [], "fps": []}
    await asyncio.gather(*(_client(url, seconds, seed + i, stats) for i in range(sessions)))
    return stats


def run_level(url: str, size: str, sessions: int, cfg: ServeBenchConfig) -> Level:
    stats = asyncio.run(_level(url, sessions, cfg.level_seconds, cfg.seed))
    all_rtts = np.concatenate(stats["rtts"]) * 1000
    worst_p99 = max(float(np.percentile(r * 1000, 99)) for r in stats["rtts"] if len(r))
    holds = worst_p99 <= cfg.p99_goal_ms and stats["lost"] == 0 and stats["reordered"] == 0
    return Level(size, sessions, cfg.level_seconds, stats["chunks"], stats["lost"], stats["reordered"],
                 float(np.percentile(all_rtts, 50)), worst_p99, float(min(stats["fps"])), holds)


def run_soak(server: ServerProcess, sessions: int, cfg: ServeBenchConfig,
             log: Callable[[str], None]) -> dict[str, Any]:
    samples: list[tuple[float, float]] = []
    seconds = max(cfg.soak_seconds, cfg.soak_min_chunks / (sessions * FPS / CHUNK))

    async def main() -> dict:
        stats = {"chunks": 0, "lost": 0, "reordered": 0, "rtts": [], "fps": []}

        async def sample() -> None:
            start = time.perf_counter()
            while True:
                samples.append((time.perf_counter() - start, server.rss_mb()))
                await asyncio.sleep(10)

        sampler = asyncio.create_task(sample())
        await asyncio.gather(*(_client(server.url, seconds, cfg.seed + 100 + i, stats)
                               for i in range(sessions)))
        sampler.cancel()
        return stats

    stats = asyncio.run(main())
    rss = np.array(samples)
    settled = rss[rss[:, 0] >= 60] if (rss[:, 0] >= 60).sum() >= 2 else rss
    slope = float(np.polyfit(settled[:, 0] / 60.0, settled[:, 1], 1)[0]) if len(settled) >= 2 else float("nan")
    rtts = np.concatenate(stats["rtts"]) * 1000
    result = {"sessions": sessions, "seconds": seconds, "chunks": stats["chunks"],
              "lost": stats["lost"], "reordered": stats["reordered"],
              "p50_ms": float(np.percentile(rtts, 50)), "p99_ms": float(np.percentile(rtts, 99)),
              "p99_interval": list(quantile_interval(rtts, 0.99)),
              "min_fps": float(min(stats["fps"])),
              "rss_mb_first": float(settled[0, 1]), "rss_mb_last": float(settled[-1, 1]),
              "rss_mb_max": float(rss[:, 1].max()), "rss_slope_mb_per_min": slope,
              "rss_samples": rss.tolist()}
    log(f"soak: {sessions} sessions x {seconds:.0f} s, {result['chunks']} chunks, "
        f"{result['lost']} lost, {result['reordered']} reordered, p99 {result['p99_ms']:.1f}"
        f"{interval_text(result['p99_interval'])} ms, "
        f"RSS {result['rss_mb_first']:.0f} -> {result['rss_mb_last']:.0f} MB")
    return result


def run_serve_bench(cfg: ServeBenchConfig = ServeBenchConfig(),
                    log: Callable[[str], None] = print) -> ServeBenchResult:
    from .bench import environment

    result = ServeBenchResult(config=asdict(cfg), environment=environment(cfg.threads or "auto"))
    with tempfile.TemporaryDirectory() as tmp:
        for size in cfg.sizes:
            model = (["--pretrained", SHIPPED_MODEL] if size == SHIPPED_MODEL else
                     ["--run", str(_save_random_run(Path(tmp) / size, size, cfg.seed))])
            server = ServerProcess(model, cfg)
            try:
                held = 0
                for count in cfg.session_counts:
                    with BackgroundLoad(cfg.background_load):
                        level = run_level(server.url, size, count, cfg)
                    result.levels.append(level)
                    log(f"{size}: {count} sessions: p50 {level.p50_ms:.1f} ms, worst p99 "
                        f"{level.p99_ms:.1f} ms, slowest {level.min_fps:.1f} fps, {level.lost} lost, "
                        f"{level.reordered} reordered: {'holds' if level.holds else 'does not hold'}")
                    if not level.holds:
                        break
                    held = count
                result.capacity[size] = held
                if size == "tiny" and cfg.soak_seconds > 0 and held:
                    with BackgroundLoad(cfg.background_load, max_seconds=2 * cfg.soak_seconds + 900):
                        result.soak = run_soak(server, held, cfg, log)
            finally:
                server.stop()
    return result


def format_serve_report(result: ServeBenchResult) -> str:
    env = result.environment
    busy = result.config.get("background_load", 0)
    lines = [f"sarah-serve under load, {env.get('date', '')}, {env.get('cpu', '')}, "
             f"{result.config['threads'] or 'automatic'} threads, {result.config['mode']}, "
             f"{result.config['steps']} midpoint steps, chunks of {CHUNK} frames"
             + (f", beside {busy} busy processes" if busy else ""),
             "", "| size | sessions | chunks | lost | reordered | p50 ms | worst p99 ms | slowest fps | real time |",
             "|---|---:|---:|---:|---:|---:|---:|---:|:---:|"]
    for level in result.levels:
        lines.append(f"| {level.size} | {level.sessions} | {level.chunks} | {level.lost} | "
                     f"{level.reordered} | {level.p50_ms:.1f} | {level.p99_ms:.1f} | "
                     f"{level.min_fps:.1f} | {'yes' if level.holds else 'no'} |")
    lines.append("")
    lines.append("capacity (sessions holding p99 <= "
                 f"{result.config['p99_goal_ms']:.0f} ms, nothing lost): "
                 + ", ".join(f"{k} {v}" for k, v in result.capacity.items()))
    if result.soak:
        s = result.soak
        lines.append(f"soak: {s['sessions']} tiny sessions for {s['seconds']:.0f} s: {s['chunks']} "
                     f"chunks, {s['lost']} lost, {s['reordered']} reordered, p99 {s['p99_ms']:.1f}"
                     f"{interval_text(s.get('p99_interval'))} ms; "
                     f"server RSS {s['rss_mb_first']:.0f} MB after the first minute, "
                     f"{s['rss_mb_last']:.0f} MB at the end (max {s['rss_mb_max']:.0f}, "
                     f"slope {s['rss_slope_mb_per_min']:+.2f} MB/min)")
    return "\n".join(lines)
