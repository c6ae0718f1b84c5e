"""CLI: ``python -m evaluation.initialisers.mvs (--scene DIR | --images DIR --cameras MODEL)
(--image-list FILE | --names ...) --out DIR [values]``.

Dense points with a confidence from posed training views by multi-view stereo on the CPU
(evaluation/initialisers/mvs/run.py). On a prepared scene the cameras are its reference cameras
(``SCENE/sparse/0``) and the images ``SCENE/images``; on a folder of photos ``--cameras`` names
any COLMAP model of them (COLMAP's, VGGT's, bundle adjustment's ``sparse/0``). Writes
``predictions.npz``, ``sparse/0`` and ``status.json`` (docs/contracts.md, "mvs initialiser").
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import fields

from evaluation.initialisers.mvs.run import MvsConfig, run_mvs
from evaluation.initialisers.views import add_view_args, parse_training_args
from runtime.checks import flag_of
from runtime.cliargs import add_log_flags, plain

log = logging.getLogger("evaluation.initialisers.mvs")

#: each MvsConfig field's help (its docstring says the same at more length)
HELP = {
    "max_size": "long side of the working resolution, pixels; larger photos are downsampled",
    "max_sources": "source views per reference view",
    "window": "NCC window, pixels (odd)",
    "top_k": "sources averaged per depth hypothesis (0: half of the sources, at least 1)",
    "step_px": "largest move of a pixel in a source between consecutive depth planes",
    "min_planes": "fewest depth planes per view",
    "max_planes": "most depth planes per view",
    "coarse_factor": "downsampling of the coarse sweep that bounds the depths (1: none)",
    "min_std": "grey-level standard deviation below which a window is textureless",
    "margin_scale": "cost margin at which the matching confidence reaches 1 - 1/e",
    "min_conf": "matching confidence a kept pixel needs, in [0, 1]",
    "min_agree": "other views that must agree with a kept pixel",
    "tol_px": "consistency check: reprojection tolerance, pixels",
    "tol_rel": "consistency check: relative depth tolerance",
    "plane_families": "slanted plane families beside the fronto-parallel planes (ground, dominant planes)",
    "chunk": "depth planes warped at once (memory)",
    "fill_stride": "every K-th pixel stereo left without a point gets one, confidence 0, in predictions.npz (0: none)",
    "max_points": "fused points written to sparse/0 at most",
    "threads": "torch CPU threads (0: torch's default)",
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m evaluation.initialisers.mvs",
                                description=plain(__doc__.split("\n\n")[1]))
    p.add_argument("--scene", help="prepared scene with images/ and sparse/0 (reference cameras)")
    p.add_argument("--images", help="image folder (default SCENE/images)")
    p.add_argument("--cameras", help="COLMAP model of the training views (default SCENE/sparse/0)")
    add_view_args(p, split=False)
    p.add_argument("--out", required=True, help="output folder (predictions.npz, sparse/0, status.json)")
    defaults = MvsConfig()
    for f in fields(MvsConfig):
        p.add_argument(f"--{f.name.replace('_', '-')}", type=flag_of(MvsConfig, f.name),
                       default=getattr(defaults, f.name), help=HELP[f.name] + " (default %(default)s)")
    add_log_flags(p)
    return p


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args, names = parse_training_args(p, argv)
    if not args.scene and not (args.images and args.cameras):
        p.error("give --scene SCENE (its images/ and sparse/0), or --images DIR and --cameras MODEL")
    try:
        cfg = MvsConfig(**{f.name: getattr(args, f.name) for f in fields(MvsConfig)})
    except ValueError as exc:
        p.error(str(exc))
    images = args.images or f"{args.scene}/images"
    from camio.images import ImageReadError
    from runtime.outdir import prepare_out, run_stage

    def work() -> None:
        prepare_out(args.out, {"--scene": args.scene, "--images": args.images, "--cameras": args.cameras,
                               "--image-list": args.image_list}, "evaluation.initialisers.mvs")
        run_mvs(images, names, args.out, scene=args.scene, cameras=args.cameras, cfg=cfg)

    return run_stage(log, work, errors=(ValueError, ImageReadError, OSError))


if __name__ == "__main__":
    raise SystemExit(main())
