"""Choose and activate the Mitsuba variant for the split integrator: cuda_ad_rgb > llvm_ad_rgb.

The integrator is a Python integrator writing RGB buffers: in scalar variants Python would run once per
sample (~120x slower), so it accepts only the JIT RGB variants, and `auto` picks only among those. Dr.Jit's
LLVM back end needs libLLVM >= 16 here (the system's libLLVM-15 crashes Mitsuba): unless
DRJIT_LIBLLVM_PATH names one, the newest libLLVM >= 16 in the usual Debian/Ubuntu places is used.
"""

from __future__ import annotations

import glob
import os
import re
import sysconfig

from admc.errors import AdmcError

PREFERENCE = ("cuda_ad_rgb", "llvm_ad_rgb")
MIN_LLVM = 16
LLVM_PATTERNS = (
    "/usr/lib/{multiarch}/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)


class VariantError(AdmcError, RuntimeError):
    pass


def _llvm_major(path: str) -> int | None:
    """The LLVM major version a library file name says (libLLVM-19.so, libLLVM.so.19.1, llvm-19/...)."""
    match = re.search(r"/llvm-(\d+)/", path) or re.search(r"libLLVM(?:-(\d+)|\.so\.(\d+))", os.path.basename(path))
    return int(next(g for g in match.groups() if g)) if match else None


def find_llvm() -> str | None:
    """The newest shared libLLVM >= MIN_LLVM installed in the usual places, or None."""
    multiarch = sysconfig.get_config_var("MULTIARCH") or "*"
    found = {}
    for pattern in LLVM_PATTERNS:
        for path in glob.glob(pattern.format(multiarch=multiarch)):
            major = _llvm_major(path)
            if major is not None and major >= MIN_LLVM and os.path.isfile(path):
                found.setdefault(major, path)
    return found[max(found)] if found else None


def _point_drjit_at_llvm() -> None:
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        library = find_llvm()
        if library is not None:
            os.environ["DRJIT_LIBLLVM_PATH"] = library


def available_variants() -> list[str]:
    """The variants of PREFERENCE whose back end works on this machine, best first."""
    _point_drjit_at_llvm()
    import drjit as dr

    backends = {"cuda": dr.JitBackend.CUDA, "llvm": dr.JitBackend.LLVM}
    return [name for name in PREFERENCE if dr.has_backend(backends[name.split("_")[0]])]


def resolve_variant(requested: str = "auto") -> str:
    """Map 'auto' to the best usable variant; check an explicit one is one the integrator accepts and works."""
    if requested != "auto" and requested not in PREFERENCE:
        raise VariantError(
            f"render.variant {requested!r}: the split integrator runs only in {', '.join(PREFERENCE)} "
            "(a Python integrator needs a JIT variant; its buffers are RGB)"
        )
    usable = available_variants()
    if not usable:
        raise VariantError(
            "render.variant: neither CUDA nor LLVM works on this machine, and the split integrator "
            f"needs one; install libLLVM >= {MIN_LLVM} (Debian: apt-get install libllvm19) or set "
            "DRJIT_LIBLLVM_PATH to one"
        )
    if requested == "auto":
        return usable[0]
    if requested not in usable:
        raise VariantError(
            f"render.variant {requested!r} needs a back end this machine lacks; usable: {', '.join(usable)}"
        )
    return requested


def use_variant(requested: str = "auto") -> str:
    """Activate the variant in this process and return its name."""
    name = resolve_variant(requested)
    import mitsuba as mi

    mi.set_variant(name)
    return name
