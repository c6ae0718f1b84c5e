"""The initialisers beside VGGT and the baselines: COLMAP, posed, oracle, random points and the
bundle-adjustment step, each a stage command (``python -m evaluation.initialisers.<name>``),
and the reconstruction steps they share: :mod:`.triangulate` (points from known cameras) and
:mod:`.bundle` (bundle adjustment)."""
