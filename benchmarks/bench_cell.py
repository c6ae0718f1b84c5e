"""Benchmark of one pipeline cell on CPU: scene prep -> init -> bridge -> align -> train -> render -> metrics.

The cell is the n = 3 scene at 1/8 resolution trained for 2,000 iterations
(target under 10 minutes on 2 cores). Every stage runs through its documented CLI
(docs/contracts.md) in a subprocess, so the times include interpreter start-up and imports,
which is what a user (or the Snakemake workflow) gets. ``--inprocess`` calls the same CLI
``main(argv)`` functions in this process instead (no start-up cost; used by the smoke test).

Scene: LLFF fern ``images_8`` from this project's machine data (SHARED_FERN), converted and
undistorted (497x372 after undistortion), when present; otherwise the synthetic scene of ``python -m camio synth``.
Initialisers: the real VGGT checkpoint is not available on the development machine, so the
cell is initialised by the COLMAP baseline (real scene) or the oracle (synthetic scene, which
has ground-truth geometry; COLMAP is still timed there). The VGGT forward is timed separately
with RANDOM full-size weights through benchmarks/bench_vggt.py (speed only, outputs
meaningless), and an estimated VGGT cell total is reported beside the measured one.

Training uses the trainer's defaults (threads included) unless ``--threads`` is given; the
rasterizer engineer found one thread faster than two on this loaded machine, see the
docstring of splat_train/render/rasterize.py.

    python benchmarks/bench_cell.py                      # the real cell (several minutes)
    python benchmarks/bench_cell.py --no-vggt            # skip the random-weight VGGT forward
    python benchmarks/bench_cell.py --quick --scene synthetic --inprocess   # seconds
    python benchmarks/bench_cell.py --prepare-only .gpu_cell   # CPU stages here, for a GPU elsewhere:
    python benchmarks/bench_cell.py --prepared .gpu_cell --device cuda --rasterizer gsplat

Saves JSON to benchmarks/out/bench_cell_<time>.json (git-ignored) and prints a table.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script too
from experiments._proc import StageError, run_logged  # noqa: E402
from splat_train.recipes import RECIPE_NAMES  # noqa: E402

log = logging.getLogger("bench_cell")

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
OUT = HERE / "out"
# machine-data: this project's machines keep real scenes in ../shared/data/scenes, beside the
# repository; a clone has none, and the benchmark says so and uses the synthetic scene.
SHARED_FERN = REPO.parent / "shared" / "data" / "scenes" / "llff__fern"
TARGET_S = 600.0  # the full cell in under 10 minutes
QUICK_ITERATIONS = 10
QUICK_SYNTH = (10, 48)  # views, width of the --quick synthetic scene

# The CLI modules whose ``main(argv)`` the in-process launcher calls.
_MAIN_MODULES = {"camio": "camio.__main__", "bridge": "bridge.__main__", "evaluation": "evaluation.__main__",
                 "splat_train": "splat_train.__main__",
                 "evaluation.initialisers.colmap_baseline": "evaluation.initialisers.colmap_baseline",
                 "evaluation.initialisers.oracle": "evaluation.initialisers.oracle"}


def _cpu_seconds(inprocess: bool) -> float:
    """User + system CPU seconds of this process (in-process) or of its finished children."""
    ru = resource.getrusage(resource.RUSAGE_SELF if inprocess else resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_stage(name: str, module: str, args: list[str], logs: Path, inprocess: bool = False) -> tuple[float, float]:
    """Run ``python -m module args`` (or its main(args) in-process); returns (wall s, CPU s).

    The subprocess's stdout and stderr go to ``logs/<name>.log``; a failure raises StageError
    with the end of that log. CPU seconds (user + system, all threads) show how much of the
    wall time was work rather than waiting for a loaded machine.
    """
    logs.mkdir(parents=True, exist_ok=True)
    log_path = logs / f"{name}.log"
    log.info("stage %s: python -m %s %s", name, module, " ".join(args))
    t0, c0 = time.perf_counter(), _cpu_seconds(inprocess)
    if inprocess:
        import torch

        threads = torch.get_num_threads()
        try:
            rc = importlib.import_module(_MAIN_MODULES[module]).main(list(args))
        except SystemExit as exc:  # argparse errors
            rc = exc.code if isinstance(exc.code, int) else 1
        finally:
            torch.set_num_threads(threads)  # a stage may change it (splat_train --threads)
        dt = time.perf_counter() - t0
        if rc:
            raise StageError(f"stage {name} (python -m {module}) failed with status {rc}; see the log above")
        return dt, _cpu_seconds(inprocess) - c0
    dt = run_logged([sys.executable, "-m", module, *args], log_path, f"stage {name} (python -m {module})")
    cpu = _cpu_seconds(inprocess) - c0
    log.info("stage %s done in %.1f s (%.1f CPU s)", name, dt, cpu)
    return dt, cpu


def _write_lists(scene: Path, n: int, work: Path) -> tuple[Path, Path]:
    """Training list file and a folder of links to the held-out images (the workflow's chores)."""
    from camio.split import read_split

    split = read_split(scene / "split.json")
    train_txt = work / f"train_n{n}.txt"
    train_txt.write_text("".join(f"{name}\n" for name in split.train[str(n)]))
    test_dir = work / "test_images"
    shutil.rmtree(test_dir, ignore_errors=True)
    test_dir.mkdir()
    for name in split.test:
        os.symlink((scene / "images" / name).resolve(), test_dir / name)
    return train_txt, test_dir


def prepare_scene(kind: str, work: Path, n: int, quick: bool, stage) -> tuple[Path, dict]:
    """Prepare the scene into ``work/scene`` with split.json; returns (folder, description)."""
    scene = work / "scene"
    if kind == "auto":
        kind = "fern" if SHARED_FERN.is_dir() else "synthetic"
    if kind == "fern":
        if not SHARED_FERN.is_dir():
            raise FileNotFoundError(f"{SHARED_FERN} is missing; use --scene synthetic")
        stage("prep", "camio", ["convert", "--src", str(SHARED_FERN), "--images-subdir", "images_8", "--undistort",
                                "--out", str(scene), "--n", str(n)])
        return scene, {"scene": "llff/fern images_8 (1/8), undistorted", "source": str(SHARED_FERN)}
    views, width = QUICK_SYNTH if quick else (24, 504)
    stage("prep", "camio", ["synth", "--out", str(scene), "--views", str(views), "--width", str(width),
                            "--seed", "0"])
    stage("prep_split", "camio", ["split", "--scene", str(scene), "--n", str(n), "--out",
                                  str(scene / "split.json")])
    return scene, {"scene": f"synthetic ({views} views, width {width})", "source": "python -m camio synth"}


def _image_size(scene: Path) -> list[int]:
    import OpenImageIO as oiio

    first = sorted((scene / "images").iterdir())[0]
    inp = oiio.ImageInput.open(str(first))
    if inp is None:
        raise OSError(f"cannot read {first}: {oiio.geterror()}")
    spec = inp.spec()
    inp.close()
    return [spec.width, spec.height]


def vggt_random_forward(frames: int, dtype: str = "fp32", size: int = 518, threads: int = 2) -> dict:
    """One forward of the full-size VGGT with RANDOM weights via benchmarks/bench_vggt.py.

    Speed/memory only. Returns bench_vggt's row for (frames, dtype), or {"error": ...} when the
    script is missing or fails (never a made-up number).
    """
    script = HERE / "bench_vggt.py"
    if not script.is_file():
        return {"frames": frames, "dtype": dtype, "error": f"{script} is missing"}
    before = set(OUT.glob("bench_vggt_*.json")) if OUT.is_dir() else set()
    cmd = [sys.executable, str(script), "--frames", str(frames), "--dtypes", dtype, "--size", str(size),
           "--threads", str(threads)]
    log.info("VGGT random-weight forward: %s", " ".join(cmd[1:]))
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if res.returncode != 0:
        return {"frames": frames, "dtype": dtype, "error": f"bench_vggt.py exit {res.returncode}: {res.stderr[-800:]}"}
    new = sorted(set(OUT.glob("bench_vggt_*.json")) - before, key=lambda p: p.stat().st_mtime)
    if not new:
        return {"frames": frames, "dtype": dtype, "error": "bench_vggt.py wrote no JSON into benchmarks/out"}
    runs = json.loads(new[-1].read_text()).get("runs", [])
    row = next((r for r in runs if r.get("frames") == frames and r.get("dtype") == dtype), None)
    if row is None:
        return {"frames": frames, "dtype": dtype, "error": f"{new[-1].name} has no row for {frames}/{dtype}"}
    return {**row, "json": str(new[-1]), "weights": "RANDOM (speed/memory only)"}


class LoadSampler:
    """Samples the 1-minute load average every ``period`` seconds in a daemon thread."""

    def __init__(self, period: float = 10.0) -> None:
        self.period, self.samples = period, [os.getloadavg()[0]]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self.samples.append(os.getloadavg()[0])

    def __enter__(self) -> "LoadSampler":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.samples.append(os.getloadavg()[0])

    def summary(self) -> dict:
        return {"mean_1min": sum(self.samples) / len(self.samples), "max_1min": max(self.samples),
                "samples": len(self.samples), "period_s": self.period}


def run_cell(work: Path, scene_kind: str = "auto", n: int = 3, iterations: int = 2000, quick: bool = False,
             threads: int | None = None, vggt: bool = True, vggt_dtype: str = "fp32", vggt_size: int = 518,
             inprocess: bool = False, device: str | None = None, rasterizer: str | None = None,
             prepared: Path | None = None, recipe: str | None = None) -> dict:
    """Run the cell in ``work``; returns the JSON-ready breakdown (seconds per stage, see module doc).

    ``device`` and ``rasterizer`` are passed to the training and render stages when given
    (``python -m benchmarks --gpu`` runs the cell with ``cuda`` and ``gsplat``). ``prepared``: a
    folder written by :func:`prepare_bundle`; its stages up to ``align`` are not run again
    (their times, measured where it was made, are reported under ``prepared``), and
    ``scene_kind`` and ``n`` come from it. ``recipe``: splat_train's ``--recipe`` (None: its
    default).
    """
    with LoadSampler() as load:
        result = _run_cell(work, scene_kind, n, iterations, quick, threads, vggt, vggt_dtype, vggt_size, inprocess,
                           device, rasterizer, prepared, recipe)
    result["loadavg_during"] = load.summary()
    return result


class _Stages:
    """Runs stages through :func:`run_stage` and keeps their wall and CPU seconds."""

    def __init__(self, logs: Path, inprocess: bool) -> None:
        self.logs, self.inprocess = logs, inprocess
        self.times: dict[str, float] = {}
        self.cpu: dict[str, float] = {}

    def __call__(self, name: str, module: str, args: list[str]) -> float:
        dt, c = run_stage(name, module, args, self.logs, self.inprocess)
        self.times[name] = self.times.get(name, 0.0) + dt
        self.cpu[name] = self.cpu.get(name, 0.0) + c
        return dt


# What prepare_bundle keeps of a prepared cell (besides the training and held-out images).
PREPARED_FILE = "prepared.json"
_BUNDLE_PARTS = ("bridge", "align", "colmap/status.json", "scene/split.json", "scene/scene.json")


def _prepare(work: Path, scene_kind: str, n: int, quick: bool, threads: int | None, stage: _Stages) -> dict:
    """The cell's stages up to ``align`` (scene, lists, initialisers, Bridge, alignment) in
    ``work``; returns what the rest of the cell needs (JSON-ready, paths relative to ``work``)."""
    scene, desc = prepare_scene(scene_kind, work, n, quick, stage)
    synthetic = (scene / "gt" / "depth").is_dir()
    t0 = time.perf_counter()
    train_txt, test_dir = _write_lists(scene, n, work)
    stage.times["lists"] = time.perf_counter() - t0

    # Initialisers: COLMAP always (a failure is a result); the oracle where ground truth exists.
    inits: dict[str, dict] = {}
    colmap_args = ["--images", str(scene / "images"), "--image-list", str(train_txt), "--out", str(work / "colmap")]
    if threads:
        colmap_args += ["--threads", str(threads)]
    inits["colmap"] = {"wall_s": stage("init_colmap", "evaluation.initialisers.colmap_baseline", colmap_args)}
    status = json.loads((work / "colmap" / "status.json").read_text())
    inits["colmap"].update({k: status.get(k) for k in ("success_paper", "aligned_ok", "registered", "points", "reason")})
    if synthetic:
        inits["oracle"] = {"wall_s": stage("init_oracle", "evaluation.initialisers.oracle", [
            "--scene", str(scene), "--image-list", str(train_txt), "--out", str(work / "oracle")])}
    colmap_ok = bool(status.get("success_paper", status.get("success")) and status.get("aligned_ok", True))
    used = "oracle" if synthetic else ("colmap" if colmap_ok else None)
    if used is None:
        raise StageError(f"COLMAP failed on {desc['scene']} at n = {n} ({status.get('reason')}) and the scene has "
                         "no ground truth for the oracle: nothing to initialise the cell with")

    bridge = work / "bridge"
    if used == "colmap":
        stage("bridge", "bridge", ["--colmap", str(work / "colmap" / "sparse" / "0"), "--images", str(scene / "images"),
                                   "--mode", "uniform", "--out", str(bridge)])
    else:
        stage("bridge", "bridge", ["--pred", str(work / "oracle" / "predictions.npz"), "--mode", "gated",
                                   "--out", str(bridge)])
    stage("align", "evaluation", ["align", "--pred", str(bridge / "sparse" / "0"), "--ref", str(scene / "sparse" / "0"),
                                  "--train-names", str(scene / "split.json"), "--n", str(n), "--images", str(test_dir),
                                  "--out", str(work / "align")])
    return {"desc": desc, "n": n, "used": used, "inits": inits,
            "scene": str(scene.relative_to(work)), "train_txt": str(train_txt.relative_to(work)),
            "test_dir": str(test_dir.relative_to(work))}


def prepare_bundle(dest: Path, scene_kind: str = "auto", n: int = 3, quick: bool = False,
                   threads: int | None = None, inprocess: bool = False) -> Path:
    """Run the cell's stages up to ``align`` and keep, in ``dest``, only what training,
    rendering and metrics read: the Bridge's seed and cameras, the aligned held-out cameras,
    the training and held-out images (copies, no links), the lists and :data:`PREPARED_FILE`
    (the stages' times and the state). For a machine that lacks the CPU stages' packages or
    the scene (``python -m benchmarks --gpu --cell-prepared DEST`` on a lent GPU: ~2 MB for
    fern n = 3 instead of the 7 MB scene and open3d)."""
    if dest.exists():
        raise FileExistsError(f"{dest} exists; remove it or choose another folder")
    with tempfile.TemporaryDirectory(prefix="bench_cell_prep_") as tmp:
        work = Path(tmp)
        stage = _Stages(work / "logs", inprocess)
        t0 = time.perf_counter()
        state = _prepare(work, scene_kind, n, quick, threads, stage)
        state.update(stages_s=stage.times, stages_cpu_s=stage.cpu, wall_s=time.perf_counter() - t0,
                     image_size=_image_size(work / state["scene"]), made_on=os.uname().nodename,
                     made_at=time.strftime("%Y-%m-%dT%H:%M:%S"))
        staging = dest.with_name(dest.name + ".partial")
        shutil.rmtree(staging, ignore_errors=True)
        for part in _BUNDLE_PARTS:
            src = work / part
            if src.is_dir():
                shutil.copytree(src, staging / part)
            elif src.exists():
                (staging / part).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, staging / part)
        shutil.copy2(work / state["train_txt"], staging / state["train_txt"])
        images = staging / state["scene"] / "images"
        images.mkdir(parents=True)
        for name in (work / state["train_txt"]).read_text().split():
            shutil.copy2(work / state["scene"] / "images" / name, images / name)
        (staging / state["test_dir"]).mkdir()
        for link in sorted((work / state["test_dir"]).iterdir()):
            shutil.copy2(link.resolve(), staging / state["test_dir"] / link.name)  # the file, not the link
        (staging / PREPARED_FILE).write_text(json.dumps(state, indent=2) + "\n")
        staging.rename(dest)
    log.info("prepared cell (%s, n = %d, init %s) in %s", state["desc"]["scene"], n, state["used"], dest)
    return dest


