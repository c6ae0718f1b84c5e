"""The Bridge modes, listed once: how the Bridge turns an initialiser's points into seed
Gaussians (bridge/core.py), and the names of their folders in the results tree
(``n{n}/{init}/{mode}/``), which the workflow plans and evaluation reads.

* ``gated``: every point, opacity from its confidence (the paper's Eq. 2);
* ``uniform``: every point, one opacity for all (the only mode of an initialiser without a
  confidence, and the mode the study's differences are taken against);
* ``filtered``: the points above a confidence percentile, one opacity for all.

Why here, on the ground floor, and not in the bridge package: the list is a contract of the
pipeline, not of one stage. Three readers need it as a list, in its order: the Bridge builds
by it, evaluation orders its tables by it and takes differences against ``uniform`` (an order
and a reference that the files of a run do not carry), and the workflow plans its folders by
it and its config check offers it. Stages never import each other (tests/test_import_layers.py),
so a list the bridge owned would leave evaluation re-deriving it from folder names; and it is
no camera maths or file format, so not camio's. runtime, the lowest floor, already holds the
other rules every stage shares about the results tree (runtime/names.py).
"""
from __future__ import annotations

__all__ = ["BRIDGE_MODES"]

BRIDGE_MODES = ("gated", "uniform", "filtered")
