"""Inference speed-ups for generation on a CPU, each checked against the plain fp32 models.

Where the time goes (paper size, streaming, 2 CPU cores): in plain fp32 ~95 % is ``nn.Linear``
of the flow model, bound by reading the weights, not by arithmetic -- a chunk runs 8 network
evaluations over only 3 tokens x 2 guidance branches, so every evaluation streams all ~75 M
flow weights from memory. The first optimizations therefore cut the bytes of weight read per
evaluation; once those are int8, the many small operations around them are the other half of
the time, and ``fused`` cuts their number:

* ``time cache`` (all modes but "none", exact): the AdaLN-Zero modulation of every block and of
  the output layer, and the flow-time MLP, depend on the flow time tau only. The solver visits a
  fixed grid of tau values (0, 1/8, ..., 7/8 for 4 midpoint steps), so their outputs are
  memoized per exact input (``InputMemo``) and computed up front for the grid
  (``warm_time_grid``). That removes ~27 M of the ~77 M weights from every evaluation. A lookup
  is keyed by the input's bytes: it can only return what the module itself would return.
* ``rope cache`` (all modes but "none", exact): the cos/sin of the rotary angles depend on the
  token positions only, which are the same 0..L-1 in every evaluation of a streamed chunk, so
  ``RopeAngles`` is memoized too instead of recomputed 64 times per chunk (~15 small ops each).
* ``buffered decoder cache`` (all modes but "none", exact): the VAE decoder's streaming KV
  cache appends into a preallocated buffer (``BufferedKVCache``) instead of concatenating the
  whole cache at every step, which was half of a decode step.
* ``int8``: dynamic int8 quantization (``torch.ao.quantization.quantize_dynamic``: int8 weights
  with one scale per output channel, activations quantized per call) of the Linears inside the
  flow's transformer blocks (``block_linears``) -- 4x fewer weight bytes and VNNI int8
  arithmetic. Input/output projections, condition encoders and the VAE stay fp32.
* ``bf16``: the same Linears with bfloat16 weights and activations (2x fewer bytes).
* ``decoder`` (int8 and bf16 modes): the VAE decoder's Linears in bfloat16 (``BF16Linear``)
  where that measured faster than fp32 (``prefer_bf16_decoder``: AMX, or AVX512-BF16 on a
  non-Intel CPU, where torch's MKL fp32 GEMM is slow), fp32 elsewhere (``decoder="auto"``). On a
  2-core AMD EPYC it took 2 ms off a decode step for 0.5 mm more deviation at paper size.
* ``fused`` (int8 and bf16 modes): the flow's solver evaluations run ``fused.FusedFlowForward``,
  the same maths in about a third of the tensor operations (AdaLN modulation folded into the
  LayerNorm affine, gates as ``addcmul``, RoPE from tables); rounding differs from the module
  forward at the 1e-6 level, so the exact ``fp32`` mode does not use it; the same modes stream
  the VAE decoder through ``fused.FusedDecoderStep``. In every mode but "none" the decoder's
  rotary angles come from a table (``fused.RopeTable``, bit-identical).
* ``threads``: ``torch.set_num_threads`` (process-wide).
* ``compile``: ``torch.compile`` of the flow's transformer blocks (optional). Measured on the
  2-core CPU: about a minute to compile and no gain over eager mode, so it is off by default.
  In the int8 and bf16 modes the solver's evaluations run the fused forward, not the blocks, so
  there it only changes the calls that fall back to the module forward.

Not used, and why: KV caching in the flow model is not exact for the paper's protocol (history
tokens are re-noised at every solver step and the 3-token window truncates their causal
context, see ``sarah_models/flow.py``); batched guidance and per-block condition caching are
already what ``StreamingGenerator`` does; the VAE decoder already streams with a KV cache.

``optimize_for_inference`` returns optimized copies (the input models are left untouched, so the
plain fp32 models stay available as the reference); the copies are for inference only
(``torch.inference_mode``; with autograd enabled an ``InputMemo`` computes normally).
``stream_deviation`` measures how far an optimized model's generated stream moves the joints
from the reference's (the tolerance checks of ``tests/test_fast.py``).
"""

from __future__ import annotations

