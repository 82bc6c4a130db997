"""Staged training: the causal VAE first, then the flow matcher on the frozen VAE's latents.

Run folder (``out_dir``)::

    config.json        RunConfig, feature widths and audio feature name of the run
    vae.pt  flow.pt    latest checkpoint of each stage (see checkpoint.py), replaced atomically
    <stage>_log.jsonl  one JSON line per ``log_every`` steps: step, loss (+ parts), lr, steps/s
    <stage>_loss.png   loss curve, redrawn at every checkpoint

Determinism: the data order comes from ``DistributedSampler(seed, epoch)`` with a resumable
offset, and every random draw of step n (VAE noise, flow tau/eps/CFG drops) comes from a
``torch.Generator`` seeded from (seed, rank, n). A resumed run therefore repeats exactly the
losses of an uninterrupted one. Flow targets are the frozen encoder's mu (``latent="mean"``:
deterministic, and it is what the decoder sees at inference) or a posterior sample
(``latent="sample"``), standardized per channel with statistics of ``latent_stats_batches``
training batches (stored in the normalizer as ``latent``).

Multi-GPU: launch with ``torchrun``; with WORLD_SIZE > 1 the process group is initialised from
the environment (nccl on CUDA, gloo on CPU), each rank reads its own DistributedSampler slice,
and rank 0 alone writes logs and checkpoints.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping

import torch
import torch.distributed as dist
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset, DistributedSampler

from .checkpoint import (build_models, capture_rng_state, load_checkpoint, restore_rng_state,
                         save_checkpoint)
from .config import RunConfig, TrainConfig
from .flow import FlowModel
from .normalizer import Normalizer
from .vae import CausalVAE

STAGES = ("vae", "flow")


# --------------------------------------------------------------------------- distributed setup

@dataclass(frozen=True)
class DistInfo:
    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def resolve_device(device: str | torch.device | None) -> torch.device:
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def setup_distributed(device: str | torch.device | None = None) -> DistInfo:
    """Join the torchrun process group when WORLD_SIZE > 1 (idempotent); pick this rank's device."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank, local_rank = int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))
    dev = resolve_device(device)
    if dev.type == "cuda" and dev.index is None:
        dev = torch.device("cuda", local_rank if world > 1 else torch.cuda.current_device())
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo", init_method="env://",
                                rank=rank, world_size=world)
    return DistInfo(rank, world, local_rank, dev)


def cleanup_distributed() -> None:
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


# --------------------------------------------------------------------------- objectives

class VAEObjective(nn.Module):
    """Standardize the motion of a batch and return the VAE loss dict (plus the planted-foot
    term when ``vae.config.contact_weight`` > 0)."""

    def __init__(self, vae: CausalVAE, normalizer: Normalizer) -> None:
        super().__init__()
        self.vae, self.normalizer = vae, normalizer
        self.contact = PlantedFeet(vae.motion_dim) if vae.config.contact_weight > 0 else None

    @property
    def trainable(self) -> nn.Module:
        return self.vae

    def forward(self, batch: Mapping[str, Tensor], generator: torch.Generator | None = None):
        device = self.normalizer.motion_mean.device
        motion = self.normalizer.normalize_batch({"motion": batch["motion"]}, device)["motion"]
        out = self.vae(motion, generator)
        if self.contact is None:
            return out
        to_metres = lambda x: self.normalizer.denormalize("motion", x.float())  # noqa: E731
        term = self.contact(to_metres(out["x_hat"]), to_metres(motion))
        return {**out, "loss": out["loss"] + self.vae.config.contact_weight * term, "contact": term}


