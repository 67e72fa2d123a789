"""Find the Blender that renders `.blend` scenes: a Python with `bpy`, or a Blender executable.

In order: the setting `render.blender` (a path), the environment variable ADMC_BLENDER, the
`.venv-blender` that `scripts/setup.sh` creates beside admc's checkout, `blender` on the PATH.
"""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
from pathlib import Path

import admc
from admc.errors import AdmcError

SETUP_HINT = (
    "install it with `bash scripts/setup.sh --blender` (bpy 5.0.1 in .venv-blender: bpy pins NumPy < 2, so "
    "it cannot share admc's environment), or set render.blender (or ADMC_BLENDER) to a Blender executable "
    "or a Python that imports bpy"
)
CHECKOUT_VENV = Path(admc.__file__).resolve().parents[1] / ".venv-blender" / "bin" / "python"


class BlenderMissing(AdmcError, RuntimeError):
    """No Blender to render `.blend` scenes with."""


def blender_command(configured: str = "") -> list[str] | None:
    """The command that runs a script in Blender, up to the script's path: `[python]` for a Python with
    bpy, `[blender, -b, --factory-startup, --python-exit-code, 1, -P]` for an executable; None if none."""
    for candidate in (configured, os.environ.get("ADMC_BLENDER", ""), str(CHECKOUT_VENV), "blender"):
        if not candidate:
            continue
        path = shutil.which(candidate) or (candidate if Path(candidate).is_file() else None)
        if path is None:
            if candidate in (configured, os.environ.get("ADMC_BLENDER")):
                where = "render.blender" if candidate == configured else "ADMC_BLENDER"
                raise BlenderMissing(f"{candidate}: no such Blender executable or Python ({where})")
            continue
        if Path(path).name.startswith("python"):
            return [path]
        return [path, "-b", "--factory-startup", "--python-exit-code", "1", "-P"]
    return None


def require_blender(configured: str, what: str) -> list[str]:
    """The Blender command, or one message naming `what` needs it and how to get it."""
    command = blender_command(configured)
    if command is None:
        raise BlenderMissing(
            f"{what}: rendering .blend scenes needs Blender (bpy), which is not installed; {SETUP_HINT}"
        )
    if len(command) == 1 and not _has_bpy(command[0]):
        raise BlenderMissing(
            f"{what}: rendering .blend scenes needs Blender (bpy), and {command[0]} cannot import bpy; {SETUP_HINT}"
        )
    return command


@functools.cache
def _has_bpy(python: str) -> bool:
    """Whether a Python finds the bpy module (without importing it: that takes a second)."""
    probe = "import importlib.util, sys; sys.exit(importlib.util.find_spec('bpy') is None)"
    return subprocess.run([python, "-c", probe], capture_output=True, timeout=60).returncode == 0
