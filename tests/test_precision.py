"""Precision resolution: auto follows the CPU's own bf16 hardware, explicit names are kept, bad ones refused."""

from pathlib import Path

import pytest
import torch

from admc.model.precision import cpu_has_fast_bf16, resolve_precision

CPUINFO = Path("/proc/cpuinfo")


@pytest.mark.skipif(not CPUINFO.is_file(), reason="needs Linux /proc/cpuinfo to know the CPU's flags")
def test_cpu_bf16_detection_agrees_with_the_kernel_cpu_flags():
    flags = set(next(line for line in CPUINFO.read_text().splitlines() if line.startswith("flags")).split())
    hardware = bool({"avx512_bf16", "amx_bf16"} & flags)
    assert cpu_has_fast_bf16() == (hardware and torch.backends.mkldnn.is_available())
    expected = torch.bfloat16 if cpu_has_fast_bf16() else torch.float32
    assert resolve_precision("auto", torch.device("cpu")) == expected


def test_explicit_precisions():
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert resolve_precision("float32", cpu) == torch.float32
    assert resolve_precision("bfloat16", cpu) == torch.bfloat16
    assert resolve_precision("auto", cuda) == torch.bfloat16
    with pytest.raises(ValueError, match="^precision: 'half' is not one of"):
        resolve_precision("half", cpu)
