"""HuBERT features at 30 fps (the paper's audio features, section 3), offline and causal.

Architecture: ``torchaudio.models.hubert_large()`` (or ``hubert_base()``). Weights come from a local
file only: ``weights=PATH`` (``--hubert-weights PATH``), else the file torchaudio's HUBERT_LARGE
bundle would have downloaded, ``<torch.hub.get_dir()>/checkpoints/hubert_fairseq_large_ll60k.pth``.
The file may also be fairseq's release checkpoint (``hubert_large_ll60k.pt``) or a Hugging Face
model folder (``hubert-large-ll60k/`` with model.safetensors or pytorch_model.bin): their names are
mapped to torchaudio's (``_CHECKPOINT_NAMES``). Nothing is ever downloaded, and torch files load
with ``weights_only=True``. Shards record the weights' sha256 (``HubertExtractor.record``).

Alignment. HuBERT reads 16 kHz audio; its conv stack has a receptive field of 400 samples and a
stride of 320, so HuBERT frame i sees samples [320 i, 320 i + 400) and is centred at
(320 i + 200) / 16000 s (50 Hz). Motion frame t is centred at (t + 0.5) / 30 s; its feature is the
linear interpolation between the two HuBERT frames around that time (the first / last HuBERT frame
beyond either end).

Offline (training data) the whole clip goes through the model at once, as the paper did (HuBERT is
not causal: features see some future audio). Clips longer than ``max_segment_frames`` are cut into
segments that overlap by ``segment_context_frames`` on each side, whose outputs are discarded, so
attention memory stays bounded.

Streaming (paper A.2) is causal: for each chunk of up to ``chunk_frames`` new frames the model sees
the chunk and the ``past_frames`` frames before it (396 = T - s with T = 400, s = 4) and nothing
later; the chunk's features are read off the end of that window. Features therefore depend on how
frames are grouped into chunks, never on future audio.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torchaudio

from sarah_data.constants import AUDIO_SAMPLE_RATE, FPS, SAMPLES_PER_FRAME
from sarah_data.features.base import AudioFeatureExtractor, FeatureStream, fit_to_frames, register_extractor

HUBERT_SAMPLE_RATE = 16_000
HUBERT_STRIDE = 320  # samples at 16 kHz between HuBERT frames (product of the conv strides)
HUBERT_RECEPTIVE_FIELD = 400  # samples at 16 kHz that one HuBERT frame reads through the conv stack

_ARCHITECTURES = {
    "large": (torchaudio.models.hubert_large, torchaudio.pipelines.HUBERT_LARGE),
    "base": (torchaudio.models.hubert_base, torchaudio.pipelines.HUBERT_BASE),
}
# Prefixes of checkpoints that wrap a Wav2Vec2Model: HuBERTPretrainModel ("wav2vec2."), torchaudio's
# waveform-normalizing bundle wrapper ("model."), DataParallel/DDP ("module.").
_WRAPPER_PREFIXES = ("wav2vec2.", "model.", "module.", "hubert.", "w2v_model.")
# The same weights under fairseq's names (the HuBERT release's .pt) and Hugging Face's
# (hubert-large-ll60k): the first pattern that matches renames a key to torchaudio's.
_CHECKPOINT_NAMES = [(re.compile(pattern), replacement) for pattern, replacement in (
    (r"^feature_extractor\.conv_layers\.0\.2\.(weight|bias)$", r"feature_extractor.conv_layers.0.layer_norm.\1"),
    (r"^feature_extractor\.conv_layers\.(\d+)\.0\.(weight|bias)$", r"feature_extractor.conv_layers.\1.conv.\2"),
    (r"^feature_extractor\.conv_layers\.(\d+)\.2\.1\.(weight|bias)$", r"feature_extractor.conv_layers.\1.layer_norm.\2"),
    (r"^post_extract_proj\.(.+)$", r"encoder.feature_projection.projection.\1"),
    (r"^layer_norm\.(weight|bias)$", r"encoder.feature_projection.layer_norm.\1"),
    (r"^feature_projection\.(.+)$", r"encoder.feature_projection.\1"),
    (r"^encoder\.pos_conv\.0\.(.+)$", r"encoder.transformer.pos_conv_embed.conv.\1"),
    (r"^encoder\.pos_conv_embed\.(.+)$", r"encoder.transformer.pos_conv_embed.\1"),
    (r"^encoder\.layer_norm\.(.+)$", r"encoder.transformer.layer_norm.\1"),
    (r"^encoder\.layers\.(\d+)\.self_attn_layer_norm\.(.+)$", r"encoder.transformer.layers.\1.layer_norm.\2"),
    (r"^encoder\.layers\.(\d+)\.self_attn\.(.+)$", r"encoder.transformer.layers.\1.attention.\2"),
    (r"^encoder\.layers\.(\d+)\.fc1\.(.+)$", r"encoder.transformer.layers.\1.feed_forward.intermediate_dense.\2"),
    (r"^encoder\.layers\.(\d+)\.fc2\.(.+)$", r"encoder.transformer.layers.\1.feed_forward.output_dense.\2"),
    (r"^encoder\.layers\.(\d+)\.(.+)$", r"encoder.transformer.layers.\1.\2"),
)]
# Where a Hugging Face model folder keeps its weights, preferred first.
HF_WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin")
# Old-style weight norm (what torchaudio's bundle files store) -> the parametrization torchaudio uses now.
_LEGACY_WEIGHT_NORM = {".weight_g": ".parametrizations.weight.original0",
                       ".weight_v": ".parametrizations.weight.original1"}


class MissingWeightsError(FileNotFoundError):
    """The HuBERT weight file is not on this machine (it is never downloaded)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else super().__str__()


