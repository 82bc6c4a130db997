"""What this CPU is, for the choices that depend on it (measured, not theory)."""

from __future__ import annotations

import re
from pathlib import Path

CACHE_DIR = Path("/sys/devices/system/cpu/cpu0/cache")
CACHE_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30}


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


def last_level_cache(cache_dir: Path = CACHE_DIR) -> str:
    """The first CPU's largest cache level and its size as sysfs states them ("L3 260 MiB"; ""
    when unknown): whether a chunk's weights stay in cache decides its speed (the paper-size
    flow reads 48 MB per evaluation), and VMs of one model name differ here."""
    best: tuple[int, int] | None = None
    for index in sorted(cache_dir.glob("index*")):
        try:
            level = int((index / "level").read_text())
            size = (index / "size").read_text().strip()
        except (OSError, ValueError):
            continue
        parsed = re.fullmatch(r"(\d+)([KMG]?)", size)
        number = int(parsed[1]) * CACHE_UNITS[parsed[2]] if parsed else 0
        if number and (best is None or level > best[0]):
            best = (level, number)
    if best is None:
        return ""
    level, number = best
    if number >= 2**20:
        return f"L{level} {number / 2**20:g} MiB"
    return f"L{level} {number // 2**10} KiB"


def cpu_identity() -> str:
    """Family, model and last-level cache ("family 6 model 207, L3 260 MiB"; the parts known):
    VMs that report the same model name ("Intel(R) Xeon(R) Processor") ran the same stream 1.6x
    apart (docs/performance.md, 2026-12-02)."""
    family, model = cpu_info("cpu family"), cpu_info("model")
    parts = [f"family {family} model {model}"] if family and model else []
    cache = last_level_cache()
    return ", ".join(parts + ([cache] if cache else []))


def has_cpu_feature(name: str) -> bool:
    """torch's own detection of an instruction set ("amx_tile", "avx512_bf16", ...).

    This, ``onednn_linear_ops`` and ``onednn_bf16_available`` are the only places that read
    private torch helpers (``torch.cpu._is_<name>_supported``, checked against torch 2.14.1); a
    torch without one answers False."""
    import torch.cpu

    return bool(getattr(torch.cpu, f"_is_{name}_supported", lambda: False)())


def vector_isa() -> str:
    """The widest matrix instruction set torch will use here, for reports: "AMX",
    "AVX-512 VNNI", "AVX-512", "AVX2" or "" (the same model's int8 speed differs ~2x between
    an AVX2-only and a VNNI host of the same name: docs/performance.md, 2026-11-28)."""
    for feature, name in (("amx_tile", "AMX"), ("vnni", "AVX-512 VNNI"), ("avx512", "AVX-512"),
                          ("avx2", "AVX2")):
        if has_cpu_feature(feature):
            return name
    return ""


def onednn_linear_ops():
    """torch's oneDNN linear over weights reordered once into the GEMM's blocked layout -- the
    kernels inductor's freezing pass puts in compiled CPU graphs -- as ``(reorder, linear)``:
    ``reorder(weight)`` packs a (out, in) fp32 or bf16 weight, ``linear(x, packed, bias, "none",
    [], "")`` computes ``F.linear``. None where this torch has no oneDNN or lacks the ops.

    Private ops (``torch.ops.mkldnn._reorder_linear_weight``, ``_linear_pointwise``; checked
    against torch 2.14.1), read here only."""
    import torch

    if not torch.backends.mkldnn.is_available():
        return None
    try:
        return torch.ops.mkldnn._reorder_linear_weight, torch.ops.mkldnn._linear_pointwise
    except (AttributeError, RuntimeError):
        return None


def onednn_bf16_available() -> bool:
    """Whether oneDNN computes bfloat16 on this CPU (AVX-512 BF16, or AVX-NE-CONVERT): an
    AVX2-only CPU refuses to pack bf16 weights ("bf16 path needs the cpu support ..."). Private
    (``torch.ops.mkldnn._is_mkldnn_bf16_supported``, checked against torch 2.14.1), read here
    only; a torch without it answers False."""
    import torch

    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def amx_bf16_available() -> bool:
    """Whether oneDNN multiplies bfloat16 matrices on AMX tiles here (AMX usable by this
    process, and oneDNN's bf16 path): where it does, a Linear over many rows computes faster
    in bf16 than fbgemm's int8 (``linears.ByRowsLinear``)."""
    return has_cpu_feature("amx_tile") and onednn_bf16_available()


def int8_full_range() -> bool:
    """Whether fbgemm's int8 Linears may quantize activations to the full 8 bits: where the CPU
    has VNNI its kernels multiply-add into int32; without VNNI they add pairs of products in
    int16, which full-range activations can overflow, so torch's default halves their range
    (``reduce_range``; torch's own qconfig warns the same). The full range halved the int8
    flow's deviation on the shipped fixture model (6.45 -> 2.82 mm over 64 streamed frames,
    docs/performance.md)."""
    return has_cpu_feature("vnni")
