#!/usr/bin/env bash
# The GPU check, in one go on a CUDA machine (run from anywhere; at most 8 minutes, each step under its own timeout):
#   1. at once, in parallel: a tiny end-to-end pretrain + both evaluation protocols of every script with --cuda, and
#      again with --cuda --cudagraphs; tests/test_cudagraphs.py (recorded and replayed update, test-time gradient step
#      and planner against eager); and a first, untimed compile at sizes A and F that fills inductor's on-disk caches,
#   2. benchmarks/speed.py at size A, then F: eager, cudagraphs, compiled and compiled-cudagraphs side by side.
# Everything goes to one file, $OUT/gpu_check.txt (OUT defaults to the current directory); a failed or timed-out step
# is reported there (with the end of its log) and the later steps still run. Optional: PYTHON (default python3);
# SITE_ARCHIVE, a .tar.xz of extra site-packages to unpack onto PYTHONPATH first (for a machine without network, where
# pip cannot install requirements.txt; --cudagraphs needs tensordict and pyvers in it); SPEED_STEPS (timed repetitions,
# default 10); the step timeouts in seconds PARALLEL_TIMEOUT (step 1, default 200), SPEED_A_TIMEOUT (160) and
# SPEED_F_TIMEOUT (110).
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
quiet() { grep -v -e Warning -e "warnings.warn" -e "\[tensordict\]\[INFO\]"; }
# the end of a failed step's log, in the report
tail_of() { quiet <"$1" | tail -"${2:-15}" | tee -a "$report"; }
# how a background step ended: "ok", "FAILED (exit N)" or "TIMED OUT after N s"
ended() { case $1 in 0) echo ok ;; 124 | 137) echo "TIMED OUT after $2 s" ;; *) echo "FAILED (exit $1)" ;; esac; }
started=$SECONDS
parallel_timeout=${PARALLEL_TIMEOUT:-200}

log "# GPU check, $(date -u '+%Y-%m-%d %H:%M UTC'), commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | tee -a "$report"
$python -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name())" 2>&1 | tee -a "$report"
$python -c "import tensordict; print('tensordict', tensordict.__version__)" 2>&1 | tail -1 | tee -a "$report"

# 1. in parallel. Tiny end-to-end runs: size I, a short prefill, a few hundred planner steps, both protocols on every
# environment (--compile stays off at this budget: --cudagraphs records the eager functions)
runs=/tmp/gpu_check_runs
rm -rf "$runs" && mkdir -p "$runs"
tiny="--model-size I --seed-steps 100 --burst-updates 5 --batch-size 16 --num-samples 32 --num-elites 8
      --num-pi-trajs 4 --iterations 2 --online-eval-steps 100 --eval-episodes 1 --log-every 100 --threads 1 --cuda"
declare -A extra=(
    [claw]="--family reach --total-timesteps 700 --context-pool-episodes 2 --context-episodes 1"
    [film]="--family reach --total-timesteps 700 --context-pool-episodes 2 --context-episodes 1"
    [concat]="--family reach --total-timesteps 700 --context-pool-episodes 2 --context-episodes 1"
    [dr]="--family reach --rank 2 --total-timesteps 700 --offline-adapt-steps 0 2 --context-episodes 1"
    [oracle]="--family reach --rank 2 --total-timesteps 700 --offline-adapt-steps 0 2 --context-episodes 1"
    [st]="--family reach --rank 2 --total-timesteps 200 --offline-adapt-steps 0 2 --context-episodes 1"
    [posthoc]="--family cheetah_walker --rank 2 --total-timesteps 1100 --context-pool-episodes 2 --context-episodes 1"
)
declare -A pids=()
for script in "${!extra[@]}"; do
    for variant in cuda cudagraphs; do
        flags=$([ $variant = cudagraphs ] && echo --cudagraphs)
        # shellcheck disable=SC2086
        timeout "$parallel_timeout" $python "${script}_tdmpc2.py" $tiny ${extra[$script]} $flags \
            --run-dir "$runs/$script.$variant" >"$runs/$script.$variant.log" 2>&1 &
        pids[$script.$variant]=$!
    done
done
timeout "$parallel_timeout" $python -m pytest -q -p no:cacheprovider tests/test_cudagraphs.py >"$runs/test.log" 2>&1 &
pids[test]=$!
for size in A F; do
    timeout "$parallel_timeout" $python benchmarks/speed.py --cuda --sizes $size --modes compiled compiled-cudagraphs \
        --steps 1 >"$runs/warmup.$size.log" 2>&1 &
    pids[warmup.$size]=$!
done
declare -A rc=()
for name in "${!pids[@]}"; do
    wait "${pids[$name]}"
    rc[$name]=$?
done
log "## 1. end-to-end, every script with --cuda and with --cuda --cudagraphs (parallel, ${parallel_timeout} s each)"
for script in claw dr st oracle film concat posthoc; do
    for variant in cuda cudagraphs; do
        file=$runs/$script.$variant.log
        graphs=$(grep -c "CUDA graph successfully registered" "$file")  # tensordict's log line, one per recorded graph
        if [ "${rc[$script.$variant]}" = 0 ] && grep -q "^device: cuda" "$file" && grep -q "^eval offline" "$file" &&
            { [ $variant = cuda ] || [ "$graphs" -gt 0 ]; }; then
            recorded=$([ $variant = cudagraphs ] && echo "; $graphs CUDA graphs recorded")
            log "$script --$variant: ok ($(grep -c '^eval env' "$file") environments evaluated$recorded; $(grep '^eval offline' "$file" | head -1))"
        else
            why=$(ended "${rc[$script.$variant]}" "$parallel_timeout")
            [ "$why" = ok ] && why="FAILED (no evaluation on cuda, or no CUDA graph recorded)"
            log "$script --$variant: $why, the end of its log:"
            tail_of "$file"
        fi
    done
done
log "## 1. tests/test_cudagraphs.py: $(ended "${rc[test]}" "$parallel_timeout")"
quiet <"$runs/test.log" | grep -v "^$" | tail -"$([ "${rc[test]}" = 0 ] && echo 3 || echo 60)" | tee -a "$report"
for size in A F; do
    log "## 1. compile warm-up, size $size: $(ended "${rc[warmup.$size]}" "$parallel_timeout")"
    [ "${rc[warmup.$size]}" = 0 ] || [ "${rc[warmup.$size]}" = 124 ] || tail_of "$runs/warmup.$size.log"
done
log "# step 1 took $((SECONDS - started)) s"

# 2. speed, one size after the other on the otherwise idle machine (size A first: the target is >= 100 agent steps/s
# there); the rows print as they finish, so a timeout keeps the finished ones. Compile s: with the caches of step 1.
for size in A F; do
    limit=$([ $size = A ] && echo "${SPEED_A_TIMEOUT:-160}" || echo "${SPEED_F_TIMEOUT:-110}")
    log "## 2. speed, size $size: eager, cudagraphs, compiled, compiled-cudagraphs (${limit} s at most)"
    timeout "$limit" $python benchmarks/speed.py --cuda --sizes $size --modes eager cudagraphs compiled compiled-cudagraphs \
        --steps "${SPEED_STEPS:-10}" >"$runs/speed.$size.log" 2>&1
    code=$?
    quiet <"$runs/speed.$size.log" | grep -e "^|" -e "^torch" -e "^compiled" | tee -a "$report"
    if [ $code != 0 ]; then
        log "speed, size $size: $(ended $code "$limit"), the end of its log:"
        tail_of "$runs/speed.$size.log" 20
    fi
done
log "# done $(date -u '+%H:%M:%S UTC'), $((SECONDS - started)) s"
