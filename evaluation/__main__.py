"""``python -m evaluation <command>``: evaluation CLIs (argument parsing only).

Commands:
  pose     pose accuracy of a COLMAP model against reference cameras -> pose.json
  images   image metrics of renders against ground truth -> metrics.json
           (from :mod:`evaluation.metrics.images_cli`, imported only when used)
  floor    the flat image of the training views' mean colour scored like a render -> floor.json
           (from :mod:`evaluation.metrics.floor_cli`, imported only when used)
  align    Sim(3) on training cameras; reference test cameras in the model frame
  tables   results tree -> runs.parquet + tables.md
  plots    training curves and the error / run-time Pareto plot (PNG)
  report   one static HTML report with tables, plots and render grids
  floaters floater measure of Gaussian models against a synthetic scene's surface
  study    the initialisation study's report (docs/reference.md section 6)
"""

from __future__ import annotations

import argparse
import logging
import sys

from runtime.checks import flag
from runtime.cliargs import add_log_flags, plain
from runtime.logs import setup_logging

log = logging.getLogger("evaluation")


def _gate(args):
    from evaluation.metrics.pose import gate_from_args

    return gate_from_args(args)


def _add_gate_args(p: argparse.ArgumentParser) -> None:
    from evaluation.metrics.pose import add_gate_args

    add_gate_args(p)


def _cmd_pose(args) -> int:
    from evaluation.metrics.pose import run_pose

    run_pose(args.pred, args.ref, args.out, args.names, args.n, _gate(args), args.orientations)
    return 0


def _cmd_align(args) -> int:
    from evaluation.metrics.align_run import run_align

    run_align(args.pred, args.ref, args.train_names, args.test_names, args.out, n=args.n,
              images_dir=args.images, image_scale=args.image_scale,
              use_orientations=args.orientations, collinear_tol=args.collinear_tol,
              train_cameras=args.train_cameras)
    return 0


def _cmd_tables(args) -> int:
    from evaluation.reports.tables import run_tables

    run_tables(args.results, args.out, _gate(args))
    return 0


def _cmd_plots(args) -> int:
    from evaluation.reports.plots import run_plots

    run_plots(args.results, args.out)
    return 0


def _cmd_report(args) -> int:
    from evaluation.reports.report import run_report

    run_report(args.results, args.out, scenes_dir=args.scenes, gate=_gate(args), max_views=args.max_views)
    return 0


def _cmd_floaters(args) -> int:
    from evaluation.metrics.floaters import run_floaters

    models = {}
    for item in args.model:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"--model takes NAME=PLY, got {item!r}")
        models[name] = path
    run_floaters(models, args.align, args.scene, args.out, args.tau_rel)
    return 0


def _cmd_study(args) -> int:
    import json
    from pathlib import Path

    from runtime.atomic import write_json
    from evaluation.study.report import run_study

    cells = {}
    if args.cells:
        text = args.cells if args.cells.lstrip().startswith("{") else Path(args.cells).read_text()
        try:
            cells = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--cells {args.cells[:60]!r} is not JSON ({exc}): give the grid as JSON text "
                             "or a JSON file (evaluation.study.grid)") from None
    if args.write_cells:
        write_json(args.write_cells, cells)
    run_study(args.results, args.out, cells, references=args.reference, seeds=args.seeds, views=args.views)
    return 0


# The output rule (runtime.outdir) of each command: its input options, whether --out is a folder,
# the inputs whose tree may hold --out (results-tree readers), and whether the command
# replaces its --out folder whole.
_OUTPUTS: dict[str, tuple[tuple[str, ...], bool, tuple[str, ...], bool]] = {
    "pose": (("pred", "ref", "names"), False, (), False),
    "images": (("pred", "gt", "alpha_dir", "lpips_weights"), False, (), False),
    "floor": (("images", "train_names", "gt", "lpips_weights"), False, (), False),
    "align": (("pred", "ref", "train_names", "test_names", "images"), True, (), False),
    "tables": (("results",), True, ("--results",), False),
    "plots": (("results",), True, ("--results",), False),
    "report": (("results", "scenes"), True, ("--results", "--scenes"), True),
    "floaters": (("model", "align", "scene"), False, (), False),
    "study": (("results", "cells"), True, ("--results",), True),
}


# Commands that summarise a results tree: a tree with nothing in it is refused
# (after --out's own checks, before anything is written there).
_READS_RUNS = ("tables", "plots", "report")


