# Prepared scene (synthetic or converted), the split, and the per-n name lists.


rule synth_scene:
    output:
        directory(f"{SCENE}/synth"),
    log:
        f"{SCENE}/logs/synth_scene.log",
    benchmark:
        f"{SCENE}/benchmarks/synth_scene.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        args=synth_args,
    shell:
        "python -m camio synth --out {output:q} {params.args} > {log:q} 2>&1"


rule convert_scene:
    input:
        convert_source,
    output:
        directory(f"{SCENE}/converted"),
    log:
        f"{SCENE}/logs/convert_scene.log",
    benchmark:
        f"{SCENE}/benchmarks/convert_scene.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        args=convert_args,
    shell:
        "python -m camio convert {params.args} --out {output:q} > {log:q} 2>&1"


rule undistort_scene:
    input:
        convert_source,
    output:
        directory(f"{SCENE}/undistorted"),
    log:
        f"{SCENE}/logs/undistort_scene.log",
    benchmark:
        f"{SCENE}/benchmarks/undistort_scene.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        args=convert_args,
    shell:
        "python -m camio convert {params.args} --undistort --out {output:q} > {log:q} 2>&1"


rule split_scene:
    input:
        unpack(split_inputs),
    output:
        f"{SCENE}/split.json",
    log:
        f"{SCENE}/logs/split_scene.log",
    benchmark:
        f"{SCENE}/benchmarks/split_scene.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=500,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        args=split_args,
    shell:
        "python -m camio split --scene {input.scene:q} {params.args} --out {output:q} > {log:q} 2>&1"


rule train_list:
    input:
        f"{SCENE}/split.json",
    output:
        f"{SCENE}/n{{n}}/train.txt",
    log:
        f"{SCENE}/logs/train_list_n{{n}}.log",
    benchmark:
        f"{SCENE}/benchmarks/train_list_n{{n}}.tsv"
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
        "python {params.script:q} names --split {input:q} --n {wildcards.n} "
        "--out {output:q} > {log:q} 2>&1"


rule test_images:
    input:
        split=f"{SCENE}/split.json",
        scene=scene_dir,
    output:
        directory(f"{SCENE}/test_images"),
    log:
        f"{SCENE}/logs/test_images.log",
    benchmark:
        f"{SCENE}/benchmarks/test_images.tsv"
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
        "python {params.script:q} link --split {input.split:q} --which test "
        "--images {input.scene:q}/images --out {output:q} > {log:q} 2>&1"
