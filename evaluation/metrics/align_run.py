"""The ``align`` step: fit prediction -> reference on training cameras, write the test cameras
in the trained model's frame.

Outputs (``--out DIR``):

* ``DIR/align.json``: the similarity (``scale``, ``R``, ``t``, direction prediction ->
  reference), per-camera centre and rotation residuals, ``rmse``, ``collinearity``,
  ``collinear``, ``used_orientations``, the training and test names used, ``train_cameras``
  (which training cameras the fit used: "initialiser", or "refined" = the trainer's
  ``cameras_refined`` after pose refinement), and
  ``intrinsics``: which intrinsics the test cameras carry ("reference", scaled to the
  test image size, as the seed code did).
* ``DIR/sparse/0/*.txt``: the reference TEST cameras brought into the prediction frame
  (``cam_from_world' = cam_from_world_ref o sim``, translation divided by the scale; see
  :func:`evaluation.metrics.align.transform_cam_from_world`), PINHOLE, at the test image size.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from runtime.atomic import write_json
from camio.cameras import Camera
from camio.colmap import read_model, write_text_model
from evaluation.metrics.align import COLLINEAR_TOL, fit_sim3_cameras, transform_cam_from_world
from runtime.checks import file_problem

__all__ = ["load_names", "test_cameras_in_model_frame", "run_align", "TRAIN_CAMERAS"]

# Which training cameras the Sim(3) was fitted on (align.json ``train_cameras``).
TRAIN_CAMERAS = ("initialiser", "refined")

log = logging.getLogger(__name__)


def load_names(spec: str | Path, which: str = "train", n: int | None = None,
               available: list[str] | None = None) -> list[str]:
    """Image names from a text file (one per line, '#' comments), a JSON list, or a
    ``split.json`` (docs/contracts.md).

    Args:
        spec: the file.
        which: "train" or "test" (only used for split.json).
        n: for split.json and ``which="train"``: the training list ``train[str(n)]``. Without
            it, the names of ``available`` that are in the split's training pool (or any
            training list) are returned.
        available: names present in the model at hand (see ``n``).

    Returns:
        Sorted unique names.
    """
    path = Path(spec)
    problem = file_problem(path, "names file")
    if problem:
        raise FileNotFoundError(problem)
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path} is not a text file of names ({exc.reason} at byte {exc.start})") from None
    if path.suffix.lower() != ".json":
        names = sorted({ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith("#")})
    else:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path} is not valid JSON: {exc}") from exc
        if not isinstance(data, list):
            return _split_names(path, data, which, n, available)
        names = sorted(set(map(str, data)))
    if not names:  # a list given by hand that names nothing is a mistake (a split's empty list is not)
        raise ValueError(f"{path} names no image: give one image name per line (or a JSON list, or a split.json)")
    return names


def _split_names(path: Path, data: object, which: str, n: int | None, available: list[str] | None) -> list[str]:
    """:func:`load_names` of a split.json's parsed ``data``."""
    if not isinstance(data, dict) or "test" not in data or "train" not in data:
        raise ValueError(f"{path}: expected a JSON list of names or a split.json with 'test' and 'train'")
    if which == "test":
        return sorted(data["test"])
    if which != "train":
        raise ValueError(f"which must be 'train' or 'test', got {which!r}")
    train = data["train"]
    if isinstance(train, list):
        return sorted(train)
    if n is not None:
        if str(n) not in train:
            raise ValueError(f"{path} has no training list for n = {n} (has {sorted(train)})")
        return sorted(train[str(n)])
    if available is None:
        raise ValueError(f"{path} holds training lists for several n ({sorted(train)}); give n")
    pool = set(data.get("train_pool", [])) | {x for v in train.values() for x in v}
    return sorted(a for a in available if a in pool)