@dataclass(frozen=True)
class HubertConfig:
    """HuBERT feature settings.

    weights: local weight file; None -> torchaudio's cache file for the architecture.
    architecture: "large" (the paper's, 24 layers x 1024) or "base" (12 x 768).
    layer: transformer layer whose output is the feature, 1-based; None -> exactly what the model
        returns (``model(wave)``: for "large" the 24th layer's output, for "base" the 12th after the
        encoder's final layer norm), the "HuBERT features" of common use; the paper names no layer.
    normalize_waveform: zero mean, unit variance per model input (per clip offline, per window
        streaming), as torchaudio's HUBERT_LARGE bundle does.
    past_frames, chunk_frames: the streaming window (paper A.2: T - s = 396 past frames, s = 4).
    max_segment_frames, segment_context_frames: offline segmentation of long clips.
    device: None -> CUDA when available, else CPU.
    """

    weights: str | None = None
    architecture: str = "large"
    layer: int | None = None
    normalize_waveform: bool = True
    past_frames: int = 396
    chunk_frames: int = 4
    max_segment_frames: int = 1800
    segment_context_frames: int = 150
    device: str | None = None

    def __post_init__(self) -> None:
        if self.architecture not in _ARCHITECTURES:
            raise ValueError(f"hubert: architecture must be one of {sorted(_ARCHITECTURES)}, got {self.architecture!r}")
        if self.past_frames < 0 or self.chunk_frames < 1:
            raise ValueError("hubert: need past_frames >= 0 and chunk_frames >= 1")
        if self.max_segment_frames <= 2 * self.segment_context_frames or self.segment_context_frames < 0:
            raise ValueError("hubert: max_segment_frames must exceed 2 * segment_context_frames >= 0")


def bundle_file_name(architecture: str = "large") -> str:
    """The file name of torchaudio's bundle weights, e.g. hubert_fairseq_large_ll60k.pth (from
    the bundle's private ``_path``, checked with torchaudio 2.11.0: it has no public one)."""
    return Path(_ARCHITECTURES[architecture][1]._path).name


def default_weights_path(architecture: str = "large") -> Path:
    """Where torchaudio's bundle keeps the weights once downloaded (torch hub cache)."""
    return Path(torch.hub.get_dir()) / "checkpoints" / bundle_file_name(architecture)


def _checkpoint_state_dict(checkpoint: object, path: Path) -> dict[str, torch.Tensor]:
    """The tensor dict inside a checkpoint: a bare state dict or one under "state_dict"/"model"."""
    if not isinstance(checkpoint, dict):
        raise ValueError(f"{path}: not a HuBERT state dict (the file holds a {type(checkpoint).__name__})")
    for key in ("state_dict", "model"):
        if isinstance(checkpoint.get(key), dict):
            checkpoint = checkpoint[key]
    return {k: v for k, v in checkpoint.items() if isinstance(v, torch.Tensor)}


def _match_keys(state: dict[str, torch.Tensor], expected: set[str], path: Path, architecture: str
                ) -> dict[str, torch.Tensor]:
    """Rename the checkpoint's keys to the model's, dropping pretraining-only entries."""
    matched: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        name = key
        for old, new in _LEGACY_WEIGHT_NORM.items():
            if name.endswith(old):
                name = name[: -len(old)] + new
        while name not in expected and name.startswith(_WRAPPER_PREFIXES):
            name = name.split(".", 1)[1]
        if name not in expected:
            for pattern, replacement in _CHECKPOINT_NAMES:
                if pattern.match(name):
                    name = pattern.sub(replacement, name)
                    break
        if name in expected:
            matched[name] = value
    missing = sorted(expected - matched.keys())
    if missing:
        raise ValueError(f"{path}: not a HuBERT-{architecture} state dict: {len(missing)} of {len(expected)} "
                         f"weights missing (e.g. {missing[0]})")
    return matched


