"""Data-side benchmarks: prep's real-time factor, the training loader's throughput, and
HuBERT-Large's streaming cost per chunk."""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from sarah_data.atomic import atomic_path
from sarah_data.constants import AUDIO_SAMPLE_RATE, FPS, SAMPLES_PER_FRAME

from .config import CHUNK_FRAMES
from .timing import torch_threads


def write_random_hubert(path: Path, seed: int = 0) -> Path:
    """HuBERT-Large with random weights, saved as a state dict the extractor's ``weights=`` reads."""
    import torchaudio

    torch.manual_seed(seed)
    model = torchaudio.models.hubert_large()
    with atomic_path(path) as tmp:
        torch.save(model.state_dict(), tmp)
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
        with torch_threads(threads):
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
