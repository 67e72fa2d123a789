#!/usr/bin/env bash
# Set up a fresh machine for admc: system LLVM 19 for Mitsuba's llvm_ad_rgb, a venv in .venv,
# torch first (the CPU build on local disk; anything else pulls GBs of CUDA wheels), then the
# project in editable mode. Idempotent: a second run only checks and returns in seconds.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${ADMC_VENV:-.venv}
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
