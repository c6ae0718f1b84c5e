"""vggt_init: feed-forward cameras and points from VGGT-1B, exported for the bridge.

Modules:
    model/          our weight-compatible VGGT (aggregator, camera head, DPT heads; no track head)
    checkpoint      checkpoint resolution (path, $VGGT_CHECKPOINT, HF cache, download), safe strict loading
    preprocess      the reference 'crop'/'pad' image loader, bit-exact, OpenImageIO + numpy
    pillow_compat   Pillow's bicubic resize and alpha compositing in numpy (bit-exact)
    geometry        pose encoding -> extrinsics/intrinsics, depth unprojection
    export          predictions.npz (schema in its docstring) and the COLMAP sparse/0 model
    run             the stage: images -> predictions.npz, sparse/0, timing.json

CLI: ``python -m vggt_init --images DIR --out DIR [--checkpoint PATH] [--model-config JSON]
[--dtype fp32|bf16] [--device cpu|cuda] [--points-from point_head|depth] [--mode crop|pad]``.
"""
