"""Every helper the rules use (no lambdas inside rules), split by concern:

    config.smk    config validation, results layout, wildcard constraints, constants
    scenes.smk    scene discovery: format, reference cameras, undistortion, splits, initialisers
    params.smk    stage arguments, input functions and parameters of the rules
    planning.smk  target planning (what each stage target asks for)
    resources.smk cluster resources: memory, runtime, CPUs and GPUs of each job

Layout of the outputs (R = config["results"]):

    R/{dataset}/{scene}/{synth|converted|undistorted}/   prepared scene (images, sparse/0, gt/)
    R/{dataset}/{scene}/split.json                        the split used
    R/{dataset}/{scene}/n{n}/train.txt                    the n training names
    R/{dataset}/{scene}/n{n}/floor.json                   the flat mean-colour image's held-out metrics
    R/{dataset}/{scene}/test_images/                      links to the held-out images
    R/{dataset}/{scene}/n{n}/{init}/                      initialiser output (sparse/0, status.json)
    R/{dataset}/{scene}/n{n}/{init}/pose.json             pose accuracy (reference cameras only)
    R/initialisers.json                                   configured initialisers a scene cannot have
    R/{dataset}/{scene}/n{n}/{init}/{mode}/bridge/        seed.ply, bridge.json, sparse/0
    R/{dataset}/{scene}/n{n}/{init}/{mode}/align/         test cameras in the model frame
    R/{dataset}/{scene}/n{n}/{init}/{mode}/train/         model.ply, log.parquet, train.json
    R/{dataset}/{scene}/n{n}/{init}/{mode}/renders/       held-out renders
    R/{dataset}/{scene}/n{n}/{init}/{mode}/metrics.json   held-out image metrics (strict protocol)
    R/{dataset}/{scene}/n{n}/{init}/{mode}/testpose/      test-pose protocol: refine/, metrics.json
    R/tables/, R/plots/, R/report/
    R/.../logs/<rule>.log, R/.../benchmarks/<rule>.tsv    beside the outputs they describe
"""


include: "config.smk"
include: "scenes.smk"
include: "params.smk"
include: "planning.smk"
include: "resources.smk"


# Asked when the workflow is read, so that the one line saying VGGT is skipped (or the error)
# comes before any job, in a dry run too.
unavailable_inits()
