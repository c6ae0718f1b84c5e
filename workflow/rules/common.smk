"""Config validation and every helper the rules use (no lambdas inside rules).

Layout of the outputs (R = config["results"]):

    R/{dataset}/{scene}/{synth|converted|undistorted}/   prepared scene (images, sparse/0, gt/)
    R/{dataset}/{scene}/split.json                        the split used
    R/{dataset}/{scene}/n{n}/train.txt                    the n training names
    R/{dataset}/{scene}/test_images/                      links to the held-out images
    R/{dataset}/{scene}/n{n}/{init}/                      initialiser output (sparse/0, status.json)
    R/{dataset}/{scene}/n{n}/{init}/pose.json             pose accuracy (reference cameras only)
    R/initialisers.json                                   configured initialisers a scene cannot have
    R/{dataset}/{scene}/n{n}/{init}/{mode}/bridge/        seed.ply, bridge.json, sparse/0
    R/{dataset}/{scene}/n{n}/{init}/{mode}/align/         test cameras in the model frame
    R/{dataset}/{scene}/n{n}/{init}/{mode}/train/         model.ply, log.parquet, train.json
    R/{dataset}/{scene}/n{n}/{init}/{mode}/renders/       held-out renders
    R/{dataset}/{scene}/n{n}/{init}/{mode}/metrics.json   held-out image metrics
    R/tables/, R/plots/, R/report/
    R/.../logs/<rule>.log, R/.../benchmarks/<rule>.tsv    beside the outputs they describe
"""

import json

from snakemake.logging import logger
from pathlib import Path

from snakemake.utils import validate

validate(config, schema="../schemas/config.schema.yaml", set_default=True)

R = config["results"].rstrip("/")
SCENE = f"{R}/{{dataset}}/{{scene}}"
RUN = f"{SCENE}/n{{n}}/{{init}}"
MODE = f"{RUN}/{{mode}}"

# COLMAP baseline threads: the configured count, or every core snakemake was given.
COLMAP_THREADS = config["colmap"]["threads"] or max(1, int(workflow.cores or 1))

# The workflow's own helper script, found from the workflow (any working directory works).
VIEWS_SCRIPT = str(
    (Path(str(workflow.current_basedir)) / "../scripts/views.py").resolve()
)

# Formats whose source carries reference cameras.
_REFERENCE_FORMATS = ("colmap", "llff", "transforms", "dtu", "mvsnet", "strecha")
_DISTORTED = (
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "FULL_OPENCV",
    "OPENCV_FISHEYE",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "FOV",
    "THIN_PRISM_FISHEYE",
)


wildcard_constraints:
    dataset=r"[A-Za-z0-9][A-Za-z0-9_.-]*",
    scene=r"[A-Za-z0-9][A-Za-z0-9_.-]*",
    n=r"\d+",
    init=r"vggt|colmap|oracle|posed",
    mode=r"gated|uniform|filtered",


# ----------------------------------------------------------------------------- scenes


def scene_cfg(dataset, scene):
    """The config block of one scene (KeyError naming it if absent)."""
    try:
        return config["datasets"][dataset]["scenes"][scene]
    except KeyError:
        raise WorkflowError(
            f"scene {dataset}/{scene} is not in the config (datasets.{dataset}.scenes)"
        )


def all_scenes():
    """[(dataset, scene)] in config order."""
    return [
        (ds, sc) for ds, block in config["datasets"].items() for sc in block["scenes"]
    ]


def source_format(dataset, scene):
    """The source format, 'auto' resolved by camio's detection (the camera files present)."""
    cfg = scene_cfg(dataset, scene)
    if "synth" in cfg:
        return "synth"
    fmt = cfg["format"]
    if fmt != "auto":
        return fmt
    from camio.scene import detect_format

    try:
        return detect_format(cfg["path"])
    except ValueError as exc:
        raise WorkflowError(f"datasets.{dataset}.scenes.{scene}: {exc}")


def has_reference(dataset, scene):
    """Does the scene have reference cameras (pose evaluation, held-out renders)?"""
    cfg = scene_cfg(dataset, scene)
    if "reference" in cfg:
        return cfg["reference"]
    return source_format(dataset, scene) in ("synth",) + _REFERENCE_FORMATS


def has_gt_geometry(dataset, scene):
    """Ground-truth depth and points (the oracle needs them): synthetic scenes only."""
    return "synth" in scene_cfg(dataset, scene)


def needs_undistort(dataset, scene):
    """Undistort only distorted data: explicit config, else the source model's cameras."""
    cfg = scene_cfg(dataset, scene)
    if "synth" in cfg:
        return False
    if cfg["undistort"] != "auto":
        return bool(cfg["undistort"])
    from camio.datasets import source_camera_models

    return any(m in _DISTORTED for m in source_camera_models(cfg["path"]))


