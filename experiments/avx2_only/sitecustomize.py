"""Run admc on this CPU as if it had no AVX-512, to time `make demo` for an AVX2-only machine on one that is not.

Put this folder on PYTHONPATH beside torch's own switches, and every Python process admc starts (dask
workers included) loads it first:

    PYTHONPATH=experiments/avx2_only ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2 make demo

It changes two things torch's variables cannot: Dr.Jit's LLVM backend compiles the renders' kernels for an
AVX2 Zen 3 (8 lanes, not 16; its kernel cache keys on the target, so a cache of AVX-512 kernels is not reused),
and `precision.cpu_has_fast_bf16` answers False, so training and inference run in float32 as on such a CPU.
OIDN picks its kernels from CPUID and keeps AVX-512: its share of the demo is under a minute.
"""

import ctypes
import importlib.abc
import importlib.util
import os
import sys

TARGET_CPU = b"znver3"
FEATURES = (
    b"+avx2,+avx,+fma,+f16c,+sse4.2,+sse4.1,+ssse3,+sse3,+sse2,+sse,+popcnt,+bmi,+bmi2,+lzcnt,+movbe,+cx16,+xsave,"
    b"-avx512f,-avx512vl,-avx512bw,-avx512dq,-avx512cd,-avx512bf16,-avx512vnni,-avx512ifma,-avx512vbmi,"
    b"-avx512vbmi2,-avx512bitalg,-avx512vpopcntdq"
)
VECTOR_WIDTH = 8  # AVX2's 256-bit registers hold 8 float32 lanes


def _retarget_llvm() -> None:
    """Dr.Jit's `jit_llvm_set_target` (not bound in Python), after the variant has initialised the backend."""
    import drjit

    core = ctypes.CDLL(os.path.join(os.path.dirname(drjit.__file__), "libdrjit-core.so"))
    core._Z19jit_llvm_set_targetPKcS0_j(TARGET_CPU, FEATURES, VECTOR_WIDTH)


def _float32_only(precision) -> None:
    precision.cpu_has_fast_bf16 = lambda: False


def _retarget_after_variant(variants) -> None:
    use_variant = variants.use_variant

    def use_variant_avx2(*args, **kwargs):
        name = use_variant(*args, **kwargs)
        if name.startswith("llvm"):
            _retarget_llvm()
        return name

    variants.use_variant = use_variant_avx2


PATCHES = {"admc.model.precision": _float32_only, "admc.pipeline.render.variants": _retarget_after_variant}
"""Each module to patch, and its patch."""


class _PatchOnImport(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Loads the modules of PATCHES as usual, then patches them before anyone imports names from them."""

    def __init__(self) -> None:
        self.loaders = {}

    def find_spec(self, name, path, target=None):
        if name not in PATCHES:
            return None
        sys.meta_path.remove(self)
        try:
            spec = importlib.util.find_spec(name)
        finally:
            sys.meta_path.insert(0, self)
        self.loaders[name] = spec.loader
        spec.loader = self
        return spec

    def create_module(self, spec):
        return self.loaders[spec.name].create_module(spec)

    def exec_module(self, module):
        self.loaders[module.__name__].exec_module(module)
        PATCHES[module.__name__](module)


sys.meta_path.insert(0, _PatchOnImport())
