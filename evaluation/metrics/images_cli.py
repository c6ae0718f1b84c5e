"""``images`` subcommand: PSNR, SSIM and LPIPS of rendered test views against ground truth.

Usage (through the evaluation dispatcher, or standalone)::

    python -m evaluation images --pred RENDERS --gt GT_IMAGES --out metrics.json [--alpha-dir RENDERS/alpha]
    python -m evaluation.metrics.images_cli --pred RENDERS --gt GT_IMAGES --out metrics.json [--lpips-nets alex]

Matching: files are paired by *stem* (name without extension, case-sensitive), so a render
``DSC01.png`` pairs with ``DSC01.JPG``: renders are usually PNG while ground truth keeps its
original format. Every image in either folder must have a partner; otherwise the error lists
the unmatched names (pass folders holding only the test views). Two files with one stem in a
folder are an error. Pairs must have the same width and height (no implicit resizing).

Output (``metrics.json``, written atomically; docs/contracts.md)::

    {"psnr": mean, "ssim": mean, "lpips_alex": mean | null, "lpips_vgg": mean | null,
     "n_images": N,
     "per_image": [{"name": gt file name, "pred": render file name,
                    "psnr": .., "ssim": .., "lpips_alex": .. | null, "lpips_vgg": .. | null}, ...],
     "psnr_cap_db": 100.0, "psnr_capped": [names whose PSNR was >= the cap (identical: inf)],
     "lpips_weights": {"alex": path | null, "vgg": path | null},
     "pred_dir": .., "gt_dir": .., "wall_time_s": ..,
     "alpha_dir": path | null, "covered_alpha": 0.5 | null, "coverage": mean | null,
     "covered": {"psnr": .., "ssim": .., "lpips_alex": .. | null, "lpips_vgg": .. | null} | null}

With ``--alpha-dir DIR`` (the renders' accumulated opacity, ``DIR/<render stem>.png``, which
``python -m splat_train render`` writes to ``RENDERS/alpha/``; :mod:`camio.alpha`) each
``per_image`` record also holds ``coverage`` (the share of its pixels with opacity >=
``covered_alpha``) and ``covered``: PSNR (capped), SSIM and LPIPS over those pixels alone
(:mod:`imgmetrics.covered`; each null where the image has no covered pixel). The top-level
``coverage`` is the mean over the images, ``covered`` the means over the images with a covered
pixel (a measure null where none has one). Without ``--alpha-dir`` these keys are null. A render
without its alpha image, or one of another size, is refused (exit 2) naming the file.

PSNR is computed in float64 and capped at :data:`imgmetrics.psnr_ssim.PSNR_CAP_DB` (identical
images have PSNR = inf; JSON has no inf, and a mean of inf says nothing), SSIM in float64,
LPIPS in float32 (agrees with float64 to ~1e-7 on the reference images). An LPIPS backbone
whose weights are absent, or that was not requested, is null (missing), never zero.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import Sequence

import torch

from runtime.atomic import write_json
from camio.alpha import read_alpha
from camio.images import list_images, read_image
from imgmetrics.covered import COVERED_ALPHA, coverage, covered_mask, lpips_covered, psnr_covered, ssim_covered
from imgmetrics.lpips import NETS, canonical_net, find_weights, load_lpips, lpips_distance
from imgmetrics.psnr_ssim import PSNR_CAP_DB, capped_psnr, psnr, ssim
from runtime.cliargs import add_log_flags, plain
from runtime.logs import progress, setup_logging, timed

__all__ = ["match_images", "load_models", "score_pair", "evaluate_images", "add_lpips_args", "add_parser", "main"]

log = logging.getLogger(__name__)


def _by_stem(folder: Path) -> dict[str, str]:
    names = list_images(folder)
    out: dict[str, str] = {}
    for n in names:
        stem = Path(n).stem
        if stem in out:
            raise ValueError(f"{folder} holds two images with the stem {stem!r} ({out[stem]}, {n}); "
                             "images are matched by name without extension, keep one")
        out[stem] = n
    return out


def match_images(pred_dir: str | Path, gt_dir: str | Path) -> list[tuple[str, str]]:
    """Pair render and ground-truth files by stem, sorted by stem.

    Returns:
        [(pred_name, gt_name)], file names relative to their folders.

    Raises:
        FileNotFoundError: a folder is missing. ValueError: no images, duplicate stems, or
        unmatched names (all of them are listed).
    """
    pred, gt = _by_stem(Path(pred_dir)), _by_stem(Path(gt_dir))
    for what, folder, found in (("render", pred_dir, pred), ("ground-truth", gt_dir, gt)):
        if not found:
            raise ValueError(f"no images (.png/.jpg/.tif/.exr) in the {what} folder {folder}")
    only_pred = sorted(pred[s] for s in set(pred) - set(gt))
    only_gt = sorted(gt[s] for s in set(gt) - set(pred))
    if only_pred or only_gt:
        raise ValueError(f"renders and ground truth do not match by name (stem): "
                         f"{len(only_pred)} only in {pred_dir}: {only_pred[:20]}; "
                         f"{len(only_gt)} only in {gt_dir}: {only_gt[:20]}. "
                         "Pass folders that hold exactly the same (test) views")
    return [(pred[s], gt[s]) for s in sorted(gt)]


def mean_or_none(values: list[float | None]) -> float | None:
    """The mean of ``values``; None where there are none or one is None (a figure not scored)."""
    if not values or any(v is None for v in values):
        return None
    return float(sum(values) / len(values))


def load_models(lpips_nets: Sequence[str] = NETS, lpips_weights: str | Path | None = None,
                device: str | torch.device = "cpu") -> tuple[dict, dict]:
    """The LPIPS models asked for: ({net: model | None}, {net: weights path | None}) over
    :data:`imgmetrics.lpips.NETS` (None: not asked for)."""
    wanted = {canonical_net(n) for n in lpips_nets}
    models = {}
    weights_used: dict[str, str | None] = {}
    for net in NETS:
        models[net] = load_lpips(net, lpips_weights, device) if net in wanted else None
        weights_used[net] = str(find_weights(net, lpips_weights)) if models[net] is not None else None
    return models, weights_used


def score_pair(pred, gt, models: dict) -> tuple[float, dict]:
    """One image pair scored: PSNR and SSIM in float64, LPIPS in float32 (each net of
    ``models``, :func:`load_models`; null where None).

    Args:
        pred, gt: float32 RGB ``[H, W, 3]`` in [0, 1], same shape (:func:`camio.images.read_image`).

    Returns:
        (the uncapped PSNR, {"psnr": capped PSNR, "ssim", "lpips_alex", "lpips_vgg"}).
    """
    p64, g64 = torch.from_numpy(pred).double(), torch.from_numpy(gt).double()
    p64, g64 = p64.permute(2, 0, 1), g64.permute(2, 0, 1)
    raw_psnr = float(psnr(p64, g64)[0])
    rec = {"psnr": capped_psnr(raw_psnr), "ssim": float(ssim(p64, g64)[0])}
    for net in NETS:
        m = models[net]
        rec[f"lpips_{net}"] = float(lpips_distance(m, pred, gt)[0]) if m is not None else None
    return raw_psnr, rec


def _alpha_files(alpha_dir: Path, pairs: list[tuple[str, str]]) -> list[Path]:
    """The alpha image of every render (``alpha_dir/<render stem>.png``), all checked to exist
    before anything is scored; FileNotFoundError naming the first missing one otherwise."""
    if not alpha_dir.is_dir():
        raise FileNotFoundError(f"--alpha-dir folder {alpha_dir} does not exist; `python -m splat_train render --alpha` "
                                "writes RENDERS/alpha/, or leave out --alpha-dir")
    files = [alpha_dir / f"{Path(pred).stem}.png" for pred, _ in pairs]
    for f, (pred, _) in zip(files, pairs):
        if not f.is_file():
            raise FileNotFoundError(f"alpha image {f} of the render {pred} is missing; render again with "
                                    "`python -m splat_train render --alpha` (it writes alpha/), or leave out --alpha-dir")
    return files


def _covered(pred, gt, alpha_file: Path, models: dict) -> tuple[float, dict]:
    """(coverage, {psnr, ssim, lpips_alex, lpips_vgg} over the covered pixels) of one pair:
    ``pred``, ``gt`` float32 [H, W, 3]; a figure is None where no pixel is covered."""
    alpha = read_alpha(alpha_file)
    if alpha.shape != pred.shape[:2]:
        raise ValueError(f"size mismatch: alpha image {alpha_file} is {alpha.shape[1]}x{alpha.shape[0]}, its render "
                         f"{pred.shape[1]}x{pred.shape[0]} (width x height); use the alpha written with the render")
    mask = covered_mask(alpha)
    p64, g64 = pred.astype("float64"), gt.astype("float64")

    def value(v: float) -> float | None:
        return None if v != v else v  # NaN: nothing covered

    raw = value(psnr_covered(p64, g64, mask))
    out = {"psnr": None if raw is None else capped_psnr(raw), "ssim": value(ssim_covered(p64, g64, mask))}
    for net in NETS:
        m = models[net]
        out[f"lpips_{net}"] = value(lpips_covered(m, pred, gt, mask)) if m is not None else None
    return coverage(alpha), out


def _covered_means(per_image: list[dict]) -> dict:
    """Mean of each covered figure over the images that have it (None where none has)."""
    keys = ("psnr", "ssim", *(f"lpips_{net}" for net in NETS))
    vals = {k: [r["covered"][k] for r in per_image if r["covered"][k] is not None] for k in keys}
    return {k: (float(sum(v) / len(v)) if v else None) for k, v in vals.items()}


def means_line(what: str, result: dict) -> str:
    """The log line of a scored folder's means: ``what`` then the image count, PSNR, SSIM, both
    LPIPS ("missing" where null) and the time (``result``: a metrics.json or floor.json record)."""
    lp = {n: "missing" if result[f"lpips_{n}"] is None else f"{result[f'lpips_{n}']:.4f}" for n in NETS}
    return (f"{what} {result['n_images']} image(s): PSNR {result['psnr']:.3f} dB, SSIM {result['ssim']:.4f}, "
            + ", ".join(f"LPIPS-{n} {v}" for n, v in lp.items()) + f" ({result['wall_time_s']:.2f} s)")


def evaluate_images(pred_dir: str | Path, gt_dir: str | Path, out_json: str | Path | None,
                    lpips_nets: Sequence[str] = NETS, lpips_weights: str | Path | None = None,
                    device: str | torch.device = "cpu", alpha_dir: str | Path | None = None) -> dict:
    """Compute per-image and mean PSNR / SSIM / LPIPS and write ``out_json`` (if given).

    Args:
        pred_dir: folder of rendered images; gt_dir: folder of ground-truth images (matched
            by stem, see module docstring). Images are read as float32 RGB [H, W, 3] in [0, 1]
            by :func:`camio.images.read_image`.
        out_json: output path (atomic write), or None to only return the record.
        lpips_nets: LPIPS backbones among :data:`imgmetrics.lpips.NETS` (default all); others are reported null.
        lpips_weights: folder with ``{net}.safetensors`` (default: LPIPS_WEIGHTS_DIR, then
            the user cache; see :mod:`imgmetrics.lpips`).
        device: torch device for LPIPS.
        alpha_dir: folder of the renders' accumulated opacity (``<render stem>.png``,
            :mod:`camio.alpha`): adds coverage and the covered figures; None: those are null.

    Returns:
        The record written to ``out_json`` (see module docstring).
    """
    t0 = time.perf_counter()
    pred_dir, gt_dir = Path(pred_dir), Path(gt_dir)
    pairs = match_images(pred_dir, gt_dir)
    alpha_files = _alpha_files(Path(alpha_dir), pairs) if alpha_dir is not None else [None] * len(pairs)
    models, weights_used = load_models(lpips_nets, lpips_weights, device)
    log.info("evaluating %d image pairs (%s vs %s); LPIPS: %s", len(pairs), pred_dir, gt_dir,
             ", ".join(n for n in NETS if models[n] is not None) or "none")

    per_image: list[dict] = []
    capped: list[str] = []
    for (pred_name, gt_name), alpha_file in progress(zip(pairs, alpha_files), total=len(pairs), desc="image metrics"):
        pred = read_image(pred_dir / pred_name)
        gt = read_image(gt_dir / gt_name)
        if pred.shape != gt.shape:
            raise ValueError(f"size mismatch for {gt_name}: render {pred_dir / pred_name} is "
                             f"{pred.shape[1]}x{pred.shape[0]}, ground truth {gt_dir / gt_name} is "
                             f"{gt.shape[1]}x{gt.shape[0]} (width x height); render at the ground-truth size")
        raw_psnr, scores = score_pair(pred, gt, models)
        if raw_psnr >= PSNR_CAP_DB:
            capped.append(gt_name)
        rec = {"name": gt_name, "pred": pred_name, **scores}
        rec["coverage"], rec["covered"] = _covered(pred, gt, alpha_file, models) if alpha_file else (None, None)
        per_image.append(rec)
        log.debug("%s: PSNR %.3f dB, SSIM %.4f", gt_name, rec["psnr"], rec["ssim"])

    if capped:
        log.warning("%d image(s) reached the PSNR cap of %.0f dB (identical or nearly): %s",
                    len(capped), PSNR_CAP_DB, capped[:10])
    result = {
        "psnr": mean_or_none([r["psnr"] for r in per_image]),
        "ssim": mean_or_none([r["ssim"] for r in per_image]),
        "lpips_alex": mean_or_none([r["lpips_alex"] for r in per_image]),
        "lpips_vgg": mean_or_none([r["lpips_vgg"] for r in per_image]),
        "n_images": len(per_image),
        "per_image": per_image,
        "psnr_cap_db": PSNR_CAP_DB,
        "psnr_capped": capped,
        "lpips_weights": weights_used,
        "pred_dir": str(pred_dir),
        "gt_dir": str(gt_dir),
        "alpha_dir": None if alpha_dir is None else str(alpha_dir),
        "covered_alpha": None if alpha_dir is None else COVERED_ALPHA,
        "coverage": None if alpha_dir is None else mean_or_none([r["coverage"] for r in per_image]),
        "covered": None if alpha_dir is None else _covered_means(per_image),
        "wall_time_s": time.perf_counter() - t0,
    }
    log.info("%s", means_line("mean over", result))
    if alpha_dir is not None:
        log.info("covered (opacity >= %g): %.1f %% of the pixels; there PSNR %s dB, SSIM %s", COVERED_ALPHA,
                 100 * result["coverage"], result["covered"]["psnr"], result["covered"]["ssim"])
    if out_json is not None:
        write_json(out_json, result)
        log.info("wrote %s", out_json)
    return result


def _configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pred", type=Path, required=True, help="folder of rendered test views")
    p.add_argument("--gt", type=Path, required=True, help="folder of ground-truth test views (same stems)")
    p.add_argument("--out", type=Path, required=True, help="metrics.json to write")
    p.add_argument("--alpha-dir", type=Path, default=None,
                   help="folder of the renders' accumulated opacity (RENDERS/alpha, written by `splat_train render --alpha`): "
                        "adds coverage and PSNR / SSIM / LPIPS over the covered pixels")
    add_lpips_args(p)


def add_lpips_args(p: argparse.ArgumentParser) -> None:
    """--lpips-nets, --lpips-weights and --device (of every command scored like renders)."""
    p.add_argument("--lpips-nets", nargs="*", default=list(NETS), choices=NETS,
                   help=f"LPIPS backbones (default: {' '.join(NETS)}; give none to skip LPIPS)")
    p.add_argument("--lpips-weights", type=Path, default=None,
                   help="folder with {alex,vgg}.safetensors (default: $LPIPS_WEIGHTS_DIR, then the user cache)")
    p.add_argument("--device", default="cpu", help="torch device for LPIPS (cpu, cuda, ...)")


def _run(args: argparse.Namespace) -> int:
    from camio.images import ImageReadError

    try:
        with timed("image metrics", log):
            evaluate_images(args.pred, args.gt, args.out, tuple(args.lpips_nets), args.lpips_weights,
                            args.device, alpha_dir=args.alpha_dir)
    except (ImageReadError, FileNotFoundError) as exc:  # bad input: one line naming the file
        log.error("%s: %s", type(exc).__name__, exc)
        return 2
    return 0


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``images`` on an ``argparse`` subparsers object; sets ``func`` (args -> exit code)."""
    p = subparsers.add_parser("images", help="PSNR / SSIM / LPIPS of renders vs ground truth",
                              description=plain(__doc__.split("\n\n")[0]))
    _configure(p)
    p.set_defaults(func=_run)
    return p


def main(argv: list[str] | None = None) -> int:
    """Standalone entry point (``python -m evaluation.metrics.images_cli``)."""
    p = argparse.ArgumentParser(prog="python -m evaluation.metrics.images_cli", description=plain(__doc__.split("\n\n")[0]))
    _configure(p)
    add_log_flags(p)
    args = p.parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    return _run(args)


if __name__ == "__main__":
    raise SystemExit(main())