class PlantedFeet(nn.Module):
    """Squared error of the decoded feet's horizontal step while the true foot is planted.

    Planted, per foot and frame step: the true foot joint (icosahedron centroid) is below the
    foot-slide metric's height at both ends of the step and moves less than its speed. The error
    is in units of that speed's step (``foot_min_speed / FPS``: 1 mm at 30 fps), averaged over
    planted steps. Inputs: motion in metres, window frame (floor at y = 0), icosahedra first."""

    def __init__(self, motion_dim: int) -> None:
        super().__init__()
        from sarah_data.constants import FPS, JOINT, NUM_JOINTS

        from .metrics import MetricsConfig

        if motion_dim < NUM_JOINTS * 36:
            raise ValueError(f"vae.contact_weight needs the icosahedron motion layout "
                             f"({NUM_JOINTS}*12*3 channels first); this motion has {motion_dim}")
        metric = MetricsConfig()
        self.joints = [JOINT[name] for name in metric.foot_joints]
        self.max_height, self.step = metric.foot_max_height, metric.foot_min_speed / FPS

    def feet(self, motion: Tensor) -> Tensor:
        b, t, _ = motion.shape
        return torch.stack([motion[..., 36 * j:36 * (j + 1)].reshape(b, t, 12, 3).mean(2)
                            for j in self.joints], dim=2)  # (B, T, feet, 3)

    def forward(self, decoded: Tensor, true: Tensor) -> Tensor:
        pred, gt = self.feet(decoded), self.feet(true)
        true_step = gt[:, 1:, :, [0, 2]] - gt[:, :-1, :, [0, 2]]
        pred_step = pred[:, 1:, :, [0, 2]] - pred[:, :-1, :, [0, 2]]
        planted = ((torch.maximum(gt[:, 1:, :, 1], gt[:, :-1, :, 1]) < self.max_height)
                   & (true_step.norm(dim=-1) < self.step)).float()
        error = (pred_step - true_step).square().sum(-1) / self.step ** 2
        return (error * planted).sum() / planted.sum().clamp_min(1.0)


