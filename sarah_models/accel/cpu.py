"""What this CPU is, for the choices that depend on it (measured, not theory)."""

from __future__ import annotations


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


def has_cpu_feature(name: str) -> bool:
    """torch's own detection of an instruction set ("amx_tile", "avx512_bf16", ...).

    This and ``onednn_linear_ops`` are the only places that read private torch helpers
    (``torch.cpu._is_<name>_supported``, checked against torch 2.14.1); a torch without one
    answers False."""
    import torch.cpu

    return bool(getattr(torch.cpu, f"_is_{name}_supported", lambda: False)())


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


def prefer_bf16_decoder() -> bool:
    """Whether a bf16 VAE decoder beats fp32 on this CPU: AMX (bf16 tiles) wins anywhere;
    AVX512-BF16 won on an AMD EPYC, where torch's fp32 GEMM (MKL) runs a slow code path (decode
    step 8.5 -> 6.5 ms), and lost on a Xeon with AVX512-BF16 but no AMX (6.1 -> 10.1 ms), where
    MKL's fp32 is fast. docs/performance.md has both."""
    if has_cpu_feature("amx_tile"):
        return True
    return has_cpu_feature("avx512_bf16") and cpu_vendor() not in ("", "GenuineIntel")
