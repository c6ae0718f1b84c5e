"""Command line: ``python -m splat_train`` (train) and ``python -m splat_train render``.

Train::

    python -m splat_train --seed-ply seed.ply --cameras DIR --images DIR --out DIR
        [--iterations N] [--test-cameras DIR --test-images DIR] [--image-list FILE]
        [--test-image-list FILE]
        [--downsample K] [--config JSON] [--seed INT] [--checkpoint-every K]
        [--eval-every M] [--eval-lpips | --no-eval-lpips] [--lpips-weights PATH] [--pose-refine [--pose-refine-focal]] [--device auto|cpu|cuda] [--threads T]
        [--resume-dir DIR] [--rasterizer BACKEND] [--snapshot-every N]

Look at a trained model in the browser (splat_train/view)::

    python -m splat_train view --model model.ply|OUT [--cameras DIR] [--test-cameras DIR] [--seed-ply seed.ply]
        [--port P] [--host 127.0.0.1] [--no-browser]

Render a trained model into any camera set, or a fly-through video along its cameras::

    python -m splat_train render --model model.ply --cameras DIR --out DIR
        [--images DIR | --width W --height H] [--image-list FILE] [--background R,G,B]
    python -m splat_train render --model model.ply --cameras DIR --path orbit|interpolate --video out.mp4
        [--frames N] [--fps F] [--width W --height H] [--image-list FILE] [--background R,G,B]

Share a trained model in a web viewer's format (camio.splatfmt)::

    python -m splat_train export --format splat|spz|ply --out FILE model.ply

Test-pose protocol (each held-out pose optimised against its image, Gaussians frozen;
splat_train/testpose.py)::

    python -m splat_train testpose --model model.ply --cameras DIR --images DIR --out DIR
        [--steps N] [--patience K] [--lr LR] [--image-list FILE] [--device cpu|cuda] [--rasterizer BACKEND]
"""

from __future__ import annotations

import argparse
import logging
import re
import sys
from pathlib import Path

from camio.depth_prior import DEPTH_PRIOR_FILE
from camio.limits import MAX_IMAGE_SIDE
from runtime.checks import flag, flag_of
from runtime.cliargs import deprecated_flags, device_name, is_int
from runtime.logs import setup_logging

log = logging.getLogger("splat_train")

# Old spellings, kept for one release: --seed naming the seed PLY (a value that is not an
# integer) is now --seed-ply; --seed-rng is now --seed.
_OLD_TRAIN_FLAGS = {"--seed": ("--seed-ply", lambda v: not is_int(v)), "--seed-rng": ("--seed", None)}


# The config keys the train command sets by flag ({flag: flat key}); every key (these too) is
# also a --config key. Each flag's type and range, default and help come from the config field
# the key names (splat_train.config.field_of): the field's annotation, its default, its doc.
CONFIG_FLAGS = {"--iterations": "iterations", "--downsample": "downsample", "--seed": "seed",
                "--checkpoint-every": "checkpoint_every", "--eval-every": "eval_every", "--eval-lpips": "eval_lpips",
                "--lpips-weights": "lpips_weights", "--pose-refine": "pose_refine",
                "--pose-refine-focal": "pose_refine_focal", "--device": "device", "--rasterizer": "rasterizer",
                "--threads": "num_threads", "--kernel-threads": "kernel_threads"}
# what a text flag checks beyond its field (the device's spelling)
_FLAG_TYPES = {"device": dict(type=device_name, metavar="auto|cpu|cuda|cuda:N")}


class _ConfigFlag(argparse.Action):
    """Stores a config flag's value and notes that it was given (only given flags reach the
    config, over ``--config`` and the recipe)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.config_given = [*getattr(namespace, "config_given", []), self.dest]


class _ConfigSwitch(argparse.BooleanOptionalAction):
    """A true/false config flag (``--x`` / ``--no-x``) that notes it was given."""

    def __call__(self, parser, namespace, values, option_string=None):
        super().__call__(parser, namespace, values, option_string)
        namespace.config_given = [*getattr(namespace, "config_given", []), self.dest]


def _help_of(doc: str) -> str:
    """A field's doc as flag help: its first sentence, reST roles and literals as plain text,
    ``%`` escaped for argparse."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", doc)
    text = text.replace("``", "").replace("`", "")
    first = re.split(r"(?<=[.)])\s+(?=[A-Z])", text, maxsplit=1)[0].rstrip(".")
    return first.replace("%", "%%")


