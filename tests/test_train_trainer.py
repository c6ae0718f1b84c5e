"""splat_train.training.trainer on a tiny generated scene: loss goes down, resume is exact, NaN stops
the run keeping the last checkpoint, the log has its columns, pose refinement."""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

from _train_scene import kill_at_loss_call, write_scene
from camio.colmap import read_model
from camio.ply import read_gaussian_ply
from splat_train import losses as losses_mod
from splat_train.training import trainer as trainer_mod
from splat_train.training.checkpoint import list_checkpoints, load_checkpoint
from splat_train.config import TrainConfig
from splat_train.render.cpu import raster as cpu_raster
from splat_train.training.runlog import LOG_COLUMNS
from splat_train.training.trainer import NonFiniteLossError, train

# A short explicit schedule: densify at 10 and 20, one opacity reset at 15, SH +1 every 10.
SMALL = dict(iterations=24, densify_from=5, densify_until=20, densify_every=10, opacity_reset_every=15,
             sh_increase_every=10, checkpoint_every=8, eval_every=12, recipe="paper",
             device="cpu", keep_checkpoints=5)


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def scene(tmp_path_factory, one_thread):
    return write_scene(tmp_path_factory.mktemp("scene"), n_views=4, n_test=2)


def _train(scene, out, **over):
    cfg = TrainConfig(**{**SMALL, **over})
    return train(scene["seed"], scene["cameras"], scene["images"], out, cfg,
                 test_cameras=scene["test_cameras"], test_images=scene["test_images"])


def test_loss_decreases_and_outputs(scene, tmp_path):
    res = _train(scene, tmp_path / "run", iterations=40, densify_until=0, checkpoint_every=20)
    out = tmp_path / "run"
    table = pq.read_table(out / "log.parquet")
    assert tuple(table.column_names) == LOG_COLUMNS
    df = table.to_pandas()
    assert list(df["iteration"]) == list(range(1, 41))
    assert str(table.schema.field("iteration").type) == "int64"
    assert (np.diff(df["wall_time_s"]) > 0).all()
    assert df["loss"].iloc[-8:].mean() < 0.7 * df["loss"].iloc[:8].mean()
    # held-out PSNR only every eval_every (and at the end), null elsewhere
    assert list(df.index[df["test_psnr"].notna()] + 1) == [12, 24, 36, 40]
    s = json.loads((out / "train.json").read_text())
    for key in ("iterations", "wall_time_s", "num_gaussians", "train_psnr", "test_psnr", "peak_rss_mb"):
        assert key in s
    assert s["test_psnr"] > 15 and s["train_psnr"] > 15
    assert s["rasterizer"] == ("cpu" if cpu_raster.available() else "torch")  # the backend that ran
    assert sorted(p.name for p in (out / "renders").iterdir()) == ["view_01.png", "view_03.png"]
    cloud = read_gaussian_ply(out / "model.ply")
    assert len(cloud) == s["num_gaussians"] == res.summary["num_gaussians"]
    assert [i for i, _ in list_checkpoints(out)] == [20, 40]
    ck = load_checkpoint(list_checkpoints(out)[-1][1])
    assert ck["iteration"] == 40 and set(ck["params"]) >= {"means", "quats"}
    assert not (out / "cameras_refined").exists()  # pose refinement is off by default
    assert TrainConfig().pose_refine is False


def test_checkpoint_loads_onto_device_with_rng_on_cpu(scene, tmp_path):
    """A CUDA resume maps every tensor to the GPU but the generator state: the trainer's
    torch.Generator is a CPU one and refuses a CUDA state (the "meta" device stands in here)."""
    out = tmp_path / "run"
    _train(scene, out, iterations=8, densify_until=0)
    ck = load_checkpoint(list_checkpoints(out)[-1][1], "meta")
    assert all(v.device.type == "meta" for v in ck["params"].values())
    assert all(v.device.type == "meta" for v in ck["strategy_state"].values())
    assert ck["rng"].device.type == "cpu" and ck["rng"].dtype == torch.uint8
    torch.Generator().set_state(ck["rng"])  # what Trainer.restore does with it


