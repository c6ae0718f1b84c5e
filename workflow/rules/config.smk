"""Config validation and the constants every rule file uses: the results layout (R, SCENE,
RUN, MODE), the wildcard constraints, thread counts and helper-script paths."""

import importlib.util
import json
import os
import shlex
import sys

from snakemake.exceptions import IncompleteCheckpointException
from snakemake.logging import logger
from pathlib import Path

# One line per configuration problem, naming the key and the nearest valid one, before
# the defaults are filled in (a jsonschema message would be a schema dump).
_check_spec = importlib.util.spec_from_file_location(
    "check_config",
    (Path(str(workflow.current_basedir)) / "../scripts/check_config.py").resolve(),
)
_check_config = importlib.util.module_from_spec(_check_spec)
_check_spec.loader.exec_module(_check_config)
_problems = []
for (
    _file
) in workflow.configfiles:  # a key given twice: YAML keeps the last one silently
    try:
        _check_config.read_yaml(_file)
    except (OSError, ValueError) as _exc:
        _problems.append(str(_exc))
_problems += _check_config.config_problems(config)
for _problem in _problems:
    print(f"config error: {_problem}", file=sys.stderr)
if _problems:
    raise SystemExit(2)
# defaults from the checked schema: the lists and the initialisers' option blocks of the code
_check_config.fill_defaults(config)

# A scene converted from disk must be there before anything is planned (its format decides
# the jobs): one line here, not an InputFunctionException with a traceback during planning.
_missing = [
    f"datasets.{_ds}.scenes.{_sc}: the scene path {_cfg['path']} does not exist (relative paths are read "
    "from the working directory)"
    for _ds, _block in config["datasets"].items()
    for _sc, _cfg in _block["scenes"].items()
    if "path" in _cfg and not Path(_cfg["path"]).exists()
]
for _problem in _missing:
    print(f"config error: {_problem}", file=sys.stderr)
if _missing:
    raise SystemExit(2)

# ~ expanded, as the config check read it (a relative path stays relative to the workdir)
R = os.path.expanduser(config["results"]).rstrip("/")
SCENE = f"{R}/{{dataset}}/{{scene}}"
RUN = f"{SCENE}/n{{n}}/{{init}}"
MODE = f"{RUN}/{{mode}}"

# COLMAP baseline threads: the configured count, or (0) every core snakemake was given. Under
# a cluster executor the submitting snakemake has no --cores and the job's own snakemake has
# `--cores all`, so 0 would ask SLURM for 1 CPU and then start a step with all of them: there
# it means 1 (set colmap.threads for more).
if config["colmap"]["threads"]:
    COLMAP_THREADS = config["colmap"]["threads"]
elif workflow.non_local_exec or workflow.remote_exec:
    COLMAP_THREADS = 1
else:
    COLMAP_THREADS = max(1, int(workflow.resource_settings.cores or 1))

# The workflow's own helper scripts, found from the workflow (any working directory works).
VIEWS_SCRIPT = str(
    (Path(str(workflow.current_basedir)) / "../scripts/views.py").resolve()
)
PHOTOS_SCRIPT = str(
    (Path(str(workflow.current_basedir)) / "../scripts/photos_summary.py").resolve()
)

# The initialisers and the Bridge modes, each listed once (evaluation/initialisers/registry.py,
# runtime/modes.py): the wildcards, the rules and the planning read them.
from runtime.modes import BRIDGE_MODES
from evaluation.initialisers import registry as initialisers

# a wildcard constraint matching exactly these names ("(?!)", nothing, when there are none)
_alternatives = lambda names: "|".join(names) or "(?!)"

INIT_FROM_PREDICTIONS = _alternatives(initialisers.from_predictions())
INIT_FROM_COLMAP_MODEL = _alternatives(initialisers.from_colmap_model())
INIT_COMMON_RULE = _alternatives(initialisers.with_common_rule())
BA_FROM_PREDICTIONS = _alternatives(initialisers.ba_bases(confidence=True))
BA_FROM_COLMAP_MODEL = _alternatives(initialisers.ba_bases(confidence=False))
DENSE_FROM = _alternatives(initialisers.dense_bases())


wildcard_constraints:
    dataset=r"[A-Za-z0-9][A-Za-z0-9_.-]*",
    scene=r"[A-Za-z0-9][A-Za-z0-9_.-]*",
    n=r"\d+",
    init="|".join(initialisers.NAMES),
    mode="|".join(BRIDGE_MODES),
