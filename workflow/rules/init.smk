# Initialisers (VGGT, the COLMAP baseline, the noisy ground-truth oracle, the ground-truth-pose
# initialiser on posed scenes, dense multi-view stereo from the reference cameras, random points
# for the reference cameras, and any registered one without a rule of its own), their bundle-adjusted variants (*_ba) and pose accuracy.


rule vggt_init:
    input:
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        predictions=temp(f"{SCENE}/n{{n}}/vggt/predictions.npz"),
        model=directory(f"{SCENE}/n{{n}}/vggt/sparse"),
        timing=f"{SCENE}/n{{n}}/vggt/timing.json",
    log:
        f"{SCENE}/n{{n}}/vggt/logs/vggt_init.log",
    benchmark:
        f"{SCENE}/n{{n}}/vggt/benchmarks/vggt_init.tsv"
    conda:
        "../envs/project.yaml"
    threads: config["vggt"]["threads"]
    resources:
        mem_mb=vggt_mem_mb,
        runtime=vggt_runtime,
        gpu=vggt_gpus,
        cpus_per_task=cpus_per_task,
    params:
        out=out_dir,
        args=vggt_args,
    shell:
        "python -m vggt_init --images {input.scene:q}/images --image-list {input.image_list:q} "
        "--out {params.out:q} {params.args} > {log:q} 2>&1"


rule colmap_baseline:
    input:
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        status=f"{SCENE}/n{{n}}/colmap/status.json",
    log:
        f"{SCENE}/n{{n}}/colmap/logs/colmap_baseline.log",
    benchmark:
        f"{SCENE}/n{{n}}/colmap/benchmarks/colmap_baseline.tsv"
    conda:
        "../envs/project.yaml"
    threads: COLMAP_THREADS
    resources:
        mem_mb=colmap_mem_mb,
        runtime=colmap_runtime,
        cpus_per_task=cpus_per_task,
    params:
        out=out_dir,
        args=colmap_args,
    shell:
        "python -m evaluation.initialisers.colmap_baseline --images {input.scene:q}/images "
        "--image-list {input.image_list:q} --out {params.out:q} --threads {threads} "
        "{params.args} > {log:q} 2>&1"


checkpoint colmap_index:
    input:
        colmap_runs,
    output:
        f"{R}/colmap_index.json",
    log:
        f"{R}/logs/colmap_index.log",
    benchmark:
        f"{R}/benchmarks/colmap_index.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=200,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        script=VIEWS_SCRIPT,
    shell:
        "python {params.script:q} index --status {input:q} --out {output:q} > {log:q} 2>&1"


rule oracle_init:
    input:
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        predictions=temp(f"{SCENE}/n{{n}}/oracle/predictions.npz"),
        model=directory(f"{SCENE}/n{{n}}/oracle/sparse"),
        status=f"{SCENE}/n{{n}}/oracle/status.json",
    log:
        f"{SCENE}/n{{n}}/oracle/logs/oracle_init.log",
    benchmark:
        f"{SCENE}/n{{n}}/oracle/benchmarks/oracle_init.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        out=out_dir,
        args=oracle_args,
    shell:
        "python -m evaluation.initialisers.oracle --scene {input.scene:q} --image-list {input.image_list:q} "
        "--out {params.out:q} {params.args} > {log:q} 2>&1"


rule posed_init:
    input:
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        model=directory(f"{SCENE}/n{{n}}/posed/sparse"),
        status=f"{SCENE}/n{{n}}/posed/status.json",
    log:
        f"{SCENE}/n{{n}}/posed/logs/posed_init.log",
    benchmark:
        f"{SCENE}/n{{n}}/posed/benchmarks/posed_init.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        out=out_dir,
        args=posed_args,
    shell:
        "python -m evaluation.initialisers.posed --scene {input.scene:q} --image-list {input.image_list:q} "
        "--out {params.out:q} --threads {threads} {params.args} > {log:q} 2>&1"


rule mvs_init:
    input:
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        predictions=temp(f"{SCENE}/n{{n}}/mvs/predictions.npz"),
        model=directory(f"{SCENE}/n{{n}}/mvs/sparse"),
        status=f"{SCENE}/n{{n}}/mvs/status.json",
    log:
        f"{SCENE}/n{{n}}/mvs/logs/mvs_init.log",
    benchmark:
        f"{SCENE}/n{{n}}/mvs/benchmarks/mvs_init.tsv"
    conda:
        "../envs/project.yaml"
    threads: config["mvs"]["threads"]
    resources:
        mem_mb=4000,
        runtime=config["mvs"]["runtime"],
        cpus_per_task=cpus_per_task,
    params:
        out=out_dir,
        args=mvs_args,
    shell:
        "python -m evaluation.initialisers.mvs --scene {input.scene:q} --image-list {input.image_list:q} "
        "--out {params.out:q} --threads {threads} {params.args} > {log:q} 2>&1"


