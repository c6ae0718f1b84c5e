"""Configuration errors are one line naming the key and the nearest valid one, said before
anything is written (workflow/scripts/check_config.py; scripts/demo.sh and the workflow)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "workflow" / "scripts"))

import check_config  # noqa: E402


def _config() -> dict:
    return yaml.safe_load((ROOT / "config.yaml").read_text())


def test_the_default_config_is_valid():
    assert check_config.config_problems(_config()) == []


def test_a_top_level_typo_names_the_key_and_the_nearest_valid_one():
    cfg = _config()
    cfg["initializers"] = cfg.pop("initialisers")
    assert check_config.config_problems(cfg) == ["unknown key 'initializers'; did you mean 'initialisers'?"]


def test_nested_typos_and_bad_values():
    cfg = _config()
    cfg["vggt"]["devise"] = cfg["vggt"].pop("device")
    cfg["initialisers"] = ["vggt", "colmapp"]
    problems = check_config.config_problems(cfg)
    assert "unknown key 'vggt.devise'; did you mean 'device'?" in problems
    assert "initialisers.1: 'colmapp' is not a valid value; did you mean 'colmap'?" in problems
    assert len(problems) == 2


def test_demo_refuses_a_typo_in_one_line_before_writing_anything(tmp_path):
    for rel in ("scripts/demo.sh", "workflow/scripts/check_config.py", "workflow/schemas/config.schema.yaml"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / rel, tmp_path / rel)
    text = (ROOT / "config.yaml").read_text().replace("\ninitialisers:", "\ninitializers:")
    (tmp_path / "config.yaml").write_text(text)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}", "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(["bash", "scripts/demo.sh"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120, env=env)
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if ln.strip()]
    assert lines == ["config error (config.yaml): unknown key 'initializers'; did you mean 'initialisers'?"]
    assert "Traceback" not in proc.stderr and not (tmp_path / "results").exists()