def cell_train_args(cell: Path, state: dict, out: Path, iterations: int, seed: int, threads: int | None = None,
                    device: str | None = None, rasterizer: str | None = None, recipe: str | None = None) -> list[str]:
    """``python -m splat_train``'s arguments for the cell in ``cell`` (its :data:`PREPARED_FILE`
    ``state``): the Bridge's seed and cameras, the training images, the aligned held-out views;
    the model into ``out``. An option left None is the trainer's default."""
    bridge = cell / "bridge"
    args = ["--seed-ply", str(bridge / "seed.ply"), "--cameras", str(bridge / "sparse" / "0"),
            "--images", str(cell / state["scene"] / "images"), "--image-list", str(cell / state["train_txt"]),
            "--out", str(out), "--iterations", str(iterations), "--seed", str(seed),
            "--test-cameras", str(cell / "align" / "sparse" / "0"), "--test-images", str(cell / state["test_dir"])]
    for flag, value in (("--threads", threads), ("--device", device), ("--rasterizer", rasterizer),
                        ("--recipe", recipe)):
        if value:
            args += [flag, str(value)]
    return args


def _run_cell(work: Path, scene_kind: str, n: int, iterations: int, quick: bool, threads: int | None, vggt: bool,
              vggt_dtype: str, vggt_size: int, inprocess: bool, device: str | None = None,
              rasterizer: str | None = None, prepared: Path | None = None, recipe: str | None = None) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    stage = _Stages(work / "logs", inprocess)
    times, cpu = stage.times, stage.cpu
    t_start = time.perf_counter()
    load0 = os.getloadavg()
    if prepared is None:
        state = _prepare(work, scene_kind, n, quick, threads, stage)
    else:
        state = json.loads((prepared / PREPARED_FILE).read_text())
        shutil.copytree(prepared, work, dirs_exist_ok=True)
    n, used, inits, desc = state["n"], state["used"], state["inits"], state["desc"]
    scene, train_txt, test_dir = work / state["scene"], work / state["train_txt"], work / state["test_dir"]
    train_args = cell_train_args(work, state, work / "train", iterations, 0, threads=threads, device=device,
                                 rasterizer=rasterizer, recipe=recipe)
    stage("train", "splat_train", train_args)
    summary = json.loads((work / "train" / "train.json").read_text())
    stage("render", "splat_train", ["render", "--model", str(work / "train" / "model.ply"),
                                    "--cameras", str(work / "align" / "sparse" / "0"), "--images", str(test_dir),
                                    "--out", str(work / "renders")] + (["--device", device] if device else []))
    metric_args = ["images", "--pred", str(work / "renders"), "--gt", str(test_dir), "--out", str(work / "metrics.json")]
    if quick:
        metric_args.append("--lpips-nets")  # an empty list: no LPIPS in the quick run
    stage("metrics", "evaluation", metric_args)
    metrics = json.loads((work / "metrics.json").read_text())

    # The cell on its used path: every stage except the initialisers it did not use (with a
    # prepared folder, the stages it ran where it was made: times from that machine).
    all_times = {**state.get("stages_s", {}), **times}
    all_cpu = {**state.get("stages_cpu_s", {}), **cpu}
    path_stages = [k for k in all_times if not k.startswith("init_") or k == f"init_{used}"]
    cell_s = sum(all_times[k] for k in path_stages)
    cell_cpu = sum(all_cpu.get(k, 0.0) for k in path_stages)
    result = {
        **desc, "n": n, "iterations": iterations, "quick": quick,
        "image_size": state["image_size"] if prepared is not None else _image_size(scene),
        "launcher": "in-process main(argv)" if inprocess else "subprocess CLI (python -m ...)",
        "init_used": used, "inits": inits, "stages_s": all_times, "stages_cpu_s": all_cpu,
        "train": {
            "wall_s": summary["wall_time_s"], "session_s": summary.get("session_time_s"),
            "eval_s": summary.get("eval_time_s"), "it_per_s": iterations / max(summary["wall_time_s"], 1e-9),
            "final_gaussians": summary["num_gaussians"], "torch_threads": summary.get("torch_threads"),
            "test_psnr": summary.get("test_psnr"), "train_psnr": summary.get("train_psnr"),
            "peak_rss_mb": summary.get("peak_rss_mb"), "threads_arg": threads,
            "device": summary.get("device"), "rasterizer": summary.get("rasterizer"),
            "recipe": summary.get("recipe"), "peak_cuda_mb": summary.get("peak_cuda_mb"),
            "test_curve": summary.get("test_curve"),
        },
        "metrics": {k: metrics.get(k) for k in ("psnr", "ssim", "lpips_alex", "lpips_vgg", "n_images")},
        "cell_total_s": cell_s, "cell_total_cpu_s": cell_cpu, "target_s": TARGET_S, "meets_target": cell_s < TARGET_S,
        "loadavg_start": list(load0),
    }
    if prepared is not None:
        result["prepared"] = {"folder": str(prepared), "stages": sorted(state.get("stages_s", {})),
                              "made_on": state.get("made_on"), "made_at": state.get("made_at")}
    if vggt:
        row = vggt_random_forward(n, vggt_dtype, vggt_size, threads or 2)
        result["vggt_forward_random"] = row
        if "forward_s" in row:
            result["cell_total_vggt_estimate_s"] = cell_s - times[f"init_{used}"] + row["forward_s"]
    result["loadavg_end"] = list(os.getloadavg())
    result["wall_s"] = time.perf_counter() - t_start
    return result