# Multi-view stereo on another initialiser's cameras (the registry's ``cameras_from``:
# colmap_mvs, vggt_mvs), for scenes without reference cameras (your own photos).
rule mvs_on_cameras:
    input:
        init=dense_base_marker,
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        predictions=temp(f"{SCENE}/n{{n}}/{{base}}_mvs/predictions.npz"),
        model=directory(f"{SCENE}/n{{n}}/{{base}}_mvs/sparse"),
        status=f"{SCENE}/n{{n}}/{{base}}_mvs/status.json",
    log:
        f"{SCENE}/n{{n}}/{{base}}_mvs/logs/mvs_init.log",
    benchmark:
        f"{SCENE}/n{{n}}/{{base}}_mvs/benchmarks/mvs_init.tsv"
    wildcard_constraints:
        base=DENSE_FROM,
    conda:
        "../envs/project.yaml"
    threads: config["mvs"]["threads"]
    resources:
        mem_mb=4000,
        runtime=config["mvs"]["runtime"],
        cpus_per_task=cpus_per_task,
    params:
        cameras=dense_base_model,
        out=out_dir,
        args=mvs_args,
    shell:
        "python -m evaluation.initialisers.mvs --images {input.scene:q}/images --cameras {params.cameras:q} "
        "--image-list {input.image_list:q} --out {params.out:q} --threads {threads} {params.args} "
        "> {log:q} 2>&1"


rule random_init:
    input:
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        model=directory(f"{SCENE}/n{{n}}/random/sparse"),
        status=f"{SCENE}/n{{n}}/random/status.json",
    log:
        f"{SCENE}/n{{n}}/random/logs/random_init.log",
    benchmark:
        f"{SCENE}/n{{n}}/random/benchmarks/random_init.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        out=out_dir,
        args=random_args,
    shell:
        "python -m evaluation.initialisers.random_init --cameras {input.scene:q}/sparse/0 "
        "--image-list {input.image_list:q} --out {params.out:q} {params.args} > {log:q} 2>&1"


# Every initialiser without a rule of its own (the registry's ``own_rule`` False): its command
# with the registry's common flags (COMMON_ARGS) and its options (the registry's ``options``,
# valued from its config block), writing a COLMAP model and status.json.
rule registry_init:
    input:
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        model=directory(f"{RUN}/sparse"),
        status=f"{RUN}/status.json",
    log:
        f"{RUN}/logs/init.log",
    benchmark:
        f"{RUN}/benchmarks/init.tsv"
    wildcard_constraints:
        init=INIT_COMMON_RULE,
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        command=init_command,
        out=out_dir,
        args=init_option_args,
    shell:
        "python -m {params.command} --scene {input.scene:q} --image-list {input.image_list:q} "
        "--out {params.out:q} {params.args} > {log:q} 2>&1"


rule ba_predictions:
    input:
        unpack(ba_base_inputs),
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        predictions=temp(f"{SCENE}/n{{n}}/{{base}}_ba/predictions.npz"),
        model=directory(f"{SCENE}/n{{n}}/{{base}}_ba/sparse"),
        status=f"{SCENE}/n{{n}}/{{base}}_ba/status.json",
    log:
        f"{SCENE}/n{{n}}/{{base}}_ba/logs/ba_init.log",
    benchmark:
        f"{SCENE}/n{{n}}/{{base}}_ba/benchmarks/ba_init.tsv"
    wildcard_constraints:
        base=BA_FROM_PREDICTIONS,
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=4000,
    params:
        init=ba_base_dir,
        out=out_dir,
        args=ba_args,
    shell:
        "python -m evaluation.initialisers.ba_init --init {params.init:q} --images {input.scene:q}/images "
        "--image-list {input.image_list:q} --out {params.out:q} --threads {threads} {params.args} "
        "> {log:q} 2>&1"


rule ba_posed:
    input:
        unpack(ba_base_inputs),
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        model=directory(f"{SCENE}/n{{n}}/{{base}}_ba/sparse"),
        status=f"{SCENE}/n{{n}}/{{base}}_ba/status.json",
    log:
        f"{SCENE}/n{{n}}/{{base}}_ba/logs/ba_init.log",
    benchmark:
        f"{SCENE}/n{{n}}/{{base}}_ba/benchmarks/ba_init.tsv"
    wildcard_constraints:
        base=BA_FROM_COLMAP_MODEL,
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=4000,
    params:
        init=ba_base_dir,
        out=out_dir,
        args=ba_args,
    shell:
        "python -m evaluation.initialisers.ba_init --init {params.init:q} --images {input.scene:q}/images "
        "--image-list {input.image_list:q} --out {params.out:q} --threads {threads} {params.args} "
        "> {log:q} 2>&1"


rule pose_eval:
    input:
        init=init_marker,
        split=f"{SCENE}/split.json",
        scene=scene_dir,
    output:
        f"{RUN}/pose.json",
    log:
        f"{RUN}/logs/pose_eval.log",
    benchmark:
        f"{RUN}/benchmarks/pose_eval.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        model=init_model_dir,
        gate=gate_args,
    shell:
        "python -m evaluation pose --pred {params.model:q} --ref {input.scene:q}/sparse/0 "
        "--names {input.split:q} --n {wildcards.n} {params.gate} --out {output:q} > {log:q} 2>&1"
