"""``python -m camio``: synthetic scene, dataset conversion, splits.

    python -m camio synth --out DIR [--views N] [--width PX] [--seed S] [--arc-deg DEG]
    python -m camio convert --src PATH --out DIR [--format auto] [--images-subdir images_8]
                            [--downsample K | --max-size PX] [--undistort] [--skip-missing] [--allow-mixed]
    python -m camio split --scene DIR --n 3 6 9 12 [--manifest JSON] --out split.json
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from camio.limits import MAX_IMAGE_SIDE
from runtime.checks import flag
from runtime.cliargs import add_log_flags, plain
from runtime.logs import setup_logging, timed

log = logging.getLogger("camio")


def _parser() -> argparse.ArgumentParser:
    from camio.datasets import DATASET_FORMATS
    from camio.prepare import PHOTO_MAX_SIZE
    from camio.scene import FORMATS
    from camio.synthetic import ARC_DEG, VIEWS, WIDTH

    p = argparse.ArgumentParser(prog="python -m camio", description=plain(__doc__).split("\n")[0])
    add_log_flags(p)
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synth", help="write the synthetic ground-truth scene")
    s.add_argument("--out", required=True, type=Path, help="scene folder to write (images/, sparse/0, gt/)")
    s.add_argument("--views", type=flag(int, 1), default=VIEWS,
                   help="number of rendered views (default %(default)s)")
    s.add_argument("--width", type=flag(int, 4, MAX_IMAGE_SIDE), default=WIDTH,
                   help="image width in pixels, height 3/4 of it (default %(default)s)")
    s.add_argument("--seed", type=flag(int, 0), default=0, help="random seed of the scene (default %(default)s)")
    s.add_argument("--arc-deg", type=flag(float, 0, 360, lo_open=True), default=ARC_DEG,
                   help="angle the cameras span, degrees (default %(default)s)")
    s.add_argument("--layout", choices=("arc", "sphere"), default="arc",
                   help="cameras on an arc facing the scene, or spread over a sphere")
    s.add_argument("--supersample", type=flag(int, 1, 16), default=1, help="anti-aliasing rays per pixel side")
    add_log_flags(s, subcommand=True)

    c = sub.add_parser("convert", help="any supported dataset format -> prepared scene")
    c.add_argument("--src", required=True, type=Path, help="the downloaded scene folder (its format is detected)")
    c.add_argument("--out", required=True, type=Path, help="prepared scene folder to write (docs/contracts.md)")
    c.add_argument("--format", default="auto", choices=FORMATS,
                   help="input layout; auto: detected from its camera files; " + "; ".join(
                       f"{f.name}: {f.description} ({f.files})" for f in DATASET_FORMATS.values()))
    c.add_argument("--images-subdir", default=None, help="image folder relative to --src (e.g. images_8)")
    c.add_argument("--downsample", type=flag(int, 1), default=1, help="integer area-downsampling factor")
    c.add_argument("--max-size", dest="max_size", type=flag(int, 0, MAX_IMAGE_SIDE), default=None, metavar="PX",
                   help=f"a photo folder (no cameras): the long side of the working images at most PX "
                        f"(area-downsampled; default {PHOTO_MAX_SIZE}; 0 = full resolution)")
    c.add_argument("--undistort", action="store_true",
                   help="undistort distorted cameras (COLMAP, transforms.json k1 k2 p1 p2, Strecha) to PINHOLE")
    c.add_argument("--skip-missing", action="store_true",
                   help="transforms.json: drop frames whose image files are missing (warning) instead of failing")
    c.add_argument("--allow-mixed", action="store_true",
                   help="bare folder: accept images of mixed pixel types or sizes")
    c.add_argument("--n", type=flag(int, 1), nargs="+", default=[3, 6, 9, 12],
                   help="training-view counts for split.json")
    add_log_flags(c, subcommand=True)

    t = sub.add_parser("split", help="write split.json for a scene (PROTOCOL section 4)")
    t.add_argument("--scene", required=True, type=Path, help="scene folder (its images/) or an image folder")
    t.add_argument("--n", type=flag(int, 1), nargs="+", default=[3, 6, 9, 12], help="training-view counts")
    t.add_argument("--manifest", type=Path, default=None, help="JSON split manifest overriding the rule")
    t.add_argument("--out", required=True, type=Path, help="split.json to write")
    add_log_flags(t, subcommand=True)
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    from runtime.outdir import prepare_out, run_stage, seal_out

    def work() -> None:
        if args.command == "synth":
            from camio.synthetic import write_synthetic_scene

            prepare_out(args.out, {}, "camio synth", replaces=True)
            with timed("synth", log):
                write_synthetic_scene(args.out, views=args.views, width=args.width, seed=args.seed,
                                      arc_deg=args.arc_deg, layout=args.layout, supersample=args.supersample)
            seal_out(args.out, "camio synth")
        elif args.command == "convert":
            from camio.prepare import prepare_scene

            prepare_out(args.out, {"--src": args.src}, "camio convert", replaces=True)
            with timed("convert", log):
                prepare_scene(args.src, args.out, args.format, args.images_subdir, args.downsample,
                              args.undistort, tuple(args.n), allow_mixed=args.allow_mixed,
                              skip_missing=args.skip_missing, announce=lambda s: print(s, flush=True),
                              max_size=args.max_size)
            seal_out(args.out, "camio convert")
        elif args.command == "split":
            from camio.images import list_images
            from camio.split import make_split, write_split

            # split.json belongs in the scene folder (docs/contracts.md), never over an input
            prepare_out(args.out, {"--scene": args.scene, "--manifest": args.manifest}, "camio split", folder=False,
                        may_hold_out=("--scene",), same_file_as={"camio convert": ("split.json",), "camio synth": ("split.json",)})
            folder = args.scene / "images" if (args.scene / "images").is_dir() else args.scene
            split = make_split(list_images(folder), tuple(args.n), args.manifest)
            write_split(args.out, split)
            log.info("split (%s): %d test, train n = %s -> %s", split.rule, len(split.test),
                     ", ".join(split.train), args.out)

    return run_stage(log, work)


if __name__ == "__main__":
    sys.exit(main())