def test_resume_gives_identical_model(scene, tmp_path, monkeypatch):
    full = tmp_path / "full"
    _train(scene, full)
    # "killed" run: dies inside iteration 19 (checkpoints at 8 and 16), then resumes to 24.
    part = tmp_path / "part"
    restore = kill_at_loss_call(monkeypatch, 19)
    with pytest.raises(KeyboardInterrupt):
        _train(scene, part)
    assert [i for i, _ in list_checkpoints(part)] == [8, 16]
    restore()
    res = _train(scene, part)
    assert res.summary["resumed_from"].endswith("ckpt_0000016.pt")
    a, b = read_gaussian_ply(full / "model.ply"), read_gaussian_ply(part / "model.ply")
    assert len(a) == len(b)
    for k in ("means", "sh_dc", "sh_rest", "opacity_logit", "log_scales", "quats"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    la = pq.read_table(full / "log.parquet").to_pandas()
    lb = pq.read_table(part / "log.parquet").to_pandas()
    np.testing.assert_array_equal(la["loss"], lb["loss"])
    np.testing.assert_array_equal(la["num_gaussians"], lb["num_gaussians"])


def test_resume_refuses_other_config(scene, tmp_path):
    _train(scene, tmp_path / "r", iterations=8)
    with pytest.raises(ValueError, match="lr_opacity"):
        _train(scene, tmp_path / "r", iterations=8, lr_opacity=0.01)


@pytest.mark.parametrize("sync_every", [1, 10], ids=["cpu_schedule", "gpu_schedule"])
def test_nonfinite_loss_stops_and_keeps_checkpoint(scene, tmp_path, monkeypatch, sync_every):
    """A NaN loss at iteration 11 stops the run naming iteration 11 and the last good
    checkpoint (8), whether the loss is read every iteration (CPU) or only at the next read
    (every SYNC_EVERY iterations on a GPU, here at 12, the next log row: the NaN iteration's
    update has run by then, and no checkpoint after it is written)."""
    monkeypatch.setattr(trainer_mod, "host_sync_every", lambda dev: sync_every)
    real = losses_mod.photometric_loss
    calls = {"n": 0}

    def poisoned(render, target, lam):
        calls["n"] += 1
        loss, l1, s = real(render, target, lam)
        return (loss * float("nan"), l1, s) if calls["n"] == 11 else (loss, l1, s)

    monkeypatch.setattr(losses_mod, "photometric_loss", poisoned)
    out = tmp_path / "nan"
    with pytest.raises(NonFiniteLossError, match=r"iteration 11.*ckpt_0000008\.pt"):
        _train(scene, out)
    ckpts = list_checkpoints(out)
    assert [i for i, _ in ckpts] == [8]
    data = load_checkpoint(ckpts[0][1])
    assert all(torch.isfinite(v).all() for v in data["params"].values())
    assert not (out / "model.ply").exists()
    # the checkpoint is usable: a clean run resumes from it
    monkeypatch.setattr(losses_mod, "photometric_loss", real)
    res = _train(scene, out)
    assert res.summary["resumed_from"].endswith("ckpt_0000008.pt")


def test_reading_the_scalars_every_10_iterations_logs_the_same_rows(scene, tmp_path, monkeypatch):
    """The GPU schedule (loss, L1, SSIM and MSE read once every SYNC_EVERY iterations, and at
    log, evaluation and checkpoint rows) writes the very log.parquet rows of the CPU schedule
    (read every iteration), except the wall times, and the same model."""
    runs = {}
    for every in (1, 10):
        monkeypatch.setattr(trainer_mod, "host_sync_every", lambda dev, every=every: every)
        out = tmp_path / f"every{every}"
        _train(scene, out, iterations=40, checkpoint_every=40)
        runs[every] = (pq.read_table(out / "log.parquet").to_pandas(), read_gaussian_ply(out / "model.ply"))
    (la, ma), (lb, mb) = runs[1], runs[10]
    assert len(la) == len(lb) == 40
    for c in LOG_COLUMNS:
        if c != "wall_time_s":
            np.testing.assert_array_equal(la[c], lb[c], err_msg=c)
    np.testing.assert_array_equal(ma.means, mb.means)


def test_trainer_refuses_a_skewed_camera(scene, tmp_path, monkeypatch):
    """K[0, 1] != 0 is refused once, when the trainer starts (rasterize checks it per call only
    for CPU tensors: on a GPU that read would be a device sync every iteration)."""
    from splat_train.data import load_views
    from splat_train.training.trainer import Trainer

    views = load_views(scene["cameras"], scene["images"])
    views[1].camera.K[0, 1] = 0.5
    with pytest.raises(ValueError, match=f"{views[1].name}.*zero skew"):
        Trainer(TrainConfig(**SMALL), scene["seed"], views, tmp_path / "skew")


def test_pose_refinement_changes_cameras(scene, tmp_path):
    out = tmp_path / "pose"
    res = _train(scene, out, iterations=12, pose_refine=True, lr_pose=1e-3, densify_until=0, pose_refine_from=0)
    assert res.summary["pose_correction"]["max_rot_rad"] > 0
    refined = read_model(out / "cameras_refined")
    given = read_model(scene["cameras"])
    assert refined.names == given.names
    moved = max(float(np.abs(a.cam_from_world - b.cam_from_world).max())
                for a, b in zip(refined.cameras, given.cameras))
    assert 1e-5 < moved < 0.1


def test_test_psnr_at_a_reset_iteration_measures_the_model_not_the_reset(scene, tmp_path):
    """3DGS order: evaluate, then densify / reset. An evaluation right after the reset would log
    a near-black render (the error-against-run-time curve would show a false collapse)."""
    res = _train(scene, tmp_path / "run", iterations=16, eval_every=15, densify_until=20)
    df = pq.read_table(tmp_path / "run" / "log.parquet").to_pandas().set_index("iteration")
    assert df.loc[15, "test_psnr"] > 15  # opacity reset at 15 happens after this evaluation
    assert df.loc[16, "train_psnr"] < df.loc[14, "train_psnr"] - 3  # ... and then it does happen
    assert res.summary["iterations"] == 16


def test_scene_extent_covers_the_scene_for_nearby_views():
    """Three views 0.1 apart looking at points 1.0 away: the camera spread alone (the 3DGS rule)
    is 0.11; with the points the extent is 1.1 x their median distance. An object-centred
    capture keeps the camera rule."""
    from camio.cameras import Camera, look_at
    from splat_train.data import scene_extent

    K = np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]])
    near = [Camera(f"{i}", 32, 24, K, look_at([0.1 * (i - 1), 0, -1.0], [0, 0, 0])) for i in range(3)]
    pts = np.random.default_rng(0).normal(0, 0.05, (500, 3))
    assert scene_extent(near) == pytest.approx(0.11)
    assert scene_extent(near, pts) == pytest.approx(1.1 * np.median(np.linalg.norm(pts - [0, 0, -1.0], axis=1)))
    ring = [Camera(f"{i}", 32, 24, K, look_at([3 * np.cos(a), 0, 3 * np.sin(a)], [0, 0, 0]))
            for i, a in enumerate(np.linspace(0, 2 * np.pi, 8, endpoint=False))]
    assert scene_extent(ring, pts) == pytest.approx(scene_extent(ring)) == pytest.approx(3.3)
    with_nan = np.vstack([pts, [[np.nan, 0, 0]]])
    assert np.isfinite(scene_extent(near, with_nan))


