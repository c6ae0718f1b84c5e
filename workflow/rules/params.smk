"""Stage arguments and parameters of the rules (CLI arguments each one passes), input
functions, and the folders derived from a job's own files."""

# ----------------------------------------------------------------------------- stages


def set_flags(section, keys):
    """``--key-name value`` of each of ``keys`` set in a config section; a null or absent key
    (the schema's default for a value its stage owns) passes no flag, so the stage's own
    default acts."""
    return [
        f"--{k.replace('_', '-')} {section[k]}"
        for k in keys
        if section.get(k) is not None
    ]


def vggt_args(wildcards):
    v = config["vggt"]
    # the device is the workflow's: its resources ask the cluster for a GPU from it
    args = [f"--device {v['device']}"] + set_flags(v, ("dtype", "points_from"))
    if v["checkpoint"]:
        args.append(f"--checkpoint {shlex.quote(str(v['checkpoint']))}")
    if v["model_config"]:
        args.append(f"--model-config {shlex.quote(str(v['model_config']))}")
    if v["image_size"]:
        args.append(f"--image-size {v['image_size']}")
    return " ".join(args)


def colmap_args(wildcards):
    c = config["colmap"]
    args = set_flags(c, ("seed", "max_image_size", "max_num_features"))
    args += fallback_args()
    if c["repeats"] > 1:
        args.append(f"--repeats {c['repeats']}")
        if has_reference(wildcards.dataset, wildcards.scene):
            # every repeat is evaluated against the reference: ATE and gated-success spread
            args.append(
                f"--ref {shlex.quote(str(Path(scene_dir(wildcards), 'sparse', '0')))} {gate_args()}"
            )
    return " ".join(args)


def oracle_args(wildcards):
    """The oracle's arguments set in config oracle (null keys are left to
    evaluation.initialisers.oracle; the study's cells read conf_scale and downsample too).
    """
    keys = (
        "seed",
        "rot_deg",
        "trans_frac",
        "depth_rel",
        "outlier_frac",
        "conf_scale",
        "conf_noise",
        "downsample",
    )
    return " ".join(set_flags(config["oracle"], keys))


def posed_args(wildcards):
    keys = ("seed", "rot_deg", "trans_frac", "depth_rel", "outlier_frac")
    return " ".join(set_flags(config["posed"], keys) + fallback_args())


def mvs_args(wildcards):
    """evaluation.initialisers.mvs's arguments (config mvs; null keys are left to its MvsConfig,
    the one place of their defaults)."""
    return " ".join(set_flags(config["mvs"], ("max_size", "max_sources")))


def dense_base_marker(wildcards):
    """The finished-run marker of the initialiser whose cameras a dense step starts from."""
    run = RUN.format(
        dataset=wildcards.dataset,
        scene=wildcards.scene,
        n=wildcards.n,
        init=wildcards.base,
    )
    return f"{run}/{init_marker_of(wildcards.base)}"


def dense_base_model(wildcards, input):
    """That initialiser's COLMAP model (beside its marker)."""
    return f"{Path(input.init).parent}/sparse/0"


def fallback_args():
    """The random-point fallback of posed and COLMAP (config random; null keys are left to
    evaluation.initialisers.random_init, the one place of their defaults)."""
    r = config["random"]
    args = []
    if r["fallback_min_points"] is not None:
        args.append(f"--fallback-min-points {r['fallback_min_points']}")
    if r["points"] is not None:
        args.append(f"--fallback-points {r['points']}")
    return args


def random_args(wildcards):
    """evaluation.initialisers.random_init's arguments (config random)."""
    return " ".join(set_flags(config["random"], ("seed", "points")))


def ba_args(wildcards):
    """evaluation.initialisers.ba_init's arguments (config ba); the step on a base without a
    confidence (posed_ba) seeds from the triangulated points."""
    b = config["ba"]
    args = set_flags(b, ("seed", "min_points"))
    if b["refine_focal"]:
        args.append("--refine-focal")
    if not initialisers.get(wildcards.base).confidence:
        args.append("--seed-points triangulated")
    return " ".join(args)


def ba_base_inputs(wildcards):
    """The base initialiser's finished-run marker (its sparse/0 lies beside it) and, for VGGT
    and the oracle, its predictions.npz (the dense seed)."""
    run = RUN.format(
        dataset=wildcards.dataset,
        scene=wildcards.scene,
        n=wildcards.n,
        init=wildcards.base,
    )
    out = {"init": f"{run}/{init_marker_of(wildcards.base)}"}
    if initialisers.get(wildcards.base).confidence:
        out["predictions"] = f"{run}/predictions.npz"
    return out


def ba_base_dir(wildcards, input):
    """The base initialiser's output folder (beside its finished-run marker, input.init)."""
    return str(Path(input.init).parent)


def bridge_args(wildcards):
    b = config["bridge"]
    args = [f"--mode {wildcards.mode}"]
    if b["stride"]:
        args.append(f"--stride {b['stride']}")
    if b["max_points"]:
        args.append(f"--max-points {b['max_points']}")
    return " ".join(args)


def gate_args(wildcards=None):
    """The accuracy gate set in config evaluation (null keys are left to
    evaluation.metrics.pose, the one place of their defaults)."""
    return " ".join(
        set_flags(config["evaluation"], ("max_ate_rel_radius", "max_rel_rot_deg"))
    )


