#!/usr/bin/env bash
# The path users take to a cluster, as a test: a throw-away single-node Slurm (slurmctld,
# slurmd and munged started here as plain daemons, no systemd, no configuration in /etc) runs the array
# that `promptdt reproduce fig4 --budget smoke --emit jobs` writes; `--report-only` then merges it,
# and the report must equal the same sweep run locally by `reproduce`, every file of it byte for
# byte (crates/cli/tests/it/reproduce.rs compares the xargs path's cells.csv and curves.csv so).
#
#   bash scripts/slurm/test_slurm.sh        (as root: slurmd runs the jobs; a container is fine)
#
# Installs slurmctld, slurmd, slurm-client and munge (Debian/Ubuntu packages) when missing. Every
# file of the cluster (slurm.conf, munge key and socket, state, spool, logs) is under one temporary
# directory; the daemons listen on free ports found at start, so two of these tests, or a real
# Slurm, on one machine do not meet. They are stopped by the pids recorded here, on any exit.
#
# Environment: PROMPTDT_SLURM_DEADLINE (seconds for the array to finish, default 1800),
# PROMPTDT_SLURM_KEEP=1 (keep the temporary directory), PROMPTDT_BIN (a built binary: skips the
# build).
set -euo pipefail
cd "$(dirname "$0")/../.."
repo=$(pwd)
t_start=$(date +%s.%N)
elapsed() { awk -v a="$1" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }'; }
say() { echo "test_slurm: $*"; }
die() {
    echo "test_slurm: FAIL: $*" >&2
    exit 1
}

if [ "$(id -u)" != 0 ]; then
    die "run as root: slurmd starts the array's tasks as their submitter and needs root for it"
fi

# --- Slurm and munge, installed when missing ---------------------------------------------------
packages=(slurmctld slurmd slurm-client munge)
present() {
    command -v slurmctld && command -v slurmd && command -v sbatch && command -v munged
} >/dev/null
if ! present; then
    command -v apt-get >/dev/null || die "no apt-get here; install the equivalents of: ${packages[*]}"
    say "installing ${packages[*]}"
    t_install=$(date +%s.%N)
    apt_log=$(mktemp /tmp/promptdt-slurm-apt.XXXXXX)
    # policy-rc.d keeps the packages' init scripts from starting the system's own daemons (with
    # /etc's configuration) while they install: this test starts its own. One already there (a
    # Docker image has one) is left as it is.
    own_policy=0
    if [ ! -e /usr/sbin/policy-rc.d ]; then
        printf '#!/bin/sh\nexit 101\n' >/usr/sbin/policy-rc.d
        chmod +x /usr/sbin/policy-rc.d
        own_policy=1
    fi
    installed=1
    { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
        --no-install-recommends "${packages[@]}"; } >"$apt_log" 2>&1 || installed=0
    [ $own_policy = 0 ] || rm -f /usr/sbin/policy-rc.d
    if [ $installed = 0 ]; then
        tail -n 30 "$apt_log" >&2
        rm -f "$apt_log"
        die "apt-get install ${packages[*]} failed"
    fi
    rm -f "$apt_log"
    present || die "the packages are installed but slurmctld/slurmd/sbatch/munged are not on PATH"
    say "installed in $(elapsed "$t_install") s"
fi
say "$(slurmctld -V), $(munged -V 2>&1 | awk '{ print $1; exit }')"

# --- the binary ----------------------------------------------------------------------------------
if [ -n "${PROMPTDT_BIN:-}" ]; then
    bin=$(realpath "$PROMPTDT_BIN")
else
    cargo build --release -p promptdt
    bin=$repo/target/release/promptdt
fi
[ -x "$bin" ] || die "no binary at $bin"