def test_kernel_threads_default_to_every_cpu_and_results_do_not_depend_on_them(scene, tmp_path, monkeypatch):
    """torch stays at one thread; the C++ kernel (non-spinning threads) uses the idle cores.
    The kernel sums gradients in a fixed order, so the trained model is the same."""
    import os

    monkeypatch.delenv("SPLAT_TRAIN_KERNEL_THREADS", raising=False)
    _train(scene, tmp_path / "a", iterations=12)
    assert cpu_raster.kernel_threads() == len(os.sched_getaffinity(0))
    _train(scene, tmp_path / "b", iterations=12, kernel_threads=1)
    assert cpu_raster.kernel_threads() == 1
    a, b = read_gaussian_ply(tmp_path / "a" / "model.ply"), read_gaussian_ply(tmp_path / "b" / "model.ply")
    np.testing.assert_array_equal(a.means, b.means)
    np.testing.assert_array_equal(a.opacity_logit, b.opacity_logit)
    monkeypatch.setenv("SPLAT_TRAIN_KERNEL_THREADS", "3")
    assert cpu_raster.kernel_threads() == 3
    cpu_raster.set_kernel_threads(None)


def test_runlog_test_curve_keeps_best_and_last():
    from splat_train.training.runlog import RunLog

    log = RunLog()
    for it, p in [(1, float("nan")), (200, 12.0), (400, 14.5), (401, float("nan")), (600, 13.0)]:
        log.append(iteration=it, wall_time_s=0.0, loss=0.0, l1=0.0, ssim=0.0, train_psnr=0.0, num_gaussians=1,
                   test_psnr=p)
    c = log.test_curve()
    assert c["iterations"] == [200, 400, 600] and c["test_psnr"] == [12.0, 14.5, 13.0]
    assert (c["best_iteration"], c["best_test_psnr"]) == (400, 14.5)
    assert (c["last_iteration"], c["last_test_psnr"]) == (600, 13.0)
    assert RunLog().test_curve()["best_iteration"] is None


