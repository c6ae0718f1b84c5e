#!/usr/bin/env bash
# `make cluster-test`: the .test configuration through a real one-node SLURM cluster.
#
# Installs (apt, when missing) and starts, without systemd, everything the SLURM executor
# plugin needs: munged, MariaDB, slurmdbd (accounting, which the plugin's sacct queries need),
# slurmctld and slurmd, all configured in a fresh temporary folder with their own sockets and
# ports. Then runs the workflow on .test/config.yaml at one view count (n = 3: every rule of
# the config, in half the jobs of n = 3 and 6) with workflow/profiles/slurm, checks that every
# job went through SLURM (its job ids in sacct, all COMPLETED), and compares the result tables
# with a local `snakemake --cores` run of the same config. The local run starts first and runs
# beside the install, the daemons' start and the SLURM run (niced: the SLURM run's chain of
# jobs goes first), so it adds little to the test's time. The daemons it started, and the
# local run, are stopped on exit (success or not); nothing is left in /etc or /var, so it can
# run again.
#
# Needs root on Debian/Ubuntu. Exit status: 0 passed, 1 failed, 3 skipped (not root, not
# Debian, or apt could not install the packages, e.g. no network): CI treats 3 as a skip.
#
# Environment: KEEP=1 keeps the temporary folder (logs of the daemons and of both runs);
# LOCAL_RESULTS=DIR reuses the results of an earlier local run of the same config
# (.test/config.yaml with this script's test_overrides.yaml) instead of making one.
# SLURM_TEST_ETC_CONF (default /etc/slurm/slurm.conf) and SLURM_TEST_TMP (default /tmp) move
# the linked configuration and the state folder; SLURM_TEST_PREFLIGHT_ONLY=1 stops after checking
# that the configuration path is free (tests/test_slurm_preflight.py); SLURM_TEST_INSTALL_ONLY=1
# only installs the packages (.ci/run, while the suite runs).
set -euo pipefail

ROOT="$(cd "$(dirname "$0")/.." && pwd)"
SKIP=3
say() { printf '[slurm-test %s] %s\n' "$(date -u +%H:%M:%S)" "$*"; }
skip() { say "SKIP: $*"; exit "$SKIP"; }

[[ $(id -u) -eq 0 ]] || skip "needs root (it installs and starts SLURM daemons)"
[[ -f /etc/debian_version ]] || skip "needs Debian or Ubuntu (apt packages slurm-wlm, slurmdbd, munge, mariadb-server)"

PKGS=(slurm-wlm slurmdbd munge mariadb-server)
install_packages() {  # apt, when any daemon is missing; a skip when apt cannot
    if ! command -v slurmctld >/dev/null || ! command -v slurmdbd >/dev/null || ! command -v munged >/dev/null \
        || ! command -v mariadbd >/dev/null; then
        say "installing ${PKGS[*]} (apt)"
        if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
                "${PKGS[@]}"; } >/tmp/slurm_test_apt.log 2>&1; then
            tail -5 /tmp/slurm_test_apt.log
            skip "apt could not install ${PKGS[*]} (no network or mirror?); see /tmp/slurm_test_apt.log"
        fi
    fi
}
# .ci/run installs them while the suite runs (network and dpkg, little CPU)
[[ ${SLURM_TEST_INSTALL_ONLY:-0} == 1 ]] && { install_packages; say "install only: packages present"; exit 0; }

