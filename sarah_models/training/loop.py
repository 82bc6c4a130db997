"""The training loop, short enough to see whole, with its learning rate, seeds and log."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import torch
from torch import Tensor, nn

from sarah_data.atomic import atomic_write_text

from ..config import TrainConfig
from .weight_average import WeightAverage


def lr_at(step: int, config: TrainConfig, total_steps: int | None = None) -> float:
    """Linear warmup over ``warmup_steps`` to ``lr`` (paper A.2), then ``config.lr_schedule``:
    constant (the paper), or a linear or cosine decay reaching ``lr * final_lr_ratio`` at
    ``total_steps`` (the last step index is total_steps - 1)."""
    warm = min(1.0, (step + 1) / max(1, config.warmup_steps))
    if config.lr_schedule == "constant" or total_steps is None or step < config.warmup_steps:
        return config.lr * warm
    span = max(1, total_steps - 1 - config.warmup_steps)
    progress = min(1.0, (step - config.warmup_steps) / span)
    shape = 1.0 - progress if config.lr_schedule == "linear" else 0.5 * (1.0 + math.cos(math.pi * progress))
    return config.lr * (config.final_lr_ratio + (1.0 - config.final_lr_ratio) * shape)


def make_optimizer(module: nn.Module, config: TrainConfig) -> torch.optim.Optimizer:
    params = [p for p in module.parameters() if p.requires_grad]
    return torch.optim.AdamW(params, lr=config.lr, betas=tuple(config.adam_betas),
                             weight_decay=config.weight_decay)


def step_generator(device: torch.device, seed: int, rank: int, step: int) -> torch.Generator:
    """The generator of one training step: a function of (seed, rank, step) only."""
    return torch.Generator(device=device).manual_seed(
        (seed * 1_000_003 + rank * 7_919 + step) % (2**63))


def training_autocast(device: torch.device) -> torch.autocast:
    """bf16 autocast on CUDA (docs/models.md), nothing elsewhere: every forward of training."""
    return torch.autocast(device_type=device.type, dtype=torch.bfloat16,
                          enabled=device.type == "cuda")


def train_loop(objective: nn.Module, batches: Iterable[Mapping[str, Tensor]],
               optimizer: torch.optim.Optimizer, config: TrainConfig, *, total_steps: int,
               start_step: int = 0, device: torch.device | str = "cpu", rank: int = 0,
               log: RunLog | None = None,
               on_checkpoint: Callable[[int], None] | None = None,
               progress: bool = False,
               average: WeightAverage | None = None) -> list[dict[str, float]]:
    """Optimise ``objective(batch, generator) -> {"loss", ...scalars}`` from ``start_step`` to
    ``total_steps``. ``objective`` may be DDP-wrapped. Returns the logged records (one per
    ``log_every`` steps, scalars averaged over the interval); ``on_checkpoint(step)`` runs every
    ``checkpoint_every`` steps and at the end; ``average`` is updated after every step."""
    from tqdm import tqdm

    device = torch.device(device)
    trainable = [p for group in optimizer.param_groups for p in group["params"]]
    autocast = training_autocast(device)
    objective.train()
    iterator = iter(batches)
    records: list[dict[str, float]] = []
    sums: dict[str, Tensor] = {}
    count, tick = 0, time.perf_counter()
    bar = tqdm(total=total_steps, initial=start_step, disable=not progress, dynamic_ncols=True,
               desc=log.stage if log else "train")
    for step in range(start_step, total_steps):
        try:
            batch = next(iterator)
        except StopIteration:
            raise RuntimeError(f"the batch iterable ran out at step {step} of {total_steps}") from None
        lr = lr_at(step, config, total_steps)
        for group in optimizer.param_groups:
            group["lr"] = lr
        with autocast:
            out = objective(batch, step_generator(device, config.seed, rank, step))
        loss = out["loss"]
        if not torch.isfinite(loss):
            raise FloatingPointError(f"loss is {loss.item()} at step {step + 1}")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if config.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(trainable, config.grad_clip)
        optimizer.step()
        if average is not None:
            average.update()
        for key, value in out.items():
            if value.dim() == 0:
                sums[key] = sums.get(key, 0.0) + value.detach().float()
        count += 1
        done = step + 1
        if done % config.log_every == 0 or done == total_steps:
            now = time.perf_counter()
            record = {"step": done, **{k: float(v) / count for k, v in sums.items()}, "lr": lr,
                      "steps_per_s": count / max(now - tick, 1e-9)}
            if device.type == "cuda":  # what a batch size costs on this card, for sizing runs
                record["cuda_peak_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
            records.append(record)
            if log is not None:
                log.append(record)
            bar.set_postfix(loss=f"{record['loss']:.4g}", steps_s=f"{record['steps_per_s']:.2f}")
            sums, count, tick = {}, 0, now
        bar.update(1)
        if on_checkpoint is not None and (done % config.checkpoint_every == 0 or done == total_steps):
            on_checkpoint(done)
            if log is not None:
                log.plot()
            tick = time.perf_counter()  # steps/s measures training, not checkpoint writing
    bar.close()
    return records


# positive losses, drawn on a log scale
PLOTTED = ("loss", "recon", "velocity", "acceleration", "difference", "contact", "kl")


class RunLog:
    """JSON-lines log plus a loss-curve PNG for one stage."""

    def __init__(self, out_dir: Path, stage: str) -> None:
        self.path = Path(out_dir) / f"{stage}_log.jsonl"
        self.png = Path(out_dir) / f"{stage}_loss.png"
        self.stage = stage

    def records(self) -> list[dict[str, Any]]:
        if not self.path.exists():
            return []
        return [json.loads(line) for line in self.path.read_text().splitlines() if line.strip()]

    def truncate(self, step: int) -> None:
        """Drop lines logged after ``step`` (written after the checkpoint a resume starts from)."""
        kept = [r for r in self.records() if r["step"] <= step]
        atomic_write_text(self.path, "".join(json.dumps(r) + "\n" for r in kept))

    def append(self, record: Mapping[str, Any]) -> None:
        with open(self.path, "a") as fh:
            fh.write(json.dumps(dict(record)) + "\n")

    def plot(self) -> None:
        import matplotlib.pyplot as plt

        from ..generation.plots import save_figure

        rows = self.records()
        if not rows:
            return
        keys = [k for k in PLOTTED if k in rows[-1]]
        fig, ax = plt.subplots(figsize=(7, 4))
        steps = [r["step"] for r in rows]
        for key in keys:
            ax.plot(steps, [r.get(key, math.nan) for r in rows], label=key)
        ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.set_title(f"{self.stage} training loss")
        ax.legend()
        ax.grid(alpha=0.3)
        save_figure(fig, self.png)
