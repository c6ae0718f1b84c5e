"""splat_train package."""
from splat_train.rasterize import rasterize  # noqa: E402,F401
