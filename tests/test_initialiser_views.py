"""The training-view arguments every initialiser shares (evaluation.initialisers.views), and
their bad input through the initialisers' command lines: one line, exit code 2."""

from __future__ import annotations

import argparse
import json

import pytest

from evaluation.initialisers.views import add_view_args, training_names


def _args(argv, split=True):
    p = argparse.ArgumentParser()
    add_view_args(p, split=split)
    return p.parse_args(argv)


def test_each_way_of_naming_the_training_views(tmp_path):
    split = tmp_path / "split.json"
    split.write_text(json.dumps({"train": {"3": ["a.png", "b.png", "c.png"]}, "test": []}))
    lst = tmp_path / "train.txt"
    lst.write_text("# training views\na.png\n\n  b.png  \n")
    assert training_names(_args(["--split", str(split), "--n", "3"])) == ["a.png", "b.png", "c.png"]
    assert training_names(_args(["--image-list", str(lst)])) == ["a.png", "b.png"]
    assert training_names(_args(["--names", "x.png", "y.png"], split=False)) == ["x.png", "y.png"]


@pytest.mark.parametrize("argv, message", [
    (["--split", "S"], "--split needs --n"),
    (["--split", "S", "--n", "6"], "has no training list for n = 6; it has ['3']"),
    (["--image-list", "missing.txt"], "does not exist"),
    (["--image-list", "empty.txt"], "is empty"),
    ([], "give the training images: --split JSON --n N"),
])
def test_bad_choices_name_the_problem(tmp_path, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "S").write_text(json.dumps({"train": {"3": ["a.png"]}}))
    (tmp_path / "empty.txt").write_text("# nothing\n\n")
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        training_names(_args(argv))


@pytest.mark.parametrize("module", ["oracle", "colmap_baseline"])
def test_a_split_without_that_n_is_exit_2_with_one_line(tmp_path, capsys, module):
    import importlib

    main = importlib.import_module(f"evaluation.initialisers.{module}").main
    (tmp_path / "split.json").write_text(json.dumps({"train": {"3": ["a.png"]}}))
    where = ["--scene", str(tmp_path)] if module == "oracle" else ["--images", str(tmp_path)]
    with pytest.raises(SystemExit) as exc:
        main([*where, "--split", str(tmp_path / "split.json"), "--n", "6", "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    assert "has no training list for n = 6" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
