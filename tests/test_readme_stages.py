"""The README's stage commands ("Stages, one command each") run as written, in order, from a
copy of the repository root, on the synthetic scene with the posed initialiser, and write only
into ``work/``; then "Look at a model" serves the model they trained. Lines marked ``# needs ...`` (the VGGT weights, a downloaded scene, the
workflow's results) are left out; every line runs as it pastes (no ``[...]`` placeholders)."""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow  # about 2 minutes on 2 cores: COLMAP, triangulation, bundle adjustment, 300 iterations


def stage_commands(readme: str) -> tuple[list[str], list[str]]:
    """(commands to run, commands left out as marked) of the README's stage block."""
    block = readme[readme.index("## Stages, one command each"):]
    block = block[block.index("```bash") + 7:]
    block = block[: block.index("```")]
    block = re.sub(r"\\\n\s*", "", block)  # continuation lines
    run, left_out = [], []
    for line in block.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        code, _, comment = line.partition("  #")
        if comment.strip().startswith("needs "):
            left_out.append(code.strip())
            continue
        run.append(code.strip())
    return run, left_out


def view_command(readme: str) -> str:
    """The command of "Look at a model", without its comment."""
    block = readme[readme.index("## Look at a model"):]
    block = block[block.index("```bash") + 7:]
    block = re.sub(r"\\\n\s*", "", block[: block.index("```")]).strip()
    assert len(block.splitlines()) == 1, block
    return block.partition("  #")[0].strip()


def test_stage_block_parses():
    run, left_out = stage_commands((ROOT / "README.md").read_text())
    assert any(c.startswith("python -m vggt_init") for c in left_out)
    assert any(c.startswith("python -m bridge --colmap work/posed/sparse/0") for c in run)
    for cmd in run:
        assert cmd.startswith("python "), cmd
        # every path the commands write is under work/
        for opt in re.findall(r"--out (\S+)", cmd):
            assert opt.startswith("work/"), cmd


def test_readme_stage_commands_run_verbatim(tmp_path):
    run, _ = stage_commands((ROOT / "README.md").read_text())
    (tmp_path / "workflow").symlink_to(ROOT / "workflow")
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "HF_HUB_OFFLINE": "1"}
    for cmd in run:
        argv = shlex.split(cmd)
        argv[0] = sys.executable
        proc = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, f"{cmd}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    view = view_command((ROOT / "README.md").read_text())
    argv = shlex.split(view)
    argv[0] = sys.executable
    viewer = subprocess.Popen([*argv, "--no-browser", "--port", "0"], cwd=tmp_path, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = viewer.stdout.readline()
    finally:
        viewer.terminate()
        _, err = viewer.communicate(timeout=30)
    assert line.startswith("[view] serving work/train/model.ply"), f"{view}\n{line}\n{err[-3000:]}"
    work = tmp_path / "work"
    for out in ("scene/split.json", "posed/sparse/0", "bridge/seed.ply", "train/model.ply", "train/train.json",
                "metrics.json", "pose.json"):
        assert (work / out).exists(), out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["work", "workflow"]  # nothing outside work/