def _add_config_flags(p: argparse.ArgumentParser) -> None:
    """The :data:`CONFIG_FLAGS`, made from their config fields."""
    import dataclasses

    from runtime.checks import field_ranges
    from splat_train.config import field_of
    from splat_train.fields import field_docs

    group = p.add_argument_group("training config", "each flag sets the --config key of its name (the flag wins)")
    for flag_name, key in CONFIG_FLAGS.items():
        cls, name = field_of(key)
        default = next(f.default for f in dataclasses.fields(cls) if f.name == name)
        doc = _help_of(field_docs(cls)[name])
        help_text = doc if default is None else f"{doc} (default %(default)s)"
        allowed, _ = field_ranges(cls)[name]
        if bool in allowed:
            group.add_argument(flag_name, dest=key, action=_ConfigSwitch, default=default, help=help_text)
        elif int in allowed or float in allowed:
            group.add_argument(flag_name, dest=key, action=_ConfigFlag, type=flag_of(cls, name), default=default,
                               help=help_text)
        else:
            group.add_argument(flag_name, dest=key, action=_ConfigFlag, default=default, help=help_text,
                               **_FLAG_TYPES.get(key, {}))


def _train_parser() -> argparse.ArgumentParser:
    from splat_train import recipes
    from splat_train.fields import flat_names
    from splat_train.parts.configs import PARTS

    parts = "; ".join(f"{name} ({', '.join(flat_names(cls).values())})" for name, cls in PARTS.items())
    p = argparse.ArgumentParser(prog="python -m splat_train",
                                epilog=f"training parts, each set by its --config keys: {parts}",
                                description="Train 3D Gaussian Splatting from a seed PLY and posed images "
                                            "(resumes from OUT/ckpt automatically). "
                                            "`python -m splat_train render -h` renders a trained model (or a "
                                            "fly-through video), `python -m splat_train view -h` shows one in the "
                                            "browser, `python -m splat_train export -h` writes one for other viewers.")
    p.add_argument("--seed-ply", dest="seed_ply", required=True, help="the seed point cloud to start from: a PLY in the 3DGS layout, "
                   "e.g. the Bridge's seed.ply")
    p.add_argument("--cameras", required=True, help="COLMAP model folder of the training cameras")
    p.add_argument("--images", required=True, help="folder of the training images")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--recipe", choices=list(recipes.RECIPES),
                   help=f"training recipe (default {recipes.DEFAULT_RECIPE}; splat_train.recipes): "
                        + "; ".join(f"'{k}': {v}" for k, v in recipes.RECIPE_SUMMARIES.items()))
    p.add_argument("--depth-prior", dest="depth_prior",
                   help=f"the Bridge's {DEPTH_PRIOR_FILE} (default: the one beside --seed-ply, if any)")
    p.add_argument("--test-cameras", help="COLMAP model folder of held-out cameras (same frame)")
    p.add_argument("--test-images", help="folder of the held-out images")
    p.add_argument("--image-list", help="file of training image names (one per line, or a JSON list)")
    p.add_argument("--test-image-list", help="file of held-out image names (restricts --test-cameras)")
    p.add_argument("--config", help="JSON file or JSON object string of config overrides "
                                     "(the flat keys of splat_train.config.FLAT_KEYS)")
    p.add_argument("--resume-dir", help="keep checkpoints in DIR/<hash of inputs and config>/ckpt instead "
                                        "of OUT/ckpt (resume only from identical inputs; removed on success)")
    p.add_argument("--snapshot-every", type=flag(int, 1), dest="snapshot_every", metavar="N",
                   help="write OUT/snapshot.ply every N iterations and at the last, replaced atomically, its "
                        "iteration in its header (default: none); `python -m splat_train view --model OUT` "
                        "follows it live")
    _add_config_flags(p)
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (repeatable)")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    return p


