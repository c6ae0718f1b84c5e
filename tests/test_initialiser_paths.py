"""The initialisers' commands name a folder given for a file, and a file given for a folder, in
the one wording of runtime.checks (file_problem / folder_problem): exit 2, one line, nothing
written under --out."""

from __future__ import annotations

import pytest

from tests._cli import refused, run


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("initpaths")
    p = run(["-m", "camio", "synth", "--out", str(root / "scene"), "--views", "6", "--width", "48", "-q"])
    assert p.returncode == 0, p.stderr
    (root / "afile").write_text("hi\n")
    (root / "empty").mkdir()
    return {"scene": root / "scene", "afile": root / "afile", "empty": root / "empty", "root": root}


IMAGE_LIST_A_FOLDER = [  # every initialiser that reads --image-list through evaluation.initialisers.views
    ("colmap_baseline", ["--images", "@scene/images"]),
    ("random_init", ["--cameras", "@scene/sparse/0"]),
    ("oracle", ["--scene", "@scene"]),
    ("posed", ["--scene", "@scene"]),
]


@pytest.mark.parametrize("module,argv", IMAGE_LIST_A_FOLDER, ids=[c[0] for c in IMAGE_LIST_A_FOLDER])
def test_an_image_list_that_is_a_folder_is_named_as_a_folder(scene, tmp_path, module, argv):
    """views.read_image_list said `image list DIR does not exist` for a folder."""
    args = [a.replace("@scene", str(scene["scene"])) for a in argv]
    line = refused(run(["-m", f"evaluation.initialisers.{module}", *args, "--image-list", str(scene["empty"]),
                        "--out", str(tmp_path / "out")]), "image list", str(scene["empty"]), "is a folder, not a file")
    assert "does not exist" not in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("given,needle", [("afile", "is a file, not a folder"), ("nowhere", "does not exist")])
def test_posed_names_a_scene_that_is_a_file_or_missing(scene, tmp_path, given, needle):
    """posed said `scene F does not exist` for a file."""
    (tmp_path / "list.txt").write_text("view_000.png\nview_001.png\n")
    path = scene["afile"] if given == "afile" else scene["root"] / "nowhere"
    refused(run(["-m", "evaluation.initialisers.posed", "--scene", str(path), "--image-list",
                 str(tmp_path / "list.txt"), "--out", str(tmp_path / "out")]), "scene", str(path), needle)
    assert not (tmp_path / "out").exists()
