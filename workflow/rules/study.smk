# The initialisation study (docs/reference.md section 6): the oracle (or, with study.initialiser: posed,
# the posed initialiser) degraded one axis at a time, each
# cell x seed x view count x Bridge mode trained and evaluated with the regular stage rules
# (reused with `use rule ... with:`, so each stage's command stays in one place), plus the
# floater measure and the study report. Planning and layout: study_plan.smk. Nothing here is
# requested unless the config has a `study:` section.


if STUDY_INIT == "oracle":

    rule study_oracle:
        input:
            scene=scene_dir,
            image_list=f"{SCENE}/n{{n}}/train.txt",
        output:
            predictions=temp(f"{SRUN}/predictions.npz"),
            model=directory(f"{SRUN}/sparse"),
            status=f"{SRUN}/status.json",
        log:
            f"{SRUN}/logs/oracle_init.log",
        benchmark:
            f"{SRUN}/benchmarks/oracle_init.tsv"
        conda:
            "../envs/project.yaml"
        threads: 1
        resources:
            mem_mb=2000,
        params:
            out=out_dir,
            args=study_oracle_args,
        shell:
            "python -m evaluation.initialisers.oracle --scene {input.scene:q} --image-list {input.image_list:q} "
            "--out {params.out:q} {params.args} > {log:q} 2>&1"

    use rule bridge_predictions as study_bridge with:
        input:
            predictions=f"{SRUN}/predictions.npz",
        output:
            seed=f"{SMODE}/bridge/seed.ply",
            info=f"{SMODE}/bridge/bridge.json",
            cameras=directory(f"{SMODE}/bridge/sparse"),
        log:
            f"{SMODE}/logs/bridge.log",
        benchmark:
            f"{SMODE}/benchmarks/bridge.tsv"

else:

    rule study_posed:
        input:
            scene=scene_dir,
            image_list=f"{SCENE}/n{{n}}/train.txt",
        output:
            model=directory(f"{SRUN}/sparse"),
            status=f"{SRUN}/status.json",
        log:
            f"{SRUN}/logs/posed_init.log",
        benchmark:
            f"{SRUN}/benchmarks/posed_init.tsv"
        conda:
            "../envs/project.yaml"
        threads: 1
        resources:
            mem_mb=4000,
        params:
            out=out_dir,
            args=study_posed_args,
        shell:
            "python -m evaluation.initialisers.posed --scene {input.scene:q} --image-list {input.image_list:q} "
            "--out {params.out:q} --threads {threads} {params.args} > {log:q} 2>&1"

    use rule bridge_colmap as study_bridge with:
        input:
            init=f"{SRUN}/status.json",
            scene=scene_dir,
        output:
            seed=f"{SMODE}/bridge/seed.ply",
            info=f"{SMODE}/bridge/bridge.json",
            cameras=directory(f"{SMODE}/bridge/sparse"),
        log:
            f"{SMODE}/logs/bridge.log",
        benchmark:
            f"{SMODE}/benchmarks/bridge.tsv"


use rule pose_eval as study_pose_eval with:
    input:
        init=f"{SRUN}/status.json",
        split=f"{SCENE}/split.json",
        scene=scene_dir,
    output:
        f"{SRUN}/pose.json",
    log:
        f"{SRUN}/logs/pose_eval.log",
    benchmark:
        f"{SRUN}/benchmarks/pose_eval.tsv"


use rule align_test_cameras as study_align with:
    input:
        cameras=f"{SMODE}/bridge/sparse",
        split=f"{SCENE}/split.json",
        scene=scene_dir,
        test_images=f"{SCENE}/test_images",
    output:
        info=f"{SMODE}/align/align.json",
        cameras=directory(f"{SMODE}/align/sparse"),
    log:
        f"{SMODE}/logs/align.log",
    benchmark:
        f"{SMODE}/benchmarks/align.tsv"


use rule train_splats as study_train with:
    input:
        unpack(study_train_inputs),
    output:
        model=f"{SMODE}/train/model.ply",
        runlog=f"{SMODE}/train/log.parquet",
        summary=f"{SMODE}/train/train.json",
    log:
        f"{SMODE}/logs/train.log",
    benchmark:
        f"{SMODE}/benchmarks/train.tsv"


use rule render_test as study_render with:
    input:
        model=f"{SMODE}/train/model.ply",
        cameras=f"{SMODE}/align/sparse",
        test_images=f"{SCENE}/test_images",
    output:
        directory(f"{SMODE}/renders"),
    log:
        f"{SMODE}/logs/render.log",
    benchmark:
        f"{SMODE}/benchmarks/render.tsv"


use rule image_metrics as study_metrics with:
    input:
        renders=f"{SMODE}/renders",
        test_images=f"{SCENE}/test_images",
    output:
        f"{SMODE}/metrics.json",
    log:
        f"{SMODE}/logs/metrics.log",
    benchmark:
        f"{SMODE}/benchmarks/metrics.tsv"


rule study_floaters:
    input:
        seed=f"{SMODE}/bridge/seed.ply",
        model=f"{SMODE}/train/model.ply",
        align=f"{SMODE}/align/align.json",
        scene=scene_dir,
    output:
        f"{SMODE}/floaters.json",
    log:
        f"{SMODE}/logs/floaters.log",
    benchmark:
        f"{SMODE}/benchmarks/floaters.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    shell:
        "python -m evaluation floaters --model seed={input.seed:q} final={input.model:q} "
        "--align {input.align:q} --scene {input.scene:q} --out {output:q} > {log:q} 2>&1"


rule study_report:
    input:
        study_run_targets,
        study_reference_targets,
    output:
        md=f"{R}/study/report/study.md",
        html=f"{R}/study/report/index.html",
        cells=f"{R}/study/cells.json",
    log:
        f"{R}/logs/study_report.log",
    benchmark:
        f"{R}/benchmarks/study_report.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        cells=study_cells_json,
        root=study_root,
        refs=study_reference_args,
        plan=study_plan_args,
    shell:
        "python -m evaluation study --results {params.root:q} --cells {params.cells:q} "
        "--write-cells {output.cells:q} --out {params.root:q}/report {params.refs} {params.plan} "
        "> {log:q} 2>&1"