import copy
import dataclasses
import warnings
from collections import OrderedDict
from dataclasses import asdict, dataclass
from typing import Iterable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sarah_data import icosahedron
from sarah_data.constants import JOINT, NUM_JOINTS

from .flow import MODALITIES, FlowModel
from .fused import FusedFlowForward, fuse_decoder, fuse_flow
from .layers import AdaLNZeroBlock, KVCache, TransformerBlock, timestep_embedding
from .normalizer import Normalizer
from .stream import StreamConfig, StreamingGenerator
from .vae import CausalVAE, DecoderCache

MODES = ("none", "fp32", "bf16", "int8")
DECODER_PRECISIONS = ("auto", "fp32", "bf16")
MODE_HELP = {
    "none": "the plain models (only the thread count is set)",
    "fp32": "fp32 with the flow-time path memoized for the solver grid (exact)",
    "bf16": "fp32 time cache + bfloat16 Linear layers + fused forwards (+ a bf16 VAE decoder "
            "where it is faster: AMX, or AVX512-BF16 on non-Intel CPUs)",
    "int8": "fp32 time cache + dynamic int8 Linear layers (per-channel weight scales) + fused "
            "forwards (+ a bf16 VAE decoder where it is faster: AMX, or AVX512-BF16 on non-Intel "
            "CPUs)",
}


class InputMemo(nn.Module):
    """Wraps a module whose output depends on its input tensor only (no weights that change, no
    state); returns the stored output for an input seen before (exact match of dtype, shape and
    bytes), computes it otherwise.

    The cache holds at most ``max_entries`` inputs (least recently used goes first). Stored
    outputs are returned as they are: callers must not modify them in place (no caller does).
    """

    def __init__(self, module: nn.Module, max_entries: int = 64) -> None:
        super().__init__()
        self.module = module
        self.max_entries = max_entries
        self._memo: OrderedDict[tuple, Tensor] = OrderedDict()
        self.hits = 0
        self.misses = 0

    def forward(self, x: Tensor) -> Tensor:
        if torch.is_grad_enabled():  # training or autograd: never hand out stored tensors
            return self.module(x)
        key = (x.dtype, tuple(x.shape), str(x.device), x.detach().cpu().numpy().tobytes())
        out = self._memo.get(key)
        if out is not None:
            self._memo.move_to_end(key)
            self.hits += 1
            return out
        self.misses += 1
        out = self.module(x)
        self._memo[key] = out
        if len(self._memo) > self.max_entries:
            self._memo.popitem(last=False)
        return out

    def clear(self) -> None:
        self._memo.clear()


class BufferedKVCache(KVCache):
    """``KVCache`` that appends into a preallocated buffer instead of concatenating.

    ``KVCache.extend`` copies the whole cache at every call (``torch.cat``): for the VAE decoder
    (9 layers, up to 500 cached tokens) that copy was half the cost of a streaming decode step.
    Here new keys/values are written after the valid region and a view is returned; the buffer
    is compacted (valid region moved to the front) only when it is full, so the cost per call is
    amortized O(new tokens). Same values as ``KVCache`` in the same order."""

    def __init__(self, max_tokens: int | None = None) -> None:  # noqa: D107 - see KVCache
        self.max_tokens = max_tokens
        self._k: Tensor | None = None
        self._v: Tensor | None = None
        self._start = 0
        self._length = 0

    @property
    def k(self) -> Tensor | None:
        return None if self._k is None or not self._length else \
            self._k[:, :, self._start:self._start + self._length]

    @property
    def v(self) -> Tensor | None:
        return None if self._v is None or not self._length else \
            self._v[:, :, self._start:self._start + self._length]

    def __len__(self) -> int:
        return self._length

    def _reserve(self, k: Tensor, new: int) -> None:
        end = self._start + self._length + new
        if self._k is not None and end <= self._k.shape[2] and self._k.shape[:2] == k.shape[:2]:
            return
        keep = self._length + new
        capacity = 2 * max(keep, self.max_tokens or 0) + new
        shape = (*k.shape[:2], capacity, k.shape[3])
        buf_k, buf_v = k.new_empty(shape), k.new_empty(shape)
        if self._length:
            buf_k[:, :, :self._length] = self.k
            buf_v[:, :, :self._length] = self.v
        self._k, self._v, self._start = buf_k, buf_v, 0

    def extend(self, k: Tensor, v: Tensor, commit: bool = True) -> tuple[Tensor, Tensor]:
        """Return cached + new keys/values; store them only when ``commit``."""
        if not self._length:
            if commit:
                self._reserve(k, k.shape[2])
                self._write(k, v)
            return k, v
        new = k.shape[2]
        self._reserve(k, new)
        end = self._start + self._length
        self._k[:, :, end:end + new] = k
        self._v[:, :, end:end + new] = v
        full_k = self._k[:, :, self._start:end + new]
        full_v = self._v[:, :, self._start:end + new]
        if commit:
            self._length += new
            self._trim()
        return full_k, full_v

    def _write(self, k: Tensor, v: Tensor) -> None:
        n = k.shape[2]
        self._k[:, :, :n], self._v[:, :, :n] = k, v
        self._start, self._length = 0, n
        self._trim()

    def _trim(self) -> None:
        if self.max_tokens is not None and self._length > self.max_tokens:
            self._start += self._length - self.max_tokens
            self._length = self.max_tokens

    def reset(self) -> None:
        self._k = self._v = None
        self._start = self._length = 0


