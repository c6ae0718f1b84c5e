"""The initialisers beside VGGT and the baselines: COLMAP, posed, oracle, random points and the
bundle-adjustment step, each a stage command (``python -m evaluation.initialisers.<name>``)."""
