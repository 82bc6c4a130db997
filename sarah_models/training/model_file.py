"""The shareable inference model: ``model.safetensors``, one file, loaded without pickle.

A training checkpoint (``checkpoint.py``) holds optimizer and RNG state for resuming and is read
with ``torch.load``; this file holds only what generation needs, as safetensors tensors plus
string metadata:

    tensors    vae.<name>, flow.<name>, normalizer.<name>  (the modules' state dicts)
    metadata   format "sarah-model", version "1", stage "flow", step, features,
               config (RunConfig.to_dict() as JSON), dims (JSON)

``sarah-train`` writes it beside ``flow.pt`` when the flow stage ends; ``sarah-generate --run``
loads it when the run folder has no ``flow.pt`` (or ``--checkpoint model.safetensors``). The
weights are the checkpoint's, bit for bit, so the motion generated is identical.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, safe_open, save

from sarah_data.atomic import atomic_path

from ..config import DECODING_FIELDS, RunConfig, decoding_settings, set_text
from ..nn.normalizer import Normalizer
from ..nn.vae import CausalVAE
from .checkpoint import LoadedModels, build_models, load_checkpoint

MODEL_FILE = "model.safetensors"
FORMAT = "sarah-model"
VERSION = "1"
PARTS = ("vae", "flow", "normalizer")


def write_model_file(source: str | Path, out: str | Path, decoding: Sequence[str] = (),
                     shards: str | Path | None = None, decoder: str | Path | None = None) -> Path:
    """``out`` (a .safetensors path) from a flow-stage checkpoint or another model file, written
    atomically; ``decoding`` ("vae.boundary_inertia=0.8", ...) sets DECODING_FIELDS; ``shards``
    gives a model without the training data's bone lengths those of its training split;
    ``decoder`` (a checkpoint, run folder or model file) puts its VAE in place of the source's
    (``with_decoder_of``)."""
    source = Path(source)
    data = read_weights(source)
    if data["stage"] != "flow":
        raise ValueError(f"{source}: a {data['stage']}-stage checkpoint; the model file needs "
                         f"the flow stage")
    if decoder is not None:
        data = with_decoder_of(data, decoder)
    config = data["config"]
    if decoding:
        config = with_decoding(RunConfig.from_dict(config), decoding).to_dict()
    if shards is not None and "bone_length_mean" not in data["normalizer"]:
        data["normalizer"] = {**data["normalizer"], **skeleton_statistics(shards)}
    if config["vae"].get("rigid_bones") or config["vae"].get("foot_lock"):
        from ..sampling.decoding import skeleton_lengths

        skeleton_lengths(Normalizer.from_state_dict(data["normalizer"]))  # ValueError if none
    tensors = {f"{part}.{name}": value.contiguous()
               for part in PARTS for name, value in data[part].items()}
    metadata = {"format": FORMAT, "version": VERSION, "stage": "flow", "step": str(int(data["step"])),
                "features": str(data["features"]), "config": json.dumps(config, sort_keys=True),
                "dims": json.dumps(data["dims"], sort_keys=True)}
    out = Path(out)
    with atomic_path(out) as tmp:
        tmp.write_bytes(_sorted_metadata(save(tensors, metadata=metadata)))
    return out


def with_decoding(config: RunConfig, decoding: Sequence[str]) -> RunConfig:
    """``config`` with ``decoding`` ("vae.root_hold=0.15", ...) set; ValueError naming the first
    setting that is not a decoding one (DECODING_FIELDS) or that the config refuses."""
    allowed = decoding_settings()
    for text in decoding:
        if text.partition("=")[0].strip() not in allowed:
            raise ValueError(f"--set {text!r}: only decoding settings ({', '.join(allowed)}) "
                             f"change without training; train a stage to change the others")
    return config.with_overrides(decoding)


def vae_source(path: str | Path) -> Path:
    """What a path names as a VAE: a checkpoint or model file as given, a run folder's ``vae.pt``,
    or its flow checkpoint or model file when it has no ``vae.pt``."""
    path = Path(path)
    if path.is_dir() and (path / "vae.pt").is_file():
        return path / "vae.pt"
    return flow_source(path)


def with_decoder_of(data: dict, decoder: str | Path) -> dict:
    """``data`` (a flow checkpoint's contents) with the VAE of ``decoder``: a decoder stage trained
    from this model's VAE with ``train.freeze_encoder`` reads the very latents the flow learned,
    so it decodes this flow with no flow training. The VAE config comes with it (its decoder's
    sizes), the decoding settings stay the model's. ValueError naming the file unless its encoder
    and its motion statistics are the model's, tensor for tensor."""
    path = vae_source(decoder)
    other = read_weights(path)
    if other["dims"].get("motion") != data["dims"].get("motion"):
        raise ValueError(f"{path}: a VAE of {other['dims'].get('motion')} motion channels, the "
                         f"model's has {data['dims'].get('motion')}")
    own, theirs = RunConfig.from_dict(data["config"]), RunConfig.from_dict(other["config"])
    # Only the names are wanted, so only the VAE is built (a flow would draw from the global RNG).
    encoder = CausalVAE(own.vae, data["dims"]["motion"]).encoder_parameter_names()
    differ = [name for name in encoder
              if name not in other["vae"] or not torch.equal(other["vae"][name], data["vae"][name])]
    if differ:
        raise ValueError(f"{path}: its encoder is not the model's ({len(differ)} tensors differ, "
                         f"e.g. {differ[0]}), so its decoder reads other latents than the flow "
                         f"learned; train it with --init-from this model and --set "
                         f"train.freeze_encoder=true")
    motion = [name for name in other["normalizer"] if name.startswith("motion")]
    if any(name not in data["normalizer"] or not torch.equal(other["normalizer"][name],
                                                             data["normalizer"][name])
           for name in motion):
        raise ValueError(f"{path}: its motion statistics are not the model's (trained on other "
                         f"shards)")
    # in one replace: the config's checks see the model's decoding whole (vae.root_hold_turn
    # needs vae.root_hold)
    vae_config = replace(theirs.vae, **{name: getattr(own.vae, name)
                                        for name in DECODING_FIELDS.get("vae", ())})
    config = replace(own, vae=vae_config).to_dict()
    return {**data, "config": config, "vae": dict(other["vae"])}


def flow_source(path: str | Path) -> Path:
    """What a path names as finished weights: a model file or flow checkpoint as given; in a run
    folder its model file, else its ``flow.pt``.

    The model file is the run's finished model: ``sarah-train`` writes it when the flow stage
    ends, and ``--stage model`` writes it again with other decoding settings or another decoder,
    which ``flow.pt`` (a training checkpoint, with the training config) does not carry. A folder
    read through ``flow.pt`` while its model file decoded otherwise scored the benchmark recipe
    at 12x its model file's FGD_acc, undecoded (docs/results.md, seventy-fifth run)."""
    path = Path(path)
    if not path.is_dir():
        return path
    if (path / MODEL_FILE).is_file():
        return path / MODEL_FILE
    return path / "flow.pt"


def decoding_of(source: str | Path) -> list[str]:
    """The decoding settings (DECODING_FIELDS) a model file, flow checkpoint or run folder was
    written with, as ``--set`` strings: another run's model file decodes the same way without
    spelling them again."""
    # Through RunConfig, so that a file written before a field existed reads its default.
    config = RunConfig.from_dict(read_weights(flow_source(source))["config"])
    return [f"{section}.{name}={set_text(getattr(getattr(config, section), name))}"
            for section, names in DECODING_FIELDS.items() for name in names]



def skeleton_statistics(shards: str | Path) -> dict[str, torch.Tensor]:
    """The normalizer's ``bone_length`` buffers from a shards folder's statistics; stats.h5
    written before they were added is computed again from the shards (same numbers otherwise)."""
    from sarah_data.stats import compute_stats, load_stats

    stats = load_stats(shards)
    if "bone_length/mean" not in stats:
        stats = compute_stats(shards)
    norm = Normalizer({"bone_length": (stats["bone_length/mean"], stats["bone_length/std"])})
    return {name: value.clone() for name, value in norm.state_dict().items()}


def _sorted_metadata(data: bytes) -> bytes:
    """The safetensors bytes with the header's metadata keys sorted. safetensors keeps metadata in
    a Rust HashMap, whose order changes from call to call, so two writes of the same weights
    differed in their first bytes; sorted, the same checkpoint gives the same file (a digest to
    compare). The tensors' byte offsets count from the end of the header, so its length may
    change."""
    length = int.from_bytes(data[:8], "little")
    header = json.loads(data[8:8 + length])
    header["__metadata__"] = dict(sorted(header["__metadata__"].items()))
    text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    text += b" " * (-len(text) % 8)  # safetensors pads to keep the tensors 8-byte aligned
    return len(text).to_bytes(8, "little") + text + data[8 + length:]


def read_model_file(path: str | Path) -> dict:
    """A model file's contents in a training checkpoint's shape (``stage`` "flow", ``step``,
    ``config``, ``dims``, ``features`` and the ``vae``, ``flow`` and ``normalizer`` state dicts),
    so ``sarah-train --init-from`` can fine-tune a shared file; ValueError naming the file when it
    is not ours."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such model file")
    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = handle.metadata() or {}
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as error:
        raise ValueError(f"{path}: not a readable safetensors file ({error})") from None
    if metadata.get("format") != FORMAT:
        raise ValueError(f"{path}: not a SARAH model file (safetensors metadata format "
                         f"{metadata.get('format')!r})")
    if metadata.get("version") != VERSION:
        raise ValueError(f"{path}: model file version {metadata.get('version')}, expected {VERSION}")
    try:
        data = {"stage": "flow", "step": int(metadata["step"]), "features": metadata["features"],
                "config": json.loads(metadata["config"]), "dims": json.loads(metadata["dims"])}
    except (KeyError, ValueError) as error:
        raise ValueError(f"{path}: inconsistent model file metadata ({error})") from None
    for part in PARTS:
        data[part] = {name[len(part) + 1:]: value for name, value in tensors.items()
                      if name.startswith(part + ".")}
    return data


def read_weights(path: str | Path) -> dict:
    """A training checkpoint, or a model file in a checkpoint's shape (by its .safetensors name)."""
    path = Path(path)
    return read_model_file(path) if path.suffix == ".safetensors" else load_checkpoint(path)


def load_model_file(path: str | Path, device: str | torch.device | None = None) -> LoadedModels:
    """Rebuild the models of a model file; ValueError naming the file when it is not ours."""
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    data = read_model_file(path)
    try:
        config = RunConfig.from_dict(data["config"])
        vae, flow = build_models(config, data["dims"])
        vae.load_state_dict(data["vae"])
        flow.load_state_dict(data["flow"])
        normalizer = Normalizer.from_state_dict(data["normalizer"])
    except (KeyError, RuntimeError, TypeError, ValueError) as error:
        raise ValueError(f"{path}: inconsistent model file ({error})") from None
    for module in (vae, flow, normalizer):
        module.to(device).eval()
    return LoadedModels(vae, flow, normalizer, config, dict(data["dims"]), data["features"],
                        data["step"], "flow")
