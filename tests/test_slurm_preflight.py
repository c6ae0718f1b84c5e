"""The cluster test's preflight (scripts/slurm_test.sh): what it does with /etc/slurm/slurm.conf.

The script links its own slurm.conf into /etc/slurm for the run and removes the link on exit.
A run killed by SIGKILL (a CI timeout, a session that ends) runs no cleanup, and the dangling
link used to turn every later run on that machine into a skip. These tests point the script at
a temporary "/etc" (SLURM_TEST_ETC_CONF) and state folder (SLURM_TEST_TMP) and stop it after
the preflight (SLURM_TEST_PREFLIGHT_ONLY=1), so nothing outside tmp_path is touched and no
daemon starts. The script needs root on Debian; elsewhere it skips (exit 3), and so do these.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "slurm_test.sh"
SKIPPED = 3


def _preflight(tmp_path: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "SLURM_TEST_ETC_CONF": str(tmp_path / "etc" / "slurm.conf"),
           "SLURM_TEST_TMP": str(tmp_path), "SLURM_TEST_PREFLIGHT_ONLY": "1"}
    res = subprocess.run(["bash", str(SCRIPT)], env=env, capture_output=True, text=True, timeout=60)
    if res.returncode == SKIPPED and ("needs root" in res.stdout or "needs Debian" in res.stdout):
        pytest.skip(res.stdout.strip())
    return res


def _state_dir(tmp_path: Path, owner_pid: int | None) -> Path:
    """A state folder as a run of the script leaves it, linked from the temporary /etc."""
    state = tmp_path / "slurm-test.AbC123"
    state.mkdir()
    (state / "slurm.conf").write_text("ClusterName=snaketest\n")
    if owner_pid is not None:
        (state / "owner.pid").write_text(f"{owner_pid}\n")
    (tmp_path / "etc").mkdir(exist_ok=True)
    (tmp_path / "etc" / "slurm.conf").symlink_to(state / "slurm.conf")
    return state


def _dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


@pytest.mark.parametrize("owner", ["dead_pid", "no_pid_file"])
def test_link_left_by_a_killed_run_is_removed_and_the_run_goes_on(tmp_path, owner):
    state = _state_dir(tmp_path, _dead_pid() if owner == "dead_pid" else None)
    res = _preflight(tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "killed run" in res.stdout
    assert not (tmp_path / "etc" / "slurm.conf").is_symlink()
    assert not state.exists()


def test_link_of_a_run_in_progress_is_kept_and_the_test_skips(tmp_path):
    state = _state_dir(tmp_path, os.getpid())  # this process stands for the live run
    res = _preflight(tmp_path)
    assert res.returncode == SKIPPED, res.stdout + res.stderr
    assert (tmp_path / "etc" / "slurm.conf").is_symlink()
    assert (state / "slurm.conf").exists()


@pytest.mark.parametrize("kind", ["file", "foreign_link"])
def test_a_configured_slurm_is_never_touched(tmp_path, kind):
    etc = tmp_path / "etc"
    etc.mkdir()
    conf = etc / "slurm.conf"
    if kind == "file":
        conf.write_text("ClusterName=site\n")
    else:
        site = tmp_path / "site"
        site.mkdir()
        (site / "slurm.conf").write_text("ClusterName=site\n")
        conf.symlink_to(site / "slurm.conf")
    res = _preflight(tmp_path)
    assert res.returncode == SKIPPED, res.stdout + res.stderr
    assert conf.read_text() == "ClusterName=site\n"
    assert conf.is_symlink() == (kind == "foreign_link")


def test_free_conf_passes_the_preflight(tmp_path):
    res = _preflight(tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "is free" in res.stdout