def use_buffered_decoder_cache(vae: CausalVAE) -> CausalVAE:
    """Make ``vae.new_decoder_cache`` (on this instance) hand out ``BufferedKVCache`` layers."""
    def new_decoder_cache(max_blocks: int | None = None) -> DecoderCache:
        max_tokens = None if max_blocks is None else max_blocks * (vae.stride + 1)
        return DecoderCache([BufferedKVCache(max_tokens) for _ in vae.decoder])

    vae.new_decoder_cache = new_decoder_cache
    return vae


class BF16Linear(nn.Module):
    """A Linear computed in bfloat16 (weights stored in bfloat16); output in the input dtype."""

    def __init__(self, linear: nn.Linear) -> None:
        super().__init__()
        self.in_features, self.out_features = linear.in_features, linear.out_features
        self.weight = nn.Parameter(linear.weight.detach().to(torch.bfloat16), requires_grad=False)
        self.bias = (None if linear.bias is None else
                     nn.Parameter(linear.bias.detach().to(torch.bfloat16), requires_grad=False))

    def forward(self, x: Tensor) -> Tensor:
        return F.linear(x.to(torch.bfloat16), self.weight, self.bias).to(x.dtype)


def solver_times(config: StreamConfig) -> list[float]:
    """The flow times at which ``stream.solve`` evaluates the network, computed the same way."""
    h, times = 1.0 / config.steps, []
    for i in range(config.steps):
        tau = i * h
        times.append(tau)
        if config.solver == "midpoint":
            times.append(tau + 0.5 * h)
    return times


def memoize_time_path(flow: FlowModel, max_entries: int = 64) -> FlowModel:
    """Wrap (in place) the flow-time MLP and every AdaLN modulation in an ``InputMemo``."""
    if not isinstance(flow.time_mlp, InputMemo):
        flow.time_mlp = InputMemo(flow.time_mlp, max_entries)
    for module in [*flow.blocks, flow.out]:
        if not isinstance(module.modulation, InputMemo):
            module.modulation = InputMemo(module.modulation, max_entries)
    return flow


def memoize_rope(flow: FlowModel, max_entries: int = 16) -> FlowModel:
    """Wrap (in place) the rotary-angle module of every flow block in an ``InputMemo``."""
    for block in flow.blocks:
        rope = block.attn.rope
        if not isinstance(rope.angles, InputMemo):
            rope.angles = InputMemo(rope.angles, max_entries)
    return flow


@torch.inference_mode()
def warm_time_grid(flow: FlowModel, config: StreamConfig, branches: Iterable[int] = (1, 2)) -> int:
    """Fill the time caches for the solver's flow times, for batches of 1 and 2 (guidance).

    Follows ``FlowModel.forward``'s own computation of the time path, so the stored entries are
    the ones it looks up. Returns the number of (tau, batch) pairs computed."""
    device = next(flow.parameters()).device
    dtype = flow.nulls[MODALITIES[0]].dtype  # the dtype of cond_tokens, which t is cast to
    count = 0
    for tau_value in solver_times(config):
        for b in branches:
            tau = torch.as_tensor(tau_value, device=device, dtype=torch.float32).expand(b)
            t = flow.time_mlp(timestep_embedding(tau, flow.config.time_dim)).to(dtype)
            for module in [*flow.blocks, flow.out]:
                module.modulation(t)
            count += 1
        fused = flow.__dict__.get("forward")
        if isinstance(fused, FusedFlowForward):
            fused.time_terms(tau_value, dtype)
    return count


