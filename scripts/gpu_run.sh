#!/usr/bin/env bash
# The GPU check in one command, on a GPU machine that has torch with CUDA but none of this
# project's other packages and no network (the lent device: Python 3.12, torch 2.11 + cu130).
# Prepare on any x86-64 machine first (bash scripts/gpu_bundle.sh: .gpu_site or .whl, .gpu_cell,
# .gpu_wf, .gpu_agree), carry them, then in the repository root:
#
#   bash scripts/gpu_run.sh OUT_DIR [PARTS]      # PARTS: comma list (default: the training
#                                                # profile, cells, gsplat's loop, VGGT frames)
#
# The parts run in the order given (gsplat's CUDA kernels are JIT-built by the part
# gsplat_build, ~1.5 min once per machine, or beside the first parts with GSPLAT_BUILD_BG=1);
# the JSON + Markdown table are saved after each part, so a run cut short keeps what it
# measured. GPU_RUN_DEADLINE (a Unix time) keeps the VGGT parts and backend_agree from starting
# work past it; VGGT_SEARCH_BUDGET_S caps vggt_search alone. The parts that import gsplat wait
# for the background build. For example, the largest VGGT frame count and the sparse cell in
# one ~9-minute call:
#
#   GSPLAT_BUILD_BG=1 VGGT_SEARCH_BUDGET_S=300 GPU_RUN_DEADLINE=$(($(date +%s) + 560)) \
#       bash scripts/gpu_run.sh OUT vggt_search,cell_sparse
set -uo pipefail
cd "$(dirname "$0")/.."
OUTDIR=${1:?usage: gpu_run.sh OUT_DIR [PARTS]}
PARTS=${2:-gsplat_build,profile,cell,cell_sparse,native,vggt_frames}
mkdir -p "$OUTDIR"
if [ -f .gpu_site/site.tar.xz ]; then  # the same wheels unpacked and xz-packed: 32 MB instead of 53
    python3 -c "import tarfile; tarfile.open('.gpu_site/site.tar.xz').extractall('/tmp/site')" \
        || { echo "gpu_run: unpacking .gpu_site failed" >&2; exit 1; }
else
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        || { echo "gpu_run: installing .whl failed" >&2; exit 1; }
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MAX_JOBS=${MAX_JOBS:-16}
CAP=$(python3 -c "import torch; p = torch.cuda.get_device_capability(); print(f'{p[0]}.{p[1]}')") || exit 1
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-$CAP}
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"
# GSPLAT_BUILD_BG=1: gsplat's JIT build (CPU) runs beside the first parts (VGGT, GPU); the parts
# that import gsplat wait for its marker (importing gsplat during the build would remove the
# build folder)
EXTRA=()
if [ "${GSPLAT_BUILD_BG:-0}" = 1 ]; then
    export GSPLAT_BUILD_MARKER="$OUTDIR/gsplat_build.json"
    rm -f "$GSPLAT_BUILD_MARKER"
    python3 -c "import sys; from benchmarks.gpu_check import gsplat_build_marker as f; sys.exit(f(sys.argv[1]))" \
        "$GSPLAT_BUILD_MARKER" > "$OUTDIR/gsplat_build.log" 2>&1 &
fi
[ -d .gpu_agree ] && EXTRA+=(--gpu-agree-cell .gpu_agree)
[ -d .gpu_cell ] && EXTRA+=(--cell-prepared .gpu_cell)
[ -d .gpu_wf ] && EXTRA+=(--stages .gpu_wf)
python3 -m benchmarks --gpu --gpu-parts "$PARTS" "${EXTRA[@]}" --out "$OUTDIR"
rc=$?
wait
exit $rc