def _random_lpips_weights(folder):
    from _lpips_weights import random_alex_weights

    return random_alex_weights(folder)


@pytest.fixture(scope="module")
def lpips_scene(tmp_path_factory, one_thread):
    """AlexNet's pooling needs >= 31 px a side: the 32 x 24 scene is too small for LPIPS."""
    return write_scene(tmp_path_factory.mktemp("scene48"), n_views=4, n_test=2, width=48, height=36)


def test_heldout_ssim_and_lpips_along_the_run_agree_with_the_evaluation_metrics(lpips_scene, tmp_path):
    """log.parquet's test_ssim / test_lpips are imgmetrics.psnr_ssim.ssim and LPIPS-alex of the
    same float renders: recomputed here in float64 from the final model (no densification or
    reset after the last evaluation), they agree to 1e-5 (the trainer scores in float32)."""
    from imgmetrics.lpips import load_lpips, lpips_distance
    from imgmetrics.psnr_ssim import ssim as eval_ssim
    from splat_train.data import load_views
    from splat_train.export import render_views
    from splat_train.training.trainer import Trainer

    weights = _random_lpips_weights(tmp_path / "lpips")
    cfg = TrainConfig(**{**SMALL, "densify_until": 0, "opacity_reset_every": 1000, "eval_lpips": True,
                         "lpips_weights": str(weights)})
    scene = lpips_scene
    views = load_views(scene["cameras"], scene["images"])
    tests = load_views(scene["test_cameras"], scene["test_images"])
    tr = Trainer(cfg, scene["seed"], views, tmp_path / "run", tests)
    res = tr.run()
    table = pq.read_table(tmp_path / "run" / "log.parquet")
    assert tuple(table.column_names) == LOG_COLUMNS and {"test_ssim", "test_lpips"} <= set(LOG_COLUMNS)
    df = table.to_pandas().set_index("iteration")
    ev = df[df["test_psnr"].notna()]
    assert list(ev.index) == [12, 24] and ev["test_ssim"].notna().all() and ev["test_lpips"].notna().all()
    assert df["test_ssim"].isna().sum() == df["test_lpips"].isna().sum() == len(df) - 2

    renders = {}
    deg = tr.sched.sh_degree_at(tr.iteration, cfg.sh_degree)
    render_views(tr.params, deg, tests, tr.bg, on_render=lambda n, rgb, gt, alpha: renders.update({n: (rgb, gt)}))
    model = load_lpips("alex", weights)
    ssim64 = [float(eval_ssim(rgb.double().permute(2, 0, 1), gt.double().permute(2, 0, 1))[0])
              for rgb, gt in renders.values()]
    lpips64 = [float(lpips_distance(model, rgb.permute(2, 0, 1), gt.permute(2, 0, 1), dtype=torch.float64)[0])
               for rgb, gt in renders.values()]
    assert df.loc[24, "test_ssim"] == pytest.approx(np.mean(ssim64), abs=1e-5)
    assert df.loc[24, "test_lpips"] == pytest.approx(np.mean(lpips64), abs=1e-5)
    c = res.summary["test_curve"]
    assert c["iterations"] == [12, 24] and len(c["test_ssim"]) == len(c["test_lpips"]) == 2
    assert c["last_test_lpips"] == pytest.approx(df.loc[24, "test_lpips"])
    assert c["best_test_ssim"] == max(c["test_ssim"]) and c["best_test_lpips"] == min(c["test_lpips"])
    assert c["best_lpips_iteration"] in (12, 24)
    assert res.summary["heldout_lpips"] == {"enabled": True, "net": "alex",
                                            "weights": str(weights / "alex.safetensors")}


