"""Small file chores of the workflow that belong to no stage.

    python workflow/scripts/views.py names --split split.json --n 6 --out train.txt
    python workflow/scripts/views.py link --split split.json --which test --images DIR --out DIR
    python workflow/scripts/views.py index --status a/status.json b/status.json --out index.json

``names`` writes one image name per line (the training list of n, or the test list);
``link`` fills a folder with links to (or copies of, where links fail) exactly those
images, so that image metrics compare renders with the held-out views only; ``index``
gathers COLMAP status files into one JSON (the workflow's colmap_index checkpoint).

Every command keeps the stages' output rule (runtime.outdir): ``--out`` is never an input,
inside one or holding one; a file ``--out`` replaces only a file this command wrote; ``link``
replaces only a folder it wrote itself (a user's folder is refused, never emptied); a name in
the split that is not a plain file name (``../x.png``) is refused. A bad input is one error
line and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import time
from pathlib import Path

from runtime.atomic import atomic_dir, atomic_path, write_json
from runtime.names import check_name
from runtime.outdir import prepare_out, run_stage, seal_out
from camio.split import read_split
from runtime.checks import flag
from runtime.logs import setup_logging

log = logging.getLogger("workflow.views")


def split_names(split_path: str | Path, which: str, n: int | None = None) -> list[str]:
    """The training names for n, or the test names, of a split.json."""
    split = read_split(split_path)
    if which == "test":
        names = list(split.test)
    else:
        if n is None:
            raise ValueError("the training list needs --n")
        if str(n) not in split.train:
            raise ValueError(f"{split_path} has no training list for n = {n} "
                             f"(it has {sorted(split.train, key=int)}); add n to the split")
        names = list(split.train[str(n)])
    for name in names:
        check_name(name, f"{which} image name", split_path)
    if len(set(names)) != len(names):
        dup = sorted({x for x in names if names.count(x) > 1})
        raise ValueError(f"{split_path}: the {which} list names {dup[0]!r} twice: fix the split")
    return names


def write_names(names: list[str], out: str | Path) -> None:
    with atomic_path(out) as tmp:
        tmp.write_text("".join(f"{n}\n" for n in names))


def link_images(names: list[str], images: str | Path, out: str | Path) -> None:
    """Fill ``out`` (replaced atomically) with links to ``images/<name>`` for each name (plain
    file names: :func:`split_names` checks them)."""
    images = Path(images)
    for n in names:
        check_name(n, "image name", images)
    missing = [n for n in names if not (images / n).is_file()]
    if missing:
        raise FileNotFoundError(f"images missing from {images}: {missing[:5]}")
    with atomic_dir(out) as tmp:
        for n in names:
            try:
                os.symlink((images / n).resolve(), tmp / n)
            except OSError:
                shutil.copy2(images / n, tmp / n)


def _read_status(path: str) -> dict:
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read the COLMAP status file {path}: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: a COLMAP status file holds a JSON object, not {type(data).__name__}")
    return data


def index_status(paths: list[str], out: str | Path) -> dict:
    """{path: status} of COLMAP runs, with a success count, written to ``out``."""
    runs = {p: _read_status(p) for p in paths}
    keys = ("success_paper", "aligned_ok", "registered", "n_images", "points", "reason", "num_threads")
    # success_paper (docs/contracts.md); files written before the rename call it "success"
    ok = {p: bool(s.get("success_paper", s.get("success", False))) for p, s in runs.items()}
    data = {
        "n_runs": len(runs),
        "n_success_paper": sum(ok.values()),
        "runs": {p: {**{k: s.get(k) for k in keys}, "success_paper": ok[p]} for p, s in runs.items()},
    }
    write_json(out, data)
    return data


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="workflow/scripts/views.py", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    a = sub.add_parser("names", help="write the training (or test) names, one per line")
    a.add_argument("--split", required=True)
    a.add_argument("--which", choices=["train", "test"], default="train")
    a.add_argument("--n", type=flag(int, 1))
    a.add_argument("--out", required=True)
    b = sub.add_parser("link", help="a folder of links to the test (or training) images")
    b.add_argument("--split", required=True)
    b.add_argument("--which", choices=["train", "test"], default="test")
    b.add_argument("--n", type=flag(int, 1))
    b.add_argument("--images", required=True)
    b.add_argument("--out", required=True)
    c = sub.add_parser("index", help="gather COLMAP status.json files into one JSON")
    c.add_argument("--status", nargs="*", default=[])
    c.add_argument("--out", required=True)
    d = sub.add_parser("notes", help="write the configured initialisers a scene cannot have")
    d.add_argument("--skipped", required=True, help="JSON list of {dataset, scene, init, reason}")
    d.add_argument("--out", required=True)
    args = p.parse_args(argv)
    setup_logging()
    t0 = time.perf_counter()
    stage = f"views {args.command}"

    def work() -> int:
        if args.command == "names":
            prepare_out(args.out, {"--split": args.split}, stage, folder=False)
            names = split_names(args.split, args.which, args.n)
            write_names(names, args.out)
            log.info("wrote %d %s names to %s", len(names), args.which, args.out)
        elif args.command == "link":
            prepare_out(args.out, {"--split": args.split, "--images": args.images}, stage, replaces=True)
            names = split_names(args.split, args.which, args.n)
            link_images(names, args.images, args.out)
            seal_out(args.out, stage)
            log.info("linked %d %s images into %s", len(names), args.which, args.out)
        elif args.command == "notes":
            skipped = _skipped(args.skipped)
            prepare_out(args.out, {}, stage, folder=False)
            write_json(args.out, {"skipped": skipped})
            log.info("%d configured initialiser(s) not applicable: %s", len(skipped),
                     "; ".join(f"{s['init']} on {s['dataset']}/{s['scene']} ({s['reason']})" for s in skipped) or "-")
        else:
            prepare_out(args.out, {"--status": args.status}, stage, folder=False)
            data = index_status(args.status, args.out)
            log.info("COLMAP: %d of %d runs succeeded (success_paper)", data["n_success_paper"], data["n_runs"])
        log.info("done in %.2f s", time.perf_counter() - t0)
        return 0

    return run_stage(log, work, errors=(ValueError, OSError))


def _skipped(text: str) -> list[dict]:
    """The ``--skipped`` JSON: a list of {dataset, scene, init, reason} objects."""
    try:
        skipped = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--skipped is not JSON: {exc}") from None
    keys = ("dataset", "scene", "init", "reason")
    if not isinstance(skipped, list) or not all(isinstance(s, dict) and all(k in s for k in keys) for s in skipped):
        raise ValueError(f"--skipped must be a JSON list of objects with the keys {', '.join(keys)}")
    return skipped


if __name__ == "__main__":
    raise SystemExit(main())
