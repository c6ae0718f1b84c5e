"""Bad input (a missing path, a missing argument) exits 2 from every CLI, as argparse does
(docs/contracts.md, "Exit codes"), with one line that says what is wrong."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _missing_path_cases(tmp: Path) -> list[tuple[str, list[str]]]:
    none = str(tmp / "none")
    out = str(tmp / "out" / "deeper")
    return [
        ("bridge.__main__", ["--pred", none + ".npz", "--out", out, "-q"]),
        ("bridge.__main__", ["--colmap", none, "--images", none, "--out", out, "-q"]),
        ("evaluation.__main__", ["align", "--pred", none, "--ref", none, "--train-names", none, "--out", out, "-q"]),
        ("evaluation.__main__", ["pose", "--pred", none, "--ref", none, "--out", out + ".json", "-q"]),
        ("evaluation.__main__", ["tables", "--results", none, "--out", out, "-q"]),
        ("evaluation.initialisers.posed", ["--scene", none, "--names", "a.png", "b.png", "--out", out]),
        ("evaluation.initialisers.colmap_baseline", ["--images", none, "--names", "a.png", "b.png", "--out", out]),
        ("camio.__main__", ["split", "--scene", none, "--out", out + ".json", "-q"]),
    ]


@pytest.mark.parametrize("case", range(8))
def test_missing_input_exits_2_and_leaves_nothing(case, tmp_path, monkeypatch):
    import importlib

    monkeypatch.chdir(tmp_path)
    module, argv = _missing_path_cases(tmp_path)[case]
    mod = importlib.import_module(module)
    try:
        rc = mod.main(argv)
    except SystemExit as exc:
        rc = exc.code
    assert rc == 2, (module, argv)
    from runtime.outdir import tidy_outs

    tidy_outs()
    assert not (tmp_path / "out").exists(), "a failed stage left its output folder"


def test_posed_names_a_missing_scene(tmp_path, capsys):
    from evaluation.initialisers.posed import main

    assert main(["--scene", str(tmp_path / "nonexistent"), "--names", "a.png", "b.png",
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "does not exist" in err and "reference cameras" not in err


def test_colmap_baseline_without_training_names_prints_usage(tmp_path, capsys):
    from evaluation.initialisers.colmap_baseline import main

    with pytest.raises(SystemExit) as exc:
        main(["--images", str(tmp_path), "--out", str(tmp_path / "o")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: python -m evaluation.initialisers.colmap_baseline") and "--image-list" in err
    with pytest.raises(SystemExit) as exc:
        main(["--images", str(tmp_path), "--image-list", str(tmp_path / "none.txt"), "--out", str(tmp_path / "o")])
    assert exc.value.code == 2 and "does not exist" in capsys.readouterr().err


def test_splat_train_with_a_missing_seed_leaves_no_output_folder(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "splat_train", "--seed-ply", str(tmp_path / "none.ply"),
                           "--cameras", str(tmp_path / "none"), "--images", str(tmp_path / "none"),
                           "--out", "work/train"], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "none.ply" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "work").exists(), "the output folder (or its parent) was left behind"
