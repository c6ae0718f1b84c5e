"""Drawing Gaussians: the differentiable rasterizer :func:`splat_train.rasterize` and what it
is made of, in layers that import one way (bottom first):

1. the torch maths, the reference every fast path is tested against:
   :mod:`.projection` (EWA projection to the screen), :mod:`.sh` (spherical-harmonics colour)
   and :mod:`._reference` (3DGS's depth order and alpha blending, dense);
2. the fast paths built on them: :mod:`.cpu` (the C++ CPU kernels and their ctypes loaders),
   :mod:`._tiles` (torch tile binning) and :mod:`._gsplat_backend` (gsplat on CUDA);
3. the front, :mod:`.rasterize`: checks the inputs, picks a backend and runs the steps.

The kernels live inside this package, not beside it, because their loaders need the maths of
layer 1 (the :class:`.projection.Projected` record, ``TILE_SIZE``, the SH basis count, the
depth order they reproduce) while the front needs the kernels: as sibling subpackages of
``splat_train`` the two would import each other. Here the order is one line, and nothing in
this package imports any other part of ``splat_train`` (tests/test_import_layers.py checks
both). The trainer's two kernels that do not draw (:mod:`.cpu.ssim`, the loss; :mod:`.cpu.optim`,
the Adam step and densification statistics) sit with the others: all four share one build,
cache, SIMD header and thread pool (:mod:`.cpu.build`, ``python -m splat_train.render.cpu.build``).

This face imports nothing: importing a module of the package loads only what that module needs.
"""
