"""The C++ CPU kernels of :mod:`splat_train` and their ctypes loaders, one module per kernel.

Each kernel is one C++ source beside its loader, compiled on first use and cached
(:mod:`splat_train.render.cpu.build`, which also runs them on its threads):

* :mod:`splat_train.render.cpu.raster` (``raster.cpp``, ``vec8d.h``): depth sort, binning and tile
  blending, forward and backward; the ``"cpu"`` backend of :func:`splat_train.rasterize`.
* :mod:`splat_train.render.cpu.project` (``project.cpp``, ``vec8d.h``): fused EWA projection + SH
  colour, forward and backward.
* :mod:`splat_train.render.cpu.ssim` (``ssim.cpp``): the L1 + SSIM terms of the training loss.
* :mod:`splat_train.render.cpu.optim` (``optim.cpp``): the trainer's Adam step and densification
  statistics.

Dependencies run one way: these loaders import only the torch building blocks they mirror
(:mod:`splat_train.render.projection`, :mod:`splat_train.render._reference`, :mod:`splat_train.render.sh`,
:mod:`imgmetrics.ssim`), never the modules that call them (``rasterize``, ``losses``,
``densify``, ``trainer``; tests/test_import_layers.py checks). This package imports none of its
modules itself, and importing one builds nothing until its kernel is first used.

Older commit messages give measurements under these files' earlier paths: ``splat_train/cpu/``
(the same names) and, before it, ``splat_train/_cpu_build.py``, ``_cpu_kernel.py`` / ``.cpp``
(now ``raster``), ``_cpu_project``, ``_cpu_ssim``, ``_cpu_optim`` and ``_cpu_vec8d.h``.
"""
