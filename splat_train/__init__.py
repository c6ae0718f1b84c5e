"""splat_train package."""
from splat_train.rasterize import rasterize  # noqa: E402,F401
from splat_train.config import TrainConfig  # noqa: E402,F401
from splat_train.losses import psnr, ssim  # noqa: E402,F401
from splat_train.trainer import NonFiniteLossError, TrainResult, train  # noqa: E402,F401
