"""Bad input images as a user meets them: each stage's command line, not the library function.

For every stage that reads image files (``python -m vggt_init``, ``python -m
evaluation.initialisers.colmap_baseline``, ``python -m splat_train``, ``python -m evaluation images``) a
damaged image is put among good ones and the command is run in a subprocess. Each must:
exit with a non-zero code, print one error line that names the damaged file, print no Python
traceback, and leave nothing behind in its output folder. The damages: a JPEG cut in half (it
used to pass ``vggt_init`` as half-grey pixels and the COLMAP baseline as a 3/3 "success"), a
PNG cut in half, text bytes named ``.jpg`` and an empty file. Nothing here needs real scenes
or the VGGT checkpoint (images are checked before the checkpoint is looked up).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from _train_scene import write_scene
from camio.images import ImageReadError, read_image, write_image

ROOT = Path(__file__).resolve().parents[1]
KINDS = ("truncated_jpeg", "truncated_png", "text_bytes", "empty_file")


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env["HF_HUB_OFFLINE"] = "1"  # never reach for the network from a test
    env.pop("VGGT_CHECKPOINT", None)
    return env


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], cwd=cwd, env=_env(), capture_output=True,
                          text=True, timeout=300)


def _texture(seed: int, h: int = 96, w: int = 128) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.random((h // 8, w // 8, 3)).astype(np.float32)
    return np.kron(small, np.ones((8, 8, 1), dtype=np.float32))


def _damage(path: Path, kind: str) -> Path:
    """Damage the image at ``path`` (written first as a good image) in place; returns it."""
    if kind in ("truncated_jpeg", "truncated_png"):
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif kind == "text_bytes":
        path.write_text("this is not an image\n")
    elif kind == "empty_file":
        path.write_bytes(b"")
    else:  # pragma: no cover
        raise ValueError(kind)
    return path


def _image_folder(root: Path, kind: str, n: int = 3) -> tuple[Path, list[str], str]:
    """n good textured images, one of them damaged; (folder, names, damaged name)."""
    ext = ".png" if kind == "truncated_png" else ".jpg"
    folder = root / "images"
    names = [f"view_{i}{ext}" for i in range(n)]
    for i, name in enumerate(names):
        write_image(folder / name, _texture(i))
    _damage(folder / names[1], kind)
    return folder, names, names[1]


def _assert_clean_failure(proc: subprocess.CompletedProcess, bad_name: str, out: Path) -> None:
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0, f"exit 0 on a damaged image:\n{text[-3000:]}"
    assert bad_name in proc.stderr, f"the error does not name {bad_name}:\n{text[-3000:]}"
    assert "Traceback" not in text, f"a traceback for a bad input:\n{text[-3000:]}"
    left = sorted(str(p.relative_to(out)) for p in out.rglob("*")) if out.exists() else []
    assert not left, f"outputs left behind after the failure: {left}"


@pytest.mark.parametrize("kind", KINDS)
def test_unit_reader_rejects_damaged_image(tmp_path, kind):
    """The shared reader itself: ImageReadError naming the file, for every damage."""
    folder, _, bad = _image_folder(tmp_path, kind)
    with pytest.raises(ImageReadError, match=bad):
        read_image(folder / bad)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("module", ("vggt_init", "evaluation.initialisers.colmap_baseline"))
def test_image_reading_cli_rejects_damaged_image(tmp_path, module, kind):
    """The two stages that read the training images exit 2 naming the file and write nothing:
    VGGT never preprocesses it, pycolmap never sees it (no status.json at all)."""
    folder, names, bad = _image_folder(tmp_path, kind)
    (tmp_path / "train.txt").write_text("\n".join(names) + "\n")
    out = tmp_path / "out"
    proc = _run(["-m", module, "--images", str(folder), "--image-list",
                 str(tmp_path / "train.txt"), "--out", str(out)], tmp_path)
    _assert_clean_failure(proc, bad, out)
    assert proc.returncode == 2


@pytest.mark.parametrize("kind", ("truncated_png", "text_bytes", "empty_file"))
def test_trainer_cli_rejects_damaged_image(tmp_path, kind):
    sc = write_scene(tmp_path / "scene", n_views=3, n_test=1)
    _damage(sc["images"] / "view_02.png", kind)
    out = tmp_path / "out"
    proc = _run(["-m", "splat_train", "--seed-ply", str(sc["seed"]), "--cameras", str(sc["cameras"]),
                 "--images", str(sc["images"]), "--out", str(out), "--iterations", "2",
                 "--threads", "1"], tmp_path)
    _assert_clean_failure(proc, "view_02.png", out)


def test_trainer_cli_rejects_damaged_held_out_image(tmp_path):
    sc = write_scene(tmp_path / "scene", n_views=3, n_test=1)
    bad = next(sc["test_images"].iterdir())
    _damage(bad, "truncated_png")
    out = tmp_path / "out"
    proc = _run(["-m", "splat_train", "--seed-ply", str(sc["seed"]), "--cameras", str(sc["cameras"]),
                 "--images", str(sc["images"]), "--out", str(out), "--iterations", "2",
                 "--threads", "1", "--test-cameras", str(sc["test_cameras"]),
                 "--test-images", str(sc["test_images"])], tmp_path)
    _assert_clean_failure(proc, bad.name, out)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("side", ("pred", "gt"))
def test_metrics_cli_rejects_damaged_image(tmp_path, kind, side):
    ext = ".png" if kind == "truncated_png" else ".jpg"
    folders = {s: tmp_path / s for s in ("pred", "gt")}
    for i in range(2):
        for s, f in folders.items():
            write_image(f / f"t{i}{ext}", _texture(i))
    bad = _damage(folders[side] / f"t1{ext}", kind)
    out = tmp_path / "metrics" / "metrics.json"
    proc = _run(["-m", "evaluation", "images", "--pred", str(folders["pred"]), "--gt",
                 str(folders["gt"]), "--out", str(out), "--lpips-nets"], tmp_path)
    _assert_clean_failure(proc, bad.name, out.parent)


def test_colmap_baseline_cli_empty_image_list_is_one_line(tmp_path):
    """An empty --image-list: a one-line error, not a traceback from deep inside."""
    folder, _, _ = _image_folder(tmp_path, "truncated_jpeg")
    (tmp_path / "train.txt").write_text("# nothing\n\n")
    out = tmp_path / "out"
    proc = _run(["-m", "evaluation.initialisers.colmap_baseline", "--images", str(folder), "--image-list",
                 str(tmp_path / "train.txt"), "--out", str(out)], tmp_path)
    assert proc.returncode != 0
    assert "train.txt is empty" in proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    assert not out.exists()


def test_vggt_init_cli_empty_image_list_is_one_line(tmp_path):
    folder, _, _ = _image_folder(tmp_path, "truncated_jpeg")
    (tmp_path / "train.txt").write_text("\n")
    out = tmp_path / "out"
    proc = _run(["-m", "vggt_init", "--images", str(folder), "--image-list",
                 str(tmp_path / "train.txt"), "--out", str(out)], tmp_path)
    assert proc.returncode == 2
    assert "is empty" in proc.stderr and "Traceback" not in proc.stdout + proc.stderr
    assert not out.exists()


def test_hub_probe_fails_fast_on_a_closed_port():
    """A closed port is refused at once: the reason names the host, port and error."""
    from vggt_init.checkpoint import hub_unreachable_reason

    reason = hub_unreachable_reason({"HF_ENDPOINT": "http://127.0.0.1:9"}, timeout=2.0)
    assert reason is not None and "127.0.0.1:9" in reason and "ConnectionRefusedError" in reason


def test_hub_probe_is_one_connect_bounded_by_its_timeout(monkeypatch):
    """One name lookup + TCP connect, with the caller's timeout, and no retry: checked on the
    call itself (a wall-clock bound would depend on the machine's load)."""
    import socket

    from vggt_init.checkpoint import hub_unreachable_reason

    calls = []

    def silent_host(address, timeout=None, *args, **kwargs):
        calls.append((address, timeout))
        raise TimeoutError("timed out")

    monkeypatch.setattr(socket, "create_connection", silent_host)
    reason = hub_unreachable_reason({"HF_ENDPOINT": "https://hub.example:8443"}, timeout=2.0)
    assert calls == [(("hub.example", 8443), 2.0)]
    assert reason is not None and "hub.example:8443" in reason and "TimeoutError" in reason


def test_vggt_init_cli_offline_missing_checkpoint_fails_in_seconds(tmp_path):
    """No checkpoint and no hub (HF_HUB_OFFLINE unset): one probe, not ~48 s of retries; the
    message says where to put the file; no traceback; nothing written."""
    folder = tmp_path / "images"
    for i in range(2):
        write_image(folder / f"v{i}.jpg", _texture(i, 56, 56))
    env = _env()
    env.pop("HF_HUB_OFFLINE")
    env["HF_ENDPOINT"] = "http://127.0.0.1:9"  # nothing listens on the discard port
    env["HF_HOME"] = str(tmp_path / "hf_home")  # an empty cache
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "vggt_init", "--images", str(folder), "--out", str(out)],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 2, text[-3000:]
    assert "no VGGT checkpoint found" in proc.stderr and "Traceback" not in text
    # the ~48 s came from huggingface_hub's retries with back-off: the probe must stop the
    # download before any request (one refusal, no retry), which is what makes it seconds
    assert text.count("cannot be reached") == 1 and "127.0.0.1:9" in text, text[-3000:]
    assert "Retrying" not in text and "could not download" not in text, text[-3000:]
    assert not out.exists() or not any(out.rglob("*"))


