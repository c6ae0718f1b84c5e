"""Scene discovery: what each configured scene is (format, reference cameras, ground truth,
distortion: asked of camio, the one place that reads dataset layouts), how it is prepared,
its split and view counts, and which initialisers apply to it."""

from camio.scene import REFERENCE_FORMATS as _REFERENCE_FORMATS

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
    from camio.colmap import DISTORTED_MODELS
    from camio.datasets import source_camera_models

    return any(m in DISTORTED_MODELS for m in source_camera_models(cfg["path"]))


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
    """Arguments of `camio synth` for a synthetic scene: the keys its synth block sets (the
    others are camio.synthetic's defaults)."""
    s = scene_cfg(wildcards.dataset, wildcards.scene)["synth"]
    return " ".join(set_flags(s, ("views", "width", "seed")))


def convert_args(wildcards):
    """Arguments of `camio convert` (without --undistort, which the rule adds)."""
    cfg = scene_cfg(wildcards.dataset, wildcards.scene)
    args = [f"--src {shlex.quote(str(cfg['path']))}"]
    if cfg["format"] != "auto":
        args.append(f"--format {cfg['format']}")
    if cfg.get("images_subdir"):
        args.append(f"--images-subdir {shlex.quote(str(cfg['images_subdir']))}")
    args += set_flags(cfg, ("downsample",))
    if cfg.get("max_size") is not None:
        args.append(f"--max-size {cfg['max_size']}")
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
    return f"--n {views}" + (
        f" --manifest {shlex.quote(str(manifest))}" if manifest else ""
    )


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


# What a scene must have for an initialiser to run (the registry's ``needs`` that planning can
# check; VGGT's weights are looked up when its job runs).
_SCENE_CHECKS = {"reference": has_reference, "gt_geometry": has_gt_geometry}
_NOT_APPLICABLE = {
    name: (_SCENE_CHECKS[need], initialisers.NEEDS[need])
    for name, init in initialisers.INITIALISERS.items()
    for need in sorted(init.needs)
    if need in _SCENE_CHECKS
}
_told = set()

# ----------------------------------------------------------------------------- availability
# Initialisers that need weights (VGGT, and vggt_ba, which starts from VGGT) are asked once per
# run whether they can run here. The decision is made by the snakemake that plans the run and
# written to R/skipped.json (rule unavailable_initialisers, a local rule); the snakemake of a
# cluster job reads it back rather than asking again on a node that may see another network.
_NEEDS_VGGT = tuple(
    n for n, i in initialisers.INITIALISERS.items() if "weights" in i.needs
)
_unavailable = None


def _starts_from(name):
    """The initialiser whose run ``name`` starts from (its ``base`` or ``cameras_from``, followed
    to the first), or ``name`` itself."""
    init = initialisers.get(name)
    base = init.base or init.cameras_from
    return name if base is None else _starts_from(base)


def configured_inits():
    """Every initialiser some scene is configured with."""
    return {
        i
        for ds, sc in all_scenes()
        for i in scene_cfg(ds, sc).get("initialisers", config["initialisers"])
    }


def unavailable_inits():
    """{initialiser: reason} of configured initialisers that cannot run here (no VGGT
    checkpoint and no way to download one). Decided once; with ``unavailable_initialisers:
    error`` in the config a missing one stops the run before anything runs (exit 2)."""
    global _unavailable
    if _unavailable is not None:
        return _unavailable
    wanted = [i for i in _NEEDS_VGGT if i in configured_inits()]
    _unavailable = {}
    if not wanted:
        return _unavailable
    if workflow.remote_exec and Path(f"{R}/skipped.json").is_file():
        from evaluation.reports.run_status import read_skipped

        _unavailable = {i: w for i, w in read_skipped(R).items() if i in wanted}
        return _unavailable
    from vggt_init.checkpoint import skip_reason

    reason = skip_reason(explicit=config["vggt"]["checkpoint"])
    if reason is None:
        return _unavailable
    if config["unavailable_initialisers"] == "error":
        print(
            f"error: VGGT cannot run: {reason}. (unavailable_initialisers: skip runs the "
            "other initialisers instead.)",
            file=sys.stderr,
        )
        raise SystemExit(2)
    _unavailable = {
        i: (
            reason
            if _starts_from(i) == i
            else f"it starts from {_starts_from(i)}, which cannot run: {reason}"
        )
        for i in wanted
    }
    others = sorted(configured_inits() - set(_unavailable))
    logger.warning(
        f"VGGT skipped: {reason}. Running {', '.join(others) or 'no other initialiser'}; "
        f"{R}/skipped.json, the tables and the report list VGGT as skipped. (For the VGGT "
        "rows: VGGT_CHECKPOINT=/path/to/model.pt, see vggt_init/checkpoint.py; "
        "unavailable_initialisers: error makes this an error.)"
    )
    return _unavailable


def unavailable_json(wildcards=None):
    """:func:`unavailable_inits` as a JSON string (a rule parameter; a change reruns the
    tables and the report)."""
    return json.dumps(unavailable_inits(), sort_keys=True)


def write_skipped_file(out, log_file, skipped_json):
    """R/skipped.json ({initialiser: reason}; {} when all can run) and a line per entry in the log."""
    from runtime.atomic import write_json

    skipped = json.loads(skipped_json)
    write_json(out, skipped)
    Path(log_file).parent.mkdir(parents=True, exist_ok=True)
    Path(log_file).write_text(
        "".join(f"{i} skipped: {why}\n" for i, why in skipped.items())
        or "every configured initialiser can run\n"
    )


def scene_inits(dataset, scene):
    """Initialisers that apply: the oracle needs ground-truth geometry, ``posed`` reference
    cameras; one that cannot run here (:func:`unavailable_inits`) is left out. A configured
    one that does not apply is named once in the log (and in R/initialisers.json, which the
    report lists)."""
    inits = scene_cfg(dataset, scene).get("initialisers", config["initialisers"])
    skipped = unavailable_inits()
    out = []
    for i in inits:
        if i in skipped:
            continue
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
    """Bridge modes of an initialiser: the configured ones where it has a confidence (the
    registry's ``confidence``), else uniform only (COLMAP, posed, random points)."""
    return (
        config["bridge"]["modes"] if initialisers.get(init).confidence else ["uniform"]
    )
