"""CLI of the Bridge.

    python -m bridge --pred predictions.npz --out DIR [--mode gated|uniform|filtered]
        [--alpha-min A] [--alpha-max A] [--uniform-alpha A] [--stride K]
        [--max-points N] [--percentile P] [--voxel-size V] [--outlier-removal] [--points3d]
    python -m bridge --colmap MODEL_DIR [--images DIR] --out DIR [...]

Writes DIR/seed.ply, DIR/sparse/0/*.txt and DIR/bridge.json (docs/contracts.md). Every default
is BridgeConfig's (bridge/core.py), shown by --help.
"""

from __future__ import annotations

import argparse
import logging
import sys

from bridge.core import DEFAULT_PERCENTILE, MODES, BridgeConfig, run_bridge
from runtime.checks import flag_of
from runtime.logs import setup_logging, timed

log = logging.getLogger("bridge")
#: the one place of the flags' defaults
DEFAULTS = BridgeConfig()
#: --stride for a COLMAP model: every point (its points are few and all triangulated)
COLMAP_STRIDE = 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m bridge",
        description="Eq. 1 normalisation and Eq. 2 confidence-gated seeding: predictions.npz (or a "
                    "COLMAP model) -> seed.ply + normalised sparse/0 + bridge.json",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--pred", help="predictions.npz of vggt_init (or the oracle)")
    src.add_argument("--colmap", help="COLMAP model folder (text or binary; or a scene folder with sparse/0)")
    p.add_argument("--images", help="image folder of the COLMAP model (checked: every image must exist)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--mode", choices=MODES, default=DEFAULTS.mode,
                   help="opacity: gated (Eq. 2), uniform (constant), filtered (percentile, then Eq. 2); "
                        "default %(default)s")
    p.add_argument("--alpha-min", type=flag_of(BridgeConfig, "alpha_min"), default=DEFAULTS.alpha_min,
                   help="Eq. 2 a_min (default %(default)s)")
    p.add_argument("--alpha-max", type=flag_of(BridgeConfig, "alpha_max"), default=DEFAULTS.alpha_max,
                   help="Eq. 2 a_max (default %(default)s)")
    p.add_argument("--uniform-alpha", type=flag_of(BridgeConfig, "uniform_alpha"), default=DEFAULTS.uniform_alpha,
                   help="opacity of uniform mode (default %(default)s)")
    p.add_argument("--stride", type=flag_of(BridgeConfig, "stride"), default=None,
                   help=f"keep every stride-th flattened pixel (default {DEFAULTS.stride} for --pred as the paper, "
                        f"{COLMAP_STRIDE} for --colmap)")
    p.add_argument("--max-points", type=flag_of(BridgeConfig, "max_points"), default=None,
                   help="keep at most this many (most confident)")
    p.add_argument("--percentile", type=flag_of(BridgeConfig, "percentile"), default=None,
                   help=f"drop the lowest P %% by confidence (default: off; {DEFAULT_PERCENTILE:g} in filtered mode)")
    p.add_argument("--voxel-size", type=flag_of(BridgeConfig, "voxel_size"), default=None,
                   help="voxel downsampling, normalised units")
    p.add_argument("--outlier-removal", action="store_true", help="open3d statistical outlier removal")
    p.add_argument("--outlier-neighbors", type=flag_of(BridgeConfig, "outlier_neighbors"),
                   default=DEFAULTS.outlier_neighbors,
                   help="outlier removal: neighbours per point (default %(default)s)")
    p.add_argument("--outlier-std", type=flag_of(BridgeConfig, "outlier_std_ratio"), default=DEFAULTS.outlier_std_ratio,
                   help="outlier removal: standard deviations of the mean neighbour distance kept "
                        "(default %(default)s)")
    p.add_argument("--points3d", action="store_true",
                   help="also write the seed points into sparse/0/points3D.txt (for the original 3DGS loader)")
    p.add_argument("--no-depth-prior", dest="depth_prior", action="store_false",
                   help="do not write depth_prior.npz (the initialiser's per-camera depth for training's depth term)")
    p.add_argument("--depth-prior-samples", type=flag_of(BridgeConfig, "depth_prior_samples"),
                   default=DEFAULTS.depth_prior_samples,
                   help="at most this many depth-prior samples per camera (default %(default)s)")
    p.add_argument("--seed", type=flag_of(BridgeConfig, "seed"), default=DEFAULTS.seed,
                   help="random seed (capping a cloud, the depth prior's subset; default %(default)s)")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (repeatable)")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    if args.images and not args.colmap:
        log.error("--images goes with --colmap only")
        return 2
    from bridge.inputs import load_colmap, load_predictions
    from runtime.outdir import prepare_out, run_stage

    def work() -> None:
        prepare_out(args.out, {"--pred": args.pred, "--colmap": args.colmap, "--images": args.images}, "bridge")
        cfg = BridgeConfig(
            mode=args.mode, alpha_min=args.alpha_min, alpha_max=args.alpha_max,
            uniform_alpha=args.uniform_alpha,
            stride=args.stride if args.stride is not None else (DEFAULTS.stride if args.pred else COLMAP_STRIDE),
            percentile=args.percentile, voxel_size=args.voxel_size, outlier_removal=args.outlier_removal,
            outlier_neighbors=args.outlier_neighbors, outlier_std_ratio=args.outlier_std,
            max_points=args.max_points, seed=args.seed, write_points3d=args.points3d,
            depth_prior=args.depth_prior, depth_prior_samples=args.depth_prior_samples,
        )
        timings: dict[str, float] = {}
        with timed("load input", log, timings):
            inp = load_predictions(args.pred) if args.pred else load_colmap(args.colmap, args.images)
        report = run_bridge(inp, args.out, cfg, timings={"load": timings["load input"]})
        log.info("done: %d Gaussians, s = %.6g, mode %s, total %.2f s -> %s", report["points_kept"], report["s"],
                 report["mode"], report["timings_s"]["total"], args.out)

    return run_stage(log, work, errors=(ValueError, KeyError, OSError))


if __name__ == "__main__":
    sys.exit(main())
