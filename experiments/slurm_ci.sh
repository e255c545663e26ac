#!/usr/bin/env bash
# CI check of `sweep.py --launcher slurm` against a real SLURM: installs Debian's slurm-wlm and
# munge, starts a one-node cluster on this machine with all its state in a fresh temporary directory,
# submits the two-run smoke sweep, waits for it, aggregates it, checks both runs are done, preempts
# one more run and checks it resumes from its checkpoint, and shuts the daemons down on any exit. Needs root and apt-get (a fresh Debian 12 CI machine).
#
#   experiments/slurm_ci.sh [python]      # default: .venv/bin/python of this checkout
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD
python=$(realpath -s "${1:-.venv/bin/python}")  # absolute: the job runs it on the node
[ -x "$python" ] || { echo "slurm_ci: no python at $python" >&2; exit 1; }
[ "$(id -u)" = 0 ] || { echo "slurm_ci: needs root (it installs and starts slurm and munge)" >&2; exit 1; }
start=$(date +%s)

if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null; then
    # no service starts during the install: this script runs its own daemons, with its own config
    # (policy-rc.d; one already there, e.g. in a container, is left as it is)
    policy=/usr/sbin/policy-rc.d created=
    if [ ! -e $policy ]; then
        printf '#!/bin/sh\nexit 101\n' > $policy && chmod +x $policy && created=1
        trap 'rm -f $policy' EXIT
    fi
    timeout 600 apt-get update -qq
    DEBIAN_FRONTEND=noninteractive timeout 600 apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null
    [ -z "$created" ] || { rm -f $policy; trap - EXIT; }
fi

tmp=$(mktemp -d /tmp/slurm_ci.XXXXXX)
chmod 755 "$tmp"
pids=()
cleanup() {
    status=$?
    trap - TERM INT
    # cancel the jobs while the controller still runs, so that no job step outlives the cluster
    if [ -f "$tmp/slurm.conf" ] && SLURM_CONF=$tmp/slurm.conf timeout 10 squeue -h >/dev/null 2>&1; then
        SLURM_CONF=$tmp/slurm.conf timeout 10 scancel --user root || true
        for _ in $(seq 30); do
            [ -z "$(SLURM_CONF=$tmp/slurm.conf timeout 5 squeue -h -o %i 2>/dev/null)" ] && break
            sleep 1
        done
    fi
    for pid in "${pids[@]}"; do kill "$pid" 2>/dev/null || true; done
    for pid in "${pids[@]}"; do timeout 20 tail --pid "$pid" -f /dev/null || kill -9 "$pid" 2>/dev/null || true; done
    if [ $status != 0 ]; then
        for log in "$tmp"/*.log "$tmp"/sweep/.submitit/*/*.out "$tmp"/sweep/*/stdout.log; do
            [ -f "$log" ] && { echo "== $log"; tail -n 30 "$log"; }
        done
    fi
    rm -rf "$tmp"
    exit $status
}
trap cleanup EXIT
trap 'exit 143' TERM INT  # a signal (e.g. from timeout) exits through cleanup too

# daemons run under setsid: a signal to this script's process group (from timeout) leaves them to
# cleanup, which cancels the jobs first. munge: a fresh key and socket, nothing in /etc or /run
dd if=/dev/urandom of="$tmp/munge.key" bs=1024 count=1 status=none
chmod 400 "$tmp/munge.key"
setsid munged --foreground --key-file "$tmp/munge.key" --socket "$tmp/munge.sock" --pid-file "$tmp/munged.pid" \
    --log-file "$tmp/munged.log" --seed-file "$tmp/munge.seed" 2>"$tmp/munged.err.log" &
pids+=($!)

# cons_tres with CR_Core_Memory and DefMemPerCPU: otherwise one job takes the whole node
memory=$(( $(free -m | awk '/^Mem:/ {print $2}') - 512 ))
cat > "$tmp/slurm.conf" <<EOF
ClusterName=ci
SlurmctldHost=localhost
SlurmUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$tmp/munge.sock
StateSaveLocation=$tmp/state
SlurmdSpoolDir=$tmp/spool
SlurmctldPidFile=$tmp/slurmctld.pid
SlurmdPidFile=$tmp/slurmd.pid
SlurmctldLogFile=$tmp/slurmctld.log
SlurmdLogFile=$tmp/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
DefMemPerCPU=1024
ReturnToService=2
MailProg=/bin/true
MpiDefault=none
NodeName=localhost CPUs=$(nproc) RealMemory=$memory State=UNKNOWN
PartitionName=ci Nodes=localhost Default=YES MaxTime=INFINITE State=UP
EOF
mkdir -p "$tmp/state" "$tmp/spool"
export SLURM_CONF=$tmp/slurm.conf  # for sbatch, squeue and scancel (submitit calls them)
for _ in $(seq 50); do [ -S "$tmp/munge.sock" ] && break; sleep 0.1; done
setsid slurmctld -D -f "$SLURM_CONF" 2>"$tmp/slurmctld.err.log" &
pids+=($!)
setsid slurmd -D -f "$SLURM_CONF" -N localhost 2>"$tmp/slurmd.err.log" &
pids+=($!)
for i in $(seq 60); do
    [ "$(timeout 5 sinfo -h -n localhost -o %t 2>/dev/null)" = idle ] && break
    [ "$i" = 60 ] && { echo "slurm_ci: the node never became idle" >&2; exit 1; }
    sleep 0.5
done
echo "slurm_ci: one-node cluster up after $(( $(date +%s) - start )) s"

sweep=$tmp/sweep
MUJOCO_GL=disable timeout 120 "$python" experiments/sweep.py exp1 --scale smoke --methods claw \
    --launcher slurm --root "$sweep" --cpus-per-task 1 --time 10
# poll squeue (sbatch --wait polls every 10 s); bounded
for i in $(seq 600); do
    [ -z "$(timeout 10 squeue -h -o %i)" ] && break
    [ "$i" = 600 ] && { echo "slurm_ci: jobs still queued after 10 min" >&2; squeue; exit 1; }
    sleep 1
done
MUJOCO_GL=disable timeout 300 "$python" experiments/aggregate.py "$sweep"
"$python" - "$sweep" "$python" <<'EOF'
import glob, json, os, sys
records = {os.path.basename(os.path.dirname(p)): json.load(open(p)) for p in glob.glob(os.path.join(sys.argv[1], "*", "run.json"))}
print({name: (r["status"], r.get("slurm_job")) for name, r in records.items()})
assert len(records) == 2 and all(r["status"] == "done" and r.get("slurm_job") for r in records.values()), records
assert all(r["command"].startswith(sys.argv[2] + " ") for r in records.values()), "the jobs ran another python"
EOF
echo "slurm_ci: sweep checked after $(( $(date +%s) - start )) s"

# preemption: USR2 (what SLURM sends before a preemption or the --time limit) to a run's job
# requeues it (submitit), and the requeued job resumes the run from its checkpoint
preempt=$tmp/preempt
MUJOCO_GL=disable timeout 120 "$python" - "$preempt" <<'EOF'
import sys
from experiments import sweep
run = [r for r in sweep.plan_runs(["exp1"], "smoke") if r.method == "claw"][0]
run.extra[run.extra.index("--total-timesteps") + 1] = "1200"  # long enough to be preempted mid-run
run.extra += ["--checkpoint-every", "200"]
sweep.launch([run], sys.argv[1], None, False, "slurm", {"time": 10, "cpus_per_task": 1})
EOF
run_dir=$(dirname "$(ls "$preempt"/*/run.json)")
for i in $(seq 300); do
    [ -f "$run_dir/checkpoint.pt" ] && break
    [ "$i" = 300 ] && { echo "slurm_ci: no checkpoint after 5 min" >&2; exit 1; }
    sleep 1
