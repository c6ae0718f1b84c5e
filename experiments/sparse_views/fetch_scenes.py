"""Fetch the scenes of scenes.yaml that have a source, each at its pinned commit.

    python experiments/sparse_views/fetch_scenes.py DEST [--scenes NAME ...] [--convert] [--dry-run]

For every scene with a ``source`` (every evaluation scene, and the tuning scenes taken from
public repositories), or those named: a shallow, blob-less, sparse git fetch of the
scene's ``source.path`` at ``source.commit`` into ``DEST/.fetch/NAME``, whose files are then
moved to ``DEST/NAME`` (``DEST/NAME/FETCHED.json`` records repo, commit and path). A scene
already in ``DEST`` is left alone. ``--convert`` also runs ``python -m camio convert`` with the
scene's ``convert`` arguments and ``views`` into ``DEST/NAME_conv`` (images, reference cameras
scaled to them, split.json). ``--dry-run`` prints the commands and writes nothing.

Needs git >= 2.27 and network access to the sources (GitHub); ``--git-base`` points at a mirror.
The synthetic tuning scene has no source: the benchmark generates it.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCENES_YAML = Path(__file__).resolve().with_name("scenes.yaml")
GIT_BASE = "https://github.com/"
# tuning: values may be chosen on it; evaluation: it only measures; reserve: unseen, held back
# (never run) for the evaluation after the next change of values
ROLES = ("tuning", "evaluation", "reserve")
RUN_ROLES = ("tuning", "evaluation")
_COMMIT = re.compile(r"^[0-9a-f]{40}$")
_REPO = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*/[A-Za-z0-9][A-Za-z0-9_.-]*$")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


class ScenesError(ValueError):
    """scenes.yaml (or a scene named on the command line) is not usable; the message says why."""


def _need(cond: bool, msg: str) -> None:
    if not cond:
        raise ScenesError(msg)


def load_scenes(path: str | Path = SCENES_YAML) -> list[dict]:
    """The scenes of a scenes.yaml, checked: unique names, a known role, views a list of
    positive ints, an optional ``background`` of three numbers in [0, 1], an optional
    ``convert`` (a list of strings); an evaluation or reserve scene also needs ``kind``. A scene with a
    ``source`` (repo owner/name, a 40-hex commit, a path) also needs ``licence`` and ``local``;
    one without is the user's own data, found at ``local`` or under ``--data``."""
    import yaml

    path = Path(path)
    _need(path.is_file(), f"{path}: no such file")
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ScenesError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    _need(isinstance(doc, dict) and isinstance(doc.get("scenes"), list) and doc["scenes"],
          f"{path}: needs a non-empty 'scenes' list")
    seen: set[str] = set()
    for i, s in enumerate(doc["scenes"]):
        where = f"{path}: scenes[{i}]"
        _need(isinstance(s, dict), f"{where}: not a mapping")
        name = s.get("name")
        _need(isinstance(name, str) and bool(_NAME.match(name)), f"{where}: 'name' missing or not a plain folder name")
        where = f"{path}: scene {name}"
        _need(name not in seen, f"{where}: named twice")
        seen.add(name)
        _need(s.get("role") in ROLES, f"{where}: role must be one of {', '.join(ROLES)}")
        views = s.get("views")
        _need(isinstance(views, list) and bool(views) and all(isinstance(v, int) and not isinstance(v, bool) and v > 0
                                                               for v in views),
              f"{where}: 'views' must be a list of positive integers")
        bg = s.get("background")
        _need(bg is None or isinstance(bg, list) and len(bg) == 3
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= 1 for v in bg),
              f"{where}: 'background' must be three numbers in [0, 1] (RGB)")
        conv = s.get("convert", [])
        _need(isinstance(conv, list) and all(isinstance(a, str) for a in conv),
              f"{where}: 'convert' must be a list of strings (camio convert arguments)")
        if s["role"] != "tuning":
            _need(isinstance(s.get("kind"), str) and bool(s["kind"].strip()), f"{where}: 'kind' missing")
        if "source" not in s:  # generated, or the user's own data (local / --data)
            continue
        for key in ("kind", "licence", "local"):
            _need(isinstance(s.get(key), str) and bool(s[key].strip()), f"{where}: '{key}' missing")
        src = s.get("source")
        _need(isinstance(src, dict), f"{where}: 'source' (repo, commit, path) missing")
        _need(isinstance(src.get("repo"), str) and bool(_REPO.match(src["repo"])), f"{where}: source.repo must be owner/name")
        _need(isinstance(src.get("commit"), str) and bool(_COMMIT.match(src["commit"])),
              f"{where}: source.commit must be a full 40-hex commit")
        p = src.get("path")
        _need(isinstance(p, str) and bool(p) and not p.startswith("/") and ".." not in Path(p).parts,
              f"{where}: source.path must be a path inside the repo ('.' for all of it)")
    return doc["scenes"]