def _render_parser() -> argparse.ArgumentParser:
    from camio.campath import DEFAULT_FRAMES, MAX_PATH_FRAMES, PATHS
    from camio.video import DEFAULT_FPS

    p = argparse.ArgumentParser(prog="python -m splat_train render",
                                description="Render a trained model.ply into the cameras of a COLMAP folder "
                                            "(PNG per camera, named <image stem>.png, into --out), or along a "
                                            "path over those cameras into an mp4 (--path and --video; needs "
                                            "the imageio and imageio-ffmpeg packages).")
    p.add_argument("--model", required=True, help="trained model.ply")
    p.add_argument("--cameras", required=True, help="COLMAP model folder (same frame as the model)")
    p.add_argument("--out", help="output folder for the PNGs (not with --path)")
    p.add_argument("--path", choices=list(PATHS),
                   help="fly-through instead of PNGs: 'interpolate' goes through the cameras in name order "
                        "(rotations slerped, centres linear); 'orbit' circles the point their optical axes "
                        "meet at their mean distance and height, looking at it")
    p.add_argument("--video", help="the mp4 file a --path writes (H.264; one intrinsic matrix, the first "
                                   "camera's, scaled to the video size)")
    p.add_argument("--frames", type=flag(int, 1, MAX_PATH_FRAMES), help="frames per camera pair (interpolate, default "
                   f"{DEFAULT_FRAMES['interpolate']}) or per circle (orbit, default {DEFAULT_FRAMES['orbit']})")
    p.add_argument("--fps", type=flag(float, 0, 240, lo_open=True), default=DEFAULT_FPS, help=f"video frames per second ({DEFAULT_FPS})")
    p.add_argument("--images", help="take each image size from the same-named file here "
                                    "(also reports PSNR against it)")
    p.add_argument("--width", type=flag(int, 1, MAX_IMAGE_SIDE),
                   help="render every camera (or the video) at this width (with --height; a video's size is "
                        "rounded down to even numbers)")
    p.add_argument("--height", type=flag(int, 1, MAX_IMAGE_SIDE),
                   help="render every camera (or the video) at this height (with --width)")
    p.add_argument("--image-list", help="only these image names")
    p.add_argument("--alpha", action="store_true",
                   help="also write each render's accumulated opacity to OUT/alpha/<stem>.png (16-bit gray), from "
                        "which `python -m evaluation images --alpha-dir` scores the pixels the model covers")
    p.add_argument("--background", default=None,
                   help="background RGB in [0,1], e.g. 1,1,1 (default: the one the model was trained against, "
                        "from the train.json beside it; black without one)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where to render")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (repeatable)")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    return p


def _export_parser() -> argparse.ArgumentParser:
    from camio.splatfmt import EXPORT_FORMATS

    p = argparse.ArgumentParser(prog="python -m splat_train export",
                                description="Write a trained model.ply in a format other viewers load "
                                            "(camio.splatfmt): 'splat' (antimatter15's 32 bytes per Gaussian: "
                                            "no view-dependent colour), 'spz' (Niantic's compressed format, "
                                            "right-up-back frame; needs the gsply package), 'ply' (the 3DGS PLY "
                                            "this project writes).")
    p.add_argument("model", help="trained model.ply (3DGS layout)")
    p.add_argument("--format", required=True, choices=list(EXPORT_FORMATS), help="the file format to write")
    p.add_argument("--out", required=True, help="the file to write (its suffix should match --format)")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (repeatable)")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    return p


