# Your own photos (scenes without reference cameras; scripts/photos.py writes such a config):
# a render of every photo from the trained model, and R/photos.md, which names the cameras,
# seed, model and renders of each run and the exact command that views the model.


rule render_train_views:
    input:
        model=f"{MODE}/train/model.ply",
        cameras=f"{MODE}/bridge/sparse",
        scene=scene_dir,
        image_list=f"{SCENE}/n{{n}}/train.txt",
    output:
        directory(f"{MODE}/train_renders"),
    log:
        f"{MODE}/logs/render_train.log",
    benchmark:
        f"{MODE}/benchmarks/render_train.tsv"
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    shell:
        "python -m splat_train render --model {input.model:q} --cameras {input.cameras:q}/0 "
        "--images {input.scene:q}/images --image-list {input.image_list:q} --out {output:q} "
        "> {log:q} 2>&1"


rule photos_summary:
    input:
        ALL_TARGETS[0],
        ALL_TARGETS[1],
        skipped=f"{R}/skipped.json",
    output:
        f"{R}/photos.md",
    log:
        f"{R}/logs/photos_summary.log",
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=200,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        script=PHOTOS_SCRIPT,
        results=folder_of_output,
        runs=photo_runs_json,
    shell:
        "python {params.script:q} --results {params.results:q} --runs {params.runs:q} --out {output:q} "
        "> {log:q} 2>&1"