def prepare_kind(dataset, scene):
    """'synth', 'converted' or 'undistorted': the rule (and folder) that prepares the scene."""
    if has_gt_geometry(dataset, scene):
        return "synth"
    return "undistorted" if needs_undistort(dataset, scene) else "converted"


def scene_dir_of(dataset, scene):
    return f"{R}/{dataset}/{scene}/{prepare_kind(dataset, scene)}"


def scene_dir(wildcards):
    """Input function: the prepared scene folder of a job's (dataset, scene)."""
    return scene_dir_of(wildcards.dataset, wildcards.scene)


def synth_args(wildcards):
    """Arguments of `camio synth` for a synthetic scene."""
    s = scene_cfg(wildcards.dataset, wildcards.scene)["synth"]
    return f"--views {s['views']} --width {s['width']} --seed {s['seed']}"


def convert_args(wildcards):
    """Arguments of `camio convert` (without --undistort, which the rule adds)."""
    cfg = scene_cfg(wildcards.dataset, wildcards.scene)
    args = [f"--src {cfg['path']}"]
    if cfg["format"] != "auto":
        args.append(f"--format {cfg['format']}")
    if cfg.get("images_subdir"):
        args.append(f"--images-subdir {cfg['images_subdir']}")
    if cfg["downsample"] > 1:
        args.append(f"--downsample {cfg['downsample']}")
    if cfg["skip_missing"]:
        args.append("--skip-missing")
    if cfg["allow_mixed"]:
        args.append("--allow-mixed")
    return " ".join(args)


def convert_source(wildcards):
    """Input function: the source folder of a converted scene (tracked for changes)."""
    return scene_cfg(wildcards.dataset, wildcards.scene)["path"]


# ----------------------------------------------------------------------------- splits


def split_manifest(dataset, scene):
    cfg = scene_cfg(dataset, scene)["split"]
    if cfg["rule"] != "manifest":
        return None
    if "manifest" not in cfg:
        raise WorkflowError(
            f"datasets.{dataset}.scenes.{scene}.split: rule 'manifest' needs a 'manifest' file"
        )
    return cfg["manifest"]


def split_inputs(wildcards):
    """Input function: the prepared scene, plus the manifest when there is one."""
    out = {"scene": scene_dir(wildcards)}
    manifest = split_manifest(wildcards.dataset, wildcards.scene)
    if manifest:
        out["manifest"] = manifest
    return out


def split_args(wildcards):
    views = " ".join(str(n) for n in scene_views(wildcards.dataset, wildcards.scene))
    manifest = split_manifest(wildcards.dataset, wildcards.scene)
    return f"--n {views}" + (f" --manifest {manifest}" if manifest else "")


def has_test_split(dataset, scene):
    """Held-out views exist: every8 always has them; a manifest only if its test list is not empty."""
    manifest = split_manifest(dataset, scene)
    if manifest is None:
        return True
    try:
        return len(json.loads(Path(manifest).read_text()).get("test", [])) > 0
    except (OSError, ValueError) as exc:
        raise WorkflowError(f"cannot read the split manifest {manifest}: {exc}")


def scene_views(dataset, scene):
    cfg = scene_cfg(dataset, scene)
    return cfg.get("views", config["views"])


_NOT_APPLICABLE = {
    "oracle": (has_gt_geometry, "it needs ground-truth depth (synthetic scenes only)"),
    "posed": (has_reference, "it needs reference cameras and the scene has none"),
}
_told = set()


def scene_inits(dataset, scene):
    """Initialisers that apply: the oracle needs ground-truth geometry, ``posed`` reference
    cameras. A configured one that does not apply is named once in the log (and in
    R/initialisers.json, which the report lists)."""
    inits = scene_cfg(dataset, scene).get("initialisers", config["initialisers"])
    out = []
    for i in inits:
        check, why = _NOT_APPLICABLE.get(i, (None, None))
        if check is not None and not check(dataset, scene):
            if (dataset, scene, i) not in _told:
                _told.add((dataset, scene, i))
                logger.warning(
                    f"{dataset}/{scene}: initialiser '{i}' is not run: {why}"
                )
            continue
        out.append(i)
    return out


def skipped_initialisers(wildcards=None):
    """[{dataset, scene, init, reason}] of configured initialisers that do not apply."""
    out = []
    for ds, sc in all_scenes():
        inits = scene_cfg(ds, sc).get("initialisers", config["initialisers"])
        for i in inits:
            check, why = _NOT_APPLICABLE.get(i, (None, None))
            if check is not None and not check(ds, sc):
                out.append({"dataset": ds, "scene": sc, "init": i, "reason": why})
    return out


