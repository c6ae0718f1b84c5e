#!/usr/bin/env bash
# The main job: the whole DAG on the bundled synthetic scene (config.yaml) on 2 cores, then the
# tables and the HTML report. Extra arguments go to snakemake (e.g. --configfile other.yaml).
# Its run time on a 2-core CPU: README.md, "Quick start".
#
# Without the VGGT-1B checkpoint (and no way to download it) the workflow itself skips VGGT,
# says so once at the start, and lists it as skipped with the reason in $RESULTS/skipped.json,
# the tables and the report (config key unavailable_initialisers).
set -uo pipefail
cd "$(dirname "$0")/.."
# this clone's own environment (make install), when there is one
if [ -x .venv/bin/python ]; then export PATH="$(pwd)/.venv/bin:$PATH"; fi
# the configuration first, before anything is written: one line per problem, naming the key
conf=(config.yaml)
args=("$@")
for ((i = 0; i < ${#args[@]}; i++)); do
  case "${args[i]}" in
    --configfile|--configfiles) while [[ $((i + 1)) -lt ${#args[@]} && "${args[i+1]}" != -* ]]; do conf+=("${args[i+1]}"); i=$((i + 1)); done ;;
    --configfile=*) conf+=("${args[i]#--configfile=}") ;;
  esac
done
python3 workflow/scripts/check_config.py "${conf[@]}" || exit 2
RESULTS=$(python3 -c "import yaml; print(yaml.safe_load(open('config.yaml')).get('results', 'results'))")

# snakemake's progress total grows after the COLMAP checkpoint: progress.py says so in a line.
# Progress during long steps: snakemake prints a line per finished job only, and a job's own
# output goes to its log; every HEARTBEAT_S seconds (progress.py; PROGRESS_HEARTBEAT_S) it prints the time elapsed
# and the newest log line of the job that wrote last, e.g. the trainer's "it 400/1000 ...".
if python3 -m snakemake --cores 2 --keep-going "$@" 2>&1 \
    | python3 workflow/scripts/progress.py --prefix "[demo]" --heartbeat "$RESULTS"; then
  skipped=$(python3 -c "import sys; from evaluation.reports.run_status import read_skipped; print(', '.join(read_skipped(sys.argv[1])))" "$RESULTS")
  if [ -n "$skipped" ]; then
    echo "[demo] done WITHOUT $skipped (skipped, see $RESULTS/skipped.json): $RESULTS/tables/tables.md and $RESULTS/report/index.html"
  else
    echo "[demo] done: $RESULTS/tables/tables.md and $RESULTS/report/index.html"
  fi
  exit 0
fi
echo "[demo] FAILED: see the snakemake output above and the logs under $RESULTS" >&2
exit 1