def weight_file(path: Path) -> Path:
    """The weight file itself: ``path``, or inside a Hugging Face model folder its
    model.safetensors / pytorch_model.bin."""
    if path.is_dir():
        for name in HF_WEIGHT_FILES:
            if (path / name).is_file():
                return path / name
        raise MissingWeightsError(f"{path}: a folder without {' or '.join(HF_WEIGHT_FILES)} "
                                  f"(a Hugging Face HuBERT folder such as hubert-large-ll60k has one)")
    return path


def read_weight_file(path: Path) -> dict:
    """The tensors of a local weight file: safetensors, or a torch file loaded with
    ``weights_only=True`` (fairseq's release files also hold an argparse Namespace of settings,
    which is allowed; no other Python object is ever unpickled)."""
    import argparse

    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        try:
            return load_file(str(path))
        except Exception as error:  # noqa: BLE001 - a foreign or truncated file is one line
            raise ValueError(f"{path}: cannot read as safetensors ({type(error).__name__}: {error})") from None
    try:
        with torch.serialization.safe_globals([argparse.Namespace]):
            return torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception as error:  # a truncated or foreign file: name it, do not dump a traceback
        hint = ""
        if "weights_only" in str(error) or "Unsupported global" in str(error):
            hint = ("; it holds Python objects beyond tensors (e.g. a fairseq checkpoint's omegaconf "
                    "settings): save its 'model' state dict alone, torch.save(ckpt['model'], PATH)")
        first = str(error).strip().splitlines()[0] if str(error).strip() else ""
        raise ValueError(f"{path}: cannot read as a torch weight file ({type(error).__name__}: "
                         f"{first}){hint}") from None


def weights_sha256(weights: str | Path | None, architecture: str = "large") -> str:
    """The sha256 of the weight file an extractor loads (what shards record, not its path)."""
    from sarah_data.shards.h5io import file_sha256

    return file_sha256(weight_file(Path(weights).expanduser() if weights else default_weights_path(architecture)))


def load_hubert(weights: str | Path | None, architecture: str = "large") -> torch.nn.Module:
    """A torchaudio Wav2Vec2Model (HuBERT) in eval mode on CPU, weights from a local file only."""
    path = Path(weights).expanduser() if weights else default_weights_path(architecture)
    path = weight_file(path)
    if not path.is_file():
        bundle_file = bundle_file_name(architecture)
        raise MissingWeightsError(
            f"HuBERT-{architecture} weights not found at {path}: put torchaudio's {bundle_file} there or pass "
            f"--hubert-weights PATH (weights are never downloaded)")
    factory = _ARCHITECTURES[architecture][0]
    # Built on the meta device: random initialization of 300M parameters is wasted work here.
    with torch.device("meta"):
        model = factory()
    checkpoint = read_weight_file(path)
    state = _match_keys(_checkpoint_state_dict(checkpoint, path), set(model.state_dict()), path, architecture)
    try:
        model.load_state_dict(state, strict=True, assign=True)
    except RuntimeError as error:
        detail = str(error).strip().splitlines()[-1].strip()
        raise ValueError(f"{path}: weights do not fit HuBERT-{architecture}: {detail}") from None
    return model.eval().requires_grad_(False)


def _resolve_device(device: str | torch.device | None) -> torch.device:
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