done
job=$("$python" -c 'import json, sys; print(json.load(open(sys.argv[1]))["slurm_job"])' "$run_dir/run.json")
echo "slurm_ci: preempting job $job"
timeout 10 scancel --signal=USR2 "$job"
released=
for i in $(seq 600); do
    state=$(timeout 10 squeue -h -o "%T %r" -j "$job" 2>/dev/null || true)
    [ -z "$state" ] && break
    if [ -z "$released" ] && [ "$state" = "PENDING BeginTime" ] && ! pgrep -f -- "--run-dir $run_dir( |$)" >/dev/null; then
        # SLURM holds a requeued job back for two minutes: start it now, once the first instance has left the node
        # and a few seconds after the kill (slurmd refuses a relaunch whose credential dates from the second it
        # revoked the old one: "Job credential revoked"; seen once under load)
        sleep 3
        timeout 10 scontrol update JobId="$job" StartTime=now && released=1
    fi
    [ "$i" = 600 ] && { echo "slurm_ci: the requeued job still runs after 10 min" >&2; squeue; exit 1; }
    sleep 1
done
[ -n "$released" ] || { echo "slurm_ci: the job was not requeued" >&2; exit 1; }
"$python" - "$run_dir" <<'EOF'
import json, os, sys
record = json.load(open(os.path.join(sys.argv[1], "run.json")))
log = open(os.path.join(sys.argv[1], "stdout.log")).read()
print({k: record.get(k) for k in ("status", "resumed", "slurm_job")})
assert record["status"] == "done" and record["resumed"] and "resumed from" in log, (record, log[-2000:])
EOF
echo "slurm_ci: passed in $(( $(date +%s) - start )) s"
