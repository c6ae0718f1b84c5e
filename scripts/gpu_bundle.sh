#!/usr/bin/env bash
# Make `python -m benchmarks --gpu` runnable on a GPU machine that has torch but not this
# project's other packages and cannot fetch any (the lent device of this workplace: Python
# 3.12, torch with CUDA, no pycolmap / OpenImageIO / gsplat, no network, 64 MiB carried).
#
#   bash scripts/gpu_bundle.sh            # here, once: writes .whl/ and .gpu_cell/ (git-ignored)
#
# .whl/       cp312 manylinux wheels of gsplat (the pinned version), pycolmap and OpenImageIO
#             (the versions installed here), ~53 MB; their other needs (numpy, jaxtyping,
#             rich, ninja, typing_extensions) are in a torch image already;
# .gpu_site/  the same wheels unpacked into one site-packages tree, xz-packed (~32 MB): what
#             is carried (gpu_run.sh unpacks it; it installs .whl/ when .gpu_site is absent);
# .gpu_cell/  the fern n = 3 cell's CPU stages (scene, COLMAP seed, Bridge, alignment) run
#             here, ~2 MB (benchmarks/bench_cell.py --prepare-only), so the GPU machine needs
#             neither the real scenes nor open3d;
# .gpu_wf/    config.yaml's synthetic oracle n = 3 cell run by Snakemake here, its inputs and
#             results (~1 MB, benchmarks/gpu_stages.py prepare), for the stage commands on CUDA;
# .gpu_agree/ the sparse-view grid's fern n = 3 cell (~2.6 MB, python -m benchmarks.backend_agree
#             pack; its work folder is $AGREE_WORK, default /tmp/gpu_agree_work), for the part
#             backend_agree; skipped with a line when the grid's fern data is not here.
# Then, on the GPU machine, in the repository root (one command; it prints what it measured
# after each part and saves the JSON + table after each part, see benchmarks/README.md):
#
#   bash scripts/gpu_run.sh OUT_DIR
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
[ -x "$PY" ] || { echo "gpu_bundle: $PY not found; run 'make install' first or set PYTHON" >&2; exit 1; }
export PATH="$(cd "$(dirname "$PY")" && pwd):$PATH"  # the stages' subprocesses use this interpreter
version() { "$PY" -c "import importlib.metadata as m; print(m.version('$1'))"; }
GSPLAT=$("$PY" -c "from splat_train.render._gsplat_backend import GSPLAT_VERSION; print(GSPLAT_VERSION)")
PLATFORMS=()
for p in manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux_2_27_x86_64 manylinux_2_28_x86_64 \
         manylinux_2_31_x86_64 manylinux_2_34_x86_64 manylinux_2_35_x86_64; do
    PLATFORMS+=(--platform "$p")
done

rm -rf .whl.partial .gpu_cell .gpu_wf .gpu_agree
mkdir -p .whl.partial
echo "gpu_bundle: downloading gsplat==$GSPLAT pycolmap==$(version pycolmap) OpenImageIO==$(version OpenImageIO) (cp312)"
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    "${PLATFORMS[@]}" -d .whl.partial \
    "gsplat==$GSPLAT" "pycolmap==$(version pycolmap)" "OpenImageIO==$(version OpenImageIO)"
rm -rf .whl && mv .whl.partial .whl
# the wheels unpacked (a site-packages tree) and xz-packed: 32 MB instead of their 53 MB of
# zip, which with the tracked files and the cells stayed over the 64 MiB a GPU call carries
echo "gpu_bundle: packing the wheels into .gpu_site/site.tar.xz"
rm -rf .gpu_site .gpu_site.partial && mkdir -p .gpu_site.partial/tree
for w in .whl/*.whl; do "$PY" -m zipfile -e "$w" .gpu_site.partial/tree; done
tar -C .gpu_site.partial/tree -cf - . | xz -T0 -6 > .gpu_site.partial/site.tar.xz
rm -rf .gpu_site.partial/tree && mv .gpu_site.partial .gpu_site

echo "gpu_bundle: preparing the fern n = 3 cell's CPU stages into .gpu_cell"
"$PY" benchmarks/bench_cell.py --prepare-only .gpu_cell --scene fern

echo "gpu_bundle: running config.yaml's synthetic oracle n = 3 cell with snakemake into .gpu_wf"
"$PY" benchmarks/gpu_stages.py prepare .gpu_wf

echo "gpu_bundle: packing the sparse-view grid's fern n = 3 cell into .gpu_agree"
"$PY" -m benchmarks.backend_agree pack .gpu_agree --work "${AGREE_WORK:-/tmp/gpu_agree_work}" \
    || echo "gpu_bundle: no .gpu_agree (the part backend_agree needs it)" >&2

TREE=$(git ls-files -z | xargs -0 du -cb | tail -1 | cut -f1)
EXTRA=$(du -cb .gpu_site .gpu_cell .gpu_wf $( [ -d .gpu_agree ] && echo .gpu_agree) | tail -1 | cut -f1)
TOTAL=$((TREE + EXTRA))
echo "gpu_bundle: tracked files $((TREE / 1048576)) MiB + .gpu_site, .gpu_cell, .gpu_wf, .gpu_agree $((EXTRA / 1048576)) MiB = $((TOTAL / 1048576)) MiB"
if [ "$TOTAL" -gt $((64 * 1048576)) ]; then
    echo "gpu_bundle: WARNING: over the lent device's 64 MiB working-tree limit" >&2
fi
echo "gpu_bundle: done; carry .gpu_site, .gpu_cell, .gpu_wf and .gpu_agree, then: bash scripts/gpu_run.sh OUT_DIR"