def _require_runs(results: str) -> None:
    """Refuse a results folder that holds no run and no skipped initialiser: a wrong path (or a
    workflow that has not run) would otherwise give empty tables and exit 0."""
    from evaluation.reports.results import find_runs
    from evaluation.reports.run_status import read_skipped

    if not find_runs(results, warn=False) and not read_skipped(results):  # the command warns, once
        raise ValueError(f"--results {results}: no run found (expected {{dataset}}/{{scene}}/n{{n}}/{{initialiser}}/ "
                         "folders with result files, as the workflow writes them): nothing to summarise")


def _prepare_out(args) -> None:
    """Apply camio's output rule to ``args.out`` of the command (:data:`_OUTPUTS`)."""
    from runtime.outdir import prepare_out

    spec = _OUTPUTS.get(args.command)
    if spec is None or getattr(args, "out", None) is None:
        return
    names, folder, hold, replaces = spec
    inputs = {}
    for name in names:
        val = getattr(args, name, None)
        if name == "model" and val:
            val = [item.partition("=")[2] for item in val]
        if name == "cells" and val and str(val).lstrip().startswith("{"):
            val = None  # JSON text, not a file
        inputs["--" + name.replace("_", "-")] = val
    prepare_out(args.out, inputs, f"evaluation {args.command}", folder=folder, may_hold_out=hold,
                replaces=replaces)


def _seal_out(args) -> None:
    """Record what a command that replaces its folder whole wrote (runtime.outdir.seal_out)."""
    from runtime.outdir import seal_out

    spec = _OUTPUTS.get(args.command)
    if spec is not None and spec[3]:
        seal_out(args.out, f"evaluation {args.command}")


def _missing(command: str, exc: Exception):
    def run(args) -> int:
        log.error("the '%s' command is not available: importing evaluation.metrics.%s_cli failed "
                  "(%s). Check that the evaluation package is complete and installed (pip install -e .).",
                  command, command, exc)
        return 2
    return run


# Commands registered from evaluation.metrics.<command>_cli (torch: imported only when used).
_LAZY = {
    "images": "image metrics of renders against ground truth -> metrics.json",
    "floor": "the flat image of the training views' mean colour scored like a render -> floor.json",
}