def _testpose_parser() -> argparse.ArgumentParser:
    from splat_train.render.rasterize import BACKENDS
    from splat_train.testpose import DEFAULT_LR, DEFAULT_PATIENCE, DEFAULT_STEPS

    p = argparse.ArgumentParser(prog="python -m splat_train testpose",
                                description="Test-pose protocol: optimise each held-out camera's pose against its "
                                            "image with the model frozen; write the refined cameras "
                                            "(sparse/0), renders/ and testpose.json.")
    p.add_argument("--model", required=True, help="trained model.ply")
    p.add_argument("--cameras", required=True, help="COLMAP model folder of the starting held-out cameras "
                                                    "(the strict protocol's aligned cameras, model frame)")
    p.add_argument("--images", required=True, help="the held-out images")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--steps", type=flag(int, 0), default=DEFAULT_STEPS, help=f"Adam steps per view ({DEFAULT_STEPS})")
    p.add_argument("--patience", type=flag(int, 0), default=DEFAULT_PATIENCE,
                   help=f"stop a view after K steps in a row without a new lowest loss ({DEFAULT_PATIENCE}; 0: "
                        "every step; recorded in testpose.json with each view's steps_run)")
    p.add_argument("--lr", type=flag(float, 0, lo_open=True), default=DEFAULT_LR, help=f"Adam rate ({DEFAULT_LR})")
    p.add_argument("--image-list", help="only these image names")
    p.add_argument("--alpha", action="store_true", help="also write each render's accumulated opacity to "
                   "OUT/renders/alpha/<stem>.png (16-bit gray), from which `python -m evaluation images --alpha-dir` "
                   "scores the pixels the model covers")
    p.add_argument("--device", default="cpu", choices=["auto", "cpu", "cuda"],
                   help="where to render and optimise (auto: CUDA when available, else CPU; default cpu)")
    p.add_argument("--rasterizer", default="auto", choices=list(BACKENDS), help="rasterizer backend (auto: "
                   "gsplat on CUDA, the C++ kernel on a CPU)")
    p.add_argument("-v", "--verbose", action="count", default=0)
    p.add_argument("-q", "--quiet", action="store_true")
    return p


def _out_ok(out: str, inputs: dict, stage: str, fresh: bool = False, folder: bool = True, flag: str = "--out") -> bool:
    """camio's output rule for ``--out`` (runtime.outdir); False after logging the one-line refusal.
    ``fresh``: the command writes a folder of results (renders) and first removes its earlier
    run's files, so the folder never mixes two runs (seal it with runtime.outdir.seal_out).
    ``folder``: False for a command that writes one file (an export, a video); ``flag``: the
    option that named ``out`` (``--video``), as the refusal names it."""
    from runtime.ledger import OutputFolderError
    from runtime.outdir import prepare_out

    try:
        prepare_out(out, inputs, stage, fresh=fresh, folder=folder, flag=flag)
    except OutputFolderError as exc:
        log.error("%s", exc)
        return False
    return True


def _export(args: argparse.Namespace) -> int:
    """``python -m splat_train export``: the model read, checked, and written as ``--format``."""
    setup_logging(args.verbose, args.quiet)
    from camio.splatfmt import check_export_out, export_cloud

    note = check_export_out(args.out, args.format)  # before anything is written: a contradicting suffix is refused
    if note:
        log.warning("%s", note)
    if not _out_ok(args.out, {"MODEL": args.model}, "splat_train export", folder=False):
        return 2
    from camio.ply import check_seed_cloud, read_gaussian_ply

    for warning in check_seed_cloud(read_gaussian_ply(args.model), args.model, role="model"):
        log.warning("degenerate model: %s", warning)
    cloud, out = export_cloud(args.model, args.format, args.out)
    print(f"exported {len(cloud)} Gaussians of {args.model} as {args.format}: {out} "
          f"({out.stat().st_size / 1e6:.2f} MB)")
    return 0