def block_linears(flow: FlowModel) -> list[str]:
    """Names (in ``flow``) of the Linears inside the transformer blocks, outside any InputMemo:
    the ones that run at every evaluation and hold ~97 % of its weights. The input and output
    projections and the condition encoders stay fp32: quantizing them too multiplied the
    deviation by ten for a 2 % gain in speed."""
    memo = [name for name, m in flow.named_modules() if isinstance(m, InputMemo)]
    return [name for name, m in flow.named_modules() if isinstance(m, nn.Linear)
            and name.startswith("blocks.")
            and not any(name == p or name.startswith(p + ".") for p in memo)]


def _set_submodule(root: nn.Module, name: str, module: nn.Module) -> None:
    parent, _, child = name.rpartition(".")
    setattr(root.get_submodule(parent) if parent else root, child, module)


def quantize_int8(flow: FlowModel) -> FlowModel:
    """Dynamic int8 quantization (per-channel weight scales) of ``block_linears`` (in place)."""
    from torch.ao.quantization import per_channel_dynamic_qconfig, quantize_dynamic

    spec = {name: per_channel_dynamic_qconfig for name in block_linears(flow)}
    with warnings.catch_warnings():  # torch marks the eager quantization API as deprecated
        warnings.simplefilter("ignore")
        return quantize_dynamic(flow, spec, dtype=torch.qint8, inplace=True)


def linears_to_bf16(root: nn.Module, names: Iterable[str]) -> nn.Module:
    """Replace the Linears ``names`` of ``root`` by ``BF16Linear`` (in place)."""
    for name in names:
        _set_submodule(root, name, BF16Linear(root.get_submodule(name)))
    return root


def to_bf16(flow: FlowModel) -> FlowModel:
    """Replace ``block_linears`` by ``BF16Linear`` (in place)."""
    return linears_to_bf16(flow, block_linears(flow))


def cpu_info(field: str) -> str:
    """A field of /proc/cpuinfo ("vendor_id", "model name", ...) for the first CPU; "" when
    unknown (not Linux, or no such field)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as cpuinfo:
            for line in cpuinfo:
                if line.split(":", 1)[0].strip() == field:
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def cpu_vendor() -> str:
    """The CPU's vendor id ("GenuineIntel", "AuthenticAMD", ...; "" when unknown)."""
    return cpu_info("vendor_id")


def prefer_bf16_decoder() -> bool:
    """Whether a bf16 VAE decoder beats fp32 on this CPU, from measurements, not theory: AMX
    (bf16 tiles) wins anywhere; AVX512-BF16 won on an AMD EPYC, where torch's fp32 GEMM (MKL) runs
    a slow code path (decode step 8.5 -> 6.5 ms), and lost on a Xeon with AVX512-BF16 but no AMX
    (6.1 -> 10.1 ms), where MKL's fp32 is fast. docs/performance.md has both."""
    import torch.cpu

    def has(name: str) -> bool:  # private torch helpers, so guarded
        return bool(getattr(torch.cpu, name, lambda: False)())

    if has("_is_amx_tile_supported"):
        return True
    return has("_is_avx512_bf16_supported") and cpu_vendor() not in ("", "GenuineIntel")


def decoder_linears(vae: CausalVAE) -> list[str]:
    """Names (in ``vae``) of the Linears a streamed decode step runs: the latent input, every
    decoder layer's and the frame output."""
    return [name for name, m in vae.named_modules() if isinstance(m, nn.Linear)
            and (name.startswith("decoder.") or name in ("latent_in", "frame_out"))]


def decoder_to_bf16(vae: CausalVAE) -> CausalVAE:
    """Replace ``decoder_linears`` by ``BF16Linear`` (in place; the encoder stays fp32)."""
    return linears_to_bf16(vae, decoder_linears(vae))


