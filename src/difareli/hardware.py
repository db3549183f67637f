"""What this machine has: its CPU's instruction-set flags (one reader of /proc/cpuinfo), whether it does bf16
natively (``auto_precision``: the default precision of every command) and its nominal peak FLOP/s.

At the package root because the config loader (the ``${difareli_precision:}`` resolver) and the runtime both ask.
"""

from __future__ import annotations

import os
import re

import torch


def auto_precision(device: torch.device | str) -> str:
    """``runtime.precision=auto`` (the default): bf16 where the hardware has native bf16 arithmetic (a CUDA GPU that
    supports it; a CPU with ``avx512_bf16`` or ``amx_bf16``), else fp32. On such a CPU a whole ffhq128 relight took
    0.81x the fp32 time (0.62x compiled), and a trained model's relight changed by the error docs/official_code.md
    states."""
    device = torch.device(device)
    if device.type == "cuda":
        return "bf16" if torch.cuda.is_bf16_supported() else "fp32"
    info = _cpuinfo()
    return "bf16" if info is not None and _cpu_flags(info) & {"avx512_bf16", "amx_bf16"} else "fp32"


def _cpuinfo() -> str | None:
    """The text of /proc/cpuinfo (None where there is none)."""
    try:
        with open("/proc/cpuinfo") as f:
            return f.read()
    except OSError:
        return None


def _cpu_flags(info: str) -> set[str]:
    """The instruction-set flags of a /proc/cpuinfo text (empty without a flags line)."""
    found = re.search(r"^flags\s*:(.*)$", info, re.MULTILINE)
    return set(found.group(1).split()) if found else set()


#: Dense bf16 tensor-core peaks (FLOP/s) by a substring of ``torch.cuda.get_device_name``; H200 is the H100 chip.
GPU_BF16_PEAK = {"H200": 989e12, "H100 PCIe": 756e12, "H100 NVL": 835e12, "H100": 989e12, "A100": 312e12}


def peak_flops(device: torch.device | str, precision: str = "bf16") -> tuple[float | None, str]:
    """``(peak FLOP/s or None, how it was obtained)`` of a device at a precision (nominal, not measured)."""
    device = torch.device(device)
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
        for key, peak in GPU_BF16_PEAK.items():
            if key in name:
                # fp32 runs on the tensor cores as TF32 at half the bf16 rate when allowed; report bf16 only.
                return (peak, f"{name}: dense bf16 datasheet") if precision != "fp32" else (None, name)
        return None, f"{name}: peak unknown"
    return _cpu_peak(precision)


def _cpu_peak(precision: str, info: str | None = None, cores: int | None = None) -> tuple[float | None, str]:
    """Nominal FLOP/s of this CPU (or of ``info``, a /proc/cpuinfo text, with ``cores`` cores) at a precision."""
    info = _cpuinfo() if info is None else info
    if info is None:
        return None, "no /proc/cpuinfo"
    flags = _cpu_flags(info)
    mhz = float(re.search(r"^cpu MHz\s*:\s*([\d.]+)", info, re.M).group(1))
    family = int(re.search(r"^cpu family\s*:\s*(\d+)", info, re.M).group(1))
    vendor = re.search(r"^vendor_id\s*:\s*(\S+)", info, re.M).group(1)
    cores = cores or len(os.sched_getaffinity(0))
    # FP32 FLOP/cycle/core: two FMA pipes x lanes x 2. AMD Zen 4 (family 25) runs AVX-512 on 256-bit pipes.
    if "avx512f" in flags:
        fp32 = 32 if vendor == "AuthenticAMD" and family == 25 else 64
    elif "fma" in flags:
        fp32 = 32
    else:
        fp32 = 8
    per_cycle, how = fp32, f"{cores} cores x {mhz:.0f} MHz x {fp32} FP32 FLOP/cycle"
    if precision == "bf16" and "amx_bf16" in flags:
        # Intel AMX: one TDPBF16PS (16x16 += 16x32 . 32x16, 8,192 multiply-adds) per 16 cycles per core, 1,024
        # bf16 FLOP/cycle; oneDNN runs bf16 convolutions and matmuls on it (a 3x3 conv measured above the AVX-512
        # figure on such a CPU, so that figure cannot be the peak).
        per_cycle, how = 1024, f"{cores} cores x {mhz:.0f} MHz x 1024 bf16 FLOP/cycle (AMX tiles)"
    elif precision in ("bf16", "fp16") and "avx512_bf16" in flags:
        per_cycle, how = 2 * fp32, f"{cores} cores x {mhz:.0f} MHz x {2 * fp32} bf16 FLOP/cycle (avx512_bf16 dot)"
    return cores * mhz * 1e6 * per_cycle, how + " (nominal; /proc/cpuinfo clock)"