def skipped_initialisers_json(wildcards=None):
    """:func:`skipped_initialisers` as a JSON string (a rule parameter)."""
    return json.dumps(skipped_initialisers())


def init_modes(init):
    """Bridge modes of an initialiser: COLMAP and posed have no confidence, so uniform only."""
    return ["uniform"] if init in ("colmap", "posed") else config["bridge"]["modes"]


# ----------------------------------------------------------------------------- stages


def vggt_args(wildcards):
    v = config["vggt"]
    args = [f"--dtype {v['dtype']}", f"--points-from {v['points_from']}"]
    if v["checkpoint"]:
        args.append(f"--checkpoint {v['checkpoint']}")
    if v["model_config"]:
        args.append(f"--model-config {v['model_config']}")
    if v["image_size"]:
        args.append(f"--image-size {v['image_size']}")
    return " ".join(args)


def colmap_args(wildcards):
    c = config["colmap"]
    args = [
        f"--seed {c['seed']}",
        f"--max-image-size {c['max_image_size']}",
        f"--max-num-features {c['max_num_features']}",
    ]
    if c["repeats"] > 1:
        args.append(f"--repeats {c['repeats']}")
        if has_reference(wildcards.dataset, wildcards.scene):
            # every repeat is evaluated against the reference: ATE and gated-success spread
            args.append(f"--ref {scene_dir(wildcards)}/sparse/0 {gate_args()}")
    return " ".join(args)


def oracle_args(wildcards):
    o = config["oracle"]
    return " ".join(
        f"--{k.replace('_', '-')} {o[k]}"
        for k in (
            "seed",
            "rot_deg",
            "trans_frac",
            "depth_rel",
            "outlier_frac",
            "conf_scale",
            "conf_noise",
            "downsample",
        )
    )


def posed_args(wildcards):
    o = config["posed"]
    return " ".join(
        f"--{k.replace('_', '-')} {o[k]}"
        for k in ("seed", "rot_deg", "trans_frac", "depth_rel", "outlier_frac")
    )


def bridge_args(wildcards):
    b = config["bridge"]
    args = [f"--mode {wildcards.mode}"]
    if b["stride"]:
        args.append(f"--stride {b['stride']}")
    if b["max_points"]:
        args.append(f"--max-points {b['max_points']}")
    return " ".join(args)


def gate_args(wildcards=None):
    e = config["evaluation"]
    return (
        f"--max-ate-rel-radius {e['max_ate_rel_radius']} "
        f"--max-rel-rot-deg {e['max_rel_rot_deg']}"
    )


def lpips_args(wildcards):
    return f"--lpips-nets {' '.join(config['evaluation']['lpips_nets'])}"


def has_heldout(wildcards):
    """Held-out evaluation applies: reference cameras and a test split."""
    return has_reference(wildcards.dataset, wildcards.scene) and has_test_split(
        wildcards.dataset, wildcards.scene
    )


def init_marker_of(init):
    """The file that marks a finished initialiser run: VGGT writes timing.json, the COLMAP
    baseline, the oracle and posed status.json."""
    return "timing.json" if init == "vggt" else "status.json"


def init_marker(wildcards):
    """Input function: the finished-run marker of a job's initialiser."""
    return f"{RUN.format(**wildcards)}/{init_marker_of(wildcards.init)}"


def train_inputs(wildcards):
    """Input function of training: seed, cameras, images, list; held-out views when they exist."""
    base = MODE.format(**wildcards)
    out = {
        "seed": f"{base}/bridge/seed.ply",
        "cameras": f"{base}/bridge/sparse",
        "scene": scene_dir(wildcards),
        "image_list": f"{SCENE.format(**wildcards)}/n{wildcards.n}/train.txt",
    }
    if has_heldout(wildcards):
        out["test_cameras"] = f"{base}/align/sparse"
        out["test_images"] = f"{SCENE.format(**wildcards)}/test_images"
    return out


def train_test_args(wildcards, input):
    if "test_cameras" in input.keys():
        return (
            f"--test-cameras {input.test_cameras}/0 --test-images {input.test_images}"
        )
    return ""


# ----------------------------------------------------------------------------- params
# Folders passed to the CLIs are derived from each job's own files (no hard-coded prefixes).


def out_dir(wildcards, output):
    """The folder of a job's first output file (the stage CLI's --out)."""
    return str(Path(output[0]).parent)


def init_model_dir(wildcards, input):
    """The initialiser's COLMAP model, beside its finished-run marker (input.init)."""
    return f"{Path(input.init).parent}/sparse/0"


def results_of_output(wildcards, output):
    """The results root, two levels above R/<folder>/<file>."""
    return str(Path(output[0]).parents[1])