def lpips_args(wildcards):
    """--lpips-nets when set in config evaluation ([] = none); null: the command's default."""
    nets = config["evaluation"]["lpips_nets"]
    return "" if nets is None else f"--lpips-nets {' '.join(nets)}"


def testpose_args(wildcards):
    """The test-pose job's device (training's) and, when set, its steps and patience."""
    ev = config["evaluation"]
    args = [f"--device {config['train']['device']}"]
    if ev["testpose_steps"] is not None:
        args.append(f"--steps {ev['testpose_steps']}")
    if ev["testpose_patience"] is not None:
        args.append(f"--patience {ev['testpose_patience']}")
    return " ".join(args)


def has_heldout(wildcards):
    """Held-out evaluation applies: reference cameras and a test split."""
    return has_reference(wildcards.dataset, wildcards.scene) and has_test_split(
        wildcards.dataset, wildcards.scene
    )


def init_marker_of(init):
    """The file that marks a finished initialiser run (the registry's ``marker``: VGGT's
    timing.json, every other initialiser's status.json)."""
    return initialisers.get(init).marker


def init_command(wildcards):
    """The module the common rule runs for a job's initialiser (the registry's ``command``)."""
    return initialisers.get(wildcards.init).command


def init_option_args(wildcards):
    """The flags of a common-rule initialiser's options (the registry's ``options``), valued from
    its config block (the config check filled in each default)."""
    init = initialisers.get(wildcards.init)
    block = config.get(init.name) or {}
    return " ".join(
        shlex.quote(a)
        for o in init.options
        for a in o.args(block.get(o.key, o.default))
    )


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


def train_resume_dir(wildcards, output):
    """Checkpoints of a training job: beside train/, outside the rule's outputs, so Snakemake
    never deletes them as incomplete and a killed job's rerun resumes from them."""
    return str(Path(output.model).parent.parent / "train_resume")


def train_test_args(wildcards, input):
    if "test_cameras" in input.keys():
        return (
            f"--test-cameras {shlex.quote(str(Path(input.test_cameras, '0')))} "
            f"--test-images {shlex.quote(input.test_images)}"
        )
    return ""


def pose_refine_args(wildcards):
    """splat_train's pose-refinement switches (train.pose_refine, train.pose_refine_focal)."""
    t = config["train"]
    if not t["pose_refine"]:
        return ""
    return "--pose-refine" + (" --pose-refine-focal" if t["pose_refine_focal"] else "")


def train_recipe_args(wildcards):
    """--recipe, --iterations and the recipe parts set in the config (null keys are left to
    splat_train, whose recipes and config are the one place of their defaults)."""
    import json

    t = config["train"]
    args = [f"--recipe {t['recipe']}"] if t["recipe"] is not None else []
    if t["iterations"] is not None:
        args.append(f"--iterations {t['iterations']}")
    keys = (
        "dropout_rate",
        "depth_weight",
        "binocular_weight",
        "opacity_decay",
        "gaussians_per_pixel",
        "depth_use_confidence",
    )
    parts = {k: t[k] for k in keys if t[k] is not None}
    if parts:
        args.append(f"--config {shlex.quote(json.dumps(parts, sort_keys=True))}")
    return " ".join(args)


def train_set_args(wildcards):
    """--seed, --eval-every and --checkpoint-every when set in config train; null keys are
    left to splat_train (TrainConfig, the one place of their defaults)."""
    keys = ("seed", "eval_every", "checkpoint_every")
    return " ".join(set_flags(config["train"], keys))


def train_snapshot_args(wildcards):
    """--snapshot-every N from train.snapshot_every; nothing when null (no snapshots)."""
    n = config["train"]["snapshot_every"]
    return "" if n is None else f"--snapshot-every {int(n)}"


def train_lpips_args(wildcards):
    """--eval-lpips / --no-eval-lpips from train.eval_lpips; nothing when null (the trainer's
    default, splat_train.config, decides)."""
    v = config["train"]["eval_lpips"]
    return "" if v is None else ("--eval-lpips" if v else "--no-eval-lpips")


def heldout_cameras(wildcards):
    """The held-out cameras the renders use: aligned with the refined training cameras when
    pose refinement is on (align_refined/), else with the initialiser's (align/)."""
    base = MODE.format(**wildcards)
    folder = "align_refined" if config["train"]["pose_refine"] else "align"
    return f"{base}/{folder}/sparse"


def refined_cameras_dir(wildcards, input):
    """The trainer's refined training cameras, beside its train.json (input.summary)."""
    return f"{Path(input.summary).parent}/cameras_refined"


# ----------------------------------------------------------------------------- params
# Folders passed to the CLIs are derived from each job's own files (no hard-coded prefixes).


def out_dir(wildcards, output):
    """The folder of a job's first output file (the stage CLI's --out)."""
    return str(Path(output[0]).parent)


def init_dir(wildcards, input):
    """The initialiser's output folder, holding its finished-run marker (input.init)."""
    return str(Path(input.init).parent)


def init_model_dir(wildcards, input):
    """The initialiser's COLMAP model, beside its finished-run marker (input.init)."""
    return f"{Path(input.init).parent}/sparse/0"


def results_of_output(wildcards, output):
    """The results root, two levels above R/<folder>/<file>."""
    return str(Path(output[0]).parents[1])


def folder_of_output(wildcards, output):
    """The folder of the first output, R for R/<file>."""
    return str(Path(output[0]).parent)


def results_of_input(wildcards, input):
    """The results root, two levels above the first input R/<folder>/<file>."""
    return str(Path(input[0]).parents[1])
