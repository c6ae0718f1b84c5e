"""The mvs initialiser's accuracy, confidence and speed, printed (not a test).

    python -m experiments.mvs_accuracy [--synthetic-views 3 6 12] [--scene SCENE ...] [--out JSON]

* Synthetic scene (generated: 24 views, 256x192, the tuning scene of the sparse-view benchmark),
  against its exact depth, at each view count of its split: AbsRel, the share of kept pixels
  with delta < 1.25, completeness (kept / pixels with depth), AbsRel per confidence decile,
  wall time and peak memory of the run.
* Each ``--scene`` (a prepared scene with reference cameras and a split.json, e.g. `camio
  convert` of LLFF fern at images_8, 497x372): at its n = 3 (and 12 where the pool holds it)
  training views, the fused points seen from the held-out views: the share of a held-out view
  they cover and the colour error of the nearest point per covered pixel against the photo,
  beside the same points with their colours shuffled (geometry that says nothing), and the
  wall time and peak memory (the speed targets: 3 views of about 500x375 within 60 s, 12 within
  5 min, on 2 cores); and, where the scene's reference model has points with observations in
  the held-out views, the fused points' depth there against the reference points' (median
  relative error, share within 5 %, share of observations with a fused point on their pixel).

Each run is the CLI in its own process (``python -m evaluation.initialisers.mvs``), timed as a
whole; the machine's load average is printed beside the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def _cli(scene: Path, names: list[str], out: Path) -> dict:
    lst = out.parent / f"{out.name}.txt"
    lst.write_text("\n".join(names) + "\n")
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "evaluation.initialisers.mvs", "--scene", str(scene), "--image-list",
                    str(lst), "--out", str(out), "-q"], check=True, cwd=REPO)
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    status = json.loads((out / "status.json").read_text())
    return {"wall_s": wall, "peak_rss_mb": max(peak, before) / 1024, "working_size": status["working_size"],
            "kept_share": status["kept_share"], "points": status["points"]}


def synthetic(work: Path, views: list[int]) -> list[dict]:
    from camio.synthetic import write_synthetic_scene
    from evaluation.initialisers.mvs.accuracy import depth_accuracy

    scene = write_synthetic_scene(work / "synthetic", views=24, width=256, ns=tuple(views))
    split = json.loads((scene / "split.json").read_text())
    rows = []
    for n in views:
        names = split["train"][str(n)]
        out = work / f"synthetic_n{n}"
        run = _cli(scene, names, out)
        pred = np.load(out / "predictions.npz")
        gt = [np.load(scene / "gt" / "depth" / f"{Path(m).stem}.npy") for m in names]
        acc = depth_accuracy(list(np.where(pred["depth"] > 0, pred["depth"], np.nan)), list(pred["depth_conf"]), gt)
        rows.append({"scene": "synthetic", "n": n, **run, **{k: acc[k] for k in ("abs_rel", "delta1", "completeness")},
                     "abs_rel_by_conf_decile": [d["mean_error"] for d in acc["deciles"]]})
        r = rows[-1]
        print(f"synthetic n={n:2d}: AbsRel {r['abs_rel']:.4f}  delta1 {r['delta1']:.3f}  completeness "
              f"{r['completeness']:.3f}  {r['wall_s']:.1f} s  {r['peak_rss_mb']:.0f} MB", flush=True)
        print("    AbsRel per confidence decile, lowest first: "
              + " ".join(f"{e:.4f}" for e in r["abs_rel_by_conf_decile"]), flush=True)
    return rows


def real(scene: Path, work: Path) -> list[dict]:
    from camio.colmap import read_model
    from camio.images import read_image_uint8
    from evaluation.initialisers.mvs.accuracy import heldout_depth_error, heldout_reprojection, visible_points

    split = json.loads((scene / "split.json").read_text())
    ref = read_model(scene / "sparse" / "0")
    rows = []
    pool = split["train_pool"]
    for n in (3, 12):
        if n > len(pool):
            continue
        names = split["train"].get(str(n)) or [pool[int(round(i))] for i in np.linspace(0, len(pool) - 1, n)]
        out = work / f"{scene.name}_n{n}"
        run = _cli(scene, names, out)
        model = read_model(out / "sparse" / "0")
        held = [heldout_reprojection(model.points, model.colors, read_image_uint8(scene / "images" / t),
                                     ref.camera(t).K, ref.camera(t).cam_from_world) for t in split["test"]]
        mean = {k: float(np.mean([h[k] for h in held])) for k in ("coverage", "colour_error", "colour_error_shuffled")}
        depth = []
        for t in split["test"] if len(ref.points) else []:
            c = ref.camera(t)
            obs = ref.observations.get(t)
            if obs is None or not len(obs[1]):  # a model without tracks: the points the view sees
                obs = visible_points(ref.points, c.K, c.cam_from_world, c.width, c.height)
            depth.append(heldout_depth_error(model.points, ref.points, *obs, c.K, c.cam_from_world, c.width, c.height))
        if depth:
            w = np.array([d["observations"] for d in depth], float)
            for k in ("matched", "median_rel_error", "share_within_5pct"):
                mean[f"depth_{k}"] = float(np.nansum([d[k] * x for d, x in zip(depth, w)]) / w.sum())
        rows.append({"scene": scene.name, "n": n, **run, **mean, "test_views": len(held)})
        r = rows[-1]
        print(f"{scene.name} n={n:2d} at {r['working_size'][0]}x{r['working_size'][1]}: held-out coverage "
              f"{r['coverage']:.3f}, colour error {r['colour_error']:.1f} (shuffled {r['colour_error_shuffled']:.1f}) "
              f"of 255, {r['points']} points, {r['wall_s']:.1f} s, {r['peak_rss_mb']:.0f} MB", flush=True)
        if "depth_matched" in r:
            print(f"    against the reference points seen in the held-out views: {r['depth_matched']:.3f} have a "
                  f"fused point, median relative depth error {r['depth_median_rel_error']:.4f}, "
                  f"{r['depth_share_within_5pct']:.3f} within 5 %", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.mvs_accuracy", description=__doc__.split("\n\n")[0])
    p.add_argument("--synthetic-views", nargs="*", type=int, default=[3, 6, 12])
    p.add_argument("--scene", nargs="*", type=Path, default=[], help="prepared scenes with reference cameras")
    p.add_argument("--out", type=Path, help="write the figures as JSON")
    args = p.parse_args(argv)
    print(f"load average {os.getloadavg()}, {os.cpu_count()} cores", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        rows = synthetic(Path(tmp), args.synthetic_views) if args.synthetic_views else []
        for s in args.scene:
            rows += real(s, Path(tmp))
    if args.out:
        args.out.write_text(json.dumps({"load_avg": os.getloadavg(), "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
