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

Multi-GPU: launch with ``torchrun`` (``distributed.py``). The pieces: ``objectives.py`` (what
is minimised), ``batches.py`` (data order), ``loop.py`` (the loop), ``checkpoint.py``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Collection, Mapping

import torch
import torch.distributed as dist
from torch import Tensor
from torch.utils.data import Dataset

from sarah_data.atomic import atomic_write_text
from sarah_data.moments import Moments
from sarah_data.skeleton import ICOSAHEDRON_POINTS, ROOT, MotionLayout

from ..config import DECODING_FIELDS, RunConfig, TrainConfig
from ..nn.normalizer import Normalizer
from ..nn.vae import CausalVAE
from .batches import EpochBatches, echoed_batches, phased_batches
from .checkpoint import (
    build_models,
    capture_rng_state,
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
    seed_global_rngs,
)
from .distributed import DistInfo, setup_distributed
from .loop import RunLog, make_optimizer, step_generator, train_loop, training_autocast
from .model_file import read_weights
from .objectives import FlowObjective, VAEObjective
from .weight_average import WeightAverage

STAGES = ("vae", "flow")


MIN_EPOCH_BATCHES = 100  # small corpora: draw more random windows per epoch than pairs


def training_windows(shards_dir: str | Path, config: TrainConfig, world_size: int = 1) -> Dataset:
    """The training WindowDataset of ``config.window`` frames, with at least enough windows for
    MIN_EPOCH_BATCHES batches per epoch."""
    from sarah_data.dataset import WindowDataset

    def make(length: int | None) -> Dataset:
        return WindowDataset(shards_dir, config.split, extractor=config.audio_features,
                             window=config.window, seed=config.seed, length=length)

    dataset = make(None)
    wanted = MIN_EPOCH_BATCHES * config.batch_size * world_size
    if len(dataset) < wanted:  # same windows distribution, just longer epochs
        dataset = make(wanted)
    return dataset


def load_data(shards_dir: str | Path, config: TrainConfig,
              world_size: int = 1) -> tuple[Dataset, dict[str, tuple]]:
    """The training WindowDataset and the model statistics from the shards' stats.h5."""
    from sarah_data.stats import load_stats

    return (training_windows(shards_dir, config, world_size),
            model_stats(load_stats(shards_dir), config.audio_features, shards_dir))


def model_stats(raw: Mapping[str, Any], features: str,
                source: str | Path = "stats.h5") -> dict[str, tuple]:
    """stats.h5's ``motion/mean``, ``user_head/std``, ``audio/<features>/mean`` ... as the
    Normalizer's {"motion", "user_head", "audio"} -> (mean, std), and "bone_length" where the
    shards' statistics have it."""
    out = {}
    for key, prefix in (("motion", "motion"), ("user_head", "user_head"),
                        ("audio", f"audio/{features}")):
        if f"{prefix}/mean" not in raw or f"{prefix}/std" not in raw:
            have = sorted({k.rsplit("/", 1)[0] for k in raw})
            raise ValueError(f"{source}: no statistics {prefix}/mean and /std (has {have}); "
                             f"were the shards prepared with the {features!r} extractor?")
        out[key] = (raw[f"{prefix}/mean"], raw[f"{prefix}/std"])
    if "bone_length/mean" in raw:  # the skeleton a rigid decoding holds bones to
        out["bone_length"] = (raw["bone_length/mean"], raw["bone_length/std"])
    return out


def feature_dims(dataset: Dataset, window: int) -> dict[str, int]:
    item = dataset[0]
    motion, audio = item["motion"], item["agent_audio"]
    if motion.shape[0] != window:
        raise ValueError(f"dataset windows have {motion.shape[0]} frames, config.window is {window}")
    return {"motion": int(motion.shape[-1]), "audio": int(audio.shape[-1])}


def _silent(_: str) -> None:
    pass


def stored_config(checkpoint: Mapping[str, Any]) -> dict[str, Any]:
    """A checkpoint's run config with every field spelled out: runs saved before a field
    existed get its default (the value they were trained with), so comparing with the
    requested config compares meanings, not key sets."""
    return RunConfig.from_dict(checkpoint["config"]).to_dict()


def stale_stages(out_dir: Path, config: RunConfig, stages: tuple[str, ...]) -> list[str]:
    """The stages among ``stages`` whose checkpoint in ``out_dir`` was trained with another
    config of that stage; a changed VAE makes its flow stale too (the flow learned its latents)."""
    stale: list[str] = []
    for stage in STAGES:
        path = out_dir / f"{stage}.pt"
        if stage not in stages or not path.is_file():
            continue
        if stale or stored_config(load_checkpoint(path))[stage] != config.to_dict()[stage]:
            stale.append(stage)
    if "vae" in stale and (out_dir / "flow.pt").is_file() and "flow" not in stale:
        stale.append("flow")
    return stale