class FlowObjective(nn.Module):
    """Encode a batch with the frozen VAE and return the flow-matching loss dict."""

    def __init__(self, flow: FlowModel, vae: CausalVAE, normalizer: Normalizer,
                 latent: str = "mean") -> None:
        super().__init__()
        self.flow, self.vae, self.normalizer, self.latent = flow, vae, normalizer, latent
        self.vae.requires_grad_(False).eval()

    @property
    def trainable(self) -> nn.Module:
        return self.flow

    def train(self, mode: bool = True) -> "FlowObjective":
        super().train(mode)
        self.vae.eval()  # frozen: always in inference mode
        return self

    @torch.no_grad()
    def latents(self, motion: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Raw (unstandardized) latents of standardized motion."""
        mu, logvar = self.vae.encode(motion)
        if self.latent == "sample":
            noise = torch.randn(mu.shape, generator=generator, device=mu.device, dtype=mu.dtype)
            mu = mu + noise * (0.5 * logvar).exp()
        return mu.float()

    def forward(self, batch: Mapping[str, Tensor], generator: torch.Generator | None = None):
        inputs = self.normalizer.normalize_batch(batch, self.normalizer.motion_mean.device)
        z = self.normalizer.normalize("latent", self.latents(inputs["motion"], generator))
        return self.flow.loss(z, inputs, generator)


# --------------------------------------------------------------------------- data order

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


# --------------------------------------------------------------------------- logging

PLOTTED = ("loss", "recon", "velocity", "contact", "kl")  # positive losses, drawn on a log scale


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
        _atomic_write_text(self.path, "".join(json.dumps(r) + "\n" for r in kept))

    def append(self, record: Mapping[str, Any]) -> None:
        with open(self.path, "a") as fh:
            fh.write(json.dumps(dict(record)) + "\n")

    def plot(self) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

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
        tmp = self.png.with_name(f".{self.png.name}.tmp")
        fig.savefig(tmp, format="png", dpi=100)
        plt.close(fig)
        os.replace(tmp, self.png)


def _atomic_write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


# --------------------------------------------------------------------------- the loop

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


def train_loop(objective: nn.Module, batches: Iterable[Mapping[str, Tensor]],
               optimizer: torch.optim.Optimizer, config: TrainConfig, *, total_steps: int,
               start_step: int = 0, device: torch.device | str = "cpu", rank: int = 0,
               log: RunLog | None = None,
               on_checkpoint: Callable[[int], None] | None = None,
               progress: bool = False) -> list[dict[str, float]]:
    """Optimise ``objective(batch, generator) -> {"loss", ...scalars}`` from ``start_step`` to
    ``total_steps``. ``objective`` may be DDP-wrapped. Returns the logged records (one per
    ``log_every`` steps, scalars averaged over the interval); ``on_checkpoint(step)`` runs every
    ``checkpoint_every`` steps and at the end."""
    from tqdm import tqdm

    device = torch.device(device)
    trainable = [p for group in optimizer.param_groups for p in group["params"]]
    autocast = torch.autocast(device_type=device.type, dtype=torch.bfloat16,
                              enabled=device.type == "cuda")
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
        for key, value in out.items():
            if value.dim() == 0:
                sums[key] = sums.get(key, 0.0) + value.detach().float()
        count += 1
        done = step + 1
        if done % config.log_every == 0 or done == total_steps:
            now = time.perf_counter()
            record = {"step": done, **{k: float(v) / count for k, v in sums.items()}, "lr": lr,
                      "steps_per_s": count / max(now - tick, 1e-9)}
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


# --------------------------------------------------------------------------- stages

MIN_EPOCH_BATCHES = 100  # small corpora: draw more random windows per epoch than pairs


def load_data(shards_dir: str | Path, config: TrainConfig,
              world_size: int = 1) -> tuple[Dataset, dict[str, tuple]]:
    """The training WindowDataset and the model statistics from the shards' stats.h5."""
    from sarah_data.dataset import WindowDataset
    from sarah_data.stats import load_stats

    def make(length: int | None) -> Dataset:
        return WindowDataset(shards_dir, config.split, extractor=config.audio_features,
                             window=config.window, seed=config.seed, length=length)

    dataset = make(None)
    wanted = MIN_EPOCH_BATCHES * config.batch_size * world_size
    if len(dataset) < wanted:  # same windows distribution, just longer epochs
        dataset = make(wanted)
    return dataset, model_stats(load_stats(shards_dir), config.audio_features, shards_dir)


def model_stats(raw: Mapping[str, Any], features: str,
                source: str | Path = "stats.h5") -> dict[str, tuple]:
    """stats.h5's ``motion/mean``, ``user_head/std``, ``audio/<features>/mean`` ... as the
    Normalizer's {"motion", "user_head", "audio"} -> (mean, std)."""
    out = {}
    for key, prefix in (("motion", "motion"), ("user_head", "user_head"),
                        ("audio", f"audio/{features}")):
        if f"{prefix}/mean" not in raw or f"{prefix}/std" not in raw:
            have = sorted({k.rsplit("/", 1)[0] for k in raw})
            raise ValueError(f"{source}: no statistics {prefix}/mean and /std (has {have}); "
                             f"were the shards prepared with the {features!r} extractor?")
        out[key] = (raw[f"{prefix}/mean"], raw[f"{prefix}/std"])
    return out


def feature_dims(dataset: Dataset, window: int) -> dict[str, int]:
    item = dataset[0]
    motion, audio = item["motion"], item["agent_audio"]
    if motion.shape[0] != window:
        raise ValueError(f"dataset windows have {motion.shape[0]} frames, config.window is {window}")
    return {"motion": int(motion.shape[-1]), "audio": int(audio.shape[-1])}


def _silent(_: str) -> None:
    pass


def _check_same(name: str, wanted: Any, stored: Any, path: Path) -> None:
    if wanted != stored:
        raise ValueError(f"{path}: stored {name} config {stored} differs from the requested "
                         f"{wanted}; resume with the same config or use another --out")


# Fields a fine-tune may change: they shape the loss, not the weights.
LOSS_FIELDS = {"vae": ("beta", "velocity_weight", "contact_weight", "latent_noise"),
               "flow": ("drop_prob", "min_denominator")}


def load_init_source(path: str | Path, stage: str) -> dict[str, Any]:
    """The checkpoint ``--init-from`` names for ``stage``: a file, or ``<folder>/<stage>.pt``."""
    path = Path(path)
    file = path / f"{stage}.pt" if path.is_dir() else path
    data = load_checkpoint(file)
    if stage not in data:
        raise ValueError(f"{file}: a {data['stage']} checkpoint holds no {stage} weights to "
                         f"initialise the {stage} stage from")
    return {**data, "path": file}


def _check_compatible(source: Mapping[str, Any], stage: str, config: RunConfig,
                      dims: Mapping[str, int], features: str) -> None:
    """Refuse an --init-from source whose weights cannot be this stage's, naming the difference."""
    file = source["path"]
    wanted, stored = config.to_dict()[stage], source["config"][stage]
    differ = sorted(k for k in wanted if k not in LOSS_FIELDS[stage] and wanted[k] != stored.get(k))
    if differ:
        pairs = ", ".join(f"{k}: {stored.get(k)} there, {wanted[k]} here" for k in differ)
        raise ValueError(f"{file}: the {stage} architecture differs ({pairs}); --init-from needs "
                         f"the same sizes (use the same --config and --set)")
    if stage == "flow":
        for key in ("latent_dim", "stride"):
            if source["config"]["vae"][key] != config.to_dict()["vae"][key]:
                raise ValueError(f"{file}: its VAE has {key} {source['config']['vae'][key]}, "
                                 f"this run's has {config.to_dict()['vae'][key]}")
    if dict(source["dims"]) != dict(dims):
        raise ValueError(f"{file}: feature widths {dict(source['dims'])} differ from this "
                         f"data's {dict(dims)}")
    if source["features"] != features:
        raise ValueError(f"{file}: trained on audio features {source['features']!r}, this run "
                         f"uses {features!r}")


def train(stage: str, config: RunConfig, shards_dir: str | Path | None, out_dir: str | Path,
          resume: bool = False, device: str | torch.device | None = None, *,
          init_from: str | Path | None = None,
          dataset: Dataset | None = None, stats: Mapping[str, Any] | None = None,
          progress: bool = True, echo: Callable[[str], None] = print) -> Path:
    """Train one stage into ``out_dir`` and return its checkpoint path.

    ``dataset``/``stats`` default to the shards' WindowDataset and stats.h5. The flow stage
    needs ``out_dir/vae.pt`` and takes the VAE's config, widths and data statistics from it.
    Without ``resume`` an existing checkpoint of the stage is an error, never overwritten.

    ``init_from`` (a checkpoint, or a run folder holding ``<stage>.pt``) fine-tunes: the stage's
    weights start from it, while step count, optimizer and LR schedule start afresh, so loss
    weights, dropout and schedule may differ from the source run (the architecture may not).
    A VAE keeps the source's data statistics; a flow refits its latent statistics on this run's
    VAE. The checkpoint records the source as ``init_from``."""
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; choose from {STAGES}")
    if init_from is not None and resume:
        raise ValueError("--init-from starts a new run from another run's weights; --resume "
                         "continues this run: use one of them")
    info = setup_distributed(device)
    out_dir = Path(out_dir)
    tcfg = config.train
    if dataset is None or stats is None:
        if shards_dir is None:
            raise ValueError("train: give shards_dir or both dataset and stats")
        loaded_dataset, loaded_stats = load_data(shards_dir, tcfg, info.world_size)
        dataset = dataset if dataset is not None else loaded_dataset
        stats = stats if stats is not None else loaded_stats
    ckpt_path = out_dir / f"{stage}.pt"
    total = tcfg.vae_steps if stage == "vae" else tcfg.flow_steps
    previous = None
    if ckpt_path.exists():
        if not resume:
            raise FileExistsError(f"{ckpt_path} exists: pass resume=True (--resume) to continue, "
                                  f"or choose another output folder")
        previous = load_checkpoint(ckpt_path)
    source = None if init_from is None else load_init_source(init_from, stage)

    # Initial weights are a function of the seed (resumed runs load theirs over them).
    torch.manual_seed(tcfg.seed + STAGES.index(stage))
    if stage == "vae":
        dims = feature_dims(dataset, tcfg.window)
        if previous is not None:
            _check_same("vae", config.to_dict()["vae"], previous["config"]["vae"], ckpt_path)
            normalizer = Normalizer.from_state_dict(previous["normalizer"])
        elif source is not None:
            _check_compatible(source, "vae", config, dims, tcfg.audio_features)
            normalizer = Normalizer.from_state_dict(source["normalizer"])
        else:
            normalizer = Normalizer(stats)
        vae, _ = build_models(config, dims)
        if previous is not None:
            vae.load_state_dict(previous["vae"])
        elif source is not None:
            vae.load_state_dict(source["vae"])
        if tcfg.freeze_encoder:
            for part in vae.encoder_modules():
                part.requires_grad_(False)
        run_config, objective = config, VAEObjective(vae, normalizer)
    else:
        if not (out_dir / "vae.pt").is_file():
            raise FileNotFoundError(f"{out_dir / 'vae.pt'}: the flow stage needs a trained VAE; "
                                    f"run the vae stage first (--stage vae or all)")
        vae_ckpt = load_checkpoint(out_dir / "vae.pt")
        if vae_ckpt["features"] != tcfg.audio_features:
            raise ValueError(f"{out_dir / 'vae.pt'} holds statistics of audio features "
                             f"{vae_ckpt['features']!r}, the flow stage asks for "
                             f"{tcfg.audio_features!r}")
        if vae_ckpt["step"] < vae_ckpt["total_steps"] and info.is_main:
            echo(f"note: {out_dir / 'vae.pt'} stopped at step {vae_ckpt['step']} of "
                 f"{vae_ckpt['total_steps']}; the flow trains on that VAE")
        run_config = RunConfig.from_dict({**config.to_dict(), "vae": vae_ckpt["config"]["vae"]})
        if tcfg.window % run_config.vae.stride:
            raise ValueError(f"window {tcfg.window} is not a multiple of the VAE stride "
                             f"{run_config.vae.stride}")
        dims = dict(vae_ckpt["dims"])
        if feature_dims(dataset, tcfg.window) != dims:
            raise ValueError(f"dataset widths {feature_dims(dataset, tcfg.window)} differ from "
                             f"the VAE's {dims} in {out_dir / 'vae.pt'}")
        vae, flow = build_models(run_config, dims)
        vae.load_state_dict(vae_ckpt["vae"])
        if previous is not None:
            _check_same("flow", config.to_dict()["flow"], previous["config"]["flow"], ckpt_path)
            flow.load_state_dict(previous["flow"])
            normalizer = Normalizer.from_state_dict(previous["normalizer"])
        else:
            if source is not None:
                _check_compatible(source, "flow", run_config, dims, tcfg.audio_features)
                flow.load_state_dict(source["flow"])
            normalizer = Normalizer.from_state_dict(vae_ckpt["normalizer"])
        objective = FlowObjective(flow, vae, normalizer, tcfg.latent)

    objective.to(info.device)
    if stage == "flow" and previous is None:
        _fit_latent_stats(objective, dataset, tcfg, info)
    optimizer = make_optimizer(objective.trainable, tcfg)
    start = 0
    if previous is not None:
        optimizer.load_state_dict(previous["optimizer"])
        restore_rng_state(previous["rng"])
        start = int(previous["step"])
    if info.is_main:
        out_dir.mkdir(parents=True, exist_ok=True)
        _atomic_write_text(out_dir / "config.json", json.dumps(
            {**run_config.to_dict(), "dims": dims, "features": tcfg.audio_features}, indent=2))
    log = RunLog(out_dir, stage) if info.is_main else None
    if log is not None:
        log.truncate(start)
    if not info.is_main:
        echo = _silent
    if start >= total:
        echo(f"{stage}: already trained to step {start} (>= {total}); nothing to do")
        return ckpt_path
    origin = previous.get("init_from") if previous is not None else None
    if source is not None:
        origin = {"path": str(source["path"]), "step": int(source["step"])}
    echo(f"{stage}: steps {start} -> {total} on {info.device} (world size {info.world_size}), "
         f"{sum(p.numel() for p in objective.trainable.parameters()) / 1e6:.2f}M parameters"
         + (f" ({sum(p.numel() for p in objective.trainable.parameters() if p.requires_grad) / 1e6:.2f}M "
            f"trained, encoder frozen)" if stage == "vae" and tcfg.freeze_encoder else "")
         + (f", initialised from {origin['path']} (step {origin['step']})" if origin else ""))

    model = objective
    if info.world_size > 1:
        from torch.nn.parallel import DistributedDataParallel

        model = DistributedDataParallel(
            objective, device_ids=[info.device.index] if info.device.type == "cuda" else None)

    def save(step: int) -> None:
        if not info.is_main:
            return
        payload = {"stage": stage, "step": step, "total_steps": total,
                   "config": run_config.to_dict(), "dims": dims, "features": tcfg.audio_features,
                   "normalizer": normalizer.state_dict(), "vae": vae.state_dict(),
                   "optimizer": optimizer.state_dict(), "rng": capture_rng_state()}
        if stage == "flow":
            payload["flow"] = objective.flow.state_dict()
        if origin is not None:
            payload["init_from"] = origin
        save_checkpoint(ckpt_path, payload)

    loader = EpochBatches(dataset, tcfg, info, start_batch=start)
    train_loop(model, loader, optimizer, tcfg, total_steps=total, start_step=start,
               device=info.device, rank=info.rank, log=log, on_checkpoint=save,
               progress=progress and info.is_main)
    if info.world_size > 1:
        dist.barrier()
    return ckpt_path


@torch.no_grad()
def _fit_latent_stats(objective: FlowObjective, dataset: Dataset, config: TrainConfig,
                      info: DistInfo) -> None:
    """Per-channel mean/std of the frozen encoder's latents over the first batches of a fixed
    order; every rank reads the same batches, so all ranks agree without communicating."""
    single = DistInfo(0, 1, 0, info.device)
    loader = EpochBatches(dataset, config, single, seed_offset=1)
    total = torch.zeros((), dtype=torch.float64, device=info.device)
    s1 = s2 = None
    for i, batch in zip(range(config.latent_stats_batches), loader):
        motion = objective.normalizer.normalize_batch({"motion": batch["motion"]}, info.device)
        z = objective.latents(motion["motion"], step_generator(info.device, config.seed, 0, i))
        z = z.reshape(-1, z.shape[-1]).double()
        s1 = z.sum(0) if s1 is None else s1 + z.sum(0)
        s2 = z.square().sum(0) if s2 is None else s2 + z.square().sum(0)
        total += z.shape[0]
    mean = s1 / total
    std = (s2 / total - mean.square()).clamp_min(0).sqrt()
    objective.normalizer.set("latent", mean.float().cpu(), std.float().cpu())
    objective.normalizer.to(info.device)