# /etc/slurm/slurm.conf must be free: this test links its own configuration there for the run.
# A link into a folder of this test whose run was killed (SIGKILL, power loss: no cleanup ran)
# is removed with that folder, so one killed run does not turn every later run into a skip. The
# run counts as killed when the PID it recorded is gone and no process names its folder.
ETC_CONF="${SLURM_TEST_ETC_CONF:-/etc/slurm/slurm.conf}"
STATE_PREFIX="${SLURM_TEST_TMP:-/tmp}/slurm-test."
run_is_alive() {  # run_is_alive DIR: a process of the test run that owns DIR still exists
    local dir=$1 pid
    pid="$(cat "$dir/owner.pid" 2>/dev/null || true)"
    [[ -n $pid ]] && kill -0 "$pid" 2>/dev/null && return 0
    pgrep -f -- "$dir" >/dev/null 2>&1 && return 0
    return 1
}
if [[ -L $ETC_CONF ]]; then
    PREV="$(readlink "$ETC_CONF")"; PREV_DIR="${PREV%/slurm.conf}"
    if [[ $PREV == "$STATE_PREFIX"*/slurm.conf && ${PREV_DIR#"$STATE_PREFIX"} != */* ]] \
        && ! run_is_alive "$PREV_DIR"; then
        say "removing what a killed run of this test left: $ETC_CONF -> $PREV (no process of that run is alive)"
        rm -f "$ETC_CONF"; rm -rf "$PREV_DIR"
    fi
fi
if [[ -e $ETC_CONF || -L $ETC_CONF ]]; then
    skip "$ETC_CONF exists (a configured SLURM, or a run of this test in progress); this test sets up its own cluster"
fi
[[ ${SLURM_TEST_PREFLIGHT_ONLY:-0} == 1 ]] && { say "preflight only: $ETC_CONF is free"; exit 0; }

T0=$(date +%s)
CPUS="$(nproc)"
PY="${PYTHON:-python3}"
# The workflow's shell commands run `python`, and the jobs (local or under SLURM) inherit this
# environment: the interpreter this test was given (CI: the clone's .venv) goes first on PATH.
# Without it a machine whose default python lacks the packages fails every job with
# "No module named 'open3d'" (.ci/run calls this script outside make, which sets PATH itself).
PY_DIR="$(dirname "$(command -v "$PY")")"
export PATH="$PY_DIR:$PATH"
SNAKEMAKE=("$PY" -m snakemake)
"$PY" -c "import snakemake_executor_plugin_slurm" 2>/dev/null \
    || { say "FAIL: snakemake-executor-plugin-slurm is not installed for $PY"; exit 1; }

S="$(mktemp -d "${STATE_PREFIX}XXXXXX")"
chmod 755 "$S"
echo $$ >"$S/owner.pid"
PIDS=()
SNAKE_PID=
LOCAL_PID=
cleanup() {
    local rc=$?
    if [[ -n $LOCAL_PID ]] && kill -0 "$LOCAL_PID" 2>/dev/null; then  # the local run, its own process group
        kill -- -"$LOCAL_PID" 2>/dev/null || kill "$LOCAL_PID" 2>/dev/null || true
        for _ in $(seq 100); do kill -0 "$LOCAL_PID" 2>/dev/null || break; sleep 0.1; done
        kill -9 -- -"$LOCAL_PID" 2>/dev/null || true
    fi
    if [[ -n $SNAKE_PID ]] && kill -0 "$SNAKE_PID" 2>/dev/null; then  # interrupted mid-run
        kill "$SNAKE_PID" 2>/dev/null || true
        scancel --user root 2>/dev/null || true  # this private cluster's jobs, all ours
        # before slurmd stops: a job it no longer watches would outlive the test
        for _ in $(seq 100); do [[ -z $(squeue -h 2>/dev/null) ]] && break; sleep 0.2; done
        for _ in $(seq 100); do kill -0 "$SNAKE_PID" 2>/dev/null || break; sleep 0.1; done
        kill -9 "$SNAKE_PID" 2>/dev/null || true
    fi
    # The daemons all at once (one by one took 20 s): their state goes with the folder, so none
    # needs another to stop cleanly. SIGKILL for any still there after 10 s.
    local pid left
    for pid in "${PIDS[@]}"; do kill "$pid" 2>/dev/null || true; done
    for _ in $(seq 100); do
        left=0
        for pid in "${PIDS[@]}"; do kill -0 "$pid" 2>/dev/null && left=1; done
        [[ $left -eq 0 ]] && break
        sleep 0.1
    done
    for pid in "${PIDS[@]}"; do kill -9 "$pid" 2>/dev/null || true; done
    [[ -z ${CREATED_RUN_MUNGE:-} ]] || rm -rf /run/munge
    [[ -z ${LINKED_CONF:-} ]] || rm -f "$ETC_CONF"
    if [[ ${KEEP:-0} == 1 || ($rc -ne 0 && $rc -ne $SKIP) ]]; then say "logs kept in $S"; else rm -rf "$S"; fi
    exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# Both runs: COLMAP with one thread (it is bitwise repeatable only so: config schema) and one
# view count (n = 3 runs every rule that n = 6 runs).
cat >"$S/test_overrides.yaml" <<'EOF'
colmap: {threads: 1}
views: [3]
EOF
copy_repo() { tar -C "$ROOT" --exclude=./.git --exclude=./.venv --exclude=./.test/results --exclude=./results -cf - . \
    | tar -C "$1" -xf -; }

# --- the same config locally, started now (its own process group, so that cleanup stops all of
# it); its exit status and seconds go to local_run.done. LOCAL_RESULTS=DIR: none, DIR is used.
if [[ -n ${LOCAL_RESULTS:-} ]]; then
    LOCAL="$LOCAL_RESULTS"
else
    mkdir -p "$S/local"
    copy_repo "$S/local"
    LOCAL="$S/local/.test/results"
    say "the same config locally (snakemake --cores $CPUS, niced), beside the SLURM install and run"
    set -m
    (
        t=$(date +%s); rc=0
        cd "$S/local" && PYTHONPATH="$S/local" nice -n 5 "${SNAKEMAKE[@]}" --cores "$CPUS" \
            --configfile .test/config.yaml "$S/test_overrides.yaml" >"$S/local_run.log" 2>&1 </dev/null || rc=$?
        echo "$rc $(( $(date +%s) - t ))" >"$S/local_run.done"
        exit "$rc"
    ) &
    LOCAL_PID=$!
    set +m
fi

install_packages
T_INSTALL=$(( $(date +%s) - T0 ))

free_port() { "$PY" -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
wait_for() {  # wait_for SECONDS DESCRIPTION COMMAND...: poll until COMMAND succeeds
    local secs=$1 what=$2; shift 2
    for _ in $(seq $((secs * 5))); do "$@" >/dev/null 2>&1 && return 0; sleep 0.2; done
    say "FAIL: $what did not come up in ${secs} s"; tail -20 "$S"/*.log 2>/dev/null || true; exit 1
}
# A daemon in the foreground of a background job: its PID is the daemon's own.
start() { local log=$1; shift; "$@" >>"$log" 2>&1 & PIDS+=($!); }

HOST="$(hostname -s)"
MEM_MB="$(awk '/MemTotal/ {print int($2 / 1024 * 0.9)}' /proc/meminfo)"
DB_PORT=$(free_port); DBD_PORT=$(free_port); CTLD_PORT=$(free_port); SLURMD_PORT=$(free_port)
mkdir -p "$S"/{munge,mysql,ctld,slurmd,jobs}

# --- munge. SLURM 22.05's clients (sacctmgr, sacct) ignore AuthInfo=socket= when they talk to
# slurmdbd, so munged must listen on the default socket: a running one is used as it is,
# otherwise one is started there with a fresh key (the socket goes when it stops).
MUNGE_SOCK=/run/munge/munge.socket.2
if munge -n -S "$MUNGE_SOCK" 2>/dev/null | unmunge -S "$MUNGE_SOCK" >/dev/null 2>&1; then
    say "using the running munged ($MUNGE_SOCK)"
else
    [[ -d /run/munge ]] || { mkdir -p /run/munge; CREATED_RUN_MUNGE=1; }
    dd if=/dev/urandom of="$S/munge/munge.key" bs=1024 count=1 status=none
    chmod 700 "$S/munge"; chmod 400 "$S/munge/munge.key"
    start "$S/munged.out" munged --foreground --force --key-file="$S/munge/munge.key" \
        --socket="$MUNGE_SOCK" --pid-file="$S/munge/munged.pid" --log-file="$S/munge.log" \
        --seed-file="$S/munge/munge.seed"
    wait_for 20 munged bash -c "munge -n -S $MUNGE_SOCK | unmunge -S $MUNGE_SOCK"
fi

# --- MariaDB for slurmdbd, on a local TCP port
mariadb-install-db --user=root --datadir="$S/mysql" --auth-root-authentication-method=socket \
    --skip-test-db >"$S/mariadb-install.log" 2>&1
start "$S/mariadb.log" mariadbd --no-defaults --user=root --datadir="$S/mysql" --socket="$S/mysql.sock" \
    --pid-file="$S/mysql.pid" --bind-address=127.0.0.1 --port="$DB_PORT" --innodb-buffer-pool-size=64M
wait_for 60 mariadb mariadb --no-defaults -S "$S/mysql.sock" -u root -e "select 1"
DB_PASS="$(head -c 12 /dev/urandom | od -An -tx1 | tr -d ' \n')"
mariadb --no-defaults -S "$S/mysql.sock" -u root -e "
    CREATE USER 'slurm'@'127.0.0.1' IDENTIFIED BY '$DB_PASS';
    GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1';"

# --- SLURM configuration (SLURM_CONF points every daemon and client here)
cat >"$S/slurm.conf" <<EOF
ClusterName=snaketest
SlurmctldHost=$HOST
SlurmUser=root
SlurmdUser=root
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
AuthType=auth/munge
AuthInfo=socket=$MUNGE_SOCK
CredType=cred/munge
StateSaveLocation=$S/ctld
SlurmdSpoolDir=$S/slurmd
SlurmctldPidFile=$S/slurmctld.pid
SlurmdPidFile=$S/slurmd.pid
SlurmctldLogFile=$S/slurmctld.log
SlurmdLogFile=$S/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
SlurmctldTimeout=30
SlurmdTimeout=30
InactiveLimit=0
KillWait=5
MinJobAge=300
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
AccountingStoragePort=$DBD_PORT
JobCompType=jobcomp/none
NodeName=$HOST CPUs=$CPUS RealMemory=$MEM_MB State=UNKNOWN
PartitionName=cpu Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF
cat >"$S/slurmdbd.conf" <<EOF
AuthType=auth/munge
AuthInfo=socket=$MUNGE_SOCK
DbdHost=localhost
DbdPort=$DBD_PORT
SlurmUser=root
PidFile=$S/slurmdbd.pid
LogFile=$S/slurmdbd.log
StorageType=accounting_storage/mysql
StorageHost=127.0.0.1
StoragePort=$DB_PORT
StorageUser=slurm
StoragePass=$DB_PASS
StorageLoc=slurm_acct_db
EOF
chmod 600 "$S/slurmdbd.conf"
printf 'CgroupPlugin=autodetect\n' >"$S/cgroup.conf"
export SLURM_CONF="$S/slurm.conf"
# srun inside a job (the executor plugin's job step) reads /etc/slurm/slurm.conf whatever
# SLURM_CONF says: link ours there for the run (checked free above).
mkdir -p "$(dirname "$ETC_CONF")"
ln -s "$S/slurm.conf" "$ETC_CONF"; LINKED_CONF=1

start "$S/slurmdbd.out" slurmdbd -D
wait_for 60 slurmdbd sacctmgr -n list cluster
sacctmgr -i add cluster snaketest >/dev/null
sacctmgr -i add account snaketest Description=cluster-test Organization=none >/dev/null
sacctmgr -i add user root Account=snaketest DefaultAccount=snaketest >/dev/null
start "$S/slurmctld.out" slurmctld -D
wait_for 60 slurmctld scontrol ping
start "$S/slurmd.out" slurmd -D -N "$HOST"
wait_for 60 "slurmd (node idle)" bash -c "sinfo -h -N -o %t | grep -qx idle"
T_UP=$(( $(date +%s) - T0 - T_INSTALL ))
say "SLURM up in ${T_UP} s (node $HOST: $CPUS CPUs, $MEM_MB MB; state in $S)"

# --- the workflow through SLURM, from a copy of the repository (results stay out of it)
WORK="$S/work"
mkdir -p "$WORK"
copy_repo "$WORK"
T1=$(date +%s)
say "workflow through SLURM (profile workflow/profiles/slurm, .test/config.yaml at n = 3)"
# Status checks every second: the plugin adds 10 s to the wait after each check that finds no
# job finished, so a short first wait is what keeps a chain of short jobs moving.
(cd "$WORK" && PYTHONPATH="$WORK${PYTHONPATH:+:$PYTHONPATH}" exec "${SNAKEMAKE[@]}" \
    --profile workflow/profiles/slurm --configfile .test/config.yaml "$S/test_overrides.yaml" \
    --default-resources slurm_account=snaketest --slurm-logdir "$S/jobs" --latency-wait 5 --retries 0 \
    --jobs 4 --slurm-init-seconds-before-status-checks 1 --seconds-between-status-checks 1 \
    >"$S/slurm_run.log" 2>&1 </dev/null) &
SNAKE_PID=$!
RC=0; wait "$SNAKE_PID" || RC=$?
SNAKE_PID=
T_SLURM=$(( $(date +%s) - T1 ))
if [[ $RC -ne 0 ]]; then
    tail -40 "$S/slurm_run.log"; say "FAIL: the workflow failed under SLURM (rc $RC)"; exit 1
fi
say "workflow through SLURM done in ${T_SLURM} s"

# --- every job went through SLURM: its job ids, all COMPLETED, in the accounting database
sacct -X -n -P -S now-1days -o JobID,JobName,State,Elapsed,AllocCPUS,ReqMem,Comment%80 >"$S/sacct.txt"
N_JOBS=$(grep -c . "$S/sacct.txt" || true)
N_DONE=$(grep -c '|COMPLETED|' "$S/sacct.txt" || true)
N_SUBMITTED=$(grep -c "Job .* has been submitted with SLURM jobid" "$S/slurm_run.log" || true)
say "sacct: $N_JOBS SLURM jobs, $N_DONE COMPLETED; the run submitted $N_SUBMITTED"
sed 's/^/    /' "$S/sacct.txt"
if [[ $N_JOBS -eq 0 || $N_DONE -ne $N_JOBS || $N_SUBMITTED -ne $N_JOBS ]]; then
    say "FAIL: not every job ran through SLURM and completed"; exit 1
fi

# --- the local run (started at the beginning); the tables must agree
T_LOCAL=0
if [[ -n $LOCAL_PID ]]; then
    say "waiting for the local run"
    LRC=0; wait "$LOCAL_PID" || LRC=$?
    LOCAL_PID=
    if [[ $LRC -ne 0 ]]; then tail -40 "$S/local_run.log"; say "FAIL: the local run failed (rc $LRC)"; exit 1; fi
    read -r _ T_LOCAL <"$S/local_run.done"
fi
"$PY" "$ROOT/scripts/compare_tables.py" "$LOCAL" "$WORK/.test/results" || { say "FAIL: tables differ"; exit 1; }

say "PASS: $N_JOBS jobs through SLURM. Times: install ${T_INSTALL} s, daemons ${T_UP} s," \
    "SLURM run ${T_SLURM} s, local run ${T_LOCAL} s (beside them), total $(( $(date +%s) - T0 )) s"