def set_aside(out_dir: Path, stages: list[str]) -> Path | None:
    """Move the files of ``stages`` (checkpoint, log, loss plot; the model file with the flow)
    into ``out_dir/replaced-<UTC time>/``; nothing is deleted. Returns that folder."""
    if not stages:
        return None
    import datetime
    import shutil

    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    aside = out_dir / f"replaced-{stamp}"
    aside.mkdir()
    for stage in stages:
        names = [f"{stage}.pt", f"{stage}_log.jsonl", f"{stage}_loss.png"]
        if stage == "flow":
            names.append("model.safetensors")
        for name in names:
            if (out_dir / name).exists():
                shutil.move(str(out_dir / name), str(aside / name))
    return aside


def _check_same(name: str, wanted: Any, stored: Any, path: Path) -> None:
    if wanted != stored:
        raise ValueError(f"{path}: stored {name} config {stored} differs from the requested "
                         f"{wanted}; resume with the same config or use another --out")


# Fields a fine-tune may change: they shape the loss, the decoding or which tokens attend to
# which (flow.attention_window and flow.streamed_context: masks, no weight), not the weights.
FINE_TUNE_FIELDS = {
    "vae": ("beta", "velocity_weight", "acceleration_weight", "contact_weight", "head_weight",
            "root_weight", "lift_weight", "spectral_weight", "moment_weight", "moment_parts",
            "latent_noise", "recon_units", "energy_weight", "energy_frames", "energy_per_point",
            *DECODING_FIELDS["vae"]),
    "flow": ("drop_prob", "gaze_drop_prob", "min_denominator", "difference_weight", "attention_window",
             "streamed_context", "place_noise", "stance_weight", "time_logit_mean", "time_logit_std")}
# Fields that shape the weights only in part: a fine-tune may change one where its rule holds
# for (the source's value, this run's). ``vae.detail_dim``: a deterministic VAE fine-tuned into
# a stochastic decoder keeps all its weights, its new detail input starting from its
# initialisation (``_with_new_detail_input``). ``vae.stance_weight``: the weight makes the
# stance head exist (> 0) and weighs its loss; with a head on both sides only the loss differs.
FINE_TUNE_RULES = {
    "vae": {"detail_dim": lambda stored, wanted: not stored,
            "stance_weight": lambda stored, wanted: bool(stored) and wanted > 0},
    "flow": {}}


def _flow_run_config(config: RunConfig, stored_vae: Mapping[str, Any],
                     vae_settings: Collection[str], path: Path) -> RunConfig:
    """The flow stage's config: ``config`` with the VAE of ``path`` (see ``train``)."""
    try:
        stored = RunConfig.from_dict({**config.to_dict(), "vae": stored_vae})
    except ValueError as error:  # a flow setting this VAE cannot serve (flow.stance_weight)
        raise ValueError(f"{path}: the flow stage trains on this VAE: {error}") from None
    decoding = set(DECODING_FIELDS["vae"])
    differ = {name: (getattr(config.vae, name), getattr(stored.vae, name))
              for name in sorted(vae_settings)
              if getattr(config.vae, name) != getattr(stored.vae, name)}
    clash = [f"vae.{name}={wanted} (it has {has})" for name, (wanted, has) in differ.items()
             if name not in decoding]
    if clash:
        raise ValueError(f"{path}: the flow stage trains on this VAE, and --set asks for "
                         f"another: {', '.join(clash)}; train a VAE with it (--stage vae or "
                         f"all), or leave it out")
    return replace(stored, vae=replace(stored.vae, **{name: wanted for name, (wanted, _) in
                                                      differ.items()}))


def load_init_source(path: str | Path, stage: str) -> dict[str, Any]:
    """The weights ``--init-from`` names for ``stage``: a checkpoint, ``<folder>/<stage>.pt``, or
    a model file (``model.safetensors``, a shipped model included: both stages' weights)."""
    path = Path(path)
    file = path / f"{stage}.pt" if path.is_dir() else path
    data = read_weights(file)
    if stage not in data:
        raise ValueError(f"{file}: a {data['stage']} checkpoint holds no {stage} weights to "
                         f"initialise the {stage} stage from")
    return {**data, "path": file}


