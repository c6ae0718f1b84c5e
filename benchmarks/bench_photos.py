"""Your own photos to a trained, viewable model: wall time and peak memory (printed, not a test).

    python -m benchmarks.bench_photos PHOTOS [--count 8] [--work DIR] [--out JSON] [-- PHOTOS_PY_FLAGS...]

Copies the first ``--count`` photos of ``PHOTOS`` (sorted by name) into a fresh folder and runs
``python scripts/photos.py`` on them at its default settings (or with the flags after ``--``),
as a user would: COLMAP, the initialisers, training and the report, on this machine. Prints the
wall time of the whole command, the largest resident memory of any of its processes, each
workflow step's time and memory from Snakemake's ``benchmark`` files, the photos' sizes and the
machine's load average, and writes them to ``--out`` as JSON. The target it is read against:
8 twelve-megapixel photos in at most 15 minutes on a 2-core machine. Without a photo folder it
says so and exits 0, so that ``python -m benchmarks`` stays runnable anywhere; a PHOTOS that is
not a folder of at least ``--count`` photos, a missing ``--work`` or a folder ``--out`` is one
line and exit 2 before the run.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
#: the target: seconds for 8 twelve-megapixel photos on a 2-core machine
TARGET_S = 15 * 60
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".exr")


def _sizes(photos: list[Path]) -> list[list[int]]:
    from camio.images import image_size

    return [list(image_size(p)) for p in photos]


def _steps(out: Path) -> list[dict]:
    """Each Snakemake ``benchmark`` file under ``out``: its step, seconds and max RSS (MB)."""
    rows = []
    for tsv in sorted(out.rglob("benchmarks/*.tsv")):
        with open(tsv, newline="") as f:
            for r in csv.DictReader(f, delimiter="\t"):
                rows.append({"step": str(tsv.relative_to(out)), "s": float(r["s"]),
                             "max_rss_mb": float(r["max_rss"]) if r.get("max_rss") not in (None, "", "NA") else None})
    return rows


def pick_photos(photos_dir: Path, count: int) -> list[Path]:
    """The first ``count`` photos of ``photos_dir`` by name (suffixes :data:`PHOTO_SUFFIXES`).
    ValueError naming the folder, what it holds and what to do when it holds fewer."""
    photos = sorted(p for p in photos_dir.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)[:count]
    if len(photos) < count:
        raise ValueError(f"{photos_dir} holds {len(photos)} photos ({', '.join(sorted(PHOTO_SUFFIXES))}), "
                         f"{count} asked for: pass --count {len(photos)} or a folder with more" if photos else
                         f"{photos_dir} holds no photos ({', '.join(sorted(PHOTO_SUFFIXES))}): name a folder of photos")
    return photos


def run(photos: list[Path], work: Path, extra: list[str]) -> dict:
    src = work / "photos"
    src.mkdir(parents=True)
    for p in photos:
        shutil.copy2(p, src / p.name)
    out = work / "out"
    cmd = [sys.executable, str(REPO / "scripts" / "photos.py"), str(src), "--out", str(out), *extra]
    print("bench_photos:", " ".join(cmd), flush=True)
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=REPO)
    wall = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return {"photos": [p.name for p in photos], "sizes": _sizes(photos), "command": cmd[1:],
            "exit": res.returncode, "wall_s": wall, "peak_rss_mb": peak, "steps": _steps(out),
            "target_s": TARGET_S, "loadavg_start": list(load0), "loadavg_end": list(os.getloadavg()),
            "cpu_count": os.cpu_count()}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("photos", type=Path, nargs="?", help="a folder of photos (none: say so, exit 0)")
    p.add_argument("--count", type=int, default=8, help="photos taken, the first by name (default %(default)s)")
    p.add_argument("--work", type=Path, default=None, help="where the run goes (default: a temporary folder)")
    p.add_argument("--out", type=Path, default=None, help="write the figures here as JSON")
    args = p.parse_args(argv)
    if args.photos is None:
        print("bench_photos: no photo folder given (python -m benchmarks.bench_photos PHOTOS); nothing measured")
        return 0
    if args.count < 1:
        p.error(f"--count must be >= 1, got {args.count}")
    # everything a user can get wrong, before the long run: one line each, exit 2
    if not args.photos.is_dir():
        p.error(f"PHOTOS {args.photos} is not a folder: name the folder that holds the photos")
    if args.work is not None and not args.work.is_dir():
        p.error(f"--work {args.work} is not a folder: name an existing folder (the run goes in a temporary one inside it)")
    if args.out is not None and args.out.is_dir():
        p.error(f"--out {args.out} is a folder: name the JSON file to write")
    try:
        photos = pick_photos(args.photos, args.count)
    except ValueError as exc:
        p.error(str(exc))
    with tempfile.TemporaryDirectory(dir=args.work) as tmp:
        fig = run(photos, Path(tmp), extra)
    mp = [w * h / 1e6 for w, h in fig["sizes"]]
    print(f"\n{len(fig['photos'])} photos, {min(mp):.1f}-{max(mp):.1f} MP; exit {fig['exit']}; "
          f"wall {fig['wall_s']:.0f} s (target {TARGET_S} s: {'met' if fig['wall_s'] <= TARGET_S and fig['exit'] == 0 else 'not met'}); "
          f"largest process {fig['peak_rss_mb']:.0f} MB; load {fig['loadavg_start'][0]:.1f} -> {fig['loadavg_end'][0]:.1f} "
          f"on {fig['cpu_count']} CPUs")
    for s in sorted(fig["steps"], key=lambda r: -r["s"]):
        rss = "" if s["max_rss_mb"] is None else f"  {s['max_rss_mb']:.0f} MB"
        print(f"  {s['s']:8.1f} s{rss}  {s['step']}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(fig, indent=1) + "\n")
    return 0 if fig["exit"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
