"""Following a training run live: ``python -m splat_train --snapshot-every N`` replaces
``OUT/snapshot.ply`` (its iteration in its header) and ``python -m splat_train view --model OUT``,
started before the run, serves each new snapshot with its iteration (``/state.json``, the
``X-Model-Iteration`` header); the last snapshot is the run's model.ply."""

from __future__ import annotations

import http.client
import json
import subprocess
import sys
import time

import numpy as np
import pytest

from _cli import ENV, ROOT, refused, run
from _train_scene import write_scene
from camio.ply import read_gaussian_ply
from splat_train.training.snapshot import SNAPSHOT_FILE, snapshot_iteration
from splat_train.view import server

ITERATIONS, EVERY = 600, 10  # ~7 s of training on one CPU core at 32x24: several looks of the viewer


def _get(port: int, path: str) -> http.client.HTTPResponse:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=20)
    conn.request("GET", path)
    r = conn.getresponse()
    r.body = r.read()
    conn.close()
    return r


def _train_args(scene: dict, out) -> list[str]:
    return ["-m", "splat_train", "--seed-ply", str(scene["seed"]), "--cameras", str(scene["cameras"]),
            "--images", str(scene["images"]), "--out", str(out), "--device", "cpu", "-q"]


def test_the_viewer_follows_a_training_run(tmp_path):
    try:
        server.check_installed()
    except server.ViewerNotInstalled as e:
        pytest.skip(str(e))
    scene = write_scene(tmp_path / "scene")
    out = tmp_path / "out"
    out.mkdir()  # the run's folder, empty: the viewer waits for its first snapshot
    viewer = subprocess.Popen([sys.executable, "-m", "splat_train", "view", "--model", str(out), "--no-browser",
                               "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              cwd=ROOT, env=ENV)
    trainer = None
    try:
        line = viewer.stdout.readline()
        assert "http://127.0.0.1:" in line and "live" in line, line
        port = int(line.split("http://127.0.0.1:")[1].split("/")[0])
        assert _get(port, "/model.ply").status == 503  # nothing to show yet
        assert json.loads(_get(port, "/state.json").body)["version"] == 0
        trainer = subprocess.Popen([sys.executable, *_train_args(scene, out), "--iterations", str(ITERATIONS),
                                    "--snapshot-every", str(EVERY)], stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True, cwd=ROOT, env=ENV)
        seen: list[int] = []
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            state = json.loads(_get(port, "/state.json").body)
            if state["iteration"] is not None and (not seen or state["iteration"] != seen[-1]):
                seen.append(state["iteration"])
            if trainer.poll() is not None and seen and seen[-1] == ITERATIONS:
                break
            time.sleep(0.05)
        t_out, t_err = trainer.communicate(timeout=60)
        assert trainer.returncode == 0, t_err[-3000:]
        assert len(seen) >= 2 and seen[-1] > seen[0], seen  # a newer iteration than the first served
        assert all(i % EVERY == 0 for i in seen) and seen == sorted(seen), seen
        # the bytes served are the snapshot's, with the iteration their header names
        r = _get(port, "/model.ply")
        assert r.status == 200 and r.getheader("X-Model-Iteration") == str(ITERATIONS)
        assert r.body == (out / SNAPSHOT_FILE).read_bytes() and snapshot_iteration(r.body) == ITERATIONS
    finally:
        if trainer is not None and trainer.poll() is None:
            trainer.kill()
            trainer.communicate()
        viewer.terminate()
        _, v_err = viewer.communicate(timeout=30)
    assert "Traceback" not in v_err, v_err
    # the last snapshot is the run's model
    snap, model = read_gaussian_ply(out / SNAPSHOT_FILE), read_gaussian_ply(out / "model.ply")
    np.testing.assert_array_equal(snap.means, model.means)
    np.testing.assert_array_equal(snap.sh_rest, model.sh_rest)
    assert not list(out.glob(".snapshot*"))  # no temporary left beside it


@pytest.mark.parametrize("bad", ["0", "-5"])
def test_snapshot_every_below_one_is_refused(tmp_path, bad):
    scene = write_scene(tmp_path / "scene")
    proc = run([*_train_args(scene, tmp_path / "out"), "--iterations", "5", "--snapshot-every", bad])
    refused(proc, "--snapshot-every", bad)
    assert not (tmp_path / "out").exists()