def results_of_input(wildcards, input):
    """The results root, two levels above the first input R/<folder>/<file>."""
    return str(Path(input[0]).parents[1])


# ----------------------------------------------------------------------------- targets


def colmap_runs(wildcards=None):
    """status.json of every configured COLMAP run (inputs of the colmap_index checkpoint)."""
    return [
        f"{RUN.format(dataset=ds, scene=sc, n=n, init='colmap')}/status.json"
        for ds, sc in all_scenes()
        if "colmap" in scene_inits(ds, sc)
        for n in scene_views(ds, sc)
    ]


def colmap_status(dataset, scene, n):
    """status.json of a finished COLMAP run. Read through the colmap_index checkpoint, which
    waits for every COLMAP run, so the jobs after COLMAP are planned once all results exist
    (success or failure) rather than one checkpoint at a time."""
    checkpoints.colmap_index.get()
    run = RUN.format(dataset=dataset, scene=scene, n=n, init="colmap")
    path = f"{run}/status.json"
    return json.loads(Path(path).read_text())


def run_targets(dataset, scene, n, init, stage):
    """The files of one (scene, n, initialiser) run up to ``stage``, leaving out what does
    not apply. COLMAP results that failed stop at their status.json (a recorded result);
    held-out stages need >= 3 registered views for the Sim(3) alignment."""
    w = dict(dataset=dataset, scene=scene, n=n, init=init)
    run = RUN.format(**w)
    ref = has_reference(dataset, scene)
    heldout = ref and has_test_split(dataset, scene)
    out = [f"{run}/{init_marker_of(init)}"]
    if stage == "init":
        return out
    aligned = True
    if init == "colmap":
        status = colmap_status(dataset, scene, n)
        if not status.get("success_paper", status.get("success")):
            return out
        aligned = status["aligned_ok"]
    if ref and stage in ("pose", "all"):
        out.append(f"{run}/pose.json")
    if stage == "pose" or not config["train"]["enabled"]:
        return out
    for mode in init_modes(init):
        m = MODE.format(mode=mode, **w)
        out.append(f"{m}/bridge/seed.ply")
        if stage == "bridge":
            continue
        if heldout and aligned and stage in ("align", "render", "metrics", "all"):
            out.append(f"{m}/align/align.json")
        if stage == "align":
            continue
        out.append(f"{m}/train/model.ply")
        if stage == "train" or not (heldout and aligned):
            continue
        out.append(f"{m}/renders")
        if stage == "render":
            continue
        out.append(f"{m}/metrics.json")
    return out


def stage_targets(stage, colmap):
    """Every run's files up to ``stage`` over all scenes, view counts and initialisers;
    the COLMAP runs (``colmap=True``, read through the checkpoint) or all the others.

    Target rules take the two halves as separate input functions, so the runs that do not
    depend on COLMAP are planned (and shown by a dry run) before the checkpoint completes.
    """
    out = []
    for ds, sc in all_scenes():
        if not colmap:
            out.append(f"{R}/{ds}/{sc}/split.json")
        for n in scene_views(ds, sc):
            for init in scene_inits(ds, sc):
                if (init == "colmap") == colmap:
                    out += run_targets(ds, sc, n, init, stage)
    return out


def targets_of(stage):
    """Two input functions for a stage target: (non-COLMAP runs, COLMAP runs)."""

    def others(wildcards=None):
        return stage_targets(stage, colmap=False)

    def colmap(wildcards=None):
        return stage_targets(stage, colmap=True)

    others.__name__ = f"{stage}_targets"
    colmap.__name__ = f"{stage}_colmap_targets"
    return others, colmap


def plot_dirs(wildcards=None):
    """The plots folder when there is training to plot (curves, PSNR/run-time Pareto)."""
    return [f"{R}/plots"] if config["train"]["enabled"] else []


def final_targets(wildcards=None):
    """What `all` makes: tables, plots (if training ran) and the report."""
    return [f"{R}/tables/tables.md", *plot_dirs(), f"{R}/report/index.html"]


def prepared_scenes(wildcards=None):
    return [scene_dir_of(ds, sc) for ds, sc in all_scenes()]


def splits(wildcards=None):
    return [f"{R}/{ds}/{sc}/split.json" for ds, sc in all_scenes()]


INIT_TARGETS = targets_of("init")
POSE_TARGETS = targets_of("pose")
BRIDGE_TARGETS = targets_of("bridge")
ALIGN_TARGETS = targets_of("align")
TRAIN_TARGETS = targets_of("train")
RENDER_TARGETS = targets_of("render")
METRIC_TARGETS = targets_of("metrics")
ALL_TARGETS = targets_of("all")
