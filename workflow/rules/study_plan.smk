"""Planning of the initialisation study (rules: study.smk; docs/reference.md section 6): the grid
expanded from the config's `study:` section, its layout, targets and stage arguments. Empty
when the config has no `study:` section.

Layout (R = config["results"]):
    R/study/cells.json                                               the expanded grid
    R/study/{cell}/s{seed}/{dataset}/{scene}/n{n}/{init}/           initialiser output, pose.json
    R/study/{cell}/s{seed}/{dataset}/{scene}/n{n}/{init}/{mode}/    bridge/ align/ train/
                                             renders/ metrics.json floaters.json (GT mesh only)
    {init} = study.initialiser: oracle (default; scenes with ground-truth geometry, every
    Bridge mode) or posed (scenes with reference cameras; uniform only: no confidence).
    R/study/report/                          study.md, runs.csv, cells.csv, plots/, index.html

Reference initialisers (`study.references`, e.g. COLMAP): their regular runs
R/{dataset}/{scene}/n{n}/{init}/ (planning.smk's run_targets, through the colmap_index
checkpoint: a failed COLMAP stops at its status.json and is reported as failed) are inputs of
the study report, which shows them as one row each beside the cells.
"""

from evaluation.study.grid import expand_cells

STUDY = config.get("study")
STUDY_CELLS = expand_cells(STUDY) if STUDY else {}
# the studied initialiser: study.initialiser (the config check filled in the schema's default)
STUDY_INIT = STUDY["initialiser"] if STUDY else initialisers.studied()[0]
# the noise keys every studied initialiser takes (the registry's ``study``); those of the
# confidence (conf_noise, conf_mode) only apply to one with a confidence
POSED_NOISE = ("rot_deg", "trans_frac", "depth_rel", "outlier_frac")
if not initialisers.get(STUDY_INIT).confidence:
    _conf_cells = [
        c
        for c, info in STUDY_CELLS.items()
        if info["noise"].get("conf_noise", 0)
        or info["noise"].get("conf_mode", "ranked") != "ranked"
    ]
    if _conf_cells:
        raise ValueError(
            f"study cells {_conf_cells} set conf_noise / conf_mode, but study.initialiser "
            f"'{STUDY_INIT}' has no confidence (only {', '.join(POSED_NOISE)} apply)"
        )
STUDY_REFERENCES = list((STUDY or {}).get("references", []))
_missing_refs = [i for i in STUDY_REFERENCES if i not in config["initialisers"]]
if _missing_refs:
    raise ValueError(
        f"study.references {_missing_refs} must also be in `initialisers` "
        f"({config['initialisers']}): the study reports their regular runs"
    )
SRUN = f"{R}/study/{{cell}}/s{{seed}}/{{dataset}}/{{scene}}/n{{n}}/{STUDY_INIT}"
SMODE = f"{SRUN}/{{mode}}"


wildcard_constraints:
    cell=r"[A-Za-z0-9][A-Za-z0-9_.-]*",
    seed=r"\d+",


def study_scenes():
    """(dataset, scene) pairs of the study: the scenes that have what the studied initialiser
    needs (the registry's ``needs``: ground-truth geometry for the oracle, reference cameras
    for posed)."""
    checks = [
        _SCENE_CHECKS[n]
        for n in initialisers.get(STUDY_INIT).needs
        if n in _SCENE_CHECKS
    ]
    return [(ds, sc) for ds, sc in all_scenes() if all(ok(ds, sc) for ok in checks)]


def study_run_targets(wildcards=None):
    """metrics.json of every cell x seed x scene x n x mode, and floaters.json where the scene
    has a ground-truth mesh (the floater measure needs it)."""
    out = []
    for cell in STUDY_CELLS:
        for seed in STUDY["seeds"]:
            for ds, sc in study_scenes():
                for n in scene_views(ds, sc):
                    for mode in init_modes(STUDY_INIT):
                        m = SMODE.format(
                            cell=cell, seed=seed, dataset=ds, scene=sc, n=n, mode=mode
                        )
                        out.append(f"{m}/metrics.json")
                        if has_gt_geometry(ds, sc):
                            out.append(f"{m}/floaters.json")
                    run = SRUN.format(cell=cell, seed=seed, dataset=ds, scene=sc, n=n)
                    out.append(f"{run}/pose.json")
    return out


def study_reference_runs():
    """(init, dataset, scene, n) of every reference run of the study."""
    return [
        (init, ds, sc, n)
        for init in STUDY_REFERENCES
        for ds, sc in study_scenes()
        if init in scene_inits(ds, sc)
        for n in scene_views(ds, sc)
    ]


def study_reference_targets(wildcards=None):
    """The regular runs' files the report reads (run_targets: a failed COLMAP gives only its
    status.json; read through the colmap_index checkpoint)."""
    out = []
    for init, ds, sc, n in study_reference_runs():
        out += run_targets(ds, sc, n, init, "all")
    return out


def study_reference_args(wildcards=None):
    """--reference RUN_DIR for every reference run (evaluation study)."""
    return " ".join(
        f"--reference {shlex.quote(RUN.format(dataset=ds, scene=sc, n=n, init=init))}"
        for init, ds, sc, n in study_reference_runs()
    )


def study_final_targets(wildcards=None):
    """The study report when the config has a study section, else nothing."""
    return [f"{R}/study/report/study.md"] if STUDY else []


def study_oracle_args(wildcards):
    """Oracle CLI arguments of one cell and seed (downsample and conf_scale: config oracle,
    passed only when set: a null leaves the oracle's own default)."""
    noise = STUDY_CELLS[wildcards.cell]["noise"]
    args = [f"--{k.replace('_', '-')} {v}" for k, v in noise.items()]
    args += [f"--seed {wildcards.seed}"]
    args += set_flags(config["oracle"], ("conf_scale", "downsample"))
    return " ".join(args)


def study_posed_args(wildcards):
    """Posed-initialiser CLI arguments of one cell and seed (its noise keys, POSED_NOISE), and
    the random-point fallback of config random."""
    noise = STUDY_CELLS[wildcards.cell]["noise"]
    args = [f"--{k.replace('_', '-')} {noise[k]}" for k in POSED_NOISE if k in noise]
    return " ".join(args + [f"--seed {wildcards.seed}"] + fallback_args())


def study_scene_inputs(wildcards):
    return {
        "scene": scene_dir(wildcards),
        "image_list": f"{SCENE.format(**wildcards)}/n{wildcards.n}/train.txt",
        "split": f"{SCENE.format(**wildcards)}/split.json",
        "test_images": f"{SCENE.format(**wildcards)}/test_images",
    }


def study_train_inputs(wildcards):
    base = SMODE.format(**wildcards)
    s = study_scene_inputs(wildcards)
    return {
        "seed": f"{base}/bridge/seed.ply",
        "cameras": f"{base}/bridge/sparse",
        "scene": s["scene"],
        "image_list": s["image_list"],
        "test_cameras": f"{base}/align/sparse",
        "test_images": s["test_images"],
    }


def study_plan_args(wildcards=None):
    """--seeds / --views of the planned grid, so the report leaves out other runs in the tree."""
    views = sorted({int(n) for ds, sc in study_scenes() for n in scene_views(ds, sc)})
    seeds = " ".join(str(s) for s in STUDY["seeds"])
    return f"--seeds {seeds} --views {' '.join(str(n) for n in views)}"


def study_root(wildcards, output):
    """R/study, the folder of the study_report rule's cells.json output."""
    return str(Path(output.cells).parent)


def study_cells_json(wildcards=None):
    return json.dumps(STUDY_CELLS)