def test_cameras_in_model_frame(ref_cameras: list[Camera], sim, size: tuple[int, int] | None = None,
                                scale: float | None = None) -> list[Camera]:
    """Reference cameras expressed in the prediction (trained model) frame.

    Args:
        ref_cameras: cameras in the reference frame.
        sim: the fitted similarity prediction -> reference.
        size: (width, height) of the test images, or None.
        scale: image scale factor (e.g. 0.125) when ``size`` is None; None keeps the size.

    Returns:
        Cameras with ``cam_from_world`` in the prediction frame and intrinsics scaled to the
        test image size.
    """
    inv = sim.inverse()
    out = []
    for cam in ref_cameras:
        if size is not None:
            w, h = size
        elif scale is not None:
            w, h = round(cam.width * scale), round(cam.height * scale)
        else:
            w, h = cam.width, cam.height
        scaled = cam.scaled(w, h)
        out.append(Camera(cam.name, w, h, scaled.K, transform_cam_from_world(cam.cam_from_world, inv)))
    return out


def run_align(pred_dir: str | Path, ref_dir: str | Path, train_names: str | Path,
              test_names: str | Path | None, out: str | Path, n: int | None = None,
              images_dir: str | Path | None = None, image_scale: float | None = None,
              use_orientations: str = "auto", collinear_tol: float = COLLINEAR_TOL,
              train_cameras: str = "initialiser") -> dict:
    """Fit the alignment and write ``align.json`` and ``sparse/0`` (see the module docstring).

    Args:
        pred_dir: the initialiser's (or bridge's) COLMAP model: its frame is the model's frame.
        ref_dir: the reference COLMAP model.
        train_names, test_names: names files (see :func:`load_names`); ``test_names`` None
            uses the "test" list of ``train_names`` when that is a split.json.
        out: output folder.
        n: training-view count, to pick the list from a split.json.
        images_dir: folder of the test images; their sizes set the test camera size.
        image_scale: size factor when ``images_dir`` is not given (None: reference size).
        train_cameras: what ``pred_dir`` holds, recorded in align.json: "initialiser" or
            "refined" (the training cameras after pose refinement).

    Returns:
        The align.json record.
    """
    if train_cameras not in TRAIN_CAMERAS:
        raise ValueError(f"train_cameras must be one of {TRAIN_CAMERAS}, got {train_cameras!r}")
    t0 = time.perf_counter()
    out = Path(out)
    pred = read_model(pred_dir)
    ref = read_model(ref_dir)
    train = load_names(train_names, "train", n, available=pred.names)
    test = load_names(test_names if test_names is not None else train_names, "test")
    leak = sorted(set(train) & set(test))
    if leak:
        raise ValueError(f"names are both training and test views: {leak[:5]}; check the split")
    al = fit_sim3_cameras({c.name: c.cam_from_world for c in pred.cameras},
                          {c.name: c.cam_from_world for c in ref.cameras}, train,
                          use_orientations=use_orientations, collinear_tol=collinear_tol)
    missing = [t for t in test if t not in ref.names]
    if missing:
        log.warning("%d test views have no reference camera and are skipped: %s", len(missing), missing[:5])
    present = [t for t in test if t in ref.names]
    if not present:
        raise ValueError(f"none of the {len(test)} test views has a reference camera in {ref_dir}")
    cams = []
    for name in present:
        size = None
        if images_dir is not None:
            from camio.images import image_size

            size = image_size(Path(images_dir) / name)
        cams += test_cameras_in_model_frame([ref.camera(name)], al.sim, size, image_scale)
    write_text_model(out / "sparse" / "0", cams)
    record = {
        **al.to_json(),
        "pred": str(pred_dir), "ref": str(ref_dir),
        "train_names": train, "test_names": present, "test_names_missing": missing,
        "intrinsics": "reference", "train_cameras": train_cameras,
        "test_image_sizes": {c.name: [c.width, c.height] for c in cams},
        "wall_time_s": time.perf_counter() - t0,
    }
    write_json(out / "align.json", record)
    log.info("align: %d training cameras fitted (ATE %.4g), %d test cameras written to %s in %.2f s",
             len(al.names), al.rmse, len(cams), out / "sparse" / "0", record["wall_time_s"])
    return record
