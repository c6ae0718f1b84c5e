"""The newer commands as a hostile user runs them: ``splat_train export``, ``render --path
--video``, ``view`` on odd names, ``experiments.results_doc``, ``experiments.sparse_views floor``,
``benchmarks.bench_photos`` and ``scripts/photos.py``. Every bad input is exit 2, one line
naming the value and what to do, nothing written; every legitimate one works (docs/robustness.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from _cli import ROOT, refused, run
from _view_scene import make_cameras, make_model
from camio import Camera
from camio.cameras import look_at
from camio.colmap import write_text_model
from camio.images import write_image
from camio.ply import _field_names, write_gaussian_ply


def _listing(root) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _raw_ply(path, n_rest: int, n: int = 10) -> str:
    """A 3DGS-layout PLY with ``n_rest`` f_rest fields (another trainer's, any count)."""
    names = _field_names(n_rest)
    d = np.random.default_rng(0).normal(size=(n, len(names))).astype("<f4") * 0.1
    d[:, names.index("rot_0")] = 1
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n"
    head += "".join(f"property float {x}\n" for x in names) + "end_header\n"
    path.write_bytes(head.encode() + d.tobytes())
    return str(path)


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("models")
    c = make_model(40)
    c.sh_rest = np.clip(c.sh_rest, -0.99, 0.99)
    out = {"root": root, "model": str(write_gaussian_ply(root / "model.ply", c))}
    bad = make_model(40)
    bad.means[0, 1] = np.nan
    out["nan"] = str(write_gaussian_ply(root / "nan.ply", bad))
    bad = make_model(40)
    bad.log_scales[2, 0] = np.inf
    out["inf"] = str(write_gaussian_ply(root / "inf.ply", bad))
    out["empty"] = str(write_gaussian_ply(root / "empty.ply", make_model(0)))
    (root / "text.ply").write_text("a text file\n")
    out["text"] = str(root / "text.ply")
    out["deg4"] = _raw_ply(root / "deg4.ply", 72)
    out["odd"] = _raw_ply(root / "odd.ply", 30)
    cams = make_cameras(48, 36, 4)
    out["cams"] = str(write_text_model(root / "cams", cams))
    out["one"] = str(write_text_model(root / "one", cams[:1]))
    twin = Camera("twin.png", 48, 36, cams[0].K, cams[0].cam_from_world.copy())
    out["same"] = str(write_text_model(root / "same", [cams[0], twin]))
    K = cams[0].K
    out["parallel"] = str(write_text_model(root / "parallel", [
        Camera(f"p{i}.png", 48, 36, K, look_at(np.array([0.5 * i, 0, -3.0]), np.array([0.5 * i, 0, 0])))
        for i in range(3)]))
    return out


def _export(models, fmt, out, model="model") -> object:
    return run(["-m", "splat_train", "export", "--format", fmt, "--out", str(out), models[model]])


# -- splat_train export ---------------------------------------------------------------------

EXPORT_REFUSALS = [  # (id, format, out name, model, needles in the one line)
    ("out-is-model", "ply", "@model", "model", ("is the input MODEL",)),
    ("out-is-folder", "splat", "@folder", "model", ("is a folder",)),
    ("suffix-other-format", "spz", "m.splat", "model", ("ends in .splat", "--format splat", "m.spz")),
    ("suffix-other-format-ply", "splat", "m.ply", "model", ("ends in .ply", "--format ply")),
    ("nan-model", "splat", "n.splat", "nan", ("nan.ply", "non-finite", "positions")),
    ("inf-model", "spz", "i.spz", "inf", ("inf.ply", "non-finite", "log scales")),
    ("zero-gaussians", "splat", "e.splat", "empty", ("empty.ply", "no Gaussians")),
    ("not-a-ply", "splat", "t.splat", "text", ("text.ply", "not a PLY")),
    ("model-a-folder", "splat", "f.splat", "root", ("is a folder, not a file", "name the file (it holds")),
    ("sh-degree-4-to-ply", "ply", "d.ply", "deg4", ("d.ply", "SH degree 4", "degree 3 at most")),
    ("sh-degree-4-to-spz", "spz", "d.spz", "deg4", ("d.spz", "SH degree 4", "--format splat")),
    ("f-rest-count-no-degree", "splat", "o.splat", "odd", ("odd.ply", "30 f_rest", "3DGS layout")),
    ("name-too-long", "splat", "a" * 300 + ".splat", "model", ("306 bytes", "shorter name")),
    ("name-leaves-no-room-for-temporary", "splat", "b" * 244 + ".splat", "model", ("250 bytes", "shorter name")),
    ("path-too-long", "splat", "/".join(["c" * 200] * 25) + ".splat", "model", ("longer than", "shorter path")),
]


@pytest.mark.parametrize("case,fmt,name,model,needles", EXPORT_REFUSALS, ids=[c[0] for c in EXPORT_REFUSALS])
def test_export_refuses(models, tmp_path, case, fmt, name, model, needles):
    (tmp_path / "folder").mkdir()
    out = models["model"] if name == "@model" else tmp_path / name.replace("@", "")
    before, model_bytes = _listing(tmp_path), open(models["model"], "rb").read()
    refused(_export(models, fmt, out, model), *needles)
    assert _listing(tmp_path) == before  # nothing written, not even a temporary
    assert open(models["model"], "rb").read() == model_bytes


def test_export_legitimate_outs(models, tmp_path):
    """A missing folder is made; a rerun replaces its own file; an upper-case suffix is the
    format's; a suffix of no export format writes with a warning; degree 4 goes to .splat."""
    out = tmp_path / "new" / "deeper" / "m.splat"
    for _ in range(2):
        p = _export(models, "splat", out)
        assert p.returncode == 0 and out.stat().st_size == 32 * 40, p.stderr
    p = _export(models, "spz", tmp_path / "M.SPZ")
    assert p.returncode == 0 and "does not end" not in p.stderr, p.stderr
    p = _export(models, "splat", tmp_path / "m.bin")
    assert p.returncode == 0 and "does not end in .splat" in p.stderr, p.stderr
    p = _export(models, "splat", tmp_path / "d.splat", "deg4")
    assert p.returncode == 0 and (tmp_path / "d.splat").stat().st_size == 32 * 10, p.stderr


def test_export_never_replaces_a_users_file(models, tmp_path):
    (tmp_path / "mine.ply").write_bytes(b"the user's own")
    refused(_export(models, "ply", tmp_path / "mine.ply"), "mine.ply", "not written by")
    assert (tmp_path / "mine.ply").read_bytes() == b"the user's own"


# -- splat_train render --path --video ------------------------------------------------------

def _video(models, cams, video, *extra) -> object:
    return run(["-m", "splat_train", "render", "--model", models["model"], "--cameras", models[cams],
                "--width", "32", "--height", "24", "--frames", "2", *extra,
                *(["--video", str(video)] if video is not None else [])])


VIDEO_REFUSALS = [  # (id, cameras, video name, extra flags, needles)
    ("frames-0", "cams", "v.mp4", ("--path", "orbit", "--frames", "0"), ("--frames",)),
    ("frames-huge", "cams", "v.mp4", ("--path", "orbit", "--frames", "100000000"), ("--frames", "10000")),
    ("one-camera-interpolate", "one", "v.mp4", ("--path", "interpolate"), ("one", "at least 2", "--out")),
    ("one-camera-orbit", "one", "v.mp4", ("--path", "orbit"), ("one", "at least 2")),
    ("identical-cameras-orbit", "same", "v.mp4", ("--path", "orbit"), ("same", "do not meet", "interpolate")),
    ("parallel-axes-orbit", "parallel", "v.mp4", ("--path", "orbit"), ("parallel", "do not meet", "interpolate")),
    ("gif-suffix", "cams", "v.gif", ("--path", "orbit"), ("v.gif", ".mp4")),
    ("no-suffix", "cams", "video", ("--path", "orbit"), ("video", "must end in .mp4")),
    ("video-over-model", "cams", "@model", ("--path", "orbit"), ("model.ply", "must end in .mp4")),
    ("video-inside-cameras", "cams", "@cams/v.mp4", ("--path", "orbit"), ("inside the input --cameras",)),
    ("video-without-path", "cams", "v.mp4", (), ("--path and --video go together",)),
    ("path-without-video", "cams", None, ("--path", "orbit"), ("--path and --video go together",)),
    ("path-with-out", "cams", "v.mp4", ("--path", "orbit", "--out", "@pngs"), ("--video FILE, not --out",)),
]


@pytest.mark.parametrize("case,cams,name,extra,needles", VIDEO_REFUSALS, ids=[c[0] for c in VIDEO_REFUSALS])
def test_video_refuses(models, tmp_path, case, cams, name, extra, needles):
    video = None if name is None else (models["model"] if name == "@model" else
                                       models["cams"] + name[5:] if name.startswith("@cams") else tmp_path / name)
    extra = tuple(str(tmp_path / "pngs") if x == "@pngs" else x for x in extra)
    before, inputs = _listing(tmp_path), _listing(models["root"])
    refused(_video(models, cams, video, *extra), *needles)
    assert _listing(tmp_path) == before and _listing(models["root"]) == inputs


def test_video_legitimate(models, tmp_path):
    """Two identical cameras interpolate to a still video; a missing folder is made; a rerun
    replaces its own video; .MP4 is mp4."""
    from camio.video import count_frames

    out = tmp_path / "new" / "still.mp4"
    for _ in range(2):
        p = _video(models, "same", out, "--path", "interpolate")
        assert p.returncode == 0, p.stderr
    assert count_frames(out) == 3
    p = _video(models, "cams", tmp_path / "O.MP4", "--path", "orbit")
    assert p.returncode == 0 and count_frames(tmp_path / "O.MP4") == 2, p.stderr


# -- splat_train view on odd names ----------------------------------------------------------

@pytest.mark.parametrize("fmt", ["ply", "splat", "spz"])
def test_view_serves_a_model_whose_path_has_spaces_quotes_and_unicode(models, tmp_path, fmt):
    from _viewer import Viewer

    folder = tmp_path / "my \"quoted\" 'model' é 模型"
    path = folder / f"m é.{fmt}"
    assert _export(models, fmt, path).returncode == 0
    v = Viewer("--model", str(path))
    try:
        r = v.get(f"/model.{fmt}")
        assert r.status == 200 and r.body == path.read_bytes()
        assert json.loads(v.get("/state.json").body)["file"] == path.name
    finally:
        _, err = v.stop()
    assert "Traceback" not in err and err.strip() == "", err


# -- experiments.results_doc and experiments.sparse_views --------------------------------------

def test_results_doc_refuses_a_page_it_did_not_write(tmp_path):
    records = ROOT / "experiments" / "records"
    (tmp_path / "notes.md").write_text("my notes\n")
    (tmp_path / "link.md").symlink_to(tmp_path / "notes.md")
    (tmp_path / "folder").mkdir()
    for name, needle in (("notes.md", "not written by this command"), ("link.md", "symbolic link"),
                         ("folder", "not a file"), ("notes.md/r.md", "is a file, not a folder")):
        p = run(["-m", "experiments.results_doc", "--doc", str(tmp_path / name), "--records", str(records)])
        refused(p, name, needle)
    assert (tmp_path / "notes.md").read_text() == "my notes\n"
    for flag in ("--records", "--bench-records"):
        for records_arg, needle in ((tmp_path / "nowhere", "does not exist"), (tmp_path / "notes.md", "is not a folder")):
            p = run(["-m", "experiments.results_doc", "--doc", str(tmp_path / "r.md"), flag, str(records_arg)])
            refused(p, str(records_arg), needle, flag)
    assert not (tmp_path / "r.md").exists()
    for _ in range(2):  # a new page, then its rerun over its own page
        p = run(["-m", "experiments.results_doc", "--doc", str(tmp_path / "new" / "r.md"), "--records", str(records)])
        assert p.returncode == 0, p.stderr


def test_seeds_report_refuses_a_page_it_did_not_write(tmp_path):
    (tmp_path / "notes.md").write_text("my notes\n")
    p = run(["-m", "experiments.sparse_views.seeds", "report", "--records", str(tmp_path / "rec"),
             "--doc", str(tmp_path / "notes.md")])
    refused(p, "notes.md", "not written by this command")
    assert (tmp_path / "notes.md").read_text() == "my notes\n" and not (tmp_path / "rec").exists()
    for _ in range(2):  # a new page, then its rerun over its own page
        p = run(["-m", "experiments.sparse_views.seeds", "report", "--records", str(tmp_path / "rec"),
                 "--doc", str(tmp_path / "seeds.md")])
        assert p.returncode == 0, p.stderr


def test_sparse_views_floor_refuses_bad_folders(tmp_path):
    (tmp_path / "file").write_text("x\n")
    inside = ROOT / "floor_work_of_a_test"
    cases = [(("--records", str(tmp_path / "rec")), ("--work", str(inside)), ("lies inside the repository", "work/")),
             (("--records", str(tmp_path / "rec")), ("--work", str(tmp_path / "file")), ("--work", "not a folder")),
             (("--records", str(tmp_path / "file")), ("--work", str(tmp_path / "w")), ("--records", "not a folder"))]
    for records, work, needles in cases:
        p = run(["-m", "experiments.sparse_views", *records, "floor", "--role", "tuning", "--scenes", "synthetic",
                 "--n", "3", *work])
        refused(p, *needles)
    assert not inside.exists() and not (tmp_path / "rec").exists() and not (tmp_path / "w").exists()


# -- benchmarks.bench_photos and scripts/photos.py ------------------------------------------

@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ph") / "my \"quoted\" 'photos' dir"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(4):
        write_image(folder / f"p{i}.png", rng.uniform(size=(96, 128, 3)).astype(np.float32))
    return folder


BENCH_REFUSALS = [  # (id, args, needles)
    ("fewer-photos-than-count", ("@photos", "--count", "8"), ("holds 4 photos", "--count 4")),
    ("count-0", ("@photos", "--count", "0"), ("--count must be >= 1",)),
    ("a-file", ("@file",), ("is not a folder",)),
    ("a-missing-folder", ("@missing",), ("is not a folder",)),
    ("no-photos", ("@empty",), ("holds no photos",)),
    ("work-missing", ("@photos", "--count", "2", "--work", "@missing"), ("--work", "not a folder")),
    ("out-a-folder", ("@photos", "--count", "2", "--out", "@empty"), ("--out", "is a folder")),
]


@pytest.mark.parametrize("case,args,needles", BENCH_REFUSALS, ids=[c[0] for c in BENCH_REFUSALS])
def test_bench_photos_refuses(photos, tmp_path, case, args, needles):
    (tmp_path / "file").write_text("x\n")
    (tmp_path / "empty").mkdir()
    where = {"@photos": str(photos), "@file": str(tmp_path / "file"), "@missing": str(tmp_path / "missing"),
             "@empty": str(tmp_path / "empty")}
    before = _listing(tmp_path)
    refused(run(["-m", "benchmarks.bench_photos", *[where.get(a, a) for a in args]]), *needles)
    assert _listing(tmp_path) == before


PHOTOS_REFUSALS = [  # (id, extra flags, needles)
    ("max-size-negative", ("--max-size", "-5"), ("--max-size", "-5")),
    ("max-size-huge", ("--max-size", "100000000"), ("--max-size", "up to 32768", "100000000")),
    ("iterations-0", ("--iterations", "0"), ("--iterations must be at least 1",)),
]


@pytest.mark.parametrize("case,extra,needles", PHOTOS_REFUSALS, ids=[c[0] for c in PHOTOS_REFUSALS])
def test_photos_refuses(photos, tmp_path, case, extra, needles):
    refused(run(["scripts/photos.py", str(photos), "-n", "--out", str(tmp_path / "out"), *extra]), *needles)
    assert not (tmp_path / "out").exists()


def test_photos_folder_of_only_unsupported_files(tmp_path):
    folder = tmp_path / "unsupported"
    folder.mkdir()
    for name in ("a.heic", "b.txt", "c.raw"):
        (folder / name).write_bytes(b"x")
    refused(run(["scripts/photos.py", str(folder), "-n", "--out", str(tmp_path / "o1")]), "a.heic", "JPEG")
    (folder / "a.heic").unlink()
    refused(run(["scripts/photos.py", str(folder), "-n", "--out", str(tmp_path / "o2")]), "no images", "unsupported")
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()


def test_photos_dry_run_on_a_folder_named_with_spaces_and_quotes(photos, tmp_path):
    p = run(["scripts/photos.py", str(photos), "-n", "--out", str(tmp_path / "out")], timeout=300)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    assert "Traceback" not in p.stdout + p.stderr
