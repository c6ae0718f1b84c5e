"""Stop signals through every stage command (runtime.stops, runtime.outdir.run_stage).

Each stage command is started the way Snakemake, SLURM or a user starts it, on a small
generated input; once it is working (a file or a log line shows it, after its heavy imports:
where a stage uses pycolmap, pycolmap is loaded, so glog's own SIGTERM handler was installed),
it gets SIGTERM, SIGINT or SIGHUP. It must end with exit code 128 + the signal and one line
naming the signal, no traceback, no native crash dump ("***"), and leave nothing half-made in
its output folder or beside it: no temporary file or folder, no lock, a marker saying the run
did not finish (a rerun removes what it had written).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import pytest

from _cli import ENV, ROOT
from runtime.ledger import LEDGER, LOCK, MARKER

SIGNALS = [signal.SIGTERM, signal.SIGINT, signal.SIGHUP]
READY_S = 240  # generous: the machine may be loaded; the command is stopped as soon as it is ready


def _stop_signals_default() -> None:
    """In the child: the stop signals at their defaults, whatever the test runner inherited
    (``nohup`` ignores SIGHUP; a background job ignores SIGINT; an ignored signal stays so)."""
    for s in SIGNALS:
        signal.signal(s, signal.SIG_DFL)


def _mapped(pid: int, library: str) -> bool:
    """Has process ``pid`` loaded a shared library whose path holds ``library``?"""
    try:
        return library in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


class _Run:
    """A stage command running in the background, its stderr collected as it comes."""

    def __init__(self, argv: list[str], cwd: Path = ROOT):
        self.proc = subprocess.Popen([sys.executable, *argv], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                     text=True, cwd=cwd, env=ENV, preexec_fn=_stop_signals_default)
        self.err: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.err.append(line)

    @property
    def text(self) -> str:
        return "".join(self.err)

    def stop_when(self, ready: Callable[["_Run"], bool], sig: int) -> tuple[int, str]:
        deadline = time.monotonic() + READY_S
        while not ready(self):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.proc.kill()
                self.proc.wait()
                self._reader.join(10)
                pytest.fail(f"the command never got to work (exit {self.proc.returncode}):\n{self.text[-3000:]}")
            time.sleep(0.005)
        self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout=READY_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise
        self._reader.join(30)
        return rc, self.text


def _file(pattern: str, root: Path) -> Callable[[_Run], bool]:
    return lambda run: any(root.glob(pattern))


def _line(regex: str) -> Callable[[_Run], bool]:
    return lambda run: re.search(regex, run.text) is not None


def _and(*tests: Callable[[_Run], bool]) -> Callable[[_Run], bool]:
    return lambda run: all(t(run) for t in tests)


def _pycolmap(run: _Run) -> bool:
    return _mapped(run.proc.pid, "pycolmap")


def _torch(run: _Run) -> bool:
    return _mapped(run.proc.pid, "libtorch")


def check_stopped(rc: int, err: str, sig: int, out: Path, stage: str | None) -> None:
    """What a stopped command must look like (module docstring)."""
    name = signal.Signals(sig).name
    assert rc == 128 + sig, err[-3000:]
    assert "Traceback" not in err and "***" not in err, err[-3000:]
    stops = [ln for ln in err.splitlines() if "stopped by" in ln]
    assert len(stops) == 1 and name in stops[0], err[-3000:]
    loud = [ln for ln in err.splitlines()
            if re.search(r"\b(ERROR|WARNING|CRITICAL|Error|error)\b", ln) or "stopped by" in ln]
    assert loud == stops, err[-3000:]  # the stop line is the only complaint
    leftovers = [str(p) for p in out.parent.rglob("*")
                 if ".tmp" in p.name or p.name.startswith(".colmap_work") or p.name == LOCK]
    assert not leftovers, [(p, sorted(os.listdir(p)) if os.path.isdir(p) else None) for p in leftovers]
    if out.is_dir() and (out / MARKER).is_file():
        lines = (out / MARKER).read_text().splitlines()
        # a stopped run is recorded as not finished: a rerun removes what it wrote
        assert lines[0] == stage and (len(lines) == 1 or lines[1] == "#kept"), lines[:3]
    for ledger in out.parent.rglob(LEDGER):  # a file output never written is not recorded as written
        names = [ln.split("\t")[0] for ln in ledger.read_text().splitlines()]
        assert all((ledger.parent / n).is_file() for n in names), (ledger, names)


# --- inputs -----------------------------------------------------------------------------------

TRAIN = ["0001.png", "0002.png", "0003.png", "0004.png", "0005.png", "0006.png", "0007.png", "0009.png",
         "0010.png", "0011.png"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    """A synthetic scene: 12 views, 128 px, exact cameras, a split."""
    from camio.synthetic import write_synthetic_scene

    out = tmp_path_factory.mktemp("signals") / "scene"
    write_synthetic_scene(out, views=12, width=128, seed=0, n_gt_points=5000, n_ref_points=500)
    (out.parent / "train.txt").write_text("".join(f"{n}\n" for n in TRAIN))
    return out


@pytest.fixture(scope="module")
def splats(tmp_path_factory) -> dict:
    """A tiny Gaussian scene for the trainer, the renderer and the test-pose protocol: 24
    training views and 24 held-out ones at 32x24 px."""
    from _train_scene import write_scene

    return write_scene(tmp_path_factory.mktemp("splats"), n_views=24, n_test=24)


@pytest.fixture(scope="module")
def posed(scene, tmp_path_factory) -> Path:
    """The posed initialiser's output on ``scene`` (the bundle adjustment's input)."""
    from _cli import run

    out = tmp_path_factory.mktemp("posed") / "posed"
    proc = run(["-m", "evaluation.initialisers.posed", "--scene", str(scene), "--names", *TRAIN, "--out", str(out)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def renders(tmp_path_factory) -> Path:
    """Two folders of 40 images, 480x360 px: renders/ and gt/ beside it."""
    import numpy as np

    from camio.images import write_image

    root = tmp_path_factory.mktemp("renders")
    rng = np.random.default_rng(0)
    for i in range(40):
        img = rng.uniform(0, 1, (360, 480, 3)).astype(np.float32)
        write_image(root / "gt" / f"v{i:02d}.png", img)
        write_image(root / "renders" / f"v{i:02d}.png", np.clip(img + 0.05, 0, 1))
    return root / "renders"


@pytest.fixture(scope="module")
def big(tmp_path_factory) -> Path:
    """A COLMAP scene folder to convert: 60 noise images of 640x480 px and their cameras."""
    import numpy as np

    from _train_scene import make_cameras
    from camio.colmap import write_text_model
    from camio.images import write_image

    out = tmp_path_factory.mktemp("big") / "src"
    cams = make_cameras(60, 640, 480)
    rng = np.random.default_rng(0)
    for c in cams:
        write_image(out / "images" / c.name, rng.uniform(0, 1, (480, 640, 3)).astype(np.float32))
    write_text_model(out / "sparse" / "0", cams)
    return out


# (stage id, marker stage name or None, argv builder (inputs, out) -> argv, readiness (inputs, out) -> test)
def _stages():
    def colmap(i, o):
        return (["-m", "evaluation.initialisers.colmap_baseline", "--images", str(i["scene"] / "images"),
                 "--names", *TRAIN, "--out", str(o)],
                _and(_file(".colmap_work.*", o), _pycolmap))

    def posed(i, o):
        return (["-m", "evaluation.initialisers.posed", "--scene", str(i["scene"]), "--names", *TRAIN,
                 "--out", str(o), "-v"], _and(_pycolmap, _line(r"incremental_pipeline|triangulat|Triangulat")))

    def mvs(i, o):
        return (["-m", "evaluation.initialisers.mvs", "--scene", str(i["scene"]), "--names", *TRAIN,
                 "--out", str(o)], _and(_torch, _line(r"torch threads")))

    def train(i, o):
        s = i["splats"]
        return (["-m", "splat_train", "--seed-ply", str(s["seed"]), "--cameras", str(s["cameras"]),
                 "--images", str(s["images"]), "--out", str(o), "--iterations", "100000",
                 "--checkpoint-every", "10", "--eval-every", "100000", "--device", "cpu"],
                _file("ckpt/*", o))

    def render(i, o):
        s = i["splats"]
        return (["-m", "splat_train", "render", "--model", str(s["seed"]), "--cameras", str(s["test_cameras"]),
                 "--width", "320", "--height", "240", "--out", str(o)], _file("*.png", o))

    def testpose(i, o):
        s = i["splats"]
        return (["-m", "splat_train", "testpose", "--model", str(s["seed"]), "--cameras", str(s["test_cameras"]),
                 "--images", str(s["test_images"]), "--out", str(o), "--steps", "100000", "--patience", "100000"],
                _and(_torch, _line(r"test-pose|testpose|background")))

    def bridge(i, o):
        return (["-m", "bridge", "--colmap", str(i["scene"] / "sparse" / "0"), "--images", str(i["scene"] / "images"),
                 "--out", str(o), "--outlier-removal"], _file("*", o))

    def oracle(i, o):
        return (["-m", "evaluation.initialisers.oracle", "--scene", str(i["scene"]), "--names", *TRAIN,
                 "--out", str(o)], _file(LOCK, o))

    def random_init(i, o):
        return (["-m", "evaluation.initialisers.random_init", "--cameras", str(i["scene"] / "sparse" / "0"),
                 "--image-list", str(i["scene"].parent / "train.txt"), "--points", "3000000", "--out", str(o)],
                _file(LOCK, o))

    def ba_init(i, o):
        return (["-m", "evaluation.initialisers.ba_init", "--init", str(i["posed"]), "--images",
                 str(i["scene"] / "images"), "--image-list", str(i["scene"].parent / "train.txt"),
                 "--seed-points", "triangulated", "--out", str(o)], _and(_file(LOCK, o), _pycolmap))

    def metrics(i, o):
        return (["-m", "evaluation", "images", "--pred", str(i["renders"]), "--gt", str(i["renders"].parent / "gt"),
                 "--lpips-nets", "--out", str(o / "metrics.json")], _and(_torch, _line(r"evaluating \d+ image pairs")))

    def convert(i, o):
        return (["-m", "camio", "convert", "--src", str(i["big"]), "--downsample", "2", "--out", str(o)],
                _file(".out.*.tmp/images/*", o.parent))

    return [
        ("colmap_baseline", "evaluation.colmap_baseline", colmap),
        ("posed", "evaluation.posed", posed),
        ("mvs", "evaluation.initialisers.mvs", mvs),
        ("splat_train", "splat_train", train),
        ("splat_train render", "splat_train render", render),
        ("splat_train testpose", "splat_train testpose", testpose),
        ("bridge", "bridge", bridge),
        ("oracle", "evaluation.oracle", oracle),
        ("random_init", "evaluation.random_init", random_init),
        ("ba_init", "evaluation.ba_init", ba_init),
        ("evaluation images", None, metrics),
        ("camio convert", "camio convert", convert),
    ]


STAGES = _stages()


class _Inputs:
    """The module's input fixtures by name, each made when a stage first asks for it."""

    def __init__(self, request):
        self._request = request

    def __getitem__(self, name: str):
        return self._request.getfixturevalue(name)



