# One target per stage (each runs everything its stage needs).


rule scenes:
    input:
        prepared_scenes,


rule splits:
    input:
        splits,


rule inits:
    input:
        INIT_TARGETS[0],
        INIT_TARGETS[1],


rule poses:
    input:
        POSE_TARGETS[0],
        POSE_TARGETS[1],


rule bridges:
    input:
        BRIDGE_TARGETS[0],
        BRIDGE_TARGETS[1],


rule aligns:
    input:
        ALIGN_TARGETS[0],
        ALIGN_TARGETS[1],


rule trains:
    input:
        TRAIN_TARGETS[0],
        TRAIN_TARGETS[1],


rule renders:
    input:
        RENDER_TARGETS[0],
        RENDER_TARGETS[1],


rule metrics:
    input:
        METRIC_TARGETS[0],
        METRIC_TARGETS[1],
