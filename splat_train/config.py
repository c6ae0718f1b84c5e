"""Training hyperparameters (the evaluation protocol's defaults) and the schedule they imply.

The seed code trained for 10k iterations: densify from iteration 500 to 10000 every 100,
reset opacity every 3000, raise the SH degree every 1000 up to 3. A run with fewer iterations
(the CPU default is :data:`DEFAULT_ITERATIONS` = 1000) scales the *windows* by
``f = iterations / schedule_reference_iterations`` (never by more than 1, so longer runs keep
the seed schedule), rounded and kept >= 1: densify_from, densify_until, opacity_reset_every
and sh_increase_every. The densification *period* (100) is not scaled: densifying 5x as often
in a 5x shorter run gives the same number of clone/split rounds as the 10k run with 5x fewer
steps between them to settle; measured on the 256 px synthetic scene (12 views, 2000
iterations) that grew 4000 seeds to 120k Gaussians by iteration 400 and made the run many
times slower. So 1000 iterations densify at 100, 200, ..., 900 (after 50, before 1000, every
100), reset opacity at 300, 600, 900 and reach SH degree 3 at iteration 301. The scaled opacity-reset
period is kept >= 3 densification periods (as in the seed schedule, a reset needs time to
recover: a 30-iteration run would otherwise reset every 9 steps and end nearly transparent).
The learning rates are
not scaled; the position rate decays exponentially over the whole run whatever its length.
``scale_schedule=False`` keeps the seed code's absolute iteration counts.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["TrainConfig", "Schedule", "DEFAULT_ITERATIONS", "PAPER_ITERATIONS", "default_iterations", "resolve_device",
           "RESUME_FREE_KEYS", "POSE_KEYS", "load_config"]

# Chosen from measured CPU runs on the 256x192 synthetic scene (`python -m camio synth`, 12
# training views, ground-truth seed through the Bridge, 1 thread on a shared 2-core machine):
# 1000 iterations 478 s, 51k Gaussians, held-out PSNR 26.85 dB; 2000 iterations 1277 s, 95k
# Gaussians, 27.92 dB (benchmarks/train_synthetic.json). 1000 is the CPU default that
# finishes in minutes; the paper's 10,000 take ~13 min on the 2-core CPU for the fern n = 3
# cell (212k Gaussians; benchmarks/README.md, "The paper's 10,000-iteration cell").
DEFAULT_ITERATIONS = 1000
# The paper's budget ("10K iterations", PROTOCOL.md section 3): the default on a GPU, and the
# run length the seed code's schedule was written for.
PAPER_ITERATIONS = 10000


def resolve_device(device: str) -> str:
    """The config's ``device`` with 'auto' resolved: 'cuda' when torch sees a CUDA GPU, else 'cpu'."""
    if device == "auto":
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def default_iterations(device: str) -> int:
    """Iterations of a run that names none: :data:`PAPER_ITERATIONS` where training runs on a
    GPU (``device`` 'cuda', or 'auto' with a CUDA device visible), :data:`DEFAULT_ITERATIONS`
    on a CPU."""
    return PAPER_ITERATIONS if resolve_device(device) == "cuda" else DEFAULT_ITERATIONS

# Config fields that do not change the optimisation result: they may differ on resume.
# The rasterizer backend is among them: the backends are parity-tested against one reference
# (tests/test_raster_parity.py, tests/test_raster_gsplat.py), so a run started on CPU may go on
# on a GPU, and checkpoints written before the key existed still resume.
RESUME_FREE_KEYS = ("checkpoint_every", "keep_checkpoints", "eval_every", "num_threads", "kernel_threads",
                    "rasterizer", "eval_lpips", "lpips_weights")
# Config fields that only matter with pose_refine: a run without refinement may resume a
# checkpoint that differs in them (or predates them).
POSE_KEYS = ("lr_pose", "pose_refine_from", "pose_warmup", "pose_refine_focal", "lr_focal")