class _Hubert:
    """Model plus the window -> per-motion-frame computation, shared by offline and streaming."""

    def __init__(self, model: torch.nn.Module, config: HubertConfig, device: torch.device) -> None:
        self.model = model.to(device)
        self.config = config
        self.device = device
        num_layers = len(model.encoder.transformer.layers)
        self.layer = num_layers if config.layer is None else config.layer
        if not 1 <= self.layer <= num_layers:
            raise ValueError(f"hubert: layer must be in [1, {num_layers}], got {config.layer}")
        self.dim = model.encoder.feature_projection.projection.out_features

    def move_to(self, device: torch.device) -> None:
        self.model.to(device)
        self.device = device

    @torch.inference_mode()
    def window(self, audio: np.ndarray, first_sample: int, frames: np.ndarray) -> np.ndarray:
        """Features of motion ``frames`` from one model pass over 48 kHz ``audio`` that starts at
        absolute sample ``first_sample``; (len(frames), D) float32."""
        x = torch.from_numpy(np.ascontiguousarray(audio)).to(self.device, torch.float32)
        x = torchaudio.functional.resample(x, AUDIO_SAMPLE_RATE, HUBERT_SAMPLE_RATE)
        if len(x) < HUBERT_RECEPTIVE_FIELD:  # shorter than one HuBERT frame: complete it with silence
            x = torch.nn.functional.pad(x, (0, HUBERT_RECEPTIVE_FIELD - len(x)))
        x = x[None]
        if self.config.normalize_waveform:
            x = torch.nn.functional.layer_norm(x, x.shape)  # what torchaudio's HUBERT_LARGE bundle does
        if self.config.layer is None:
            hidden = self.model(x)[0][0]
        else:
            hidden = self.model.extract_features(x, num_layers=self.layer)[0][self.layer - 1][0]
        # Interpolate from HuBERT frame centres to motion frame centres, in 16 kHz samples of the window.
        centres = (torch.as_tensor(frames, dtype=torch.float64) + 0.5) * (HUBERT_SAMPLE_RATE / FPS)
        centres -= first_sample * (HUBERT_SAMPLE_RATE / AUDIO_SAMPLE_RATE)
        position = ((centres - HUBERT_RECEPTIVE_FIELD / 2) / HUBERT_STRIDE).clamp(0, hidden.shape[0] - 1)
        low = position.floor().long()
        high = (low + 1).clamp_max(hidden.shape[0] - 1)
        weight = (position - low).to(hidden.dtype)[:, None].to(self.device)
        low, high = low.to(self.device), high.to(self.device)
        features = hidden[low] * (1 - weight) + hidden[high] * weight
        return features.float().cpu().numpy()


class HubertStream(FeatureStream):
    """Causal HuBERT: each chunk is read from a window of past audio ending at the chunk's end."""

    def __init__(self, hubert: _Hubert) -> None:
        self._hubert = hubert
        super().__init__(hubert.dim)

    def _keep_from(self, next_frame: int) -> int:
        return max(0, next_frame - self._hubert.config.past_frames) * SAMPLES_PER_FRAME

    def _frames(self, first: int, end: int) -> np.ndarray:
        chunk, past = self._hubert.config.chunk_frames, self._hubert.config.past_frames
        out = []
        for start in range(first, end, chunk):
            stop = min(start + chunk, end)
            window_start = max(0, start - past) * SAMPLES_PER_FRAME
            audio = self._audio(window_start, stop * SAMPLES_PER_FRAME)
            out.append(self._hubert.window(audio, window_start, np.arange(start, stop)))
        return np.concatenate(out)


@register_extractor
class HubertExtractor(AudioFeatureExtractor):
    """HuBERT features (torchaudio architecture, local weights) at 30 fps; causal when streaming."""

    name = "hubert-large"
    config_type = HubertConfig

    def __init__(self, config: HubertConfig | None = None) -> None:
        super().__init__(config)
        model = load_hubert(self.config.weights, self.config.architecture)
        self._hubert = _Hubert(model, self.config, _resolve_device(self.config.device))

    @property
    def dim(self) -> int:
        return self._hubert.dim

    def record(self) -> dict:
        """The configuration with the weights' sha256 instead of their path (a path says nothing
        about which weights another machine has); hashed once per extractor."""
        if not hasattr(self, "_weights_sha256"):
            self._weights_sha256 = weights_sha256(self.config.weights, self.config.architecture)
        config = super().record()
        config.pop("weights", None)
        config.pop("device", None)
        return {**config, "weights_sha256": self._weights_sha256}

    @property
    def device(self) -> torch.device:
        return self._hubert.device

    def to(self, device: str | None) -> "HubertExtractor":
        self._hubert.move_to(_resolve_device(device))  # in place: open streams follow
        return self

    def extract(self, wave: np.ndarray, num_frames: int) -> np.ndarray:
        wave = fit_to_frames(wave, num_frames)
        if num_frames == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        size, context = self.config.max_segment_frames, self.config.segment_context_frames
        if num_frames <= size:
            return self._hubert.window(wave, 0, np.arange(num_frames))
        core = size - 2 * context
        out = []
        for start in range(0, num_frames, core):
            stop = min(start + core, num_frames)
            lo, hi = max(0, start - context), min(num_frames, stop + context)
            audio = wave[lo * SAMPLES_PER_FRAME: hi * SAMPLES_PER_FRAME]
            out.append(self._hubert.window(audio, lo * SAMPLES_PER_FRAME, np.arange(start, stop)))
        return np.concatenate(out)

    def stream(self) -> HubertStream:
        return HubertStream(self._hubert)
