"""Compute precision, chosen from the hardware: the one place training and inference ask.

bf16 (mixed precision: matmuls in bfloat16, accumulation and the output layer in float32) is
native on CPUs with AMX or AVX512-BF16 (unless oneDNN / ATen are restricted below those ISAs
with ONEDNN_MAX_CPU_ISA / ATEN_CPU_CAPABILITY) and on CUDA devices that support it. Everywhere
else bf16 is emulated, ~30x slower than fp32 on an AVX2 CPU, so "auto" means fp32 there.

"auto" for training: bf16 wherever it is native. "auto" for queries: bf16 on AMX CPUs and CUDA
only. A query's regressor pass is one small batch; on AVX512-BF16 kernels without AMX its bf16
pass was slower than fp32 (BENCHMARKS.md, "Mapping time and query time").
"""

from __future__ import annotations

import os
import warnings
from contextlib import AbstractContextManager
from functools import lru_cache

import torch

from slamreloc.registry import PRECISIONS

# oneDNN ISA caps (ONEDNN_MAX_CPU_ISA) under which bf16 matmuls are emulated
_ONEDNN_NO_BF16 = {"SSE41", "AVX", "AVX2", "AVX2_VNNI", "AVX2_VNNI_2", "AVX512_CORE",
                   "AVX512_CORE_VNNI"}


class EmulatedBf16Warning(UserWarning):
    """bf16 was asked for on hardware that emulates it."""


USES = ("train", "query")


@lru_cache(maxsize=None)
def bf16_kind(device_type: str = "cpu") -> tuple[str | None, str]:
    """("cuda" | "amx" | "avx512_bf16" | None, reason): which native bf16 `device_type` has,
    as torch will use it (None: emulated)."""
    if device_type == "cuda":
        if torch.cuda.is_available() and torch.cuda.is_bf16_supported():
            return "cuda", "CUDA device supports bf16"
        return None, "CUDA device without bf16"
    flags = _cpu_flags()
    if "amx_bf16" in flags:
        hw = "AMX"
    elif "avx512_bf16" in flags:
        hw = "AVX512-BF16"
    else:
        return None, "CPU without AMX or AVX512-BF16"
    cap = os.environ.get("ONEDNN_MAX_CPU_ISA", os.environ.get("DNNL_MAX_CPU_ISA", "")).upper()
    if cap in _ONEDNN_NO_BF16:
        return None, f"{hw} CPU, but oneDNN is limited to {cap}"
    aten = torch.backends.cpu.get_cpu_capability()
    if aten in ("DEFAULT", "AVX2"):
        return None, f"{hw} CPU, but ATen is limited to {aten}"
    if not cap or cap == "ALL":
        return hw.lower().replace("-", "_"), f"{hw} CPU"
    # an ISA cap names AMX only where it lets oneDNN use it (AVX512_CORE_AMX, AVX10_1_512_AMX...)
    kind = "amx" if hw == "AMX" and "AMX" in cap else "avx512_bf16"
    return kind, f"{hw} CPU, oneDNN capped at {cap}"


def bf16_support(device_type: str = "cpu") -> tuple[bool, str]:
    """(native, reason): does `device_type` ("cpu" | "cuda") run bf16 matmuls natively?"""
    kind, reason = bf16_kind(device_type)
    return kind is not None, reason


def resolve_precision(request: str = "auto", device_type: str = "cpu", use: str = "train") -> str:
    """"auto" | "fp32" | "bf16" -> "fp32" | "bf16" for `device_type` and `use` ("train" |
    "query"). "auto": bf16 where it is native, for queries only on AMX CPUs and CUDA (module
    docstring). Asking for bf16 where it is emulated is honoured, with a warning that it will
    be slow."""
    if request not in PRECISIONS:
        raise ValueError(f"unknown precision '{request}' (known: {', '.join(PRECISIONS)})")
    if use not in USES:
        raise ValueError(f"unknown use '{use}' (known: {', '.join(USES)})")
    kind, reason = bf16_kind(device_type)
    if request == "auto":
        fast = kind is not None if use == "train" else kind in ("amx", "cuda")
        return "bf16" if fast else "fp32"
    if request == "bf16" and kind is None:
        warnings.warn(f"bf16 asked for on {device_type} ({reason}): it is emulated there and "
                      "will be much slower than fp32", EmulatedBf16Warning, stacklevel=2)
    return request


def autocast(device_type: str, precision: str) -> AbstractContextManager:
    """Mixed-precision context for a resolved precision ("fp32" disables autocast)."""
    return torch.autocast(device_type, dtype=torch.bfloat16, enabled=precision == "bf16")


def _cpu_flags() -> set[str]:
    """The CPU's feature flags (Linux /proc/cpuinfo; empty elsewhere, which means fp32)."""
    try:
        with open("/proc/cpuinfo") as f:
            line = next((ln for ln in f if ln.startswith("flags")), "")
    except OSError:
        return set()
    return set(line.partition(":")[2].split())
