# Held-out image metrics, tables, plots and the report.


rule image_metrics:
    input:
        renders=f"{MODE}/renders",
        test_images=f"{SCENE}/test_images",
    output:
        f"{MODE}/metrics.json",
    log:
        f"{MODE}/logs/metrics.log",
    benchmark:
        f"{MODE}/benchmarks/metrics.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        lpips=lpips_args,
    shell:
        "python -m evaluation images --pred {input.renders:q} --gt {input.test_images:q} "
        "--alpha-dir {input.renders:q}/alpha {params.lpips} --out {output:q} > {log:q} 2>&1"


# The floor (docs/contracts.md, floor.json): the flat image of the training views' mean colour,
# scored on the held-out views like a render; one per (scene, n), whatever the initialiser.
rule floor:
    input:
        scene=scene_dir,
        train=f"{SCENE}/n{{n}}/train.txt",
        test_images=f"{SCENE}/test_images",
    output:
        f"{SCENE}/n{{n}}/floor.json",
    log:
        f"{SCENE}/logs/floor_n{{n}}.log",
    benchmark:
        f"{SCENE}/benchmarks/floor_n{{n}}.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        lpips=lpips_args,
    shell:
        "python -m evaluation floor --images {input.scene:q}/images --train-names {input.train:q} "
        "--gt {input.test_images:q} {params.lpips} --out {output:q} > {log:q} 2>&1"


# The test-pose protocol (docs/protocols.md): each held-out pose optimised against its image
# with the model frozen, starting from the strict protocol's aligned cameras; scored like
# the strict renders. Off with evaluation.testpose: false.
rule testpose_refine:
    input:
        model=f"{MODE}/train/model.ply",
        cameras=heldout_cameras,
        test_images=f"{SCENE}/test_images",
    output:
        directory(f"{MODE}/testpose/refine"),
    log:
        f"{MODE}/logs/testpose_refine.log",
    benchmark:
        f"{MODE}/benchmarks/testpose_refine.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=short_runtime,
        gpu=train_gpus,
        cpus_per_task=cpus_per_task,
    params:
        args=testpose_args,
    shell:
        "python -m splat_train testpose --model {input.model:q} --cameras {input.cameras:q}/0 "
        "--images {input.test_images:q} --alpha --out {output:q} {params.args} > {log:q} 2>&1"


rule testpose_metrics:
    input:
        refine=f"{MODE}/testpose/refine",
        test_images=f"{SCENE}/test_images",
    output:
        f"{MODE}/testpose/metrics.json",
    log:
        f"{MODE}/logs/testpose_metrics.log",
    benchmark:
        f"{MODE}/benchmarks/testpose_metrics.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        lpips=lpips_args,
    shell:
        "python -m evaluation images --pred {input.refine:q}/renders --gt {input.test_images:q} "
        "--alpha-dir {input.refine:q}/renders/alpha {params.lpips} --out {output:q} > {log:q} 2>&1"


rule unavailable_initialisers:
    output:
        f"{R}/skipped.json",
    log:
        f"{R}/logs/unavailable_initialisers.log",
    localrule: True
    params:
        skipped=unavailable_json,
    run:
        write_skipped_file(output[0], log[0], params.skipped)


rule tables:
    input:
        ALL_TARGETS[0],
        ALL_TARGETS[1],
        skipped=f"{R}/skipped.json",
    output:
        md=f"{R}/tables/tables.md",
        runs=f"{R}/tables/runs.parquet",
    log:
        f"{R}/logs/tables.log",
    benchmark:
        f"{R}/benchmarks/tables.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        results=results_of_output,
        out=out_dir,
        gate=gate_args,
    shell:
        "python -m evaluation tables --results {params.results:q} --out {params.out:q} "
        "{params.gate} > {log:q} 2>&1"


rule plots:
    input:
        f"{R}/tables/runs.parquet",
    output:
        directory(f"{R}/plots"),
    log:
        f"{R}/logs/plots.log",
    benchmark:
        f"{R}/benchmarks/plots.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        results=results_of_input,
    shell:
        "python -m evaluation plots --results {params.results:q} --out {output:q} > {log:q} 2>&1"


rule initialiser_notes:
    output:
        f"{R}/initialisers.json",
    log:
        f"{R}/logs/initialiser_notes.log",
    benchmark:
        f"{R}/benchmarks/initialiser_notes.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=200,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        script=VIEWS_SCRIPT,
        skipped=skipped_initialisers_json,
    shell:
        "python {params.script:q} notes --skipped {params.skipped:q} --out {output:q} > {log:q} 2>&1"


rule report:
    input:
        tables=f"{R}/tables/tables.md",
        notes=f"{R}/initialisers.json",
        skipped=f"{R}/skipped.json",
        plots=plot_dirs,
        scenes=prepared_scenes,
        study=study_final_targets,
    output:
        f"{R}/report/index.html",
    log:
        f"{R}/logs/report.log",
    benchmark:
        f"{R}/benchmarks/report.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=1000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        results=results_of_output,
        out=out_dir,
        gate=gate_args,
    shell:
        "python -m evaluation report --results {params.results:q} --out {params.out:q} "
        "--scenes {params.results:q} {params.gate} > {log:q} 2>&1"