def test_skip_reason_offline_and_with_checkpoint(tmp_path):
    """The demo's up-front question: why VGGT cannot run here (one sentence), or None."""
    from vggt_init.checkpoint import skip_reason

    env = {"HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf")}
    reason = skip_reason(env)
    assert reason and "HF_HUB_OFFLINE" in reason and "checkpoint" in reason
    unreachable = skip_reason({"HF_ENDPOINT": "http://127.0.0.1:9", "HF_HOME": str(tmp_path / "hf")})
    assert unreachable and "cannot be reached" in unreachable
    ckpt = tmp_path / "model.pt"
    ckpt.write_bytes(b"x")
    assert skip_reason({"VGGT_CHECKPOINT": str(ckpt), "HF_HUB_OFFLINE": "1"}) is None
    bad = skip_reason({"VGGT_CHECKPOINT": str(tmp_path / "nope.pt")})
    assert bad and "nope.pt" in bad


def test_colmap_baseline_ref_is_used_with_a_single_run(tmp_path, monkeypatch):
    """--ref used to be ignored silently unless --repeats >= 2; a single run now evaluates it."""
    import evaluation.initialisers.colmap_repeats as repeats
    from evaluation.initialisers.colmap_baseline import main

    calls = []
    monkeypatch.setattr(repeats, "run_colmap_repeats",
                        lambda images, names, out, seeds, **kw: calls.append((seeds, kw.get("ref"))))
    folder = tmp_path / "images"
    for i in range(3):
        write_image(folder / f"v{i}.jpg", _texture(i))
    assert main(["--images", str(folder), "--names", "v0.jpg", "v1.jpg", "v2.jpg", "--out",
                 str(tmp_path / "out"), "--ref", str(tmp_path / "ref"), "--seed", "4"]) == 0
    assert calls == [([4], str(tmp_path / "ref"))]


