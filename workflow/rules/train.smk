# Held-out cameras in the model frame, 3DGS optimisation and the held-out renders. With
# train.pose_refine the renders use the test cameras aligned with the refined training cameras
# (align_refined/); align/ (initialiser cameras) still feeds the held-out curve during training.


rule align_test_cameras:
    input:
        cameras=f"{MODE}/bridge/sparse",
        split=f"{SCENE}/split.json",
        scene=scene_dir,
        test_images=f"{SCENE}/test_images",
    output:
        info=f"{MODE}/align/align.json",
        cameras=directory(f"{MODE}/align/sparse"),
    log:
        f"{MODE}/logs/align.log",
    benchmark:
        f"{MODE}/benchmarks/align.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        out=out_dir,
    shell:
        "python -m evaluation align --pred {input.cameras:q}/0 --ref {input.scene:q}/sparse/0 "
        "--train-names {input.split:q} --n {wildcards.n} --images {input.test_images:q} "
        "--out {params.out:q} > {log:q} 2>&1"


rule train_splats:
    input:
        unpack(train_inputs),
    output:
        model=f"{MODE}/train/model.ply",
        runlog=f"{MODE}/train/log.parquet",
        summary=f"{MODE}/train/train.json",
    log:
        f"{MODE}/logs/train.log",
    benchmark:
        f"{MODE}/benchmarks/train.tsv"
    conda:
        "../envs/project.yaml"
    threads: config["train"]["threads"]
    resources:
        mem_mb=train_mem_mb,
        runtime=train_runtime,
        gpu=train_gpus,
        cpus_per_task=cpus_per_task,
    params:
        out=out_dir,
        recipe=train_recipe_args,
        settings=train_set_args,
        device=config["train"]["device"],
        resume=train_resume_dir,
        test=train_test_args,
        pose=pose_refine_args,
        lpips=train_lpips_args,
        snapshot=train_snapshot_args,
    shell:
        "python -m splat_train --seed-ply {input.seed:q} --cameras {input.cameras:q}/0 "
        "--images {input.scene:q}/images --image-list {input.image_list:q} --out {params.out:q} "
        "{params.recipe} {params.settings} --resume-dir {params.resume:q} --device {params.device} --threads {threads} "
        "{params.test} {params.pose} {params.lpips} {params.snapshot} > {log:q} 2>&1"


rule align_refined_cameras:
    input:
        summary=f"{MODE}/train/train.json",
        split=f"{SCENE}/split.json",
        scene=scene_dir,
        test_images=f"{SCENE}/test_images",
    output:
        info=f"{MODE}/align_refined/align.json",
        cameras=directory(f"{MODE}/align_refined/sparse"),
    log:
        f"{MODE}/logs/align_refined.log",
    benchmark:
        f"{MODE}/benchmarks/align_refined.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        out=out_dir,
        pred=refined_cameras_dir,
    shell:
        "python -m evaluation align --pred {params.pred:q} --train-cameras refined "
        "--ref {input.scene:q}/sparse/0 --train-names {input.split:q} --n {wildcards.n} "
        "--images {input.test_images:q} --out {params.out:q} > {log:q} 2>&1"


rule render_test:
    input:
        model=f"{MODE}/train/model.ply",
        cameras=heldout_cameras,
        test_images=f"{SCENE}/test_images",
    output:
        directory(f"{MODE}/renders"),
    log:
        f"{MODE}/logs/render.log",
    benchmark:
        f"{MODE}/benchmarks/render.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    shell:
        "python -m splat_train render --model {input.model:q} --cameras {input.cameras:q}/0 "
        "--images {input.test_images:q} --alpha --out {output:q} > {log:q} 2>&1"
