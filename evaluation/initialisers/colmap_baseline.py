"""CLI of the train-only COLMAP baseline: ``python -m evaluation.initialisers.colmap_baseline``.

The reconstruction itself is :func:`evaluation.initialisers.colmap_run.run_colmap` (settings, success,
reproducibility and outputs are described there), repeated seeded runs are
:mod:`evaluation.initialisers.colmap_repeats`; this module only parses the command line and calls one or
the other, so the two import this one never and each other one way. A run that leaves fewer
than ``--fallback-min-points`` points but registered cameras gets random points for those
cameras, recorded in status.json (:func:`evaluation.initialisers.random_init.apply_fallback`); its success
stays the reconstruction's.
"""

from __future__ import annotations

import argparse
import logging

from camio.images import ImageReadError
from runtime.outdir import prepare_out, run_stage, seal_out, typed_line
from evaluation.initialisers import colmap_repeats
from evaluation.initialisers.colmap_run import DEFAULT_THREADS, ColmapSettings, available_cores, model_fingerprint, run_colmap
from evaluation.metrics.pose import add_gate_args, gate_from_args
from evaluation.initialisers.random_init import add_fallback_args, apply_fallback
from evaluation.initialisers.views import add_view_args, parse_training_args
from runtime.checks import flag
from runtime.cliargs import add_log_flags

__all__ = ["main", "ColmapSettings", "available_cores", "model_fingerprint", "run_colmap"]

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> int:
    """CLI: ``python -m evaluation.initialisers.colmap_baseline --images DIR (--split JSON --n N |
    --image-list FILE | --names ...) --out DIR [--seed S | --repeats K --seeds ...]``."""
    p = argparse.ArgumentParser(prog="python -m evaluation.initialisers.colmap_baseline",
                                description="The train-only COLMAP baseline, seeded and repeatable.")
    p.add_argument("--images", required=True, help="scene image folder")
    add_view_args(p)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=flag(int, 0), default=0, help="PRNG seed (default %(default)s)")
    p.add_argument("--repeats", type=flag(int, 1), default=1,
                   help="run K times with seeds seed, seed+1, ... (or --seeds) and report the spread")
    p.add_argument("--seeds", type=flag(int, 0), nargs="+", help="explicit seeds for the repeats")
    p.add_argument("--ref", help="reference COLMAP model: evaluate every run's poses "
                   "(ATE, rotation error, both success criteria) and report their spread; "
                   "written as a repeats summary, also for a single run")
    add_gate_args(p, "accuracy gate for --ref")
    defaults = ColmapSettings()
    p.add_argument("--max-image-size", type=flag(int, 16), default=defaults.max_image_size,
                   help="SIFT extraction: longest image side in pixels (default %(default)s)")
    p.add_argument("--max-num-features", type=flag(int, 16), default=defaults.max_num_features,
                   help="SIFT features per image at most (default %(default)s)")
    p.add_argument("--no-guided-matching", action="store_true", help="turn off COLMAP's guided matching")
    p.add_argument("--threads", type=flag(int, 0), default=DEFAULT_THREADS,
                   help=f"threads per COLMAP stage (default {DEFAULT_THREADS}: the same model every run; 0 = every "
                        "available core, faster, the model may differ between runs)")
    p.add_argument("--keep-work", action="store_true", help="keep the database and image links")
    add_fallback_args(p)
    add_log_flags(p)
    args, names = parse_training_args(p, argv)
    settings = ColmapSettings(args.max_image_size, args.max_num_features,
                              not args.no_guided_matching, "PINHOLE", args.threads)
    seeds = args.seeds or [args.seed + i for i in range(max(1, args.repeats))]
    if args.seeds and args.repeats not in (1, len(args.seeds)):
        p.error(f"--repeats {args.repeats} disagrees with {len(args.seeds)} --seeds")

    def work() -> None:
        # the stage's name in its .stage marker stays the flat layout's (reruns into older folders)
        # fresh: a rerun with fewer --repeats never leaves the earlier run's extra seeds behind
        prepare_out(args.out, {"--images": args.images, "--split": args.split, "--image-list": args.image_list,
                               "--ref": args.ref}, "evaluation.colmap_baseline", fresh=True)
        _run_cli(args, names, seeds, settings)
        apply_fallback(args.out, args.fallback_min_points, args.fallback_points, seeds[0])
        seal_out(args.out, "evaluation.colmap_baseline")

    return run_stage(log, work, errors=(ImageReadError, FileNotFoundError, ValueError), line=typed_line)


def _run_cli(args, names: list[str], seeds: list[int], settings: ColmapSettings) -> None:
    if len(seeds) == 1 and not args.ref:
        run_colmap(args.images, names, args.out, seed=seeds[0], settings=settings,
                   keep_work=args.keep_work)
    else:
        gate = None
        if args.ref:
            gate = gate_from_args(args)
        colmap_repeats.run_colmap_repeats(args.images, names, args.out, seeds, settings=settings,
                           ref=args.ref, gate=gate)


if __name__ == "__main__":
    raise SystemExit(main())