def _fmt1(x) -> str:
    return "" if x is None else f"{x:.1f}"


def _num(x) -> str:
    return "missing" if x is None else f"{x:.3f}"


def format_cell(r: dict) -> str:
    """The cell breakdown as Markdown-style text."""
    lines = [f"Cell: {r['scene']}, {r['image_size'][0]}x{r['image_size'][1]}, n = {r['n']}, "
             f"{r['iterations']} iterations, init {r['init_used']} ({r['launcher']})",
             "", "| stage | wall s | CPU s | note |", "|---|---:|---:|---|"]
    tr = r["train"]
    notes = {"train": f"{tr['it_per_s']:.2f} it/s (training loop {tr['wall_s']:.1f} s, held-out evals "
                      f"{(tr['eval_s'] or 0):.1f} s), {tr['final_gaussians']} Gaussians, torch threads "
                      f"{tr['torch_threads']}",
             "metrics": f"PSNR {r['metrics']['psnr']:.2f} dB, SSIM {r['metrics']['ssim']:.3f}, LPIPS alex/vgg "
                        f"{_num(r['metrics']['lpips_alex'])}/{_num(r['metrics']['lpips_vgg'])}"}
    for name in r.get("prepared", {}).get("stages", []):
        notes[name] = f"prepared on {r['prepared'].get('made_on')} at {r['prepared'].get('made_at')}"
    for name, info in r["inits"].items():
        ok = "success" if info.get("success_paper", info.get("success", True)) else f"failed ({info.get('reason')})"
        notes[f"init_{name}"] = ("used" if name == r["init_used"] else "timed, not used") + (
            f"; {ok}, {info.get('registered')} registered, {info.get('points')} points" if name == "colmap" else "")
    for name, dt in r["stages_s"].items():
        c = r.get("stages_cpu_s", {}).get(name)
        lines.append(f"| {name} | {dt:.1f} | {'' if c is None else f'{c:.1f}'} | {notes.get(name, '')} |")
    lines.append(f"| **cell total** | **{r['cell_total_s']:.1f}** | {r.get('cell_total_cpu_s', float('nan')):.1f} | "
                 f"target < {r['target_s']:.0f} s wall: {'MET' if r['meets_target'] else 'NOT MET'} |")
    v = r.get("vggt_forward_random")
    if v is not None:
        if "forward_s" in v:
            lines.append(f"| vggt forward, RANDOM weights | {v['forward_s']:.1f} | {_fmt1(v.get('forward_cpu_s'))} | {v['frames']} frames {v['size']}px "
                         f"{v['dtype']}, peak RSS {v.get('peak_rss_gb', float('nan')):.2f} GB (speed only) |")
            lines.append(f"| cell total with VGGT (estimate) | {r['cell_total_vggt_estimate_s']:.1f} | | "
                         "COLMAP init replaced by the forward; checkpoint loading not included |")
        else:
            lines.append(f"| vggt forward, RANDOM weights | missing | | {v['error'][:120]!r} |")
    during = r.get("loadavg_during", {})
    lines.append(f"load average (1 min): start {r['loadavg_start'][0]:.1f}, end {r['loadavg_end'][0]:.1f}, "
                 f"mean {during.get('mean_1min', float('nan')):.1f}, max {during.get('max_1min', float('nan')):.1f} "
                 f"on {os.cpu_count()} CPUs")
    curve = r["train"].get("test_curve") or {}
    if curve.get("iterations"):
        by_it = dict(zip(curve["iterations"], curve["test_psnr"]))
        marks = [i for i in (1000, 2000, 5000, 10000) if i in by_it]
        lines.append("")
        lines.append("held-out PSNR (training loop's evaluation): " + ", ".join(f"{i}: {by_it[i]:.2f} dB" for i in marks)
                     + f"; best {curve['best_test_psnr']:.2f} dB at iteration {curve['best_iteration']}, last "
                     f"{curve['last_test_psnr']:.2f} dB at {curve['last_iteration']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                epilog="Times are one run on a shared machine: compare within a run.")
    p.add_argument("--scene", choices=["auto", "fern", "synthetic"], default="auto",
                   help="auto: LLFF fern where this machine has it, else synthetic")
    p.add_argument("--n", type=int, default=3, help="training views (default 3)")
    p.add_argument("--iterations", type=int, default=None, help=f"default 2000 ({QUICK_ITERATIONS} with --quick)")
    p.add_argument("--quick", action="store_true", help="tiny synthetic sizes for a smoke run")
    p.add_argument("--threads", type=int, default=None, help="torch threads for training (default: trainer's)")
    p.add_argument("--no-vggt", action="store_true", help="skip the random-weight VGGT forward")
    p.add_argument("--vggt-dtype", choices=["fp32", "bf16"], default="fp32")
    p.add_argument("--inprocess", action="store_true", help="call the CLI main()s in this process")
    p.add_argument("--work", type=Path, default=None, help="keep the cell's files here (default: a temp dir)")
    p.add_argument("--out", type=Path, default=None, help="JSON path (default benchmarks/out/bench_cell_<time>.json)")
    p.add_argument("--prepare-only", type=Path, metavar="DEST", default=None,
                   help="run the stages up to align and keep what the rest reads in DEST (a few MB), for "
                        "--prepared on another machine (a lent GPU without pycolmap's mapper or the scene)")
    p.add_argument("--prepared", type=Path, metavar="DIR", default=None,
                   help="a --prepare-only folder: train, render and score from it (--scene and --n from it)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default=None, help="training and render device")
    p.add_argument("--rasterizer", default=None, help="training rasterizer backend (splat_train --rasterizer)")
    p.add_argument("--recipe", choices=list(RECIPE_NAMES), default=None,
                   help="training recipe (splat_train --recipe; default: the trainer's)")
    args = p.parse_args(argv)
    from runtime.atomic import write_json
    from runtime.logs import setup_logging

    setup_logging()
    if args.prepare_only is not None:
        prepare_bundle(args.prepare_only, args.scene, args.n, args.quick, args.threads, args.inprocess)
        return 0
    iterations = args.iterations or (QUICK_ITERATIONS if args.quick else 2000)
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_cell_")
    work = args.work or Path(tmp.name)
    try:
        result = run_cell(work, args.scene, args.n, iterations, args.quick, args.threads, not args.no_vggt,
                          args.vggt_dtype, inprocess=args.inprocess, device=args.device, rasterizer=args.rasterizer,
                          prepared=args.prepared, recipe=args.recipe)
    finally:
        if tmp is not None:
            tmp.cleanup()
    out = args.out or OUT / f"bench_cell_{time.strftime('%Y%m%d_%H%M%S')}.json"
    write_json(out, result)
    print(format_cell(result))
    log.info("saved %s", out)
    return 0


if __name__ == "__main__":
    from runtime.stops import run_command

    # a stop signal (SLURM's SIGTERM, Ctrl-C, SIGHUP) ends the runner with one line and 128 + the
    # signal, after the stage command it was running has ended cleanly (experiments._proc)
    sys.exit(run_command(main))
