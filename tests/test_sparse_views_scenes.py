"""experiments/sparse_views: the scene list's protocol (tuning apart from evaluation) and the
fetch script, its dry run, a real fetch from a local mirror, and its one-line errors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from experiments.sparse_views import fetch_scenes
from camio.__main__ import _parser as camio_parser

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "experiments" / "sparse_views" / "fetch_scenes.py"


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], cwd=cwd, capture_output=True, text=True)


def test_scene_list_keeps_tuning_apart_and_each_evaluation_scene_converts_with_camio_arguments():
    scenes = fetch_scenes.load_scenes()
    tuning = {s["name"] for s in scenes if s["role"] == "tuning"}
    evaluation = [s for s in scenes if s["role"] == "evaluation"]
    # the scenes of the earlier evaluations were measured, then informed a tuning round: tuning
    # scenes for good
    assert tuning == {"llff__fern", "synthetic", "strecha__fountain-P11", "strecha__Herz-Jesus-P25",
                      "strecha__castle-P30", "strecha__entry-P10", "ingp__fox", "nerd__ethiopianHead",
                      "llff__horns", "llff__flower", "nerd__moldGoldCape", "nerd__maryRose",
                      "nerd__StatueOfLiberty", "dtu__scan24", "dtu__scan37", "tnt__Train",
                      "blender__lego", "blender__mic", "blender__chair", "strecha__Herz-Jesus-P8",
                      "strecha__castle-P19", "middlebury__templeSparseRing", "middlebury__dinoSparseRing",
                      "llff__fortress", "llff__trex", "llff__room", "fornex__ollie", "fornex__canclip",
                      "own__milk", "own__vrdesk", "own__fruit", "own__ultraman", "llff__orchids",
                      "own__beercan", "own__woodbird", "own__drinkbox", "dtu__scan65", "own__cokecan",
                      "own__gumjar", "own__stitch", "own__sargos", "ibrnet__qq11", "nags__bench", "in2n__bear",
                      "mipnerf360__garden"}
    # at least four unseen scenes with published cameras, of at least two kinds, one of them a
    # real capture that is not of a site the recipe was tuned on
    assert len(evaluation) >= 4
    assert len({s["kind"] for s in evaluation}) >= 2
    assert {s["name"] for s in evaluation} == {"own__rails", "own__dragonstatue", "own__artcar", "own__plushray",
                                                 "own__copier", "own__horsestatue", "own__gamebox", "own__archmodel",
                                                 "own__figurine", "own__kanazawadrone"}
    # every pre-registered set is of evaluation scenes only, and no two sets share a scene (a
    # scene measured by one registration is never the unseen scene of the next)
    import yaml

    regs = sorted((Path(fetch_scenes.__file__).parent / "registered").glob("*.yaml"))
    assert len(regs) >= 2
    seen: set[str] = set()
    for reg in regs:
        names = set(yaml.safe_load(reg.read_text())["scenes"])
        assert names <= {s["name"] for s in evaluation}, reg.name
        assert not names & seen, reg.name
        seen |= names
    # no scene is held in reserve until the next one is listed before a change of value
    reserve = [s for s in scenes if s["role"] == "reserve"]
    assert reserve == []
    for s in [*evaluation, *reserve]:  # the shipped list's unseen scenes are public: where, at which commit, licence
        assert set(s["source"]) == {"repo", "commit", "path"} and s["licence"], s["name"]
    for s in [*evaluation, *(s for s in scenes if "source" in s)]:
        assert 3 in s["views"]
        # the stored arguments are ones camio convert accepts, and leave --src/--out/--n to the script
        args = camio_parser().parse_args(["convert", "--src", "a", "--out", "b", *s["convert"]])
        assert args.downsample >= 1
        assert not {"--src", "--out", "--n"} & set(s["convert"])


def test_dry_run_prints_every_pinned_fetch_and_conversion_and_writes_nothing(tmp_path):
    dest = tmp_path / "scenes"
    r = _cli(dest, "--dry-run", "--convert")
    assert r.returncode == 0, r.stderr
    for s in fetch_scenes.select(fetch_scenes.load_scenes(), None):
        src = s["source"]
        assert f"https://github.com/{src['repo']}.git" in r.stdout
        assert f"origin {src['commit']}" in r.stdout
        assert f"--out {dest / (s['name'] + '_conv')} {' '.join(s['convert'])} --n" in r.stdout
    assert "llff__fern_conv" in r.stdout  # a tuning scene from a public repo is fetched too
    assert str(dest / "synthetic") not in r.stdout  # the generated one is not
    assert not dest.exists()


def _mirror(tmp_path: Path) -> tuple[Path, str]:
    """A bare repo own/rep.git whose first commit has data/s/a.txt, the second also c.txt."""
    src = tmp_path / "src"
    (src / "data" / "s").mkdir(parents=True)
    (src / "other").mkdir()
    (src / "data" / "s" / "a.txt").write_text("a")
    (src / "other" / "b.txt").write_text("b")
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t", "-C", str(src)]
    subprocess.run(["git", "init", "-q", str(src)], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "one"], check=True)
    first = subprocess.run([*git, "rev-parse", "HEAD"], check=True, capture_output=True, text=True).stdout.strip()
    (src / "data" / "s" / "c.txt").write_text("c")
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "two"], check=True)
    base = tmp_path / "base"
    (base / "own").mkdir(parents=True)
    subprocess.run(["git", "clone", "-q", "--bare", str(src), str(base / "own" / "rep.git")], check=True)
    return base, first


def _yaml(path: Path, commit: str, scene_path: str) -> Path:
    path.write_text(f"""scenes:
  - name: sc
    role: evaluation
    kind: outdoor
    licence: test
    local: /nowhere
    source: {{repo: own/rep, commit: {commit}, path: {scene_path}}}
    convert: [--format, folder]
    views: [3]
