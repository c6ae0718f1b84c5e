"""`python -m evaluation report` on a photo-folder run (scripts/photos.py): no held-out view, so
the report shows each training photo beside its render with the training-view PSNR, the
training curve, the cameras from above and the model's size, and no held-out section.

The tree is the smallest a photo run leaves (workflow/rules/common.smk layout): the scene's
split.json with no test view, the photos at the working resolution (``converted/images``),
COLMAP's status and cameras, the Bridge's cameras, a trained model.ply and its log.parquet, and
the render of every photo that the rule render_train_views makes with ``python -m splat_train
render``."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import numpy as np

from _cli import run

NAMES = ("IMG_01.png", "IMG_02.png", "IMG_03.png")
W, H = 32, 24


def photo_run(root: Path) -> Path:
    """``root/results`` of one photo scene ``photos/garden`` (3 photos) trained from COLMAP."""
    from camio.cameras import Camera, look_at
    from camio.colmap import write_text_model
    from camio.images import write_image
    from camio.ply import GaussianCloud, write_gaussian_ply
    from splat_train.training.runlog import RunLog

    results = root / "results"
    scene = results / "photos" / "garden"
    scene.mkdir(parents=True)
    (scene / "split.json").write_text(json.dumps({"rule": "manifest", "test": [], "train_pool": list(NAMES),
                                                  "train": {"3": list(NAMES)}}))
    rng = np.random.default_rng(0)
    for name in NAMES:
        write_image(scene / "converted" / "images" / name, rng.uniform(0.2, 0.8, (H, W, 3)).astype(np.float32))
    K = np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]])
    cams = [Camera(name, W, H, K, look_at(np.array([4 * np.sin(a), 0.0, -4 * np.cos(a)]), np.zeros(3))[:3])
            for name, a in zip(NAMES, (-0.4, 0.0, 0.4))]
    run_dir = scene / "n3" / "colmap"
    points = rng.uniform(-1, 1, (200, 3))
    write_text_model(run_dir / "sparse" / "0", cams, points)
    (run_dir / "status.json").write_text(json.dumps({"success": True, "success_paper": True, "aligned_ok": False,
                                                     "registered": 3, "n_images": 3, "points": 200}))
    mode = run_dir / "uniform"
    write_text_model(mode / "bridge" / "sparse" / "0", cams, points)
    (mode / "bridge" / "bridge.json").write_text(json.dumps({"mode": "uniform"}))
    cloud = GaussianCloud.from_points(points, rng.uniform(0, 1, (200, 3)), np.full(200, 0.6), np.full(200, 0.15))
    write_gaussian_ply(mode / "train" / "model.ply", cloud)
    lg = RunLog()
    for it in range(1, 31):
        lg.append(iteration=it, wall_time_s=0.1 * it, loss=0.3 / it, l1=0.2 / it, ssim=0.5, train_psnr=12 + it / 5,
                  num_gaussians=200)
    lg.write_parquet(mode / "train" / "log.parquet")
    (mode / "train" / "train.json").write_text(json.dumps({"num_gaussians": 200, "wall_time_s": 3.0}))
    return results


def _report(results: Path, out: Path) -> str:
    proc = run(["-m", "evaluation", "report", "--results", str(results), "--out", str(out), "--scenes",
                str(results), "-q"], timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return (out / "index.html").read_text()


def _render(results: Path) -> float:
    """render_train_views' command on the run; returns the mean PSNR it logs (float renders)."""
    scene = results / "photos" / "garden"
    mode = scene / "n3" / "colmap" / "uniform"
    proc = run(["-m", "splat_train", "render", "--model", str(mode / "train" / "model.ply"), "--cameras",
                str(mode / "bridge" / "sparse" / "0"), "--images", str(scene / "converted" / "images"),
                "--out", str(mode / "train_renders")], timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return float(re.search(r"mean PSNR (\d+\.\d+) dB", proc.stdout + proc.stderr).group(1))


def test_photo_report_shows_each_photo_beside_its_render(tmp_path):
    results = photo_run(tmp_path)
    mean_psnr = _render(results)
    out = tmp_path / "report"
    page = _report(results, out)
    srcs = re.findall(r'<img src="([^"]+)" alt="([^"]+)"', page)
    for src, _ in srcs:
        assert (out / src).read_bytes()[:4] == b"\x89PNG", src
    alts = {alt: src for src, alt in srcs}
    grid = page[page.index('<table class="grid">'):]
    grid = grid[: grid.index("</table>")]
    rows = re.findall(r"<tr><th>(IMG_0\d)</th>(.*?)</tr>", grid, re.S)
    assert [stem for stem, _ in rows] == ["IMG_01", "IMG_02", "IMG_03"]
    scores = []
    for stem, cells in rows:
        # the photo, then the model's render of its camera with the training-view PSNR under it
        assert f'alt="photo {stem}"' in cells and f'alt="colmap (uniform) render {stem}"' in cells
        scores.append(float(re.search(r"training-view PSNR (\d+\.\d\d) dB", cells).group(1)))
    # scored on the 8-bit render files: within rounding of the render command's float renders
    assert abs(np.mean(scores) - mean_psnr) < 0.1, (scores, mean_psnr)
    assert "training-view fit" in page and "<code>train_renders/</code> of the run" in page
    # the curve and the camera plot exist; the model's size is stated
    assert (out / alts["photos / garden, n = 3 training curve"]).is_file()
    assert (out / alts["photos / garden, n = 3 camera plot"]).is_file()
    assert "200 Gaussians, " in page and " kB" in page
    # nothing held out: no ground truth, no held-out tables or PSNR plots, one line saying why
    body = page[page.index("<body>"):]
    assert "ground truth" not in body and "missing" not in body
    for held_out in ("Table I", "Table II", "Pose accuracy", "error against run time", "pareto__", "curves/"):
        assert held_out not in page, held_out
    assert page.count("No views were held out") == 1
    assert "1 run from" in page and "1 runs" not in page


def test_photo_report_without_train_renders_gives_the_command_that_makes_them(tmp_path):
    """A run whose renders were never made (the workflow stopped before render_train_views):
    each photo says it has no render, and the run's row gives the command, which makes them."""
    results = photo_run(tmp_path)
    page = _report(results, tmp_path / "report")
    grid = page[page.index('<table class="grid">'):]
    assert grid[: grid.index("</table>")].count("no render (see the run's renders above)") == 3
    cmd = re.search(r"make it with <code>(.*?)</code>", page).group(1)
    argv = shlex.split(re.sub(r"<[^>]+>", "", cmd))
    assert argv[:4] == ["python", "-m", "splat_train", "render"]
    proc = run(argv[1:], timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    mode = results / "photos" / "garden" / "n3" / "colmap" / "uniform"
    assert sorted(p.name for p in (mode / "train_renders").glob("*.png")) == ["IMG_01.png", "IMG_02.png", "IMG_03.png"]


def test_tables_of_a_photo_run_leave_the_held_out_tables_out(tmp_path):
    """``python -m evaluation tables`` on a photo run: tables.md says in one line that no view
    was held out and holds no held-out table (Table I, Table II, pose accuracy), as the report
    does; the run status stays."""
    results = photo_run(tmp_path)
    proc = run(["-m", "evaluation", "tables", "--results", str(results), "--out", str(tmp_path / "t"), "-q"])
    assert proc.returncode == 0, proc.stdout + proc.stderr
    text = (tmp_path / "t" / "tables.md").read_text()
    from evaluation.reports.photos import NO_HELDOUT_NOTE
    from evaluation.reports.tables import HELDOUT_TABLES, RUN_STATUS

    assert text.count(NO_HELDOUT_NOTE) == 1 and f"## {RUN_STATUS}" in text
    assert not any(title in text for title in HELDOUT_TABLES), text


def test_cameras_from_above_keep_distances_and_look_at_what_they_look_at():
    """The camera plot's projection: cameras around a target at one height keep their distances
    and their arrows point at the target, whatever the world's up axis."""
    from camio.cameras import look_at
    from evaluation.reports.photos import top_down

    target = np.array([0.5, 2.0, -1.0])
    for up in (np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 1.0])):
        a = np.cross(up, [1.0, 0.3, 0.2])
        a /= np.linalg.norm(a)
        b = np.cross(up, a)
        eyes = [target + 3 * (np.cos(t) * a + np.sin(t) * b) for t in 0.2 + np.arange(4) * np.pi / 2]
        centres, dirs = top_down(np.stack([look_at(e, target, up)[:3] for e in eyes]))
        eyes = np.stack(eyes)
        assert np.allclose(np.linalg.norm(centres[:, None] - centres[None], axis=-1),
                           np.linalg.norm(eyes[:, None] - eyes[None], axis=-1))
        to_target = centres.mean(axis=0) - centres  # the target: the centre of the square of cameras
        cos = np.sum(dirs * to_target, axis=1) / np.linalg.norm(dirs, axis=1) / np.linalg.norm(to_target, axis=1)
        assert np.allclose(cos, 1.0)