def test_colmap_baseline_cli_keeps_pycolmap_chatter_off_the_console(tmp_path):
    """pycolmap's own log (25-60 lines a call) stays out of stdout and, without -v, out of
    stderr too; the stage's own lines remain."""
    folder = tmp_path / "images"
    names = [f"v{i}.jpg" for i in range(3)]
    for i, name in enumerate(names):
        write_image(folder / name, _texture(i))
    out = tmp_path / "out"
    proc = _run(["-m", "evaluation.initialisers.colmap_baseline", "--images", str(folder), "--names", *names,
                 "--out", str(out)], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout == ""
    pycolmap_lines = [ln for ln in proc.stderr.splitlines() if re.match(r"^[IW]\d{8} ", ln)]
    assert not pycolmap_lines, pycolmap_lines[:5]
    assert "COLMAP baseline: success=" in proc.stderr
    assert (out / "status.json").is_file()


# --- the other input rows of the catalogue, through the command a user runs ----------------------

def _cut(path: Path, keep: float) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    return path


def _train_cmd(sc: dict, out: Path, *extra: str) -> list[str]:
    return ["-m", "splat_train", "--seed-ply", str(sc["seed"]), "--cameras", str(sc["cameras"]),
            "--images", str(sc["images"]), "--out", str(out), "--iterations", "2", "--threads", "1", *extra]


def _assert_one_line_error(proc: subprocess.CompletedProcess, *needles: str) -> None:
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    for needle in needles:
        assert needle in proc.stderr, f"{needle!r} not in:\n{proc.stderr[-3000:]}"


@pytest.mark.parametrize("keep", (0.0, 0.05, 0.6))
def test_trainer_cli_truncated_seed_ply(tmp_path, keep):
    """Row 35 at the command line: one line naming the seed, no model.ply."""
    sc = write_scene(tmp_path / "scene", n_views=3)
    _cut(sc["seed"], keep)
    out = tmp_path / "out"
    proc = _run(_train_cmd(sc, out), tmp_path)
    _assert_one_line_error(proc, str(sc["seed"]))
    assert not (out / "model.ply").exists()


@pytest.mark.parametrize("fname", ("cameras.txt", "images.txt"))
def test_trainer_cli_camera_model_cut_mid_line(tmp_path, fname):
    """Rows 10/11 at the command line: a damaged --cameras model is one line, nothing trained."""
    sc = write_scene(tmp_path / "scene", n_views=3)
    f = sc["cameras"] / fname
    f.write_text(f.read_text()[:-7])
    out = tmp_path / "out"
    proc = _run(_train_cmd(sc, out), tmp_path)
    _assert_one_line_error(proc, fname, "truncated")
    assert not (out / "model.ply").exists()


def test_trainer_cli_truncated_newest_checkpoint(tmp_path):
    """Row 36 at the command line: the output rule's ledger sees the checkpoint it wrote has
    changed since, before the trainer reads it: one line naming it, nothing changed (the trainer's
    own "cannot read checkpoint ...; delete it" is the library's, test_faults_corrupt)."""
    sc = write_scene(tmp_path / "scene", n_views=3)
    out = tmp_path / "out"
    cfg = '{"densify_until": 0}'
    first = _run(_train_cmd(sc, out, "--checkpoint-every", "2", "--config", cfg), tmp_path)
    assert first.returncode == 0, first.stderr[-3000:]
    newest = sorted((out / "ckpt").iterdir())[-1]
    _cut(newest, 0.5)
    cmd = _train_cmd(sc, out, "--checkpoint-every", "2", "--config", cfg)
    cmd[cmd.index("--iterations") + 1] = "4"
    proc = _run(cmd, tmp_path)
    _assert_one_line_error(proc, newest.name, "changed since", "nothing was changed")
    assert newest.stat().st_size > 0  # left as it was


def test_vggt_init_cli_truncated_safetensors_checkpoint(tmp_path):
    """Row 18 at the command line: CheckpointFormatError naming the file, exit 2, nothing written."""
    import torch
    from safetensors.torch import save_file

    folder = tmp_path / "images"
    for i in range(2):
        write_image(folder / f"v{i}.jpg", _texture(i, 56, 56))
    ckpt = tmp_path / "model.safetensors"
    save_file({"w": torch.zeros(1000)}, str(ckpt))
    _cut(ckpt, 0.5)
    out = tmp_path / "out"
    proc = _run(["-m", "vggt_init", "--images", str(folder), "--out", str(out), "--checkpoint", str(ckpt)],
                tmp_path)
    _assert_one_line_error(proc, "CheckpointFormatError", str(ckpt))
    assert proc.returncode == 2
    assert not out.exists() or not any(out.rglob("*"))


def test_pose_cli_reference_model_cut_at_a_line_boundary(tmp_path):
    """Row 11 at the command line: `evaluation pose --ref` with images.txt missing its last image."""
    from _train_scene import make_cameras
    from camio.colmap import write_text_model

    pred = write_text_model(tmp_path / "pred", make_cameras(4))
    ref = write_text_model(tmp_path / "ref", make_cameras(4))
    f = ref / "images.txt"
    lines = f.read_text().splitlines(keepends=True)
    f.write_text("".join(lines[:-2]))
    out = tmp_path / "pose" / "pose.json"
    proc = _run(["-m", "evaluation", "pose", "--pred", str(pred), "--ref", str(ref), "--out", str(out)], tmp_path)
    _assert_one_line_error(proc, "the header says 4 images but 3 were read")
    assert not out.exists()


def test_metrics_cli_truncated_lpips_weights(tmp_path):
    """Row 48 at the command line: truncated LPIPS weights are one line naming the file and the
    converter; no metrics.json."""
    from safetensors.torch import save_file

    from imgmetrics.lpips import LPIPS

    weights = tmp_path / "w"
    weights.mkdir()
    save_file(LPIPS("alex").state_dict(), str(weights / "alex.safetensors"), metadata={"net": "alex"})
    _cut(weights / "alex.safetensors", 0.5)
    for s in ("pred", "gt"):
        for i in range(2):
            write_image(tmp_path / s / f"t{i}.png", _texture(i, 32, 32))
    out = tmp_path / "m" / "metrics.json"
    proc = _run(["-m", "evaluation", "images", "--pred", str(tmp_path / "pred"), "--gt", str(tmp_path / "gt"),
                 "--out", str(out), "--lpips-nets", "alex", "--lpips-weights", str(weights)], tmp_path)
    _assert_one_line_error(proc, "alex.safetensors", "lpips_convert")
    assert not out.exists()


@pytest.mark.parametrize("case", ("empty_folder", "truncated_jpeg"))
def test_camio_convert_cli_bad_scene_folder(tmp_path, case):
    """Rows 7 and 1 (inside a scene) at the command line: `camio convert` on a folder scene (a
    photo folder may mix sizes: tests/test_camio_datasets.py)."""
    src = tmp_path / "src" / "images"
    src.mkdir(parents=True)
    needle = {"empty_folder": "no images", "truncated_jpeg": "v1.jpg"}[case]
    if case != "empty_folder":
        for i in range(3):
            write_image(src / f"v{i}.jpg", _texture(i, 96, 128))
        if case == "truncated_jpeg":
            _damage(src / "v1.jpg", "truncated_jpeg")
    out = tmp_path / "out"
    proc = _run(["-m", "camio", "convert", "--src", str(tmp_path / "src"), "--format", "folder",
                 "--out", str(out)], tmp_path)
    _assert_one_line_error(proc, needle)
    assert not out.exists() or not any(out.rglob("*"))


def test_camio_split_cli_too_many_views(tmp_path):
    """Row 9 at the command line: more training views than the pool holds."""
    scene = tmp_path / "scene"
    proc = _run(["-m", "camio", "synth", "--out", str(scene), "--views", "6", "--width", "64"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = tmp_path / "split.json"
    proc = _run(["-m", "camio", "split", "--scene", str(scene), "--n", "3", "40", "--out", str(out)], tmp_path)
    _assert_one_line_error(proc, "40")
    assert not out.exists()


def test_oracle_cli_rejects_damaged_image(tmp_path):
    """The oracle initialiser reads the training images for its colours: same reader, same error."""
    scene = tmp_path / "scene"
    proc = _run(["-m", "camio", "synth", "--out", str(scene), "--views", "6", "--width", "64"], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    names = sorted(p.name for p in (scene / "images").iterdir())[:3]
    _damage(scene / "images" / names[1], "truncated_png")
    out = tmp_path / "out"
    proc = _run(["-m", "evaluation.initialisers.oracle", "--scene", str(scene), "--names", *names, "--out", str(out)],
                tmp_path)
    _assert_clean_failure(proc, names[1], out)