@pytest.mark.parametrize("sig", SIGNALS, ids=[s.name for s in SIGNALS])
@pytest.mark.parametrize("stage", STAGES, ids=[s[0].replace(" ", "_") for s in STAGES])
def test_a_stage_stopped_while_it_works_ends_cleanly(request, tmp_path, stage, sig):
    name, marker, build = stage
    out = tmp_path / "out"
    argv, ready = build(_Inputs(request), out)
    rc, err = _Run(argv).stop_when(ready, sig)
    check_stopped(rc, err, sig, out, marker)


def _processes_naming(text: str) -> list[str]:
    """Command lines of the running processes that name ``text``."""
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            args = cmdline.read_bytes().decode(errors="replace").split("\0")
        except OSError:
            continue
        if any(text in a for a in args):
            found.append(" ".join(args))
    return found


@pytest.mark.parametrize("sig", SIGNALS, ids=[s.name for s in SIGNALS])
def test_a_benchmark_runner_passes_the_stop_on_to_its_stage(tmp_path, sig):
    """The recipe study, stopped while its first stage command (``camio synth``) works: the
    stage gets the same signal and ends cleanly first (no temporary folder, no orphan process),
    then the runner ends with one line and 128 + the signal."""
    work = tmp_path / "cell"
    run = _Run(["experiments/recipe_study.py", "--scene", "synthetic", "--n", "3", "--init", "oracle",
                "--iterations", "10", "--variants", "sparse", "--seeds", "0", "--work", str(work)])
    rc, err = run.stop_when(_file(LOCK, work / "scene"), sig)
    check_stopped(rc, err, sig, work / "scene", "camio synth")
    assert not _processes_naming(str(work)), _processes_naming(str(work))
    log = (work / "prepare.log").read_text()
    assert f"stopped by {signal.Signals(sig).name}" in log and "Traceback" not in log, log[-3000:]