@dataclass
class TrainConfig:
    """Every hyperparameter of a training run. Field names are the JSON override keys.

    Attributes (learning rates are Adam step sizes for the stored parameterisation):
        iterations: optimisation steps; None (the default): :func:`default_iterations` of
            ``device`` (10,000 on a GPU, 1,000 on a CPU), resolved when the config is made.
        seed: seed of the run's random generator (view order, random backgrounds, splits).
        sh_degree: maximum SH degree (3 as in 3DGS).
        sh_increase_every: raise the active SH degree by one every so many iterations.
        lr_position_init, lr_position_final: position rate at the start / end, multiplied by
            the scene extent; exponential decay over the run.
        lr_sh_dc, lr_sh_rest, lr_opacity, lr_scaling, lr_rotation: constant rates.
        adam_eps: Adam epsilon (3DGS uses 1e-15).
        lambda_dssim: weight of (1 - SSIM) in the loss (1 - w) L1 + w (1 - SSIM).
        background: RGB in [0, 1] behind the Gaussians.
        random_background: draw a uniform random background every iteration instead.
        densify_from, densify_until, densify_every: densification window and period.
        densify_grad_threshold: mean view-space (NDC) positional gradient norm above which a
            Gaussian is cloned (small) or split (large).
        percent_dense: a Gaussian is "large" when its largest scale exceeds this fraction of
            the scene extent.
        opacity_reset_every: set every opacity to min(opacity, opacity_reset_value) this often.
        prune_opacity: remove Gaussians whose opacity falls below this at densification.
        prune_screen_size: after the first opacity reset, also remove Gaussians whose 2D
            radius exceeded this many pixels ...
        prune_world_size: ... or whose largest scale exceeds this fraction of the extent.
        max_gaussians: densification stops adding Gaussians above this count (None: no cap).
        schedule_reference_iterations, scale_schedule: see the module docstring.
        pose_refine: learn small se(3) corrections of the training cameras (off by default;
            the first camera and the scale stay fixed, :mod:`splat_train.pose`).
        lr_pose: Adam rate of the pose corrections (rotation in radians, translation in units
            of the RMS distance of the training-camera centres from the first one).
        pose_refine_from: first iteration at which the poses move (the Gaussians settle first).
        pose_warmup: the pose (and focal) rate ramps linearly from 0 to its value over this
            many iterations after ``pose_refine_from`` (0: no ramp).
        pose_refine_focal: with ``pose_refine``, also learn one log-focal correction per
            camera (fx and fy scaled together).
        lr_focal: Adam rate of the log-focal corrections.
        downsample: integer area-downsampling factor of the training images.
        checkpoint_every, keep_checkpoints: checkpoint period and how many to keep.
        eval_every: held-out evaluation period (only with test cameras): PSNR and SSIM, and
            LPIPS with ``eval_lpips``; 0 disables (final only).
        eval_lpips: also compute LPIPS (v0.1, AlexNet) at every held-out evaluation
            (``log.parquet`` ``test_lpips``). Off by default: the AlexNet pass and the weight
            file are a cost a plain training run need not pay (measured at 128 x 96 px, 1
            thread, load 2.6 on 2 cores: PSNR + SSIM 4.5 ms a view, LPIPS-alex 24 ms more);
            the study configs turn it on. Without weights the column stays null and a warning says how to get them.
        lpips_weights: folder or file of the LPIPS-alex safetensors weights (None: the
            :func:`evaluation.lpips.find_weights` search order, LPIPS_WEIGHTS_DIR then the
            user cache).
        device: "auto" (CUDA when available), "cpu" or "cuda".
        rasterizer: the :func:`splat_train.rasterize` backend; "auto" = the C++ kernel on CPU,
            gsplat on CUDA when installed (else the PyTorch tile code, with a warning). The
            backend that ran is logged and written to ``train.json`` (``rasterizer``).
        extent_from_points: the scene extent (position rate, world-size prune) is at least 1.1 x
            the median seed distance from the camera mean, not only the camera spread (see
            :func:`splat_train.data.scene_extent`); False keeps the plain 3DGS rule.
        kernel_threads: threads of the C++ rasterizer kernel on CPU (0: every CPU available to
            the process). Its threads do not spin, so it uses the cores torch leaves idle.
        num_threads: torch CPU threads (0: leave torch's default). Default 1: on the 2-core CPU
            machines here, 2 intra-op threads made 30 iterations on a 128x96 scene take 26.7 s
            instead of 0.8 s whenever the other core was busy (spinning worker threads), and
            the rasterizer benchmark saw 2-8x slowdowns at every size; one thread per training
            job also lets Snakemake run two jobs side by side on --cores 2.
    """

    iterations: int | None = None
    seed: int = 0
    sh_degree: int = 3
    sh_increase_every: int = 1000
    lr_position_init: float = 1.6e-4
    lr_position_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20.0
    lr_opacity: float = 0.05
    lr_scaling: float = 5e-3
    lr_rotation: float = 1e-3
    adam_eps: float = 1e-15
    lambda_dssim: float = 0.2
    background: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    random_background: bool = False
    densify_from: int = 500
    densify_until: int = 10000
    densify_every: int = 100
    densify_grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    opacity_reset_every: int = 3000
    opacity_reset_value: float = 0.01
    prune_opacity: float = 0.005
    prune_screen_size: float = 20.0
    prune_world_size: float = 0.1
    max_gaussians: int | None = None
    schedule_reference_iterations: int = PAPER_ITERATIONS
    scale_schedule: bool = True
    pose_refine: bool = False
    # From benchmarks/bench_pose.py --quick (posed/oracle + VGGT-level noise, 300 iterations): rate
    # 1e-3 from iteration 1 walked the cameras away on fern (ATE 1.5 -> 30 % of the radius) while
    # the Gaussians were still a blur; 1e-4 after 100 iterations with a 100-iteration ramp lowered
    # both errors on both scenes (benchmarks/README.md).
    lr_pose: float = 1e-4
    pose_refine_from: int = 100
    pose_warmup: int = 100
    pose_refine_focal: bool = False
    lr_focal: float = 1e-4
    downsample: int = 1
    checkpoint_every: int = 500
    keep_checkpoints: int = 2
    eval_every: int = 200
    eval_lpips: bool = False
    lpips_weights: str | None = None
    device: str = "auto"
    rasterizer: str = "auto"
    num_threads: int = 1
    kernel_threads: int = 0
    extent_from_points: bool = True

    def __post_init__(self) -> None:
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be 'auto', 'cpu' or 'cuda', got {self.device!r}")
        if self.iterations is None:
            self.iterations = default_iterations(self.device)
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0..3, got {self.sh_degree}")
        if len(self.background) != 3:
            raise ValueError(f"background must be 3 numbers (RGB in [0, 1]), got {self.background}")
        self.background = [float(x) for x in self.background]
        if int(self.downsample) != self.downsample or self.downsample < 1:
            raise ValueError(f"downsample must be a positive integer, got {self.downsample}")
        if self.checkpoint_every < 1:
            raise ValueError(f"checkpoint_every must be >= 1, got {self.checkpoint_every}")
        if self.keep_checkpoints < 1:
            raise ValueError(f"keep_checkpoints must be >= 1, got {self.keep_checkpoints}")
        if self.pose_refine_from < 0 or self.pose_warmup < 0:
            raise ValueError(f"pose_refine_from and pose_warmup must be >= 0, got "
                             f"{self.pose_refine_from} and {self.pose_warmup}")
        from splat_train.rasterize import BACKENDS

        if self.rasterizer not in BACKENDS:
            raise ValueError(f"rasterizer must be one of {BACKENDS}, got {self.rasterizer!r}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replace(self, **overrides: Any) -> "TrainConfig":
        """A copy with ``overrides`` applied; unknown keys raise ValueError naming them."""
        _check_keys(overrides)
        return dataclasses.replace(self, **overrides)

    def schedule(self) -> "Schedule":
        """The iteration counts this run uses (scaled as described in the module docstring)."""
        f = 1.0
        if self.scale_schedule:
            f = min(1.0, self.iterations / float(self.schedule_reference_iterations))

        def sc(n: int) -> int:
            return max(1, int(round(n * f))) if f < 1.0 else int(n)

        return Schedule(
            densify_from=sc(self.densify_from),
            densify_until=sc(self.densify_until),
            densify_every=int(self.densify_every),
            opacity_reset_every=(max(sc(self.opacity_reset_every), 3 * int(self.densify_every))
                                 if f < 1.0 else int(self.opacity_reset_every)),
            sh_increase_every=sc(self.sh_increase_every),
            factor=f,
        )



@dataclass(frozen=True)
class Schedule:
    """Iteration counts in effect for one run (after scaling); ``factor`` is the scale used."""

    densify_from: int
    densify_until: int
    densify_every: int
    opacity_reset_every: int
    sh_increase_every: int
    factor: float

    def sh_degree_at(self, iteration: int, max_degree: int) -> int:
        """Active SH degree at 1-based ``iteration``: +1 every ``sh_increase_every``."""
        return min(max_degree, (iteration - 1) // self.sh_increase_every)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _check_keys(keys: dict[str, Any]) -> None:
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(keys) - known)
    if unknown:
        raise ValueError(f"unknown training config keys {unknown}; valid keys: {sorted(known)}")


def load_config(overrides: str | Path | dict | None = None, **cli: Any) -> TrainConfig:
    """Defaults, then JSON overrides (a file path, a JSON string or a dict), then ``cli``
    values that are not None (the CLI flags win)."""
    data: dict[str, Any] = {}
    if isinstance(overrides, dict):
        data = dict(overrides)
    elif overrides is not None:
        text = str(overrides)
        p = Path(text)
        try:
            data = json.loads(p.read_text() if p.is_file() else text)
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"--config must be a JSON file or a JSON object string: {exc}") from exc
        if not isinstance(data, dict):
            raise ValueError(f"--config must hold a JSON object, got {type(data).__name__}")
    data.update({k: v for k, v in cli.items() if v is not None})
    _check_keys(data)
    return TrainConfig(**data)  # made once, so an unset iterations follows the device given
