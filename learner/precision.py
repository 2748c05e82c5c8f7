"""`run.precision`: the learner's matrix products in bfloat16 where the hardware has it.

"float32" (the default) computes everything in float32. "bf16" runs each update under
`torch.autocast(dtype=torch.bfloat16)`: matrix products (the agents' input projection and GRU,
the heads, QMIX's hypernetworks) take bfloat16 operands and accumulate in float32, while
parameters, optimiser state, losses and RDN's critic and counterfactual targets (float32-only
custom layers; `learner.rdn` turns autocast off around them) stay float32. It is a different
computation, not the same values faster: use it as the default only after a learning
comparison.

Detected at run time: on a CPU without AVX512-BF16 or AMX-BF16 (bfloat16 products there are
emulated and slower), or a GPU without bfloat16, "bf16" falls back to "float32" with a warning.
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path

import torch

log = logging.getLogger(__name__)

PRECISIONS = ("float32", "bf16")


def cpu_model_and_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> tuple[str, set[str]]:
    """The first CPU's model name and instruction-set flags as Linux lists them; ("", set())
    where the file cannot be read."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return "", set()
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.setdefault(key.strip(), value.strip())
    return fields.get("model name", ""), set(fields.get("flags", "").split())


def cpu_has_bf16(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Whether the CPU has bfloat16 instructions (Linux's flags: avx512_bf16 or amx_bf16)."""
    return bool({"avx512_bf16", "amx_bf16"} & cpu_model_and_flags(cpuinfo)[1])


def effective_precision(precision: str, device: torch.device) -> str:
    """The precision a run gets: `precision`, or "float32" where bfloat16 is missing."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision == "float32":
        return precision
    has = torch.cuda.is_bf16_supported() if device.type == "cuda" else cpu_has_bf16()
    if not has:
        log.warning("run.precision=bf16: this %s has no bfloat16 arithmetic; float32", device)
        return "float32"
    return precision


def autocast(precision: str, device: torch.device) -> contextlib.AbstractContextManager:
    """The context an update runs in: bfloat16 autocast for "bf16", nothing otherwise."""
    if precision != "bf16":
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16)


def float32_only(device: torch.device) -> contextlib.AbstractContextManager:
    """Autocast switched off (for layers written for float32 only)."""
    return torch.autocast(device.type, enabled=False)
