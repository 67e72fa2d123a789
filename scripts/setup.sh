#!/usr/bin/env bash
# Set up a fresh machine for admc: system LLVM 19 for Mitsuba's llvm_ad_rgb, a venv in .venv,
# torch first (the CPU build on local disk; anything else pulls GBs of CUDA wheels), then the
# project in editable mode. Idempotent: a second run only checks and returns in seconds.
# --blender also makes .venv-blender: Blender as a Python module (bpy 5.0.1, ~374 MB), which renders
# .blend corpus scenes with Cycles. It is a venv of its own because bpy 5.0.1 (the newest for
# Python 3.11) pins NumPy < 2 and admc's stack needs NumPy 2; admc runs it as a separate process.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${ADMC_VENV:-.venv}
BLENDER_VENV=${ADMC_BLENDER_VENV:-.venv-blender}
BPY="bpy==5.0.1"

setup_blender() {
  if [ -f "$BLENDER_VENV/.admc-bpy" ] && [ "$(cat "$BLENDER_VENV/.admc-bpy")" = "$BPY" ]; then
    echo "setup: Blender up to date ($BLENDER_VENV, $BPY)"
    return
  fi
  echo "setup: installing $BPY (Blender as a Python module, ~374 MB) into $BLENDER_VENV"
  python3 -m venv "$BLENDER_VENV"
  "$BLENDER_VENV/bin/python" -m pip install -q "$BPY" >"$BLENDER_VENV/setup.log" 2>&1 \
    || { cat "$BLENDER_VENV/setup.log"; echo "setup: pip install $BPY failed"; exit 1; }
  "$BLENDER_VENV/bin/python" -c "import bpy" >/dev/null 2>&1 || { echo "setup: bpy does not import"; exit 1; }
  echo "$BPY" > "$BLENDER_VENV/.admc-bpy"
}
if [ "${1:-}" = "--blender" ]; then setup_blender; fi
LLVM=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1

if [ ! -e "$LLVM" ]; then
  echo "setup: installing libllvm19 (the system LLVM 15 crashes Mitsuba's llvm_ad_rgb)"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi

if [ ! -x "$VENV/bin/python" ]; then
  python3 -m venv "$VENV"
fi
PY="$VENV/bin/python"
stamp="$VENV/.admc-setup-stamp"
want=$(cat pyproject.toml setup.py scripts/setup.sh | sha256sum | cut -c1-16)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && "$PY" -c "import admc, torch, mitsuba" 2>/dev/null; then
  echo "setup: up to date ($VENV)"
  exit 0
fi
log="$VENV/setup.log"
pip_install() {  # quiet unless it fails: setuptools' build warnings are noise to a user
  "$PY" -m pip install -q "$@" >>"$log" 2>&1 || { cat "$log"; echo "setup: pip install $* failed (log: $log)"; exit 1; }
}
: >"$log"
echo "setup: installing torch 2.13.0 (CPU), then admc and its dependencies into $VENV"
pip_install --upgrade pip
pip_install "torch==2.13.0"
pip_install -e ".[dev,cluster]"
echo "$want" > "$stamp"
echo "setup: done ($VENV, $("$PY" -c 'import torch, mitsuba; print("torch", torch.__version__, "mitsuba", mitsuba.__version__)'))"
