# The Bridge: initialiser output -> normalised cameras and the seed Gaussians.


rule bridge_predictions:
    input:
        predictions=f"{RUN}/predictions.npz",
    output:
        seed=f"{MODE}/bridge/seed.ply",
        info=f"{MODE}/bridge/bridge.json",
        cameras=directory(f"{MODE}/bridge/sparse"),
    log:
        f"{MODE}/logs/bridge.log",
    benchmark:
        f"{MODE}/benchmarks/bridge.tsv"
    wildcard_constraints:
        init=INIT_FROM_PREDICTIONS,
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        out=out_dir,
        args=bridge_args,
    shell:
        "python -m bridge --pred {input.predictions:q} --out {params.out:q} {params.args} "
        "> {log:q} 2>&1"


rule bridge_colmap:
    input:
        init=f"{RUN}/status.json",
        scene=scene_dir,
    output:
        seed=f"{MODE}/bridge/seed.ply",
        info=f"{MODE}/bridge/bridge.json",
        cameras=directory(f"{MODE}/bridge/sparse"),
    log:
        f"{MODE}/logs/bridge.log",
    benchmark:
        f"{MODE}/benchmarks/bridge.tsv"
    wildcard_constraints:
        init=INIT_FROM_COLMAP_MODEL,
        mode="uniform",
    conda:
        "../envs/project.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=short_runtime,
        cpus_per_task=cpus_per_task,
    params:
        init=init_dir,
        out=out_dir,
    shell:
        # the model the initialiser seeds from: its sparse/0, or its random-point fallback's
        # when status.json records one (evaluation/initialisers/random_init.py)
        "model=$(python -m evaluation.initialisers.random_init seed-model {params.init:q} 2> {log:q}) && "
        'python -m bridge --colmap "$model" --images {input.scene:q}/images --mode uniform '
        "--out {params.out:q} >> {log:q} 2>&1"