def select(scenes: list[dict], names: list[str] | None) -> list[dict]:
    """The scenes that have a ``source`` (every evaluation scene, and the tuning scenes taken from
    public repositories), or those of ``names`` (each must have one)."""
    by_name = {s["name"]: s for s in scenes}
    if not names:
        return [s for s in scenes if "source" in s]
    for n in names:
        _need(n in by_name, f"unknown scene {n!r} (known: {', '.join(by_name)})")
        _need("source" in by_name[n], f"scene {n!r} has no source to fetch (it is generated or local)")
    return [by_name[n] for n in names]


def fetch_commands(scene: dict, work: Path, git_base: str = GIT_BASE) -> list[list[str]]:
    """The git commands that fill ``work`` with the scene's source path at its commit."""
    src = scene["source"]
    url = f"{git_base.rstrip('/')}/{src['repo']}.git"
    w = str(work)
    cmds = [["git", "init", "-q", w], ["git", "-C", w, "remote", "add", "origin", url]]
    if src["path"] != ".":
        cmds.append(["git", "-C", w, "sparse-checkout", "set", "--no-cone", "/" + src["path"].strip("/") + "/"])
    cmds += [["git", "-C", w, "fetch", "-q", "--depth", "1", "--filter=blob:none", "origin", src["commit"]],
             ["git", "-C", w, "checkout", "-q", "FETCH_HEAD"]]
    return cmds


def convert_command(scene: dict, dest: Path) -> list[str]:
    """``python -m camio convert`` for the fetched scene, into DEST/NAME_conv."""
    name = scene["name"]
    return [sys.executable, "-m", "camio", "convert", "--src", str(dest / name), "--out", str(dest / f"{name}_conv"),
            *scene.get("convert", []), "--n", *map(str, scene["views"])]


def _run(cmd: list[str], cwd: Path | None = None) -> None:
    r = subprocess.run(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if r.returncode != 0:
        tail = (r.stdout or "").strip().splitlines()[-1:] or ["(no output)"]
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {r.returncode}): {tail[0]}")


def fetch_scene(scene: dict, dest: Path, git_base: str = GIT_BASE, dry_run: bool = False) -> Path:
    """Fetch one scene into ``dest/NAME`` (module docstring); returns that folder."""
    name, src = scene["name"], scene["source"]
    target, work = dest / name, dest / ".fetch" / name
    if target.exists():
        print(f"{name}: {target} exists, left as it is")
        return target
    for cmd in fetch_commands(scene, work, git_base):
        print("+", " ".join(cmd))
        if not dry_run:
            _run(cmd)
    moved = work if src["path"] == "." else work / src["path"]
    print(f"+ move {moved} -> {target}")
    if dry_run:
        return target
    if not moved.is_dir():
        raise RuntimeError(f"{name}: {src['path']} is not a folder at {src['commit']} of {src['repo']}")
    if src["path"] == ".":
        shutil.rmtree(work / ".git")
    (moved / "FETCHED.json").write_text(json.dumps({"repo": src["repo"], "commit": src["commit"], "path": src["path"]},
                                                   indent=1) + "\n")
    moved.rename(target)
    shutil.rmtree(work, ignore_errors=True)
    return target


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="fetch_scenes.py", description=__doc__.split("\n")[0])
    p.add_argument("dest", type=Path, help="folder to fetch the scenes into (DEST/NAME)")
    p.add_argument("--scenes", nargs="+", default=None,
                   help="scenes to fetch (default: every scene with a source, evaluation and tuning)")
    p.add_argument("--yaml", type=Path, default=SCENES_YAML, help="the scene list (default: scenes.yaml beside this script)")
    p.add_argument("--convert", action="store_true", help="also run camio convert into DEST/NAME_conv")
    p.add_argument("--dry-run", action="store_true", help="print the commands; fetch and write nothing")
    p.add_argument("--git-base", default=GIT_BASE, help="where the repos live (default: %(default)s)")
    args = p.parse_args(argv)
    try:
        scenes = select(load_scenes(args.yaml), args.scenes)
    except ScenesError as e:
        print(f"fetch_scenes.py: error: {e}", file=sys.stderr)
        return 2
    if not args.dry_run and shutil.which("git") is None:
        print("fetch_scenes.py: error: git is not on PATH", file=sys.stderr)
        return 2
    try:
        for scene in scenes:
            fetch_scene(scene, args.dest, args.git_base, args.dry_run)
            if args.convert:
                cmd = convert_command(scene, args.dest)
                print("+", " ".join(cmd))
                if (args.dest / f"{scene['name']}_conv").exists():
                    print(f"{scene['name']}: {scene['name']}_conv exists, left as it is")
                elif not args.dry_run:
                    _run(cmd, cwd=ROOT)
    except (RuntimeError, OSError) as e:
        print(f"fetch_scenes.py: error: {e}", file=sys.stderr)
        return 1
    if not args.dry_run:
        shutil.rmtree(args.dest / ".fetch", ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