def _render_video(args: argparse.Namespace, bg: tuple[float, float, float] | None) -> int:
    """``python -m splat_train render --path P --video FILE``: a fly-through (splat_train.flythrough)."""
    if not (args.path and args.video):
        log.error("--path and --video go together: --path orbit|interpolate --video out.mp4")
        return 2
    if args.out or args.images:
        log.error("--path writes one video: give --video FILE, not --out or --images")
        return 2
    if args.frames is not None and args.frames < 1 or not args.fps > 0:
        log.error("--frames must be >= 1 and --fps > 0, got --frames %s --fps %s", args.frames, args.fps)
        return 2
    if (args.width is None) != (args.height is None) or (args.width is not None and min(args.width, args.height) < 2):
        log.error("give both --width and --height (each >= 2), or neither")
        return 2
    from camio.video import VideoUnavailable, check_video_path, require_imageio

    try:
        check_video_path(args.video)  # before anything is written: ffmpeg picks the container by the suffix
        require_imageio()  # before any rendering: a missing encoder is one line naming the package
    except (ValueError, VideoUnavailable) as exc:
        log.error("%s", exc)
        return 2
    if not _out_ok(args.video, {"--model": args.model, "--cameras": args.cameras, "--image-list": args.image_list},
                   "splat_train render", folder=False, flag="--video"):
        return 2
    from camio.ply import check_seed_cloud, read_gaussian_ply
    from splat_train.flythrough import render_path

    for warning in check_seed_cloud(read_gaussian_ply(args.model), args.model, role="model"):
        log.warning("degenerate model: %s", warning)
    n = render_path(args.model, args.cameras, args.path, args.video, frames=args.frames, fps=args.fps,
                    width=args.width, height=args.height, names=args.image_list, background=bg,
                    device=args.device)
    print(f"video: {args.video}  frames: {n}  path: {args.path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Train, render, test-pose or view; the output folder's writer's lock is given up when the
    command returns or raises (runtime.outdir)."""
    from runtime.ledger import OutputFolderError
    from runtime.outdir import finish_outs
    from runtime.outlock import release_locks

    try:
        rc = _main(argv)
        if rc == 0:
            finish_outs()  # record what the command wrote, file by file (runtime.outdir)
        return rc
    except OutputFolderError as exc:  # a write the output rule refused: never over a user's file
        log.error("%s", exc)
        return 2
    finally:
        release_locks()


def _main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "view":
        from splat_train.view.cli import main as view_main
        return view_main(argv[1:])
    if argv and argv[0] == "export":
        return _export(_export_parser().parse_args(argv[1:]))
    if argv and argv[0] == "render":
        args = _render_parser().parse_args(argv[1:])
        setup_logging(args.verbose, args.quiet)
        from splat_train.export import background_note, model_background, parse_background, render_model

        try:  # before anything is written: a bad flag or train.json is one line
            bg, source = ((parse_background(args.background), "--background") if args.background is not None
                          else model_background(args.model))
        except ValueError as e:
            log.error("%s", e)
            return 2
        log.info("%s", background_note(bg, source))
        if args.images and args.width:
            log.error("give --images or --width/--height, not both")
            return 2
        if args.width and args.height:
            from camio.limits import check_image_size

            check_image_size(args.width, args.height, "--width/--height")
        if args.path or args.video:
            return _render_video(args, bg)
        if not args.out:
            log.error("give --out DIR (a PNG per camera) or --path and --video FILE (a fly-through)")
            return 2
        if not _out_ok(args.out, {"--model": args.model, "--cameras": args.cameras, "--images": args.images,
                                  "--image-list": args.image_list}, "splat_train render", fresh=True):
            return 2
        from camio.ply import check_seed_cloud, read_gaussian_ply

        for warning in check_seed_cloud(read_gaussian_ply(args.model), args.model, role="model"):
            log.warning("degenerate model: %s", warning)
        render_model(args.model, args.cameras, args.out, images=args.images, width=args.width,
                     height=args.height, names=args.image_list, background=bg, device=args.device,
                     alpha=args.alpha)
        from runtime.outdir import seal_out

        seal_out(args.out, "splat_train render")
        return 0

    if argv and argv[0] == "testpose":
        args = _testpose_parser().parse_args(argv[1:])
        setup_logging(args.verbose, args.quiet)
        from splat_train.export import model_background

        model_background(args.model)  # a bad train.json beside the model: one line before anything is written
        if not _out_ok(args.out, {"--model": args.model, "--cameras": args.cameras, "--images": args.images,
                                  "--image-list": args.image_list}, "splat_train testpose", fresh=True):
            return 2
        from splat_train.config import resolve_device
        from splat_train.testpose import run_testpose

        rec = run_testpose(args.model, args.cameras, args.images, args.out, steps=args.steps, lr=args.lr,
                           device=resolve_device(args.device), backend=args.rasterizer, names=args.image_list,
                           patience=args.patience, alpha=args.alpha)
        from runtime.outdir import seal_out

        seal_out(args.out, "splat_train testpose")
        print(f"test-pose: {len(rec['views'])} views, {rec['steps']} steps, mean rotation change "
              f"{rec['mean_rotation_deg'] or 0.0:.3f} deg -> {args.out}")
        return 0

    args = _train_parser().parse_args(deprecated_flags(argv, "python -m splat_train", _OLD_TRAIN_FLAGS))
    setup_logging(args.verbose, args.quiet)
    from splat_train.training.snapshot import check_snapshot_every

    try:
        check_snapshot_every(args.snapshot_every)
    except ValueError as e:
        log.error("%s", e)
        return 2
    from splat_train.config import load_config

    # checked before anything is written: a bad --config is one line naming it, no --out
    given = {key: getattr(args, key) for key in getattr(args, "config_given", [])}  # the flags given win
    cfg = load_config(args.config, **given, recipe=args.recipe)
    if not _out_ok(args.out, {"--seed-ply": args.seed_ply, "--cameras": args.cameras, "--images": args.images,
                              "--test-cameras": args.test_cameras, "--test-images": args.test_images,
                              "--image-list": args.image_list, "--test-image-list": args.test_image_list,
                              "--resume-dir": args.resume_dir}, "splat_train"):
        return 2
    from camio.ply import check_seed_cloud, read_gaussian_ply
    from splat_train.training.trainer import train

    for warning in check_seed_cloud(read_gaussian_ply(args.seed_ply), args.seed_ply):
        log.warning("degenerate seed: %s", warning)

    from camio.images import ImageReadError

    try:
        result = train(args.seed_ply, args.cameras, args.images, args.out, cfg, test_cameras=args.test_cameras,
                       test_images=args.test_images, image_list=args.image_list,
                       test_image_list=args.test_image_list, resume_dir=args.resume_dir,
                       depth_prior=args.depth_prior, snapshot_every=args.snapshot_every)
    except (ImageReadError, FileNotFoundError) as exc:  # bad input: one line naming the file
        log.error("%s: %s", type(exc).__name__, exc)
        return 2
    s = result.summary
    test_psnr = s["test_psnr"]
    print(f"model: {result.model_path}  Gaussians: {s['num_gaussians']}  train PSNR: {s['train_psnr']:.2f}  "
          f"test PSNR: {f'{test_psnr:.2f}' if test_psnr == test_psnr and test_psnr is not None else 'n/a'}  "
          f"training time: {s['wall_time_s']:.1f} s")
    return 0


def _cli() -> int:
    """``python -m splat_train``: :func:`main`, with a bad input (unreadable seed, camera model,
    checkpoint or config) reported as one line naming it instead of a traceback (-v shows the
    traceback). :func:`main` itself still raises, for callers and tests."""
    from runtime.outdir import run_stage

    def line(exc: BaseException) -> str:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        return f"{type(exc).__name__}: {msg}"

    # a stop signal (Ctrl-C, SIGTERM, SIGHUP) is one line and 128 + the signal (runtime.stops):
    # checkpoints are written atomically, so the last one is whole and a rerun resumes from it
    return run_stage(log, main, errors=(ValueError, KeyError, OSError), line=line, traceback=True)


if __name__ == "__main__":
    # Process-wide, so only when this is the process's CLI (not for callers of main()): every
    # training iteration allocates and frees MB-sized tensors (per-Gaussian gradients, images,
    # the SSIM statistics), which glibc's defaults map and fault in anew each time: ~2,100 minor
    # faults and ~8 ms of kernel time per iteration at 100k Gaussians, 256x256, none with the
    # freed memory kept. RETAIN_FREED_MEMORY=0 turns it off.
    from runtime.memory import retain_freed_memory

    retain_freed_memory()
    sys.exit(_cli())
