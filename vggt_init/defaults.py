"""Defaults of a VGGT run, defined once: :class:`vggt_init.run.RunOptions` and the CLI's flags
(``python -m vggt_init``) both read them. No heavy imports, so ``--help`` stays fast.

The workflow's config keeps its own ``null = this default`` for ``image_size``
(workflow/schemas/config.schema.yaml) and passes the flag only when set.
"""

from __future__ import annotations

__all__ = ["POINT_SOURCES", "POINTS_FROM", "MAX_POINTS", "MODES", "MODE", "IMAGE_SIZE", "FRAMES_CHUNK"]

#: where the world points come from: the point head (the paper) or depth head + predicted cameras
POINT_SOURCES = ("point_head", "depth")
POINTS_FROM = "point_head"
#: points kept in sparse/0, the most confident first
MAX_POINTS = 100_000
#: VGGT's preprocessing modes and the default
MODES = ("crop", "pad")
MODE = "crop"
#: network input width / longer side in pixels (a multiple of 14; 518 is the paper's setting)
IMAGE_SIZE = 518
#: frames per DPT-head chunk (memory against speed)
FRAMES_CHUNK = 4