def test_a_stage_started_under_nohup_keeps_working_through_a_hangup(splats, tmp_path):
    """``nohup`` ignores SIGHUP before the command starts: the command leaves it ignored, so a
    closed terminal does not stop the training."""
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "splat_train", "--seed-ply", str(splats["seed"]), "--cameras",
                             str(splats["cameras"]), "--images", str(splats["images"]), "--out", str(out),
                             "--iterations", "20", "--checkpoint-every", "5", "--eval-every", "1000",
                             "--device", "cpu"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            cwd=ROOT, env=ENV, preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    deadline = time.monotonic() + READY_S
    while not any(out.glob("ckpt/*")) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    proc.send_signal(signal.SIGHUP)
    _, err = proc.communicate(timeout=READY_S)
    assert proc.returncode == 0 and "stopped by" not in err, err[-3000:]
    assert (out / "model.ply").is_file()


@pytest.fixture(scope="module")
def long_colmap(tmp_path_factory) -> dict:
    """A COLMAP input whose feature extraction and matching take seconds each: 6 synthetic views
    of 640 px (``camio synth``), each copied 7 times under its own name (42 images)."""
    import shutil

    from _cli import run

    root = tmp_path_factory.mktemp("longcolmap")
    proc = run(["-m", "camio", "synth", "--out", str(root / "scene"), "--views", "6", "--width", "640", "-q"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    names = []
    (root / "images").mkdir()
    for src in sorted((root / "scene" / "images").iterdir()):
        for k in range(7):
            names.append(f"c{k}_{src.name}")
            shutil.copy2(src, root / "images" / names[-1])
    return {"images": root / "images", "names": names}


NATIVE_STOPS = [("feature extraction", signal.SIGTERM), ("exhaustive matching", signal.SIGTERM),
                ("feature extraction", signal.SIGINT)]
NATIVE_STOP_S = 4.0  # from the signal to the command's end; the step itself runs far longer


@pytest.mark.parametrize("step,sig", NATIVE_STOPS, ids=[f"{s.replace(' ', '_')}-{g.name}" for s, g in NATIVE_STOPS])
def test_a_stop_inside_a_long_pycolmap_call_ends_the_command_at_once(long_colmap, tmp_path, step, sig):
    """A stop that lands inside one long native pycolmap call (runtime.native.stoppable) ends
    the command within seconds, not when the call returns: exit 128 + the signal, one line and
    nothing else after the step began, no traceback, no process left over, no scratch folder,
    nothing under the output's final names (sparse/, status.json)."""
    out = tmp_path / "out"
    seen: list[float] = []
    sent: list[float] = []

    def ready(run: _Run) -> bool:  # half a second into the step: the native call is under way
        if not seen and f"{step} started" in run.text:
            seen.append(time.monotonic())
        if seen and time.monotonic() - seen[0] > 0.5:
            sent.append(time.monotonic())
            return True
        return False

    run = _Run(["-m", "evaluation.initialisers.colmap_baseline", "--images", str(long_colmap["images"]),
                "--names", *long_colmap["names"], "--out", str(out)])
    rc, err = run.stop_when(ready, sig)
    took = time.monotonic() - sent[0]
    check_stopped(rc, err, sig, out, "evaluation.colmap_baseline")
    after = err.split(f"{step} started\n", 1)[1].splitlines()
    # the stop landed inside the call, and nothing of it speaks afterwards (pycolmap's own
    # interruption logs a glog line "Stopping thread..." and ends only its current image)
    assert len(after) == 1 and "stopped by" in after[0], err[-3000:]
    assert took < NATIVE_STOP_S, (took, err[-3000:])
    assert not _processes_naming(str(out)), _processes_naming(str(out))  # the call's child was reaped
    assert not out.exists() or not {"sparse", "status.json", "work"} & set(os.listdir(out)), os.listdir(out)