""")
    return path


@pytest.mark.skipif(shutil.which("git") is None, reason="needs git")
@pytest.mark.parametrize("scene_path, files", [("data/s", {"a.txt"}),
                                               (".", {"data/s/a.txt", "other/b.txt"})])
def test_fetch_takes_the_pinned_commit_and_only_the_scene_path(tmp_path, scene_path, files):
    base, first = _mirror(tmp_path)
    yaml_path = _yaml(tmp_path / "s.yaml", first, scene_path)
    dest = tmp_path / "out"
    r = _cli(dest, "--yaml", yaml_path, "--git-base", base)
    assert r.returncode == 0, r.stderr
    got = {p.relative_to(dest / "sc").as_posix() for p in (dest / "sc").rglob("*") if p.is_file()}
    assert got == files | {"FETCHED.json"}  # c.txt is of a later commit; nothing of .git is kept
    assert json.loads((dest / "sc" / "FETCHED.json").read_text()) == {"repo": "own/rep", "commit": first,
                                                                      "path": scene_path}
    assert sorted(p.name for p in dest.iterdir()) == ["sc"]  # the work folder is gone
    again = _cli(dest, "--yaml", yaml_path, "--git-base", base)
    assert again.returncode == 0 and "left as it is" in again.stdout


@pytest.mark.parametrize("edit, args, says", [
    (lambda t: t.replace("commit: " + "a" * 40, "commit: abc123"), [], "40-hex"),
    (lambda t: t.replace("role: evaluation", "role: eval"), [], "role must be"),
    (lambda t: t.replace("views: [3]", "views: [0]"), [], "views"),
    (lambda t: t.replace("path: data/s", "path: ../up"), [], "inside the repo"),
    (lambda t: t.replace("views: [3]", "views: [3]\n    background: [1, 1]"), [], "background"),
    (lambda t: t.replace("views: [3]", "views: [3]\n    background: [0, 2, 0]"), [], "background"),
    (lambda t: t.replace("    licence:", "    licenced:"), [], "'licence' missing"),
    (lambda t: t.replace("    kind:", "    kinds:"), [], "'kind' missing"),
    (lambda t: t, ["--scenes", "nope"], "unknown scene"),
    (lambda t: t + "  - [", [], "not valid YAML"),
])
def test_bad_scene_list_or_name_is_one_line_and_exit_2(tmp_path, edit, args, says):
    yaml_path = _yaml(tmp_path / "s.yaml", "a" * 40, "data/s")
    yaml_path.write_text(edit(yaml_path.read_text()))
    r = _cli(tmp_path / "out", "--yaml", yaml_path, "--dry-run", *args)
    assert r.returncode == 2
    assert len(r.stderr.strip().splitlines()) == 1 and says in r.stderr
    assert not (tmp_path / "out").exists()
