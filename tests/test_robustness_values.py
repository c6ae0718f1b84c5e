"""Values checked where they enter, through the commands a user runs: a trainer config value of
the wrong type or out of its range, a train.json whose background is not a colour, a numeric
flag out of its range, and an image or camera size read from a file beyond camio.limits are each
refused with one line naming the file or flag and the value, exit 2, nothing written to --out;
good values, the boundaries included, are still accepted."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import pytest

from _cli import refused, run
from camio.limits import MAX_IMAGE_SIDE, MAX_PIXELS
from tests._train_scene import write_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict[str, Path]:
    return write_scene(tmp_path_factory.mktemp("values") / "scene", n_views=2, width=16, height=12)


def _train(scene, out: Path, *extra: str):
    return run(["-m", "splat_train", "--seed-ply", str(scene["seed"]), "--cameras", str(scene["cameras"]),
                "--images", str(scene["images"]), "--out", str(out), "--rasterizer", "cpu", "-q", *extra])


# ------------------------------------------------------------------ the trainer's --config
def _refuses_config(scene, tmp_path, key, value):
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({key: value}))  # NaN and Infinity as Python's json writes them
    out = tmp_path / "out"
    refused(_train(scene, out, "--config", str(cfg)), str(cfg), key, repr(value))
    assert not out.exists()


def _ids(cases) -> list[str]:
    return [f"{k}={v!r}".replace(" ", "") for k, v in cases]


_RATES = [("lr_opacity", -1), ("lr_sh_dc", float("nan")), ("lr_position_init", float("inf")), ("lr_pose", "0.1"),
          ("noise_lr", -5e5), ("adam_eps", 0)]


@pytest.mark.parametrize("key, value", _RATES, ids=_ids(_RATES))
def test_train_refuses_a_learning_rate_that_is_negative_or_not_a_finite_number(scene, tmp_path, key, value):
    _refuses_config(scene, tmp_path, key, value)


_ITERATIONS = [("iterations", True), ("iterations", "100"), ("iterations", 0), ("iterations", 2.5),
               ("iterations", -10), ("iterations", [100])]


@pytest.mark.parametrize("key, value", _ITERATIONS, ids=_ids(_ITERATIONS))
def test_train_refuses_iterations_that_are_not_a_positive_integer(scene, tmp_path, key, value):
    _refuses_config(scene, tmp_path, key, value)


_BACKGROUNDS = [("background", [5, -3, 0]), ("background", [float("nan"), 0, 0]), ("background", [0.5, 0.5]),
                ("background", "white"), ("background", [True, 0, 0]), ("background", [0, 0, float("inf")]),
                ("background", 1)]


@pytest.mark.parametrize("key, value", _BACKGROUNDS, ids=_ids(_BACKGROUNDS))
def test_train_refuses_a_background_that_is_not_three_values_in_0_1(scene, tmp_path, key, value):
    _refuses_config(scene, tmp_path, key, value)


_FRACTIONS = [("dropout_rate", 1.0), ("lambda_dssim", 1.5), ("opacity_reset_value", -0.1), ("prune_opacity", 2),
              ("opacity_decay", 0), ("depth_ramp_fraction", float("nan")), ("binocular_from_fraction", 1.01)]


@pytest.mark.parametrize("key, value", _FRACTIONS, ids=_ids(_FRACTIONS))
def test_train_refuses_a_probability_or_fraction_outside_its_interval(scene, tmp_path, key, value):
    _refuses_config(scene, tmp_path, key, value)


_COUNTS = [("seed", -1), ("num_threads", -2), ("downsample", 0), ("sh_degree", 4), ("densify_every", 0),
           ("eval_every", -1), ("max_gaussians", 0), ("depth_min_samples", 1), ("checkpoint_every", 1.5),
           ("gaussians_per_pixel", float("-inf")), ("pose_refine", 1), ("random_background", "yes"),
           ("eval_lpips", "false")]


@pytest.mark.parametrize("key, value", _COUNTS, ids=_ids(_COUNTS))
def test_train_refuses_a_count_period_or_switch_of_the_wrong_type_or_range(scene, tmp_path, key, value):
    _refuses_config(scene, tmp_path, key, value)


def test_train_refuses_a_config_file_that_is_not_json_naming_it(scene, tmp_path):
    cfg = tmp_path / "cfg.json"
    cfg.write_text('{"iterations": 5,')
    out = tmp_path / "out"
    refused(_train(scene, out, "--config", str(cfg)), str(cfg), "JSON")
    assert not out.exists()


def test_train_accepts_config_values_at_their_boundaries(scene, tmp_path):
    """Zero rates and weights, fractions 0 and 1, a white background, the highest SH degree."""
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"iterations": 2, "lr_rotation": 0, "lambda_dssim": 1, "background": [1, 1, 1],
                               "dropout_rate": 0, "prune_opacity": 0, "opacity_decay": 1, "sh_degree": 3,
                               "binocular_from_fraction": 1.0, "seed": 0, "densify_until": 0}))
    proc = _train(scene, tmp_path / "out", "--config", str(cfg))
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((tmp_path / "out" / "train.json").read_text())
    assert summary["config"]["background"] == [1.0, 1.0, 1.0] and summary["config"]["lr_rotation"] == 0


# ------------------------------------------------------------------ train.json beside a model
_BAD_TRAIN_JSON = {
    "nan": '{"config": {"background": [NaN, 0, 0]}}',
    "above_one": '{"config": {"background": [2, 0, 0]}}',
    "negative": '{"config": {"background": [0, -0.5, 0]}}',
    "two_values": '{"config": {"background": [0, 0]}}',
    "a_word": '{"config": {"background": "mean"}}',
    "not_json": '{"config": ',
    "a_list": '[1, 2, 3]',
    "config_not_object": '{"config": 7}',
}


@pytest.fixture()
def model(scene, tmp_path) -> Path:
    m = tmp_path / "run" / "model.ply"
    m.parent.mkdir()
    m.write_bytes(scene["seed"].read_bytes())  # a 3DGS PLY, as a trained model is
    return m


@pytest.mark.parametrize("case", sorted(_BAD_TRAIN_JSON))
@pytest.mark.parametrize("command", ["render", "testpose"])
def test_render_and_testpose_refuse_a_train_json_whose_background_is_no_colour(scene, model, tmp_path, case,
                                                                              command):
    (model.parent / "train.json").write_text(_BAD_TRAIN_JSON[case])
    out = tmp_path / "out"
    args = ["-m", "splat_train", command, "--model", str(model), "--cameras", str(scene["cameras"]), "--out", str(out)]
    if command == "testpose":
        args += ["--images", str(scene["images"])]
    refused(run(args), str(model.parent / "train.json"))
    assert not out.exists()


def test_render_refuses_a_train_json_it_cannot_read(scene, model, tmp_path):
    (model.parent / "train.json").mkdir()  # not a file: reading it fails (as root, no mode bits would)
    out = tmp_path / "out"
    refused(run(["-m", "splat_train", "render", "--model", str(model), "--cameras", str(scene["cameras"]),
                 "--out", str(out)]), str(model.parent / "train.json"), "cannot be read")
    assert not out.exists()


@pytest.mark.parametrize("train_json, colour", [(None, "0,0,0 (black: no train.json"),
                                                ('{"config": {"background": [1, 1, 1]}}', "1,1,1 ("),
                                                ('{"config": {}}', "0,0,0 (black")],
                         ids=["no_train_json", "white", "no_colour"])
def test_render_draws_on_the_train_json_colour_or_black_without_one(scene, model, tmp_path, train_json, colour):
    if train_json is not None:
        (model.parent / "train.json").write_text(train_json)
    proc = run(["-m", "splat_train", "render", "--model", str(model), "--cameras", str(scene["cameras"]),
                "--out", str(tmp_path / "out")])
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"background {colour}" in proc.stderr
    assert len(list((tmp_path / "out").glob("*.png"))) == 2


# ------------------------------------------------------------------ numeric flags
_TRAIN = ["-m", "splat_train", "--seed-ply", "s.ply", "--cameras", "c", "--images", "i"]
_RENDER = ["-m", "splat_train", "render", "--model", "m", "--cameras", "c"]
_TESTPOSE = ["-m", "splat_train", "testpose", "--model", "m", "--cameras", "c", "--images", "i"]
_COLMAP = ["-m", "evaluation.initialisers.colmap_baseline", "--images", "i", "--names", "a.png", "b.png"]
_BRIDGE = ["-m", "bridge", "--pred", "p.npz"]
_ORACLE = ["-m", "evaluation.initialisers.oracle", "--scene", "s"]
_MVS = ["-m", "evaluation.initialisers.mvs", "--scene", "s", "--names", "a.png"]
_VGGT = ["-m", "vggt_init", "--images", "i"]
_FLAGS = {
    "colmap": [(_COLMAP, "--threads", "-4"), (_COLMAP, "--max-num-features", "-1"),
               (_COLMAP, "--max-image-size", "nan"), (_COLMAP, "--seed", "-1"), (_COLMAP, "--repeats", "0"),
               (_COLMAP, "--max-rel-rot-deg", "inf"), (_COLMAP, "--fallback-min-points", "-3"),
               (_COLMAP, "--seeds", "1.5")],
    "splat_train": [(_TRAIN, "--iterations", "true"), (_TRAIN, "--iterations", "0"), (_TRAIN, "--iterations", "1e3"),
                    (_TRAIN, "--threads", "-1"), (_TRAIN, "--downsample", "0"), (_TRAIN, "--seed", "-5"),
                    (_TRAIN, "--eval-every", "-200"), (_TRAIN, "--checkpoint-every", "ten"),
                    (_TRAIN, "--kernel-threads", "-1"), (_RENDER, "--width", "0"),
                    (_RENDER, "--height", str(MAX_IMAGE_SIDE + 1)), (_TESTPOSE, "--lr", "nan"),
                    (_TESTPOSE, "--lr", "0"), (_TESTPOSE, "--steps", "-1"), (_TESTPOSE, "--patience", "-1")],
    "bridge": [(_BRIDGE, "--alpha-min", "1.5"), (_BRIDGE, "--alpha-max", "0"), (_BRIDGE, "--uniform-alpha", "nan"),
               (_BRIDGE, "--stride", "0"), (_BRIDGE, "--percentile", "100"), (_BRIDGE, "--voxel-size", "inf"),
               (_BRIDGE, "--seed", "-3"), (_BRIDGE, "--max-points", "0"), (_BRIDGE, "--outlier-std", "-1"),
               (_BRIDGE, "--depth-prior-samples", "0")],
    "camio": [(["-m", "camio", "synth"], "--views", "0"), (["-m", "camio", "synth"], "--width", "999999"),
              (["-m", "camio", "synth"], "--arc-deg", "nan"), (["-m", "camio", "synth"], "--supersample", "0"),
              (["-m", "camio", "convert", "--src", "s"], "--downsample", "0"),
              (["-m", "camio", "convert", "--src", "s"], "--max-size", "-1"),
              (["-m", "camio", "split", "--scene", "s"], "--n", "0")],
    "evaluation": [(["-m", "evaluation", "pose", "--pred", "p", "--ref", "r"], "--n", "-2"),
                   (["-m", "evaluation", "pose", "--pred", "p", "--ref", "r"], "--max-ate-rel-radius", "0"),
                   (["-m", "evaluation", "align", "--pred", "p", "--ref", "r", "--train-names", "t"],
                    "--image-scale", "0"),
                   (_ORACLE, "--outlier-frac", "1.5"), (_ORACLE, "--rot-deg", "-1"), (_ORACLE, "--conf-scale", "nan"),
                   (["-m", "evaluation.initialisers.posed", "--scene", "s"], "--threads", "0"),
                   (["-m", "evaluation.initialisers.random_init", "--cameras", "c"], "--points", "0"),
                   (["-m", "evaluation.initialisers.random_init", "--cameras", "c"], "--near", "-1"),
                   (["-m", "evaluation.initialisers.ba_init", "--init", "p", "--images", "i"], "--min-points", "0"),
                   (_MVS, "--tol-rel", "nan"), (_MVS, "--window", "1"), (_MVS, "--max-size", "8")],
    "vggt_init": [(_VGGT, "--image-size", "5"), (_VGGT, "--max-memory-gb", "-1"), (_VGGT, "--threads", "-1"),
                  (_VGGT, "--frames-chunk", "0"), (_VGGT, "--max-points", "inf")],
}


def _flag_ids(cases) -> list[str]:
    return [f"{cmd[1].rsplit('.', 1)[-1]}{'-' + cmd[2] if len(cmd) > 2 and not cmd[2].startswith('-') else ''}"
            f"{flag}={value}" for cmd, flag, value in cases]


def _refuses_flag(tmp_path, cmd, flag, value):
    """Exit 2 with argparse's one error line naming the flag and the value, before the command
    does anything."""
    out = tmp_path / "out"
    line = refused(run([*cmd, "--out", str(out), flag, value]), f"argument {flag}", repr(value))
    assert "must be" in line
    assert not out.exists()


@pytest.mark.parametrize("cmd, flag, value", _FLAGS["colmap"], ids=_flag_ids(_FLAGS["colmap"]))
def test_colmap_baseline_refuses_a_flag_out_of_range_instead_of_recording_a_failed_run(tmp_path, cmd, flag, value):
    """--threads -4 used to run, fail inside COLMAP, exit 0 and count as a failed reconstruction."""
    _refuses_flag(tmp_path, cmd, flag, value)


@pytest.mark.parametrize("cmd, flag, value", _FLAGS["splat_train"], ids=_flag_ids(_FLAGS["splat_train"]))
def test_train_render_and_testpose_refuse_a_flag_out_of_range(tmp_path, cmd, flag, value):
    _refuses_flag(tmp_path, cmd, flag, value)


@pytest.mark.parametrize("cmd, flag, value", _FLAGS["bridge"], ids=_flag_ids(_FLAGS["bridge"]))
def test_bridge_refuses_a_flag_out_of_range(tmp_path, cmd, flag, value):
    _refuses_flag(tmp_path, cmd, flag, value)


@pytest.mark.parametrize("cmd, flag, value", _FLAGS["camio"], ids=_flag_ids(_FLAGS["camio"]))
def test_camio_refuses_a_flag_out_of_range(tmp_path, cmd, flag, value):
    _refuses_flag(tmp_path, cmd, flag, value)


@pytest.mark.parametrize("cmd, flag, value", _FLAGS["evaluation"], ids=_flag_ids(_FLAGS["evaluation"]))
def test_evaluation_and_initialisers_refuse_a_flag_out_of_range(tmp_path, cmd, flag, value):
    _refuses_flag(tmp_path, cmd, flag, value)


@pytest.mark.parametrize("cmd, flag, value", _FLAGS["vggt_init"], ids=_flag_ids(_FLAGS["vggt_init"]))
def test_vggt_init_refuses_a_flag_out_of_range(tmp_path, cmd, flag, value):
    _refuses_flag(tmp_path, cmd, flag, value)


_GOOD = [(_COLMAP, ["--threads", "0", "--max-num-features", "16", "--max-image-size", "16", "--seed", "0"]),
         (_ORACLE, ["--outlier-frac", "1", "--rot-deg", "0", "--conf-noise", "0"]),
         (_BRIDGE, ["--alpha-min", "0.5", "--alpha-max", "0.5", "--percentile", "0", "--stride", "1"]),
         (_TESTPOSE, ["--steps", "0", "--patience", "0", "--lr", "1e-9"]),
         (_VGGT, ["--image-size", "14", "--threads", "0"]),
         (["-m", "camio", "convert", "--src", "s"], ["--max-size", "0", "--n", "1", "2"])]


@pytest.mark.parametrize("cmd, flags", _GOOD, ids=[c[1].rsplit(".", 1)[-1] for c, _ in _GOOD])
def test_flags_at_the_ends_of_their_ranges_are_accepted(tmp_path, cmd, flags):
    """The boundaries parse: the command gets past its flags (and then stops at the missing
    input, naming it, which is not a flag's usage error)."""
    proc = run([*cmd, "--out", str(tmp_path / "out"), *flags])
    assert "argument --" not in proc.stderr and "must be" not in proc.stderr, proc.stderr[-2000:]


# ------------------------------------------------------------------ sizes read from files
def _camera_line(w: int, h: int) -> str:
    return f"1 PINHOLE {w} {h} {0.9 * w} {0.9 * w} {w / 2} {h / 2}\n"


def _text_model(folder: Path, w: int, h: int) -> Path:
    folder.mkdir(parents=True)
    (folder / "cameras.txt").write_text(_camera_line(w, h))
    (folder / "images.txt").write_text("1 1 0 0 0 0 0 0 1 view_00.png\n\n")
    (folder / "points3D.txt").write_text("")
    return folder


def _binary_model(folder: Path, w: int, h: int) -> Path:
    folder.mkdir(parents=True)
    cam = struct.pack("<QiiQQ4d", 1, 1, 1, w, h, 0.9 * w, 0.9 * w, w / 2, h / 2)  # PINHOLE
    (folder / "cameras.bin").write_bytes(cam)
    (folder / "images.bin").write_bytes(struct.pack("<Q", 0))
    (folder / "points3D.bin").write_bytes(struct.pack("<Q", 0))
    return folder


_HUGE = [(60000, 45000), (MAX_IMAGE_SIDE + 1, 10), (20000, 20000)]  # a side over the limit; too many pixels


@pytest.mark.parametrize("w, h", _HUGE, ids=[f"{w}x{h}" for w, h in _HUGE])
@pytest.mark.parametrize("kind", ["text", "binary"])
def test_render_refuses_a_colmap_camera_beyond_the_size_limit(model, tmp_path, kind, w, h):
    assert w * h > MAX_PIXELS or max(w, h) > MAX_IMAGE_SIDE
    cams = (_text_model if kind == "text" else _binary_model)(tmp_path / "sparse" / "0", w, h)
    out = tmp_path / "out"
    refused(run(["-m", "splat_train", "render", "--model", str(model), "--cameras", str(cams), "--out", str(out)]),
            str(cams), f"{w}x{h}", "limit")
    assert not out.exists()


def _transforms_scene(root: Path, w, h) -> Path:
    from camio.images import write_image
    import numpy as np

    (root / "images").mkdir(parents=True)
    for i in range(2):
        write_image(root / "images" / f"{i}.png", np.full((12, 16, 3), 0.5, np.float32))
    frames = [{"file_path": f"images/{i}.png", "transform_matrix": [[1, 0, 0, i], [0, 1, 0, 0], [0, 0, 1, 3],
                                                                     [0, 0, 0, 1]]} for i in range(2)]
    (root / "transforms.json").write_text(json.dumps({"w": w, "h": h, "fl_x": 10.0, "frames": frames}))
    return root


_BAD_WH = [(60000, 45000), (MAX_IMAGE_SIDE + 1, 12), (True, 12), ("16", 12), (-16, 12), (16.5, 12),
           (float("nan"), 12), (16, float("inf"))]


@pytest.mark.parametrize("w, h", _BAD_WH, ids=[f"{w!r}x{h!r}" for w, h in _BAD_WH])
def test_convert_refuses_a_transforms_size_that_is_huge_or_no_size(tmp_path, w, h):
    src = _transforms_scene(tmp_path / "src", w, h)
    out = tmp_path / "out"
    refused(run(["-m", "camio", "convert", "--src", str(src), "--out", str(out)]), "transforms.json")
    assert not out.exists()


def test_convert_reads_a_transforms_size_within_the_limit(tmp_path):
    src = _transforms_scene(tmp_path / "src", 16, 12)
    proc = run(["-m", "camio", "convert", "--src", str(src), "--out", str(tmp_path / "out")])
    assert proc.returncode == 0, proc.stderr[-3000:]


def _png_header_only(path: Path, w: int, h: int) -> None:
    """A PNG whose header says w x h, with almost no pixel data (the size is read before them);
    padded with a private chunk so that OpenImageIO's own guard (a header claiming over ~1000x
    the file's size) does not answer first."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    pad = chunk(b"prVt", bytes(w * h * 3 // 900))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + pad + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))


@pytest.mark.parametrize("w, h", _HUGE, ids=[f"{w}x{h}" for w, h in _HUGE])
def test_convert_refuses_an_image_whose_header_is_beyond_the_size_limit(tmp_path, w, h):
    from camio.images import write_image
    import numpy as np

    src = tmp_path / "photos"
    src.mkdir()
    write_image(src / "a.png", np.full((12, 16, 3), 0.5, np.float32))
    _png_header_only(src / "b.png", w, h)
    out = tmp_path / "out"
    refused(run(["-m", "camio", "convert", "--src", str(src), "--out", str(out)]), "b.png", f"{w}x{h}", "limit")
    assert not out.exists()


def test_llff_poses_with_a_huge_image_size_are_refused(tmp_path):
    import numpy as np
    from camio.images import write_image

    src = tmp_path / "llff"
    (src / "images").mkdir(parents=True)
    poses = np.zeros((2, 17))
    for i in range(2):
        write_image(src / "images" / f"{i}.png", np.full((12, 16, 3), 0.5, np.float32))
        m = np.concatenate([np.eye(3), [[i], [0], [0]], [[45000], [60000], [50]]], 1)
        poses[i, :15] = m.reshape(-1)
        poses[i, 15:] = (1, 10)
    np.save(src / "poses_bounds.npy", poses)
    out = tmp_path / "out"
    refused(run(["-m", "camio", "convert", "--src", str(src), "--out", str(out)]), "poses_bounds.npy", "60000x45000")
    assert not out.exists()
