"""vggt_init: feed-forward cameras and points from VGGT-1B, exported for the bridge.

Modules:
    model/          our weight-compatible VGGT (aggregator, camera head, DPT heads; no track head)
    checkpoint      checkpoint resolution (path, $VGGT_CHECKPOINT, HF cache, download), safe strict loading
    preprocess      the reference 'crop'/'pad' image loader, bit-exact, OpenImageIO + numpy
    pillow_compat   Pillow's bicubic resize and alpha compositing in numpy (bit-exact)
    geometry        pose encoding -> extrinsics/intrinsics, depth unprojection
    export          predictions.npz (schema in its docstring) and the COLMAP sparse/0 model
    run             the stage: images -> predictions.npz, sparse/0, timing.json
    defaults        the run's defaults (points source, kept points, image size, ...), defined once

CLI: ``python -m vggt_init --images DIR --out DIR [--checkpoint PATH] [--model-config JSON]
[--dtype fp32|bf16] [--device cpu|cuda] [--points-from point_head|depth] [--mode crop|pad]
[--no-retain-memory]``.
"""

from runtime.stops import early_if_main as _early

_early()  # first: a stop while `python -m` loads the command is one line, exit 128 + the signal

import os as _os

# torch's CPU allocator maps every allocation of 2 MB or more as transparent huge pages when
# THP_MEM_ALLOC_ENABLE is set. A VGGT forward allocates and frees its large activations (the
# DPT heads' full-resolution maps, the MLP hidden states) hundreds of times; with 4 kB pages
# each allocation is faulted in again: 7.9 M minor page faults for 3 frames at 518 px in fp32,
# and the DPT heads ran at half speed (7-9 s each instead of ~4 s). With huge pages: 0.8 M
# faults. torch reads the variable once, at its first allocation, so it is set here, before the
# CLI imports torch; a user's own setting wins.
_os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