def test_heldout_lpips_is_off_by_default_and_null_not_zero(scene, tmp_path):
    assert TrainConfig().eval_lpips is False  # the one default (splat_train/config.py)
    res = _train(scene, tmp_path / "run", iterations=12)
    df = pq.read_table(tmp_path / "run" / "log.parquet").to_pandas()
    assert df["test_lpips"].isna().all() and df["test_ssim"].notna().sum() == 1
    c = res.summary["test_curve"]
    assert c["test_lpips"] == [None] and c["best_lpips_iteration"] is None and 0 < c["test_ssim"][0] <= 1
    assert res.summary["heldout_lpips"]["enabled"] is False


def test_heldout_lpips_on_images_too_small_for_alexnet_is_null_not_an_error(scene, tmp_path):
    weights = _random_lpips_weights(tmp_path / "lpips")
    res = _train(scene, tmp_path / "run", iterations=12, eval_lpips=True, lpips_weights=str(weights))
    df = pq.read_table(tmp_path / "run" / "log.parquet").to_pandas()
    assert df["test_lpips"].isna().all() and df["test_ssim"].notna().sum() == 1
    assert res.summary["test_curve"]["test_lpips"] == [None]


def test_runlog_resumes_a_checkpoint_from_before_the_heldout_columns():
    """A checkpoint's log written before test_ssim / test_lpips (and test_coverage /
    test_psnr_covered) existed loads with them null."""
    from splat_train.training.runlog import RunLog

    old = {c: torch.tensor([1.0, 2.0], dtype=torch.float64)
           for c in ("iteration", "wall_time_s", "loss", "l1", "ssim", "train_psnr", "num_gaussians")}
    old["test_psnr"] = torch.tensor([float("nan"), 20.0], dtype=torch.float64)
    log = RunLog()
    log.load_state_dict(old)
    log.append(iteration=3, wall_time_s=0.0, loss=0.0, l1=0.0, ssim=0.0, train_psnr=0.0, num_gaussians=1,
               test_psnr=21.0, test_ssim=0.5, test_lpips=0.4, test_coverage=0.75, test_psnr_covered=23.0)
    c = log.test_curve()
    assert c["iterations"] == [2, 3] and c["test_ssim"] == [None, 0.5] and c["test_lpips"] == [None, 0.4]
    assert c["test_coverage"] == [None, 0.75] and c["test_psnr_covered"] == [None, 23.0]
    assert c["last_test_psnr_covered"] == 23.0 and "best_test_coverage" not in c
    assert (c["best_ssim_iteration"], c["best_lpips_iteration"], c["best_iteration"]) == (3, 3, 3)


def test_run_time_leaves_out_a_one_time_kernel_build(scene, tmp_path, monkeypatch):
    """A kernel built during the first step (here: 30 s of pretend build) is recorded apart as
    ``kernel_build_s`` and is not in ``wall_time_s``, the run time the tables and plots use."""
    clock = {"built": 0.0, "calls": 0}
    real_perf = trainer_mod.time.perf_counter

    def fake_build_seconds():
        return clock["built"]

    real_step = trainer_mod.Trainer.step

    def step(self):
        if self.iteration == 0:
            clock["built"] += 30.0
            clock["offset"] = clock.get("offset", 0.0) + 30.0  # the build's 30 s pass on the clock
        return real_step(self)

    monkeypatch.setattr(trainer_mod, "build_seconds", fake_build_seconds)
    monkeypatch.setattr(trainer_mod.Trainer, "step", step)
    monkeypatch.setattr(trainer_mod.time, "perf_counter", lambda: real_perf() + clock.get("offset", 0.0))
    _train(scene, tmp_path / "run", iterations=4, densify_until=0, checkpoint_every=4)
    summary = json.loads((tmp_path / "run" / "train.json").read_text())
    assert summary["kernel_build_s"] == 30.0
    assert 0 < summary["wall_time_s"] < 30.0
