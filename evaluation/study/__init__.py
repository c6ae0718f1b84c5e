"""The initialisation study (docs/init-study.md): its grid of cells (:mod:`.grid`) and its
report."""