def _check_compatible(source: Mapping[str, Any], stage: str, config: RunConfig,
                      dims: Mapping[str, int], features: str) -> None:
    """Refuse an --init-from source whose weights cannot be this stage's, naming the difference."""
    file = source["path"]
    wanted, stored = config.to_dict()[stage], stored_config(source)[stage]
    rules = FINE_TUNE_RULES[stage]
    differ = sorted(k for k in wanted if k not in FINE_TUNE_FIELDS[stage]
                    and wanted[k] != stored.get(k)
                    and not (k in rules and rules[k](stored.get(k), wanted[k])))
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


def _with_new_detail_input(vae: CausalVAE, state: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """``state`` plus the detail input ``vae`` has and ``state`` lacks (``FINE_TUNE_RULES``)."""
    state = dict(state)
    if vae.detail_in is not None and "detail_in.weight" not in state:
        state.update({f"detail_in.{name}": value
                      for name, value in vae.detail_in.state_dict().items()})
    return state


def source_vae_checkpoint(source: Mapping[str, Any]) -> dict[str, Any]:
    """A finished vae-stage checkpoint holding the VAE of ``source`` (a flow checkpoint or a
    model file, as ``load_init_source`` reads it), so a flow can be fine-tuned on it."""
    step = int(source["step"])
    return {"stage": "vae", "step": step, "total_steps": step, "config": source["config"],
            "dims": dict(source["dims"]), "features": source["features"],
            "normalizer": source["normalizer"], "vae": source["vae"],
            "init_from": {"path": str(source["path"]), "step": step}}


def train(stage: str, config: RunConfig, shards_dir: str | Path | None, out_dir: str | Path,
          resume: bool = False, device: str | torch.device | None = None, *,
          init_from: str | Path | None = None, vae_settings: Collection[str] = (),
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
    VAE. The checkpoint records the source as ``init_from``.

    ``vae_settings`` names the VAE fields the caller set (``--set vae.*``). The flow stage takes
    every other VAE field from ``vae.pt``; a named decoding field (DECODING_FIELDS) it takes
    from ``config`` (it changes no weight), and a named field that would change the VAE is an
    error unless ``vae.pt`` already has that value: silently training on another VAE than the
    one asked for is the one outcome a user cannot see."""
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
            raise FileExistsError(f"{ckpt_path} exists: add --resume to continue that run (a "
                                  f"finished one is left as it is), or choose another --out")
        previous = load_checkpoint(ckpt_path)
    source = None if init_from is None else load_init_source(init_from, stage)

    # Initial weights are a function of the seed (resumed runs load theirs over them).
    seed_global_rngs(tcfg.seed + STAGES.index(stage))
    short = None
    if stage == "vae":
        dims = feature_dims(dataset, tcfg.window)
        short = _short_windows(tcfg, total, shards_dir, dims, config.vae.stride, info.world_size)
        if previous is not None:
            _check_same("vae", config.to_dict()["vae"], stored_config(previous)["vae"], ckpt_path)
            normalizer = Normalizer.from_state_dict(previous["normalizer"])
        elif source is not None:
            _check_compatible(source, "vae", config, dims, tcfg.audio_features)
            normalizer = Normalizer.from_state_dict(source["normalizer"])
            if "bone_length" in stats and "bone_length" not in normalizer.keys:
                normalizer.set("bone_length", *stats["bone_length"])  # the shards' skeleton
        else:
            normalizer = Normalizer(stats)
            if config.vae.root_relative:
                _fit_root_relative_stats(normalizer, dataset, tcfg, dims["motion"],
                                         config.vae.root_steps)
        vae, _ = build_models(config, dims)
        if previous is not None:
            vae.load_state_dict(trained_weights(previous, "vae"))
        elif source is not None:
            vae.load_state_dict(_with_new_detail_input(vae, source["vae"]))
        if tcfg.freeze_encoder:
            for part in vae.encoder_modules():
                part.requires_grad_(False)
        run_config, objective = config, VAEObjective(vae, normalizer)
        if vae.block_code is not None and previous is None and source is None:
            kept = _fit_block_code(objective, dataset, tcfg)
            if info.is_main:
                echo(f"vae: block code fitted; it keeps {kept['frame']:.4f} of the weighted "
                     f"variance per frame, {kept['block']:.4f} per block")
    else:
        if not (out_dir / "vae.pt").is_file():
            if previous is not None or source is None:
                raise FileNotFoundError(f"{out_dir / 'vae.pt'}: the flow stage needs a trained "
                                        f"VAE; run the vae stage first (--stage vae or all), or "
                                        f"--init-from a model file or flow checkpoint to "
                                        f"fine-tune its flow on its own VAE")
            if info.is_main:  # a flow fine-tune on the source's VAE, kept for resuming
                out_dir.mkdir(parents=True, exist_ok=True)
                save_checkpoint(out_dir / "vae.pt", source_vae_checkpoint(source))
                echo(f"vae: {out_dir / 'vae.pt'} is the VAE of {source['path']}, unchanged")
            if info.world_size > 1:
                dist.barrier()
        vae_ckpt = load_checkpoint(out_dir / "vae.pt")
        if vae_ckpt["features"] != tcfg.audio_features:
            raise ValueError(f"{out_dir / 'vae.pt'} holds statistics of audio features "
                             f"{vae_ckpt['features']!r}, the flow stage asks for "
                             f"{tcfg.audio_features!r}")
        if vae_ckpt["step"] < vae_ckpt["total_steps"] and info.is_main:
            echo(f"note: {out_dir / 'vae.pt'} stopped at step {vae_ckpt['step']} of "
                 f"{vae_ckpt['total_steps']}; the flow trains on that VAE")
        run_config = _flow_run_config(config, vae_ckpt["config"]["vae"], vae_settings,
                                      out_dir / "vae.pt")
        if tcfg.window % run_config.vae.stride:
            raise ValueError(f"window {tcfg.window} is not a multiple of the VAE stride "
                             f"{run_config.vae.stride}")
        dims = dict(vae_ckpt["dims"])
        if feature_dims(dataset, tcfg.window) != dims:
            raise ValueError(f"dataset widths {feature_dims(dataset, tcfg.window)} differ from "
                             f"the VAE's {dims} in {out_dir / 'vae.pt'}")
        vae, flow = build_models(run_config, dims, flow_seed=tcfg.seed + STAGES.index(stage))
        vae.load_state_dict(vae_ckpt["vae"])
        if previous is not None:
            _check_same("flow", config.to_dict()["flow"], stored_config(previous)["flow"], ckpt_path)
            flow.load_state_dict(trained_weights(previous, "flow"))
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
        if "optimizer" in previous:  # not in a VAE copied from a flow fine-tune's source
            optimizer.load_state_dict(previous["optimizer"])
            restore_rng_state(previous["rng"])
        start = int(previous["step"])
    average = None
    if tcfg.ema_decay > 0:
        average = WeightAverage(objective.trainable, tcfg.ema_decay, updates=start)
        if previous is not None and "trained" in previous:
            average.load_average(previous[stage])
    if info.is_main:
        out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out_dir / "config.json", json.dumps(
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
    if tcfg.compile:  # checkpoints keep the modules' own state dicts (``objective``'s)
        model = torch.compile(model)

    def save(step: int) -> None:
        if not info.is_main:
            return
        payload = {"stage": stage, "step": step, "total_steps": total,
                   "config": run_config.to_dict(), "dims": dims, "features": tcfg.audio_features,
                   "normalizer": normalizer.state_dict(), "vae": vae.state_dict(),
                   "optimizer": optimizer.state_dict(), "rng": capture_rng_state()}
        if stage == "flow":
            payload["flow"] = objective.flow.state_dict()
        if average is not None:  # generation reads the average; --resume the trained weights
            payload["trained"], payload[stage] = payload[stage], average.state_dict()
        if origin is not None:
            payload["init_from"] = origin
        save_checkpoint(ckpt_path, payload)

    # Each phase's batches are numbered on their own, so a resumed run continues either phase.
    done_short = min(start, short.steps) if short else 0
    echo_times = tcfg.flow_echo if stage == "flow" else 1
    loader = EpochBatches(dataset, tcfg, info, start_batch=(start - done_short) // echo_times)
    if echo_times > 1:
        def prepare(batch: dict, step: int) -> dict:
            # A latent="sample" draw of its own stream, fixed by the batch's first step.
            with training_autocast(info.device):
                return objective.prepare(batch, step_generator(info.device, tcfg.seed + 1, info.rank, step))
        loader = echoed_batches(loader, prepare, echo_times, start)
    if short is not None:
        loader = phased_batches(EpochBatches(short.dataset, short.config, info, start_batch=done_short),
                                short.steps - done_short, loader)
    train_loop(model, loader, optimizer, tcfg, total_steps=total, start_step=start,
               device=info.device, rank=info.rank, log=log, on_checkpoint=save,
               progress=progress and info.is_main, average=average)
    if info.world_size > 1:
        dist.barrier()
    return ckpt_path


def trained_weights(checkpoint: Mapping[str, Any], stage: str) -> dict[str, Tensor]:
    """The weights a resumed run continues training: with ``train.ema_decay`` the checkpoint's
    stage key holds the average (``training.weight_average``), the trained ones ``"trained"``."""
    return checkpoint.get("trained", checkpoint[stage])


@dataclass(frozen=True)
class ShortWindows:
    """The VAE's first ``steps`` steps: windows of ``config.window`` frames (train.vae_short_*)."""

    steps: int
    config: TrainConfig
    dataset: Dataset


def _short_windows(config: TrainConfig, total: int, shards_dir: str | Path | None,
                   dims: Mapping[str, int], stride: int, world_size: int) -> ShortWindows | None:
    """The VAE's short-window phase, checked before any training; None when there is none."""
    steps = min(config.vae_short_steps, total)
    if steps == 0 or config.vae_short_window == config.window:
        return None
    if shards_dir is None:
        raise ValueError("train.vae_short_steps reads its short windows from the shards: give shards_dir")
    if config.vae_short_window % stride:
        raise ValueError(f"train.vae_short_window {config.vae_short_window} is not a multiple of the VAE "
                         f"stride {stride}")
    short_config = replace(config, window=config.vae_short_window)
    dataset = training_windows(shards_dir, short_config, world_size)
    if feature_dims(dataset, short_config.window) != dict(dims):
        raise ValueError(f"{shards_dir}: windows of {short_config.window} frames have other widths "
                         f"than those of {config.window}")
    return ShortWindows(steps, short_config, dataset)


@torch.no_grad()
def _fit_root_relative_stats(normalizer: Normalizer, dataset: Dataset, config: TrainConfig,
                             motion_width: int, steps: bool = False) -> None:
    """Make ``normalizer`` standardize motion root-relative (``vae.root_relative``): the root
    joint's icosahedron points (their floor steps with ``steps``, ``vae.root_steps``), then
    per-channel mean/std of the root-relative motion over the first ``latent_stats_batches``
    batches of a fixed order (every rank reads the same ones)."""
    layout = MotionLayout.from_width(motion_width)
    start = layout.joint(ROOT) * ICOSAHEDRON_POINTS
    normalizer.set_root_relative(torch.arange(start, start + ICOSAHEDRON_POINTS), steps)
    mean, std = _channel_stats(normalizer.relative_motion(batch["motion"].double())
                               for _, batch in _first_batches(dataset, config, seed_offset=2))
    normalizer.set("motion", mean, std)


@torch.no_grad()
def _fit_block_code(objective: VAEObjective, dataset: Dataset, config: TrainConfig
                    ) -> dict[str, float]:
    """Fit the VAE's block code (``vae.block_code``) to the standardized motion of the first
    ``latent_stats_batches`` batches of a fixed order, weighted as the loss weighs channels."""
    normalizer = objective.normalizer

    def batches():
        for _, batch in _first_batches(dataset, config, seed_offset=3):
            yield normalizer.normalize_batch({"motion": batch["motion"]}, "cpu")["motion"]

    return objective.vae.block_code.fit(batches, objective.channel_weight)


def _first_batches(dataset: Dataset, config: TrainConfig, seed_offset: int,
                   device: torch.device = torch.device("cpu")):
    """(index, batch) of the first ``latent_stats_batches`` batches of a fixed order, the same on
    every rank and on every call: what the fitted statistics (and the block code) are fitted on."""
    loader = EpochBatches(dataset, config, DistInfo(0, 1, 0, device), seed_offset=seed_offset)
    return zip(range(config.latent_stats_batches), loader)


def _channel_stats(chunks) -> tuple[Tensor, Tensor]:
    """Per-channel mean and population std (float32, on the CPU) of every row of a stream of
    (..., C) tensors, accumulated exactly as the shards' statistics are (``Moments``)."""
    moments = Moments()
    for chunk in chunks:
        moments.add(chunk.detach().reshape(-1, chunk.shape[-1]).double().cpu().numpy())
    mean, std = moments.mean_std(0.0)
    return torch.from_numpy(mean), torch.from_numpy(std)


@torch.no_grad()
def _fit_latent_stats(objective: FlowObjective, dataset: Dataset, config: TrainConfig,
                      info: DistInfo) -> None:
    """Per-channel mean/std of the frozen encoder's latents over the first batches of a fixed
    order; every rank reads the same batches, so all ranks agree without communicating."""
    def latents():
        for i, batch in _first_batches(dataset, config, seed_offset=1, device=info.device):
            motion = objective.normalizer.normalize_batch({"motion": batch["motion"]}, info.device)
            yield objective.latents(motion["motion"], step_generator(info.device, config.seed, 0, i))

    mean, std = _channel_stats(latents())
    objective.normalizer.set("latent", mean, std)
    objective.normalizer.to(info.device)