# --- the throw-away cluster --------------------------------------------------------------------
tmp=$(mktemp -d /tmp/promptdt-slurm.XXXXXX)
chmod 700 "$tmp"
mkdir -p "$tmp"/{munge,state,spool,joblogs,cwd}
pids=() # munged, slurmctld, slurmd, in start order
jobid=
cleanup() {
    local rc=$?
    set +e
    if [ -n "$jobid" ] && [ ${#pids[@]} -ge 2 ]; then
        scancel "$jobid" 2>/dev/null
        sleep 1
    fi
    if [ $rc != 0 ]; then
        # A daemon's .out: its log's lines (-D and -F mirror them) and any error from before it
        # opened its log.
        for f in slurmctld.out slurmd.out munged.out emit.log report.log local.log; do
            [ -f "$tmp/$f" ] && { echo "--- last lines of $f"; tail -n 30 "$tmp/$f"; }
        done
        for f in "$tmp"/joblogs/*; do
            [ -f "$f" ] && { echo "--- last lines of job output $(basename "$f")"; tail -n 15 "$f"; }
        done
    fi
    # Stop the daemons by their pids, last started first.
    local i pid
    for ((i = ${#pids[@]} - 1; i >= 0; i--)); do
        pid=${pids[i]}
        kill "$pid" 2>/dev/null || continue
        for _ in $(seq 50); do
            kill -0 "$pid" 2>/dev/null || break
            sleep 0.1
        done
        kill -0 "$pid" 2>/dev/null && kill -9 "$pid" 2>/dev/null
        wait "$pid" 2>/dev/null
    done
    if [ "${PROMPTDT_SLURM_KEEP:-0}" = 1 ] || [ $rc != 0 ]; then
        echo "test_slurm: kept $tmp"
    else
        rm -rf "$tmp"
    fi
    exit $rc
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# Two free TCP ports (nothing listening on them) for slurmctld and slurmd.
free_port() {
    local p
    for _ in $(seq 200); do
        p=$((20000 + RANDOM % 30000))
        [ "$p" = "${1:-}" ] && continue
        if ! (exec 3<>"/dev/tcp/127.0.0.1/$p") 2>/dev/null; then
            echo "$p"
            return
        fi
    done
    die "no free port found"
}
ctld_port=$(free_port)
slurmd_port=$(free_port "$ctld_port")

t_daemons=$(date +%s.%N)
# The munge key made for this test; munged keeps its socket, pid, seed and log here too.
head -c 1024 /dev/urandom >"$tmp/munge/munge.key"
chmod 400 "$tmp/munge/munge.key"
socket=$tmp/munge/munge.socket
# In the foreground (-F, -D), so $! is the daemon's own pid; each writes its log file, and its
# terminal output (the same lines) goes to a file too.
munged -F --force --key-file="$tmp/munge/munge.key" --socket="$socket" \
    --pid-file="$tmp/munge/munged.pid" --seed-file="$tmp/munge/munged.seed" \
    --log-file="$tmp/munged.log" >"$tmp/munged.out" 2>&1 &
pids+=($!)
for _ in $(seq 100); do
    [ -S "$socket" ] && break
    sleep 0.1
done
[ -S "$socket" ] || die "munged did not open $socket"

# The node as slurmd sees it (its real CPUs, sockets, cores and memory), under this host's name.
node_line=$(slurmd -C | head -n 1)
node=$(sed -n 's/^NodeName=\([^ ]*\).*/\1/p' <<<"$node_line")
[ -n "$node" ] || die "slurmd -C gave no NodeName: $node_line"
: >"$tmp/plugstack.conf"
cat >"$tmp/slurm.conf" <<CONF
ClusterName=promptdt-test
SlurmctldHost=$node(127.0.0.1)
SlurmctldPort=$ctld_port
SlurmdPort=$slurmd_port
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket=$socket
CredType=cred/munge
StateSaveLocation=$tmp/state
SlurmdSpoolDir=$tmp/spool
SlurmctldPidFile=$tmp/slurmctld.pid
SlurmdPidFile=$tmp/slurmd.pid
SlurmctldLogFile=$tmp/slurmctld.log
SlurmdLogFile=$tmp/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
PlugStackConfig=$tmp/plugstack.conf
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SwitchType=switch/none
MpiDefault=none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
MailProg=/bin/true
# Finished tasks stay in slurmctld's memory (no accounting database here) for their exit codes.
MinJobAge=3600
$node_line NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=test Nodes=$node Default=YES MaxTime=INFINITE State=UP
CONF
export SLURM_CONF=$tmp/slurm.conf
slurmctld -D -i -f "$SLURM_CONF" >"$tmp/slurmctld.out" 2>&1 &
pids+=($!)
slurmd -D -N "$node" -f "$SLURM_CONF" >"$tmp/slurmd.out" 2>&1 &
pids+=($!)
# The node is up when sinfo says it is idle.
for _ in $(seq 300); do
    for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null || die "a daemon (pid $p) exited at start"; done
    state=$(sinfo -h -N -n "$node" -o %t 2>/dev/null || true)
    [ "$state" = idle ] && break
    sleep 0.2
done
[ "$state" = idle ] || die "the node $node is not idle after 60 s (state: ${state:-none})"
daemon_s=$(elapsed "$t_daemons")
say "munged, slurmctld, slurmd started (pids ${pids[*]}; ports $ctld_port, $slurmd_port; node: $node_line) in $daemon_s s"

# --- the sweep through Slurm -------------------------------------------------------------------
# --jobs 2: each run gets cores / 2 libtorch threads, the local sweep below the same.
common=(fig4 --budget smoke --device cpu --jobs 2)
"$bin" reproduce "${common[@]}" --out "$tmp/slurm" --emit jobs >"$tmp/emit.log" 2>&1 ||
    die "reproduce --emit jobs failed"
jobs_dir=$tmp/slurm/jobs/fig4-smoke
n=$(wc -l <"$jobs_dir/jobs.txt")
[ "$n" = 9 ] || die "fig4 at smoke should be 9 runs, jobs.txt has $n"
t_submit=$(date +%s.%N)
deadline=${PROMPTDT_SLURM_DEADLINE:-1800}
# Submitted from a directory that is neither the checkout nor the output: the emitted script must
# name everything by absolute path.
out=$(cd "$tmp/cwd" && sbatch --parsable --array="1-$n" --output="$tmp/joblogs/%A_%a.out" \
    "$jobs_dir/run.slurm") || die "sbatch failed"
jobid=${out%%;*}
say "submitted array job $jobid ($n tasks)"
while :; do
    for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null || die "a daemon (pid $p) exited"; done
    queued=$(squeue -h -r -j "$jobid" -o %i) || die "squeue failed"
    left=$(grep -c . <<<"$queued" || true)
    [ "$left" = 0 ] && break
    if awk -v a="$t_submit" -v b="$(date +%s.%N)" -v d="$deadline" 'BEGIN { exit !(b - a > d) }'; then
        die "the array did not finish in $deadline s ($left tasks left)"
    fi
    sleep 2
done
slurm_s=$(elapsed "$t_submit")
# Every task completed with exit code 0 (slurmctld keeps their records: MinJobAge).
records=$(scontrol -o show job "$jobid")
done_ok=$(grep -c 'JobState=COMPLETED .*ExitCode=0:0' <<<"$records" || true)
jobid= # finished: nothing to cancel on exit
if [ "$done_ok" != "$n" ]; then
    grep -o 'JobId=[^ ]* .*ArrayTaskId=[^ ]*\|JobState=[^ ]*\|ExitCode=[^ ]*' <<<"$records" |
        paste -d ' ' - - - >&2 || true
    die "$done_ok of $n array tasks completed with exit code 0"
fi
say "array job: $n tasks completed with exit code 0 in $slurm_s s (submission to the queue empty)"
"$bin" reproduce "${common[@]}" --out "$tmp/slurm" --report-only >"$tmp/report.log" 2>&1 ||
    die "reproduce --report-only failed"

# --- the same sweep locally, and the comparison ------------------------------------------------
t_local=$(date +%s.%N)
"$bin" reproduce "${common[@]}" --out "$tmp/local" >"$tmp/local.log" 2>&1 ||
    die "the local reproduce failed"
local_s=$(elapsed "$t_local")
say "the same sweep locally (reproduce --jobs 2) in $local_s s"
a=$tmp/local/reports/fig4-smoke
b=$tmp/slurm/reports/fig4-smoke
# The report names no path and no time, so every file of it (report.md, report.json, cells.csv,
# curves.csv, the plots) must be the same bytes.
same=1
diff <(cd "$a" && ls) <(cd "$b" && ls) >&2 || same=0
for f in "$a"/*; do
    f=$(basename "$f")
    if cmp -s "$a/$f" "$b/$f"; then
        say "$f: identical, byte for byte"
    else
        diff "$a/$f" "$b/$f" | head -n 20 >&2
        say "$f: DIFFERS"
        same=0
    fi
done
[ $same = 1 ] || die "the Slurm sweep's report differs from the local one"
say "PASS: daemons $daemon_s s, array $slurm_s s, local sweep $local_s s, total $(elapsed "$t_start") s"
