"""The floor: a flat image of the training views' mean colour, scored like a model.

A model that learnt nothing but the mean colour of its training views scores this on the
held-out views; a recipe's figure means something only above it. Per (scene, n) the floor is
the mean held-out PSNR of that flat image (8-bit, as renders are scored), over the held-out
views of the cell's split (:func:`experiments.sparse_views.cells.prepare_split`: the same scene,
split and name lists as every run of the cell).

    python -m experiments.sparse_views --data DIR floor --work WORK [--scenes ...] [--n ...]

writes ``<records>/floors.json`` ({scene: {n: PSNR}}), which the summary reads; a (scene, n)
already there is kept, so the file grows as scenes are measured.
"""

from __future__ import annotations

import json
from pathlib import Path

FLOORS = "floors.json"

__all__ = ["floor_psnr", "measure_floors", "load_floors", "FLOORS"]


def floor_psnr(cell: Path) -> float | None:
    """Mean held-out PSNR of a flat image of the training views' mean colour
    (:mod:`imgmetrics.floor`, 8-bit, as the renders are scored), over the test views of a
    prepared cell (scene/, train.txt, test.txt); None where the cell is not here."""
    import numpy as np

    from camio.images import read_image_uint8
    from imgmetrics.floor import flat_colour, flat_image

    if not (cell / "train.txt").is_file():
        return None
    images = cell / "scene" / "images"
    names = lambda f: [n for n in (cell / f).read_text().split() if n]  # noqa: E731
    colour = flat_colour(read_image_uint8(images / n) for n in names("train.txt"))
    out = []
    for n in names("test.txt"):
        gt = read_image_uint8(images / n).astype(np.float64)
        flat = flat_image(colour, *gt.shape[:2]).astype(np.float64)
        mse = np.mean((gt - flat) ** 2) / 255.0 ** 2
        out.append(10 * np.log10(1.0 / max(mse, 1e-12)))
    return float(np.mean(out))


def load_floors(records: Path) -> dict[str, dict[int, float]]:
    """``<records>/floors.json`` as {scene: {n: PSNR}}; {} when there is none."""
    p = Path(records) / FLOORS
    if not p.is_file():
        return {}
    raw = json.loads(p.read_text())
    return {scene: {int(n): float(v) for n, v in per.items()} for scene, per in raw.get("floors", {}).items()}


def measure_floors(records: Path, work: Path, scenes: list, ns: list[int] | None = None) -> dict:
    """Prepare each (scene, n) cell's split in ``work`` (no seed, no training), score its floor
    and add it to ``<records>/floors.json``; (scene, n) pairs already recorded are kept as they
    are. ``scenes``: protocol scenes whose data is here; ``ns``: view counts (default the
    scene's own). Returns the whole file's floors."""
    from experiments.sparse_views.cells import cell_lock, prepare_split
    from runtime.atomic import atomic_path

    floors = load_floors(records)
    for scene in scenes:
        for n in ns or scene.views:
            if n in floors.get(scene.name, {}):
                continue
            cell = Path(work) / f"{scene.name}_n{n}"
            with cell_lock(cell):
                prepare_split(cell, scene, n)
            psnr = floor_psnr(cell)
            floors.setdefault(scene.name, {})[n] = psnr
            print(f"floor {scene.name} n={n}: {psnr:.2f} dB", flush=True)
    doc = {"what": "held-out PSNR of a flat image of the training views' mean colour (8-bit), "
                   "per scene and view count (experiments/sparse_views/floor.py)",
           "floors": {s: {str(n): v for n, v in sorted(per.items())} for s, per in sorted(floors.items())}}
    Path(records).mkdir(parents=True, exist_ok=True)
    with atomic_path(Path(records) / FLOORS) as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=1) + "\n")
    return floors
