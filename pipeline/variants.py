"""Choose and activate the Mitsuba variant: cuda_ad_rgb > llvm_ad_rgb > scalar_rgb.

A Python integrator needs a JIT variant to be fast (in scalar variants Python runs once per
sample), so `auto` never picks scalar when a JIT back end works. LLVM must be >= 16 here: the
system's libLLVM-15 crashes Mitsuba, so we point Dr.Jit at LLVM 19 when it is installed.
"""
from __future__ import annotations

import os

from admc.errors import AdmcError

LLVM_LIBRARY = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
PREFERENCE = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")


class VariantError(AdmcError, RuntimeError):
    pass


def _point_drjit_at_llvm() -> None:
    if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(LLVM_LIBRARY):
        os.environ["DRJIT_LIBLLVM_PATH"] = LLVM_LIBRARY


def available_variants() -> list[str]:
    """The variants of PREFERENCE whose back end works on this machine, best first."""
    _point_drjit_at_llvm()
    import drjit as dr

    usable = []
    for name in PREFERENCE:
        if name.startswith("cuda") and not dr.has_backend(dr.JitBackend.CUDA):
            continue
        if name.startswith("llvm") and not dr.has_backend(dr.JitBackend.LLVM):
            continue
        usable.append(name)
    return usable


def resolve_variant(requested: str = "auto") -> str:
    """Map 'auto' to the best usable variant; check an explicit one exists and works."""
    usable = available_variants()
    if requested == "auto":
        return usable[0]
    import mitsuba as mi

    if requested not in mi.variants():
        raise VariantError(f"unknown Mitsuba variant {requested!r}; known: {', '.join(mi.variants())}")
    if requested.split("_")[0] in ("cuda", "llvm") and requested not in usable and not any(
        v.split("_")[0] == requested.split("_")[0] for v in usable
    ):
        raise VariantError(f"variant {requested!r} needs a back end this machine lacks; usable: {', '.join(usable)}")
    return requested


def use_variant(requested: str = "auto") -> str:
    """Activate the variant in this process and return its name."""
    name = resolve_variant(requested)
    import mitsuba as mi

    mi.set_variant(name)
    return name