def _add_lazy(sub, command: str, wanted: bool) -> None:
    """Register ``command`` from evaluation.metrics.<command>_cli (only imported when it is the command)."""
    if wanted:
        import importlib

        try:
            module = importlib.import_module(f"evaluation.metrics.{command}_cli")
        except ImportError as exc:
            # prefix "+" so that the real command's --options land in ``rest`` unparsed
            p = sub.add_parser(command, help=f"{command} (unavailable)", prefix_chars="+")
            p.add_argument("rest", nargs=argparse.REMAINDER)
            p.set_defaults(func=_missing(command, exc))
            return
        add_log_flags(module.add_parser(sub), subcommand=True)
        return
    sub.add_parser(command, help=_LAZY[command], add_help=False)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    from evaluation.metrics.align import COLLINEAR_TOL
    from evaluation.reports.thumbs import MAX_VIEWS

    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m evaluation", description=plain(__doc__),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_log_flags(parser)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("pose", help="pose accuracy against reference cameras -> pose.json")
    p.add_argument("--pred", required=True, help="the initialiser's COLMAP model folder")
    p.add_argument("--ref", required=True, help="the reference COLMAP model folder")
    p.add_argument("--out", required=True, help="pose.json to write")
    p.add_argument("--names", help="restrict to these names (text file, JSON list or split.json)")
    p.add_argument("--n", type=flag(int, 1), help="training-view count, to pick from a split.json")
    p.add_argument("--orientations", choices=["auto", "always", "never"], default="auto",
                   help="use camera orientations in the Sim(3) fit (auto: when centres are collinear)")
    _add_gate_args(p)
    add_log_flags(p, subcommand=True)
    p.set_defaults(func=_cmd_pose)

    command = next((a for a in argv if not a.startswith("-")), None)
    for name in _LAZY:
        _add_lazy(sub, name, wanted=command == name)

    p = sub.add_parser("align", help="Sim(3) on training cameras; test cameras in the model frame")
    p.add_argument("--pred", required=True, help="the model's COLMAP cameras (its frame)")
    p.add_argument("--ref", required=True, help="the reference COLMAP model")
    p.add_argument("--train-names", required=True, help="text file, JSON list or split.json")
    p.add_argument("--test-names", help="text file, JSON list or split.json (default: --train-names' test list)")
    p.add_argument("--n", type=flag(int, 1), help="training-view count, to pick from a split.json")
    p.add_argument("--images", help="folder of the test images (their size sets the cameras' size)")
    p.add_argument("--image-scale", type=flag(float, 0, lo_open=True),
                   help="scale of the test images relative to the reference")
    p.add_argument("--orientations", choices=["auto", "always", "never"], default="auto",
                   help="use camera orientations in the Sim(3) fit (auto: when centres are collinear)")
    p.add_argument("--collinear-tol", type=flag(float, 0, 1), default=COLLINEAR_TOL,
                   help="sigma2/sigma1 of the centres below which they count as collinear (default %(default)s)")
    p.add_argument("--train-cameras", choices=["initialiser", "refined"], default="initialiser",
                   help="what --pred holds (recorded in align.json): the initialiser's cameras, or the "
                        "training cameras refined during training (splat_train --pose-refine)")
    p.add_argument("--out", required=True, help="output folder (align.json, sparse/0)")
    add_log_flags(p, subcommand=True)
    p.set_defaults(func=_cmd_align)

    p = sub.add_parser("tables", help="results tree -> runs.parquet + tables.md")
    p.add_argument("--results", required=True, help="the results tree (results/)")
    p.add_argument("--out", required=True, help="folder to write (runs.parquet, tables.md)")
    _add_gate_args(p)
    add_log_flags(p, subcommand=True)
    p.set_defaults(func=_cmd_tables)

    p = sub.add_parser("plots", help="training curves and the Pareto plot (PNG)")
    p.add_argument("--results", required=True, help="the results tree (results/)")
    p.add_argument("--out", required=True, help="folder to write (PNG plots)")
    add_log_flags(p, subcommand=True)
    p.set_defaults(func=_cmd_plots)

    p = sub.add_parser("report", help="static HTML report")
    p.add_argument("--results", required=True, help="the results tree (results/)")
    p.add_argument("--out", required=True, help="folder to write (index.html and its images)")
    p.add_argument("--scenes", help="prepared scenes root, for ground-truth images "
                   "({scenes}/{dataset}/{scene}/images or {scenes}/{scene}/images)")
    p.add_argument("--max-views", type=flag(int, 1), default=MAX_VIEWS,
                   help="test views per render grid (default %(default)s)")
    _add_gate_args(p)
    add_log_flags(p, subcommand=True)
    p.set_defaults(func=_cmd_report)

    p = sub.add_parser("floaters", help="floater measure against a synthetic scene's surface")
    p.add_argument("--model", nargs="+", required=True, help="NAME=PLY (e.g. seed=... final=...)")
    p.add_argument("--align", required=True, help="align.json of the run (model frame -> reference)")
    p.add_argument("--scene", required=True, help="prepared synthetic scene (synthetic.json, sparse/0)")
    p.add_argument("--tau-rel", type=flag(float, 0, lo_open=True), default=None,
                   help="threshold as a fraction of the reference trajectory radius "
                   "(default: evaluation.metrics.floaters.TAU_REL)")
    p.add_argument("--out", required=True, help="floaters.json to write")
    add_log_flags(p, subcommand=True)
    p.set_defaults(func=_cmd_floaters)

    p = sub.add_parser("study", help="the initialisation study's report (docs/reference.md section 6)")
    p.add_argument("--results", required=True, help="the study tree (R/study)")
    p.add_argument("--out", required=True, help="report folder (study.md, plots/, index.html)")
    p.add_argument("--cells", help="the expanded grid: JSON text or a file (evaluation.study.grid)")
    p.add_argument("--reference", action="append", default=[],
                   help="a regular run folder R/{dataset}/{scene}/n{n}/{init} (e.g. COLMAP) to report as a "
                        "reference row beside the cells (repeatable; a failed run is a reported row)")
    p.add_argument("--write-cells", help="also write the grid to this JSON file")
    p.add_argument("--seeds", type=flag(int, 0), nargs="+",
                   help="report only these seeds (default: every seed found); with --cells and --views, "
                        "runs of an earlier grid in the same tree are left out (logged)")
    p.add_argument("--views", type=flag(int, 1), nargs="+",
                   help="report only these view counts n (default: every n found)")
    add_log_flags(p, subcommand=True)
    p.set_defaults(func=_cmd_study)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(argv).parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    func = getattr(args, "func", None)
    if func is None:
        log.error("evaluation.metrics.%s_cli.add_parser did not set a handler (set_defaults(func=...))", args.command)
        return 2
    from runtime.outdir import run_stage

    def work() -> int:
        _prepare_out(args)
        if args.command in _READS_RUNS:
            _require_runs(args.results)
        rc = int(func(args) or 0)
        if rc == 0:
            _seal_out(args)
        return rc

    # bad inputs: a clear message, no traceback (-v shows it)
    return run_stage(log, work, errors=(ValueError, KeyError, OSError),
                     line=lambda exc: f"{args.command} failed: {exc}", traceback=True)


if __name__ == "__main__":
    sys.exit(main())
