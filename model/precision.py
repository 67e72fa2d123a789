"""Which device and float precision the networks run in, and the autocast / memory layout that goes with it.

bfloat16 autocast keeps float32 master weights, optimiser states and (in losses.py) the losses and
the gradient penalty; only conv/linear arithmetic runs in bf16, which has float32's exponent range,
so no loss scaling is needed. Every network tensor is channels_last, in either precision (MEMORY_FORMAT).
"""

from __future__ import annotations

import contextlib

import torch

from admc.errors import DeviceError

PRECISIONS = {"float32": torch.float32, "bfloat16": torch.bfloat16}


def cpu_has_fast_bf16() -> bool:
    """True where this CPU computes bf16 dot products in hardware (AVX512-BF16 or AMX), as torch
    itself detects it; elsewhere oneDNN emulates bf16 and it is slower than float32."""
    if not torch.backends.mkldnn.is_available():
        return False
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
    return any(getattr(torch.cpu, name, lambda: False)() for name in checks)


def resolve_precision(name: str, device: torch.device) -> torch.dtype:
    """The dtype for setting `name` ("auto", "float32", "bfloat16") on `device`: auto = bf16 on CUDA
    and on CPUs with fast bf16, float32 elsewhere."""
    if name == "auto":
        fast = device.type == "cuda" or (device.type == "cpu" and cpu_has_fast_bf16())
        return torch.bfloat16 if fast else torch.float32
    if name not in PRECISIONS:
        raise ValueError(f"precision: {name!r} is not one of {('auto', *PRECISIONS)}")
    return PRECISIONS[name]


def precision_name(dtype: torch.dtype) -> str:
    return next(name for name, d in PRECISIONS.items() if d == dtype)


def autocast_for(device: torch.device, dtype: torch.dtype) -> contextlib.AbstractContextManager:
    """bf16 autocast where `dtype` is bfloat16, plain float32 otherwise."""
    if dtype == torch.float32:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=dtype)


MEMORY_FORMAT = torch.channels_last
"""The networks' layout in both precisions, on CPUs and GPUs: oneDNN's fast one for bf16 convs, and on the
2-core CPU faster than NCHW for float32 too (the small model's training step 1.3x, a 1280x720 image
2.4x, the paper-sized generator's forward pass 1.4x)."""


def resolve_device(name: str) -> torch.device:
    """auto | cpu | cuda | cuda:N as a torch device this machine has; DeviceError naming the value otherwise."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise DeviceError(f"device {name!r}: not a device admc runs on; use auto, cpu, cuda or cuda:N")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise DeviceError(f"device {name!r}: requested, but torch sees no CUDA device on this machine")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise DeviceError(f"device {name!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return device
