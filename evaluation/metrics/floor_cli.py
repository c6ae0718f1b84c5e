"""``floor`` subcommand: the flat image of the training views' mean colour, scored like a render.

Usage (through the evaluation dispatcher)::

    python -m evaluation floor --images SCENE_IMAGES --train-names n3/train.txt --gt TEST_IMAGES \\
        [--lpips-nets alex vgg] [--lpips-weights DIR] --out floor.json

A model that learnt nothing but the mean colour of its training views scores this on the
held-out views; a figure means something only above it. The colour is
:func:`imgmetrics.floor.flat_colour` of the training images (``--images``/name, read as 8-bit);
each ground-truth image of ``--gt`` is scored against the flat image of its own size
(:func:`imgmetrics.floor.flat_image`, 8-bit as a PNG render is) by the scoring of
``evaluation images`` (:func:`evaluation.metrics.images_cli.score_pair`: PSNR float64 capped at
:data:`imgmetrics.psnr_ssim.PSNR_CAP_DB`, SSIM float64, LPIPS float32, a net not asked for or
without weights null).

Output (``floor.json``, written atomically; docs/contracts.md)::

    {"colour": [R, G, B], "psnr": mean, "ssim": mean, "lpips_alex": mean | null, "lpips_vgg": mean | null,
     "n_images": N,
     "per_image": [{"name": gt file name, "psnr": .., "ssim": .., "lpips_alex": .. | null,
                    "lpips_vgg": .. | null}, ...],
     "train_names": [sorted], "psnr_cap_db": 100.0, "psnr_capped": [...],
     "lpips_weights": {"alex": path | null, "vgg": path | null},
     "images_dir": .., "gt_dir": .., "wall_time_s": ..}

Refused (exit 2, one line, nothing written): a missing folder, a training list that is missing
or empty or names an image the ``--images`` folder does not hold, a ``--gt`` folder without
images, an unreadable image.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import Sequence

from camio.images import from_uint8, list_images, read_image, read_image_uint8
from evaluation.metrics.align_run import load_names
from evaluation.metrics.images_cli import add_lpips_args, load_models, mean_or_none, means_line, score_pair
from imgmetrics.floor import flat_colour, flat_image
from imgmetrics.lpips import NETS
from imgmetrics.psnr_ssim import PSNR_CAP_DB
from runtime.atomic import write_json
from runtime.checks import check_folder
from runtime.cliargs import plain
from runtime.logs import timed
from runtime.names import check_name_list

__all__ = ["evaluate_floor", "add_parser"]

log = logging.getLogger(__name__)


def _training_views(images_dir: Path, names: list[str]):
    """The training images, 8-bit, one at a time (refuses a name the folder does not hold)."""
    missing = [n for n in names if not (images_dir / n).is_file()]
    if missing:
        raise ValueError(f"{len(missing)} training name(s) not in the images folder {images_dir}: {missing[:10]}; "
                         "give the scene's images folder and its own train.txt")
    for n in names:
        yield read_image_uint8(images_dir / n)


def evaluate_floor(images_dir: str | Path, train_names: str | Path, gt_dir: str | Path,
                   out_json: str | Path | None, lpips_nets: Sequence[str] = NETS,
                   lpips_weights: str | Path | None = None, device: str = "cpu") -> dict:
    """Score the floor's flat image against every image of ``gt_dir``; write ``out_json`` (if given).

    Args:
        images_dir: the scene's images (the training names are looked up here).
        train_names: text file, one training image name per line (``n{n}/train.txt``; '#'
            comments), or a JSON list of names (:func:`evaluation.metrics.align_run.load_names`).
        gt_dir: the held-out ground-truth images.
        out_json: output path (atomic write), or None to only return the record.
        lpips_nets, lpips_weights, device: as for ``evaluation images``.

    Returns:
        The record (see module docstring).
    """
    t0 = time.perf_counter()
    images_dir, gt_dir = Path(images_dir), Path(gt_dir)
    check_folder(images_dir, "--images folder")
    check_folder(gt_dir, "--gt folder")
    names = check_name_list(load_names(train_names), train_names)
    gt_names = list_images(gt_dir)
    if not gt_names:
        raise ValueError(f"no images (.png/.jpg/.tif/.exr) in the ground-truth folder {gt_dir}")
    colour = flat_colour(_training_views(images_dir, names))
    log.info("floor colour %s: mean of %d training view(s) of %s", colour.tolist(), len(names), images_dir)
    models, weights_used = load_models(lpips_nets, lpips_weights, device)
    per_image, capped = [], []
    for gt_name in gt_names:
        gt = read_image(gt_dir / gt_name)
        flat = from_uint8(flat_image(colour, gt.shape[0], gt.shape[1]))
        raw_psnr, scores = score_pair(flat, gt, models)
        if raw_psnr >= PSNR_CAP_DB:
            capped.append(gt_name)
        per_image.append({"name": gt_name, **scores})
    result = {
        "colour": [int(c) for c in colour],
        **{k: mean_or_none([r[k] for r in per_image]) for k in ("psnr", "ssim", "lpips_alex", "lpips_vgg")},
        "n_images": len(per_image),
        "per_image": per_image,
        "train_names": names,
        "psnr_cap_db": PSNR_CAP_DB,
        "psnr_capped": capped,
        "lpips_weights": weights_used,
        "images_dir": str(images_dir),
        "gt_dir": str(gt_dir),
        "wall_time_s": time.perf_counter() - t0,
    }
    log.info("%s", means_line("floor over", result))
    if out_json is not None:
        write_json(out_json, result)
        log.info("wrote %s", out_json)
    return result


def _run(args: argparse.Namespace) -> int:
    with timed("floor", log):
        evaluate_floor(args.images, args.train_names, args.gt, args.out, tuple(args.lpips_nets),
                       args.lpips_weights, args.device)
    return 0


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``floor`` on an ``argparse`` subparsers object; sets ``func`` (args -> exit code)."""
    p = subparsers.add_parser("floor", help="the flat mean-colour image scored like a render -> floor.json",
                              description=plain(__doc__.split("\n\n")[0]))
    p.add_argument("--images", type=Path, required=True, help="the scene's images folder")
    p.add_argument("--train-names", type=Path, required=True, help="training names, one per line (n{n}/train.txt)")
    p.add_argument("--gt", type=Path, required=True, help="folder of the held-out ground-truth images")
    p.add_argument("--out", type=Path, required=True, help="floor.json to write")
    add_lpips_args(p)
    p.set_defaults(func=_run)
    return p
