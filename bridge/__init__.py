"""bridge: VGGT predictions (or a COLMAP model) -> normalised cameras + seed Gaussians.

Eq. 1 (:func:`global_coordinate_normalisation`) and Eq. 2 (:func:`uncertainty_gated_opacity`)
of the paper live in :mod:`bridge.equations`; point selection in :mod:`bridge.selection`;
the stage in :mod:`bridge.core`; the CLI is ``python -m bridge``.
"""

from runtime.stops import early_if_main as _early

_early()  # first: a stop while `python -m` loads the command is one line, exit 128 + the signal

from bridge.core import MODES, BridgeConfig, SeedResult, build_seed, run_bridge, write_outputs
from bridge.equations import global_coordinate_normalisation, uncertainty_gated_opacity
from bridge.inputs import BridgeInput, load_colmap, load_predictions

__all__ = [
    "MODES",
    "BridgeConfig",
    "BridgeInput",
    "SeedResult",
    "build_seed",
    "global_coordinate_normalisation",
    "load_colmap",
    "load_predictions",
    "run_bridge",
    "uncertainty_gated_opacity",
    "write_outputs",
]
