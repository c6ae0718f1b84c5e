"""Your own photos in one command: cameras, a trained model and a view of it.

    python scripts/photos.py PHOTOS [--out DIR] [--init vggt|colmap|both] [--dense] [--iterations N]
                             [--cores N] [-n] [-- SNAKEMAKE ARGS ...]

PHOTOS is a folder of photographs of one scene (3 or more; no camera files needed). Every photo
trains: there are no reference cameras and no held-out views, so there are no image metrics,
only the model and a render of every photo. This writes DIR/config.yaml (the workflow's
configuration for this folder) and DIR/split.json (every photo trains), then runs the project's
Snakemake workflow on it, so a second run resumes and the same config runs on a cluster:

    snakemake --profile workflow/profiles/slurm --configfile DIR/config.yaml

What the run leaves (DIR/photos.md lists the paths and the exact `view` command):

    DIR/photos/<name>/n<N>/<init>/sparse/0                 the initialiser's cameras (COLMAP model)
    DIR/photos/<name>/n<N>/<init>/<mode>/bridge/seed.ply   the seed point cloud
    DIR/photos/<name>/n<N>/<init>/<mode>/train/model.ply   the trained model
    DIR/photos/<name>/n<N>/<init>/<mode>/train_renders/    a render of every photo
    DIR/photos.md, DIR/report/index.html                   what ran, and why not where it did not

Without the VGGT-1B checkpoint (and no way to download it) VGGT is skipped with one line
saying why, and COLMAP runs alone. ``--dense`` adds, for each initialiser, multi-view stereo of
the photos on its cameras (``colmap_mvs``, ``vggt_mvs``: evaluation/initialisers/mvs): a dense
seed with a confidence per point, which the Bridge turns into opacity (Eq. 2).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
INITS = {"vggt": ["vggt"], "colmap": ["colmap"], "both": ["vggt", "colmap"]}
DATASET = "photos"


def _fail(msg: str) -> int:
    print(f"scripts/photos.py: error: {msg}", file=sys.stderr)
    return 2


def photo_names(folder: Path) -> list[str]:
    """The photographs of ``folder``, as `camio convert --format folder` reads them."""
    from camio.scene import load_scene

    return list(load_scene(folder, format="folder").names)


def make_config(folder: Path, out: Path, names: list[str], inits: list[str],
                iterations: int | None, vggt: dict | None = None) -> dict:
    """The workflow configuration of one photo folder (results under ``out``)."""
    scene = folder.resolve().name
    scene = "".join(c if c.isalnum() or c in "_.-" else "_" for c in scene).lstrip("_.-") or "scene"
    cfg: dict = {
        "results": str(out),
        "datasets": {DATASET: {"scenes": {scene: {
            "path": str(folder.resolve()),
            "format": "folder",
            "reference": False,
            "split": {"rule": "manifest", "manifest": str(out / "split.json")},
            "views": [len(names)],
        }}}},
        "views": [len(names)],
        "initialisers": inits,
        "evaluation": {"testpose": False},
    }
    if iterations is not None:
        cfg["train"] = {"iterations": iterations, "eval_every": max(1, iterations)}
    if vggt:
        cfg["vggt"] = dict(vggt)
    return cfg


def _write_if_changed(path: Path, text: str) -> None:
    """Rewrite only when the content changes, so that a rerun resumes rather than restarts."""
    if path.is_file() and path.read_text() == text:
        return
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    p = argparse.ArgumentParser(prog="scripts/photos.py", description=__doc__.split("\n\n")[0],
                                epilog="Arguments after -- go to snakemake (e.g. -- --profile "
                                       "workflow/profiles/slurm).")
    p.add_argument("photos", type=Path, help="folder of the photographs (3 or more)")
    p.add_argument("--out", type=Path, help="results folder (default: results_photos/<folder name>)")
    p.add_argument("--init", choices=sorted(INITS), default="both",
                   help="initialiser: vggt, colmap, or both (default both; VGGT is skipped, with "
                        "the reason, where its checkpoint is missing)")
    p.add_argument("--dense", action="store_true",
                   help="also seed from multi-view stereo of the photos on each initialiser's cameras "
                        "(colmap_mvs, vggt_mvs)")
    p.add_argument("--iterations", type=int, help="training steps (default: the workflow's, "
                                                  "workflow/schemas/config.schema.yaml)")
    p.add_argument("--vggt-checkpoint", dest="vggt_checkpoint",
                   help="VGGT weights file (default: the search order of vggt_init/checkpoint.py)")
    p.add_argument("--vggt-model-config", dest="vggt_model_config",
                   help="VGGT model configuration JSON (default: VGGT-1B)")
    p.add_argument("--vggt-image-size", dest="vggt_image_size", type=int,
                   help="VGGT input width (multiple of 14; default 518)")
    p.add_argument("--cores", type=int, default=2, help="cores snakemake may use (default 2)")
    p.add_argument("-n", "--dry-run", action="store_true", dest="dry_run",
                   help="write the config and show the jobs, run nothing")
    args = p.parse_args(argv)

    if not args.photos.is_dir():
        return _fail(f"{args.photos} is not a folder of photos")
    if args.iterations is not None and args.iterations < 1:
        return _fail(f"--iterations must be at least 1, got {args.iterations}")
    try:
        names = photo_names(args.photos)
    except (ValueError, OSError) as exc:
        return _fail(str(exc).splitlines()[0])
    if len(names) < 3:
        return _fail(f"{args.photos} holds {len(names)} photo(s); at least 3 are needed")
    out = (args.out.expanduser() if args.out else Path("results_photos") / args.photos.resolve().name).absolute()
    if out.resolve() == args.photos.resolve() or args.photos.resolve() in out.resolve().parents:
        return _fail(f"--out {out} is inside the photo folder; choose a folder outside it")
    vggt = {k: v for k, v in (("checkpoint", args.vggt_checkpoint), ("model_config", args.vggt_model_config),
                              ("image_size", args.vggt_image_size)) if v is not None}
    for key in ("checkpoint", "model_config"):
        if key in vggt:
            vggt[key] = str(Path(vggt[key]).absolute())
    inits = INITS[args.init] + ([f"{i}_mvs" for i in INITS[args.init]] if args.dense else [])
    cfg = make_config(args.photos, out, names, inits, args.iterations, vggt)

    sys.path.insert(0, str(REPO / "workflow" / "scripts"))
    from check_config import config_problems

    problems = config_problems(cfg)
    if problems:
        return _fail("; ".join(problems))
    out.mkdir(parents=True, exist_ok=True)
    import json

    _write_if_changed(out / "split.json", json.dumps({"test": [], "train": {str(len(names)): names}}, indent=1) + "\n")
    _write_if_changed(out / "config.yaml", "# Written by scripts/photos.py for " + str(args.photos.resolve())
                      + "\n" + yaml.safe_dump(cfg, sort_keys=False))
    print(f"[photos] {len(names)} photos in {args.photos}; config {out / 'config.yaml'}; "
          f"initialiser(s): {', '.join(inits)}", flush=True)
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(REPO),
           "--cores", str(args.cores), "--configfile", str(out / "config.yaml"), *(["-n"] if args.dry_run else []),
           *extra]
    from progress import annotate  # says when the progress total grows after the COLMAP checkpoint

    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1)
    for line in annotate(proc.stdout, "[photos]"):
        sys.stdout.write(line)
        sys.stdout.flush()
    rc = proc.wait()
    if rc != 0:
        print(f"[photos] FAILED (snakemake exit {rc}): see the output above and the logs under {out}",
              file=sys.stderr)
        return 1
    if not args.dry_run:
        print(f"[photos] done: {out / 'photos.md'} lists the cameras, seed, model, renders and the "
              "command to view the model", flush=True)
        summary = out / "photos.md"
        if summary.is_file():
            print(summary.read_text(), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