def resolve_decoder(decoder: str, mode: str, device: torch.device) -> str:
    """The decoder precision ``optimize_for_inference`` uses: "fp32" or "bf16"."""
    if decoder not in DECODER_PRECISIONS:
        raise ValueError(f"unknown decoder precision {decoder!r}; choose from {DECODER_PRECISIONS}")
    if mode in ("none", "fp32"):
        if decoder == "bf16":
            raise ValueError(f"mode {mode!r} keeps the models in fp32: a bf16 decoder needs mode "
                             "int8 or bf16")
        return "fp32"
    if decoder == "auto":
        return "bf16" if device.type == "cpu" and prefer_bf16_decoder() else "fp32"
    return decoder


def compile_blocks(module: nn.Module) -> nn.Module:
    """``torch.compile`` every transformer block in place (hooks and names stay as they are)."""
    for m in module.modules():
        if isinstance(m, (AdaLNZeroBlock, TransformerBlock)):
            m.compile(dynamic=False)
    return module


def _unpack(models) -> tuple[CausalVAE, FlowModel, Normalizer | None]:
    if hasattr(models, "vae") and hasattr(models, "flow"):
        return models.vae, models.flow, getattr(models, "normalizer", None)
    if isinstance(models, (tuple, list)) and len(models) in (2, 3):
        return models[0], models[1], (models[2] if len(models) == 3 else None)
    raise TypeError("optimize_for_inference expects LoadedModels or a (vae, flow[, normalizer]) "
                    f"tuple, got {type(models).__name__}")


def optimize_for_inference(models, mode: str = "int8", *, stream_config: StreamConfig | None = None,
                           threads: int | None = None, compile: bool = False,
                           decoder: str = "auto"):
    """Optimized copies of ``models`` for generation; the originals are not modified.

    models: ``checkpoint.LoadedModels`` or a ``(vae, flow[, normalizer])`` tuple; the same kind
    is returned. mode: one of ``MODES`` (see ``MODE_HELP``). stream_config: whose solver grid to
    precompute (default the paper's). threads: ``torch.set_num_threads`` when given.
    compile: also ``torch.compile`` the transformer blocks. decoder: the VAE decoder's Linears
    in int8 and bf16 modes, one of ``DECODER_PRECISIONS`` ("auto": bf16 where it measured
    faster, ``prefer_bf16_decoder``; fp32 otherwise; ``resolve_decoder``)."""
    if mode not in MODES:
        raise ValueError(f"unknown optimization mode {mode!r}; choose from {MODES}")
    if threads is not None:
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        torch.set_num_threads(threads)
    vae, flow, normalizer = _unpack(models)
    if flow is None:
        raise ValueError("optimize_for_inference needs a flow model (a flow-stage checkpoint)")
    precision = resolve_decoder(decoder, mode, next(vae.parameters()).device)
    vae, flow = copy.deepcopy(vae).eval(), copy.deepcopy(flow).eval()
    if mode != "none":
        memoize_time_path(flow)
        memoize_rope(flow)
        use_buffered_decoder_cache(vae)
        # Not int8 for the decoder: 2.7 mm from fp32 at paper size, over the 1 mm tolerance.
        if precision == "bf16":
            decoder_to_bf16(vae)  # before fuse_decoder, whose step takes the Linears' kernels
        if mode == "int8":
            device = next(flow.parameters()).device
            if device.type != "cpu":
                raise ValueError(f"int8 dynamic quantization runs on the CPU only, models are on "
                                 f"{device}")
            quantize_int8(flow)
        elif mode == "bf16":
            to_bf16(flow)
        fused = mode != "fp32"  # fused forwards round differently: not in the exact mode
        fuse_decoder(vae, steps=fused)
        if fused:
            fuse_flow(flow)
        warm_time_grid(flow, stream_config or StreamConfig())
    if compile:  # the flow only: the VAE decoder's growing KV cache would recompile per step
        compile_blocks(flow)
    if dataclasses.is_dataclass(models):
        return dataclasses.replace(models, vae=vae, flow=flow)
    return (vae, flow) if normalizer is None else (vae, flow, normalizer)


# --------------------------------------------------------------------------- tolerance checks


