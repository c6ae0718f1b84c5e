"""Target planning: the files of every (scene, n, initialiser) run up to a stage, leaving out
what does not apply. The initialisers whose status.json decides what follows (the registry's
``checkpoint``: the COLMAP baseline) are read through the colmap_index checkpoint."""

# ----------------------------------------------------------------------------- targets

# the registry's initialisers whose status.json decides what follows their run
CHECKPOINTED = initialisers.checkpointed()


def colmap_runs(wildcards=None):
    """status.json of every configured run of a checkpointed initialiser, and of those a dense
    step on its cameras starts from (inputs of the colmap_index checkpoint)."""
    return [
        f"{RUN.format(dataset=ds, scene=sc, n=n, init=base)}/status.json"
        for ds, sc in all_scenes()
        for base in CHECKPOINTED
        if any(
            i == base or initialisers.get(i).cameras_from == base
            for i in scene_inits(ds, sc)
        )
        for n in scene_views(ds, sc)
    ]


_colmap_pending = False


def checkpointed_status(dataset, scene, n, init):
    """status.json of a finished run of a checkpointed initialiser. Read through the
    colmap_index checkpoint, which waits for every such run, so the jobs after them are planned
    once all results exist (success or failure) rather than one checkpoint at a time."""
    global _colmap_pending
    try:
        checkpoints.colmap_index.get()
    except IncompleteCheckpointException:
        _colmap_pending = True
        raise
    if _colmap_pending:  # said once, when the jobs after them join the plan
        _colmap_pending = False
        logger.info(
            f"The {', '.join(CHECKPOINTED)} runs have finished: the jobs after them are planned "
            "now, so the step total grows (the steps done so far stay done)."
        )
    run = RUN.format(dataset=dataset, scene=scene, n=n, init=init)
    path = f"{run}/status.json"
    return json.loads(Path(path).read_text())


def run_targets(dataset, scene, n, init, stage):
    """The files of one (scene, n, initialiser) run up to ``stage``, leaving out what does
    not apply. COLMAP results that failed stop at their status.json (a recorded result),
    unless they fell back to random points for their cameras (status.json ``fallback``);
    held-out stages need >= 3 registered views for the Sim(3) alignment."""
    w = dict(dataset=dataset, scene=scene, n=n, init=init)
    run = RUN.format(**w)
    ref = has_reference(dataset, scene)
    heldout = ref and has_test_split(dataset, scene)
    base = initialisers.get(init).cameras_from
    if (
        base in CHECKPOINTED
        and checkpointed_status(dataset, scene, n, base).get("registered", 0) < 2
    ):
        return []  # no two cameras for stereo: the base's failure, reported as its own
    out = [f"{run}/{init_marker_of(init)}"]
    if stage == "init":
        return out
    aligned = True
    if init in CHECKPOINTED:
        status = checkpointed_status(dataset, scene, n, init)
        fallback = (status.get("fallback") or {}).get("applied", False)
        if not (status.get("success_paper", status.get("success")) or fallback):
            return out
        aligned = status["aligned_ok"]
    if base in CHECKPOINTED:
        aligned = checkpointed_status(dataset, scene, n, base)["aligned_ok"]
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
        if not ref and stage in ("render", "metrics", "all"):
            out.append(
                f"{m}/train_renders"
            )  # no held-out views: a render of every photo
        if stage == "train" or not (heldout and aligned):
            continue
        if config["train"]["pose_refine"]:
            out.append(f"{m}/align_refined/align.json")
        out.append(f"{m}/renders")
        if stage == "render":
            continue
        out.append(f"{m}/metrics.json")
        if config["evaluation"]["testpose"]:
            out.append(f"{m}/testpose/metrics.json")
    return out


def has_floor(dataset, scene):
    """The floor (floor.json per view count) applies: held-out views to score it on, and
    trained models whose metrics it is the floor of."""
    return (
        has_reference(dataset, scene)
        and has_test_split(dataset, scene)
        and config["train"]["enabled"]
    )


def stage_targets(stage, colmap):
    """Every run's files up to ``stage`` over all scenes, view counts and initialisers;
    the checkpointed runs (``colmap=True``, read through the checkpoint) or all the others
    (with, from the metrics stage on, each (scene, n)'s floor.json).

    Target rules take the two halves as separate input functions, so the runs that do not
    depend on COLMAP are planned (and shown by a dry run) before the checkpoint completes.
    """
    out = []
    for ds, sc in all_scenes():
        if not colmap:
            out.append(f"{R}/{ds}/{sc}/split.json")
        for n in scene_views(ds, sc):
            if not colmap and stage in ("metrics", "all") and has_floor(ds, sc):
                out.append(f"{R}/{ds}/{sc}/n{n}/floor.json")
            for init in scene_inits(ds, sc):
                if (init in CHECKPOINTED) == colmap:
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


def photo_scenes():
    """[(dataset, scene)] without reference cameras (your own photos): their runs end in a
    render of every photo, and R/photos.md says where everything is."""
    return [(ds, sc) for ds, sc in all_scenes() if not has_reference(ds, sc)]


def photo_runs_json(wildcards=None):
    """The runs R/photos.md describes, as a JSON string (a rule parameter)."""
    runs = [
        {
            "dataset": ds,
            "scene": sc,
            "n": n,
            "init": init,
            "modes": init_modes(init),
            "path": scene_cfg(ds, sc)["path"],
        }
        for ds, sc in photo_scenes()
        for n in scene_views(ds, sc)
        for init in scene_inits(ds, sc)
    ]
    return json.dumps(runs, sort_keys=True)


def photo_summary(wildcards=None):
    """R/photos.md when a scene has no reference cameras."""
    return [f"{R}/photos.md"] if photo_scenes() and config["train"]["enabled"] else []


def final_targets(wildcards=None):
    """What `all` makes: tables, plots (if training ran), the report, and R/photos.md for
    scenes without reference cameras."""
    return [
        f"{R}/tables/tables.md",
        *plot_dirs(),
        f"{R}/report/index.html",
        *photo_summary(),
    ]


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
