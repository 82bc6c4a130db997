"""The order of training batches: endless, deterministic, resumable at any batch."""

from __future__ import annotations

from typing import Callable, Iterable, Iterator

import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler

from ..config import TrainConfig
from .distributed import DistInfo


class EpochBatches:
    """Endless batches, resumable at any batch.

    Epoch e: ``dataset.set_epoch(e)`` when the dataset has it (WindowDataset draws new random
    windows per epoch), then ``DistributedSampler(seed).set_epoch(e)`` (this rank's shuffled
    slice) cut into full batches. A WindowDataset's batches come from one
    ``sarah_data.loader.WindowLoader`` (``num_workers`` processes filling reused batch memory):
    each batch is valid until the next is requested, and ``train_loop`` finishes its step on it
    before (``normalize_batch`` makes new tensors of it). Other datasets go through a DataLoader
    made per epoch.
    ``start_batch`` skips batches already consumed, by index only, without reading any data."""

    def __init__(self, dataset: Dataset, config: TrainConfig, info: DistInfo,
                 start_batch: int = 0, seed_offset: int = 0) -> None:
        self.dataset, self.config, self.info = dataset, config, info
        self.seed = config.seed + seed_offset
        self.sampler = DistributedSampler(range(len(dataset)), num_replicas=info.world_size,
                                          rank=info.rank, shuffle=True, seed=self.seed,
                                          drop_last=True)
        self.per_epoch = len(self.sampler) // config.batch_size
        if self.per_epoch == 0:
            raise ValueError(f"{len(dataset)} training windows give no full batch of "
                             f"{config.batch_size} per process (world size {info.world_size})")
        self.start_batch = start_batch

    def epoch_batches(self, epoch: int) -> list[list[int]]:
        self.sampler.set_epoch(epoch)
        indices = list(self.sampler)
        size = self.config.batch_size
        return [indices[b * size:(b + 1) * size] for b in range(self.per_epoch)]

    def __iter__(self) -> Iterator[dict]:
        epoch, skip = divmod(self.start_batch, self.per_epoch)
        if hasattr(self.dataset, "fill"):  # WindowDataset: batches filled in place, in reused slots
            from sarah_data.loader import WindowLoader

            with WindowLoader(self.dataset, self.config.batch_size, self.config.num_workers) as loader:
                while True:
                    self.dataset.set_epoch(epoch)
                    yield from loader.iter_batches(self.epoch_batches(epoch)[skip:])
                    epoch, skip = epoch + 1, 0
        while True:
            if hasattr(self.dataset, "set_epoch"):
                self.dataset.set_epoch(epoch)
            # collate_windows: WindowDataset batches arrive collated; other items as usual
            from sarah_data.dataset import collate_windows

            loader = DataLoader(self.dataset, batch_sampler=self.epoch_batches(epoch)[skip:],
                                collate_fn=collate_windows, num_workers=self.config.num_workers,
                                pin_memory=self.info.device.type == "cuda",
                                generator=torch.Generator().manual_seed(self.seed * 1_000_003 + epoch))
            yield from loader
            epoch, skip = epoch + 1, 0


def phased_batches(first: Iterable[dict], first_steps: int, then: Iterable[dict]) -> Iterator[dict]:
    """``first_steps`` batches of ``first``, then those of ``then`` (the VAE's short-window
    phase, then its full-length one). ``first`` is closed before ``then`` starts, so its loader
    workers are gone."""
    if first_steps > 0:
        batches = iter(first)
        try:
            for _ in range(first_steps):
                yield next(batches)
        finally:
            getattr(batches, "close", lambda: None)()
    yield from then


def echoed_batches(batches: Iterable[dict], prepare: Callable[[dict, int], dict], times: int,
                   start_step: int = 0) -> Iterator[dict]:
    """Each batch given ``times`` times in a row (``train.flow_echo``), made once by
    ``prepare(batch, step)`` with ``step`` the first training step that uses it. ``batches``
    starts at batch ``start_step // times`` (``EpochBatches(start_batch=...)``); a run resumed
    mid-echo gives that batch's remaining repeats first, so it trains on what an uninterrupted
    run does. ``prepare`` must copy what it keeps: a WindowLoader batch is valid only until the
    next is requested."""
    batch_index, skip = divmod(start_step, times)
    for batch in batches:
        prepared = prepare(batch, batch_index * times)
        for _ in range(times - skip):
            yield prepared
        batch_index, skip = batch_index + 1, 0
