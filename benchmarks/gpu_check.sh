#!/usr/bin/env bash
# The GPU check, in one go on a CUDA machine (run from anywhere; ~6-8 minutes):
#   1. a tiny end-to-end pretrain + both evaluation protocols of every script with --cuda (in parallel),
#   2. benchmarks/speed.py eager vs compiled at sizes A and F on the GPU.
# Everything goes to one file, $OUT/gpu_check.txt (OUT defaults to the current directory), each part also
# when an earlier one failed. Optional: PYTHON (default python3); SITE_ARCHIVE, a .tar.xz of extra
# site-packages to unpack onto PYTHONPATH first (for a machine without network, where pip cannot install
# requirements.txt); SPEED_STEPS (timed repetitions, default 20).
set -uo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python3}
out_dir=${OUT:-.}
report=$out_dir/gpu_check.txt
mkdir -p "$out_dir"
: >"$report"
export MUJOCO_GL=disable PYTHONUNBUFFERED=1
if [ -n "${SITE_ARCHIVE:-}" ]; then
    mkdir -p /tmp/gpu_check_site && tar -xJf "$SITE_ARCHIVE" -C /tmp/gpu_check_site
    export PYTHONPATH=/tmp/gpu_check_site${PYTHONPATH:+:$PYTHONPATH}
fi
log() { echo "$@" | tee -a "$report"; }

log "# GPU check, $(date -u '+%Y-%m-%d %H:%M UTC'), commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | tee -a "$report"
$python -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name())" 2>&1 | tee -a "$report"

# 1. tiny end-to-end runs: size I, a short prefill, a few hundred planner steps, both protocols on every environment
log "## end-to-end, every script with --cuda"
tiny="--model-size I --seed-steps 100 --burst-updates 5 --batch-size 16 --num-samples 32 --num-elites 8
      --num-pi-trajs 4 --iterations 2 --online-eval-steps 100 --eval-episodes 1 --log-every 100 --threads 2 --cuda"
runs=/tmp/gpu_check_runs
rm -rf "$runs" && mkdir -p "$runs"
declare -A extra=(
    [claw]="--family reach --total-timesteps 700 --context-pool-episodes 2 --context-episodes 1"
    [film]="--family reach --total-timesteps 700 --context-pool-episodes 2 --context-episodes 1"
    [concat]="--family reach --total-timesteps 700 --context-pool-episodes 2 --context-episodes 1"
    [dr]="--family reach --rank 2 --total-timesteps 700 --offline-adapt-steps 0 2 --context-episodes 1"
    [oracle]="--family reach --rank 2 --total-timesteps 700 --offline-adapt-steps 0 2 --context-episodes 1"
    [st]="--family reach --rank 2 --total-timesteps 200 --offline-adapt-steps 0 2 --context-episodes 1"
    [posthoc]="--family cheetah_walker --rank 2 --total-timesteps 1100 --context-pool-episodes 2 --context-episodes 1"
)
for script in "${!extra[@]}"; do
    # shellcheck disable=SC2086
    timeout 240 $python "${script}_tdmpc2.py" $tiny ${extra[$script]} --run-dir "$runs/$script" >"$runs/$script.log" 2>&1 &
done
wait
for script in claw dr st oracle film concat posthoc; do
    if grep -q "^device: cuda" "$runs/$script.log" && grep -q "^eval offline" "$runs/$script.log"; then
        log "$script: ok ($(grep -c '^eval env' "$runs/$script.log") environments evaluated; $(grep '^eval offline' "$runs/$script.log" | head -1))"
    else
        log "$script: FAILED, the end of its log:"
        grep -v Warning "$runs/$script.log" | tail -15 | tee -a "$report"
    fi
done

# 2. eager vs compiled on the GPU (size A first: the issue's target is A compiled >= 100 agent steps/s on an H100)
log "## speed, eager vs compiled"
timeout 420 $python benchmarks/speed.py --cuda --sizes A F --steps "${SPEED_STEPS:-20}" 2>&1 | grep -v -e Warning -e "warnings.warn" | tee -a "$report"
log "# done $(date -u '+%H:%M:%S UTC')"
