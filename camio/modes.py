"""The Bridge modes, listed once: how the Bridge turns an initialiser's points into seed
Gaussians (bridge/core.py), and the names of their folders in the results tree
(``n{n}/{init}/{mode}/``), which the workflow plans and evaluation reads.

Here rather than in the bridge package because evaluation and the workflow read the list and
no stage imports another (tests/test_import_layers.py).

* ``gated``: every point, opacity from its confidence (the paper's Eq. 2);
* ``uniform``: every point, one opacity for all (the only mode of an initialiser without a
  confidence);
* ``filtered``: the points above a confidence percentile, one opacity for all.
"""
from __future__ import annotations

__all__ = ["BRIDGE_MODES"]

BRIDGE_MODES = ("gated", "uniform", "filtered")