@dataclass(frozen=True)
class Deviation:
    """How far a generated stream moves from the reference model's, for the same inputs/seed.

    Joint positions are the icosahedron centroids in metres (world frame); reported in mm.
    ``motion_scale_mm`` is the reference's RMS joint distance from its own mean pose, the size
    of the motion the deviation is compared with."""

    frames: int
    max_joint_mm: float
    mean_joint_mm: float
    motion_scale_mm: float
    wrist_speed_delta: float  # m/s, |optimized - reference| of metrics.wrist_speed
    head_angle_delta: float  # |optimized - reference| of metrics.head_angle (gaze score)

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def stream_inputs(frames: int, audio_dim: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Deterministic test inputs: a user walking an arc around the agent and two noise-like
    standardized feature tracks; (frames, 2), (frames, Da), (frames, Da) float32."""
    rng = np.random.default_rng(seed)
    angle = np.linspace(-0.8, 0.8, frames)
    head = np.stack([1.6 * np.sin(angle), 1.6 * np.cos(angle)], 1)
    a = rng.normal(size=(frames, audio_dim))
    b = rng.normal(size=(frames, audio_dim))
    return head.astype(np.float32), a.astype(np.float32), b.astype(np.float32)


def generate_stream(models, inputs: tuple[np.ndarray, np.ndarray, np.ndarray],
                    config: StreamConfig = StreamConfig()) -> np.ndarray:
    """World motion (T, Dx) streamed chunk by chunk through ``StreamingGenerator``."""
    vae, flow, normalizer = _unpack(models)
    generator = StreamingGenerator(vae, flow, normalizer, config)
    head, a, b = inputs
    s = generator.stride
    return np.concatenate([generator.step(head[i:i + s], a[i:i + s], b[i:i + s])
                           for i in range(0, head.shape[0] - head.shape[0] % s, s)])


def joint_positions(motion: np.ndarray) -> np.ndarray:
    """(T, Dx) motion vector -> (T, J, 3) joint positions (icosahedron centroids)."""
    ico = motion[:, : NUM_JOINTS * 36].reshape(motion.shape[0], NUM_JOINTS, 12, 3)
    return ico.mean(axis=2)


def stream_deviation(reference, optimized, frames: int = 64, seed: int = 0,
                     config: StreamConfig = StreamConfig(),
                     inputs: tuple[np.ndarray, ...] | None = None,
                     optimized_config: StreamConfig | None = None) -> Deviation:
    """Stream the same inputs (same seed) through both models; compare their joints and the
    cheap metrics (wrist speed, head angle). Both are ``(vae, flow, normalizer)`` or
    LoadedModels; the normalizer of ``reference`` is used for both when ``optimized`` has none.
    ``optimized_config`` (default ``config``) streams the optimized side with other settings,
    e.g. fewer solver steps."""
    from .metrics import head_angle, wrist_speed

    ref_vae, ref_flow, ref_norm = _unpack(reference)
    opt_vae, opt_flow, opt_norm = _unpack(optimized)
    if inputs is None:
        inputs = stream_inputs(frames, ref_flow.audio_dim, seed)
    ref = generate_stream((ref_vae, ref_flow, ref_norm), inputs, config)
    opt = generate_stream((opt_vae, opt_flow, opt_norm or ref_norm), inputs,
                          optimized_config or config)
    p_ref, p_opt = joint_positions(ref), joint_positions(opt)
    dist = np.linalg.norm(p_opt.astype(np.float64) - p_ref, axis=-1) * 1000.0
    scale = np.sqrt(np.mean(np.sum((p_ref - p_ref.mean(axis=0)) ** 2, axis=-1))) * 1000.0
    head = JOINT["head"]
    angles = []
    for motion in (ref, opt):
        ico = motion[:, : NUM_JOINTS * 36].reshape(motion.shape[0], NUM_JOINTS, 12, 3)
        pos, rot = icosahedron.decode(ico.astype(np.float64))
        angles.append(head_angle(pos[:, head], rot[:, head], inputs[0][: motion.shape[0]]))
    return Deviation(frames=int(ref.shape[0]), max_joint_mm=float(dist.max()),
                     mean_joint_mm=float(dist.mean()), motion_scale_mm=float(scale),
                     wrist_speed_delta=abs(wrist_speed(p_opt) - wrist_speed(p_ref)),
                     head_angle_delta=abs(angles[1] - angles[0]))
