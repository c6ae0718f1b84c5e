"""The short report of a photo-folder run (scripts/photos.py): what ran, where its cameras,
seed, model and renders are, and the exact command that views the model.

    python workflow/scripts/photos_summary.py --results R --runs JSON --out R/photos.md

``--runs`` is a JSON list of {dataset, scene, n, init, modes, path} (the workflow's
photo_runs_json); initialisers skipped because they cannot run here come from R/skipped.json.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from runtime.atomic import atomic_path
from evaluation.initialisers import registry
from evaluation.reports.run_status import read_skipped


def _status(run: Path, init: str) -> tuple[bool, str]:
    """(has a model, one line on how the initialiser went)."""
    status = run / "status.json"
    if registry.get(init).marker != "status.json":  # no status to read (VGGT: timing.json)
        return (run / "sparse" / "0").is_dir(), "ran"
    if not status.is_file():
        return False, "no result (see its logs/)"
    s = json.loads(status.read_text())
    fallback = (s.get("fallback") or {}).get("applied", False)
    ok = bool(s.get("success_paper", s.get("success", False)))
    reg = f"registered {s.get('registered', '?')} of {s.get('n_images', '?')} photos"
    if ok:
        return True, f"ran, {reg}"
    if fallback:
        return True, f"ran, {reg}; trained from random points for its cameras ({s.get('reason') or 'too few points'})"
    return False, f"ran, no model: {reg} ({s.get('reason') or 'see its logs/'})"


def summary(results: str | Path, runs: list[dict]) -> str:
    """The Markdown text of R/photos.md."""
    results = Path(results)
    skipped = read_skipped(results)
    lines = ["# Your photos: what ran and where it is", ""]
    scenes: dict[tuple, list[dict]] = {}
    for r in runs:
        scenes.setdefault((r["dataset"], r["scene"], r["path"]), []).append(r)
    for (ds, sc, path), rs in scenes.items():
        lines += [f"## {sc}", "", f"Photos: {path} ({rs[0]['n']} photos, all used for training).", ""]
        for init, why in sorted(skipped.items()):
            lines += [f"- {init}: skipped: {why}", ""]
        for r in rs:
            run = results / ds / sc / f"n{r['n']}" / r["init"]
            ok, how = _status(run, r["init"])
            lines += [f"### {r['init']}: {how}", ""]
            if not ok:
                continue
            lines.append(f"- cameras (COLMAP model): {run / 'sparse' / '0'}")
            for mode in r["modes"]:
                m = run / mode
                model = m / "train" / "model.ply"
                if not model.is_file():
                    lines.append(f"- {mode}: no trained model (see {m / 'logs'})")
                    continue
                view = ["python", "-m", "splat_train", "view", "--model", str(model),
                        "--cameras", str(m / "bridge" / "sparse" / "0"), "--seed-ply", str(m / "bridge" / "seed.ply")]
                lines += [
                    f"- seed ({mode} Bridge): {m / 'bridge' / 'seed.ply'}",
                    f"- cameras in the model's frame: {m / 'bridge' / 'sparse' / '0'}",
                    f"- trained model: {model}",
                    f"- a render of every photo: {m / 'train_renders'}",
                    "- view it:",
                    "",
                    "  ```",
                    f"  {shlex.join(view)}",
                    "  ```",
                ]
            lines.append("")
    lines.append(f"The full report, each photo beside the model's render of its camera (training-view fit), the "
                 f"training curve, the cameras from above and the model's size: {results / 'report' / 'index.html'}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="workflow/scripts/photos_summary.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--results", required=True, help="the results folder")
    p.add_argument("--runs", required=True, help="JSON list of {dataset, scene, n, init, modes, path}")
    p.add_argument("--out", required=True, help="the Markdown file to write")
    args = p.parse_args(argv)
    try:
        runs = json.loads(args.runs)
    except ValueError as exc:
        print(f"workflow/scripts/photos_summary.py: error: --runs is not JSON: {exc}", file=sys.stderr)
        return 2
    text = summary(args.results, runs)
    with atomic_path(args.out) as tmp:
        tmp.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
