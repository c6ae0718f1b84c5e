"""One training run and the files it keeps: the loop (:mod:`.trainer`, :func:`splat_train.train`),
its checkpoints (:mod:`.checkpoint`), its per-iteration log (:mod:`.runlog`), the held-out
scoring along the run (:mod:`.heldout`) and the live model for the viewer (:mod:`.snapshot`).

What the run is made of sits below this package and is shared with the other commands
(``render``, ``export``, ``testpose``): the config (:mod:`splat_train.config`), the views
(:mod:`splat_train.data`), the parameters (:mod:`splat_train.gaussians`), the losses
(:mod:`splat_train.losses`), the growth strategies and training parts, and the rasterizer
(:mod:`splat_train.render`). Nothing below imports this package (tests/test_import_layers.py).

This face imports nothing.
"""
