#!/usr/bin/env bash
# The one script a GPU session runs for issue 26 (docs/gpu_session.md). Run tool call:
#   command "bash tools/gpu/session.sh", carry [".whl"], timeout_s 600
# (.whl/ from tools/gpu/fetch_wheels.sh). It installs the wheels, records the machine, then runs the stages in
# priority order, each under its own timeout and all under one budget (GPU_SESSION_BUDGET_S, default 530 s), and
# appends to at most 7 files under $OUT as it goes, so a stage that fails or is cut off leaves the others' results:
#   env.txt          machine, versions, install, stage start/end/rc, and the digest of the recipe runs
#   bench.log        benchmarks/bench_update.py stdout/stderr (a JSON line per mode as it finishes)
#   bench_push.json  its results for push (eager / compiled / compiled + CUDA graphs, recipe frames/s)
#   tests.log        pytest tests/test_cuda.py tests/training/test_update_step.py
#   recipe.log       FetchPush frames/s on cuda; FetchReach to 0.95 on cuda vs cpu (a RESULT JSON line a run)
#   cpu_workers.log  FetchPush on the CPU, 8 parallel envs vs 1 (a RESULT JSON line a run: frames_per_s, ...)
#   bench_reach.json bench_update.py for reach, last, if time is left
# GPU_SESSION_DRYRUN=1 runs the same commands here on the CPU with tiny budgets (OUT=/tmp/gpu_out,
# PYTHON=python3 unless set): the check that the script runs before a GPU session spends its minutes.
# Dry run only: GPU_SESSION_SITE=DIR uses wheels already installed in DIR instead of installing them again.
set -u
cd "$(dirname "$0")/../.." || exit 1
ROOT=$PWD
T0=$(date +%s)
DRY=${GPU_SESSION_DRYRUN:-0}
PY=${PYTHON:-python3}
if [ "$DRY" = 1 ]; then
  if [ -z "${OUT:-}" ]; then OUT=/tmp/gpu_out; rm -rf "$OUT"; fi  # a given OUT is appended to, never removed
  DEV=cpu
else
  DEV=cuda
fi
OUT=${OUT:?OUT is unset: the run tool sets it; here use GPU_SESSION_DRYRUN=1}
mkdir -p "$OUT"
BUDGET=${GPU_SESSION_BUDGET_S:-560}
RUNS=$(mktemp -d /tmp/gpu_runs.XXXX)  # recipe run dirs and memories: not under $OUT (at most 8 files come back)

log() { echo "[$(date -u +%T) +$(( $(date +%s) - T0 ))s] $*" | tee -a "$OUT/env.txt"; }

# stage NAME LIMIT_S LOGFILE CMD...: CMD under min(LIMIT_S, what is left of the budget), output appended to
# $OUT/LOGFILE; SIGINT at the limit (python prints its traceback), SIGKILL 10 s later. Skipped (status 3) under
# 20 s left; otherwise status 0 whatever CMD's, so that one stage failing does not stop the next.
stage() {
  local name=$1 limit=$2 file=$3 left t s rc
  shift 3
  left=$(( BUDGET - ($(date +%s) - T0) ))
  t=$(( limit < left ? limit : left ))
  if [ "$t" -lt 20 ]; then log "stage $name: SKIPPED (${left}s of the budget left)"; return 3; fi
  log "stage $name: start, timeout ${t}s: $*"
  echo "===== $name: $* (timeout ${t}s)" >>"$OUT/$file"
  s=$(date +%s.%N)
  timeout --signal=INT --kill-after=10 "$t" "$@" >>"$OUT/$file" 2>&1
  rc=$?
  log "stage $name: rc=$rc$([ $rc = 124 ] && echo ' (TIMED OUT)') in $(awk "BEGIN{printf \"%.1f\", $(date +%s.%N)-$s}")s"
  return 0
}

# recipe LABEL LOGFILE LIMIT_S OVERRIDES...: recipes/her/train.py on a fresh memory, then one JSON line of its
# summary.json (frames_per_s, loop_wall_s, frames, frames_to_target, cpu_s, final success) plus the process wall_s
recipe() {
  local label=$1 file=$2 limit=$3 dir=$RUNS/$1 s
  shift 3
  s=$(date +%s.%N)
  stage "recipe:$label" "$limit" "$file" "$PY" recipes/her/train.py "$@" logger.plot=false logger.backend= \
    "memory.path=$dir/m.zarr" "hydra.run.dir=$dir/out" || return 0
  "$PY" - "$label" "$dir/out/summary.json" "$(awk "BEGIN{print $(date +%s.%N)-$s}")" >>"$OUT/$file" 2>&1 <<'PY'
import json, os, sys
label, path, wall = sys.argv[1], sys.argv[2], float(sys.argv[3])
row = {"run": label, "process_wall_s": round(wall, 1)}
if os.path.exists(path):
    s = json.load(open(path))
    row.update({k: s.get(k) for k in ("frames_per_s", "loop_wall_s", "frames", "frames_to_target", "cpu_s",
                                       "process_cpu_s", "updates")})
    row["success_end"] = s["curve"][-1][1] if s.get("curve") else None
    row["curve"] = s.get("curve")
else:
    row["error"] = "no summary.json (failed or timed out: see the log above)"
print("\nRESULT " + json.dumps(row))  # own line: a progress bar may have left one open
PY
  grep '^RESULT ' "$OUT/$file" | tail -1 | cut -c8- | tee -a "$OUT/env.txt"
}

# ---- install and record the machine
log "session start: dryrun=$DRY device=$DEV budget=${BUDGET}s out=$OUT"
if [ "$DRY" = 1 ] && [ -n "${GPU_SESSION_SITE:-}" ]; then
  SITE=$GPU_SESSION_SITE
else
  SITE=/tmp/site
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl \
    >>"$OUT/env.txt" 2>&1 || { log "wheel install FAILED (is .whl/ carried? bash tools/gpu/fetch_wheels.sh)"; exit 1; }
fi
export PYTHONPATH=$SITE:$ROOT MUJOCO_GL=disable PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
log "wheels installed in $SITE"
{
  nvidia-smi -L 2>&1 || true
  nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv 2>&1 || true
  echo "nproc $(nproc); $(free -g | awk '/Mem/{print "RAM " $2 " GiB"}')"
  "$PY" - <<'PY'
import importlib.metadata as md, sys, torch
print("python", sys.version.split()[0], sys.executable)
print("torch", torch.__version__, "cuda", torch.version.cuda, "available", torch.cuda.is_available(),
      torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
for name in ("torchrl", "tensordict", "zarr", "numcodecs", "gymnasium", "gymnasium-robotics", "mujoco", "hydra-core",
             "numpy", "triton"):
    try:
        print(name, md.version(name))
    except md.PackageNotFoundError:
        print(name, "MISSING")
PY
} >>"$OUT/env.txt" 2>&1
stage smoke 90 env.txt "$PY" -c "
import torchrl_robotmem
from torchrl_robotmem import make_env
print(make_env('FetchPush-v4', seed=0).rollout(5))"

# ---- stages, most wanted first
if [ "$DRY" = 1 ]; then
  # the same commands, small enough for a busy 2-core box: fewer frames, small networks and batches
  SMALL=(optim.batch_size=64 "network.hidden_sizes=[32,32]")
  BENCH=(--updates 3 --repeat 1 --warmup 1 --rows 200)
  PUSH_RUN=(collector.total_frames=600 collector.cpu_budget_s=40 "${SMALL[@]}")
  REACH_RUN=(collector.total_frames=600 collector.cpu_budget_s=40 logger.eval_episodes=5 "${SMALL[@]}")
  WORKER_RUN=(collector.total_frames=800 collector.init_random_frames=400 "${SMALL[@]}")
  TESTS=(-n 0 -k "not parallel and not recipe and not compiled")
  export ROBOTMEM_TEST_DEVICE=cpu
  PRIOR_RUN=(collector.init_random_frames=200 memory.pretrain_updates=20 "${SMALL[@]}") PRIOR_EVAL=300 PRIOR_EPISODES=5
  THREADS=1 ENVS=2  # two torch threads on a busy 2-core box: 10x slower updates (config.yaml, num_threads)
else
  BENCH=(--compile --cudagraphs)
  # collector.cpu_budget_s: a graceful stop (summary written) before the stage's timeout would cut the run off
  PUSH_RUN=(collector.total_frames=3000 collector.cpu_budget_s=60)
  REACH_RUN=(collector.total_frames=5000 collector.cpu_budget_s=55)
  WORKER_RUN=(collector.total_frames=1200 collector.init_random_frames=400)  # 800 updates: ~30 s on one thread
  TESTS=(-n 4 -k "not parallel")  # beside the GPU track: the recipe tests mostly wait on their subprocesses
  PRIOR_RUN=() PRIOR_EVAL=5000 PRIOR_EPISODES=100  # evaluations every 5k (the CPU runs: every 2.5k), 100 episodes
  THREADS=8 ENVS=8
fi

# Two tracks run side by side, each under the one budget (a 16-core machine; one would not fit in 10 minutes):
#   GPU track: a (bench push), a2 (push recipe frames/s), c (reach cuda vs cpu), p0 (push with a prior memory), e
#   CPU track: d2 (open 1M rows), d (8 env workers vs 1), b (tests, GPU too), p1 (push with a prior, seed 1)
# Tests (and their short GPU processes) run only once the CPU stages are done; the CPU stages overlap the
# GPU track's benchmark, whose ours-vs-TorchRL ratios are same-run. Each track appends to its own files.
PRIOR=$ROOT/bench_results/prior/scripted-push-500.zarr  # carried: experiments.scripted.collect env=push episodes=500 noise=1 seed=0
# p SEED FILE CAP: the docs/results.md FetchPush setting (prior=mix, SAC+HER, 60k frames) on the device, as far as the
# time left allows: collector.cpu_budget_s stops it gracefully (summary written) about 80 s before the stage's cap
prior_run() {
  local seed=$1 file=$2 cap=$3 left
  left=$(( BUDGET - ($(date +%s) - T0) )); left=$(( cap < left ? cap : left ))
  if [ ! -d "$PRIOR" ]; then log "stage recipe:push_prior_s$seed: SKIPPED (no $PRIOR; carry it)"; return 0; fi
  recipe "push_prior_s$seed" "$file" "$cap" env=push device="$DEV" seed="$seed" prior=mix "prior.paths=[$PRIOR]" \
    optim.target_clip=null logger.eval_iter="$PRIOR_EVAL" logger.eval_episodes="$PRIOR_EPISODES" \
    collector.total_frames=60000 collector.cpu_budget_s=$(( left > 110 ? left - 80 : 30 )) "${PRIOR_RUN[@]}"
}

gpu_track() {
  # a. ms per update, TorchRL sota SAC vs the recipe's Updater, eager / compiled / compiled + CUDA graphs, push
  stage bench:push 170 bench.log "$PY" benchmarks/bench_update.py --device "$DEV" --configs push \
    --json "$OUT/bench_push.json" "${BENCH[@]}"
  # a2. the push recipe's frames/s on the GPU (its cuda default: compiled + CUDA graphs), as bench_update.py's
  # --recipe-frames runs it (500 random frames, one evaluation at the end), but under its own timeout
  recipe push_cuda recipe.log 80 env=push device="$DEV" collector.init_random_frames=500 logger.eval_iter=100000 \
    logger.eval_episodes=10 "${PUSH_RUN[@]}"
  # c. FetchReach to 0.95: wall time on the GPU (compiled + CUDA graphs, the cuda default) vs one CPU thread
  recipe reach_cuda recipe.log 75 env=reach device="$DEV" logger.target_success=0.95 "${REACH_RUN[@]}"
  recipe reach_cpu recipe.log 75 env=reach device=cpu logger.target_success=0.95 "${REACH_RUN[@]}"
  # p0. FetchPush with the noisy scripted memory as prior, seed 0: frames/s of the 60k setting, and its curve
  prior_run 0 recipe.log 150
  # e. what is left: the same benchmark for reach
  stage bench:reach 150 bench.log "$PY" benchmarks/bench_update.py --device "$DEV" --configs reach \
    --json "$OUT/bench_reach.json" "${BENCH[@]}"
}

cpu_track() {
  # d2. opening a 1M-row memory on 16 cores (the issue's <= 0.5 s goal), against LazyMemmapStorage's reopen
  stage open 120 cpu_workers.log "$PY" benchmarks/bench_open.py --rows "$OPEN_ROWS" --repeat 3
  # d. FetchPush on the CPU cores: 8 envs in worker processes vs 1 env, same threads, 400 frames a batch
  local WORKER=(env=push device=cpu collector.frames_per_batch=400 logger.eval_iter=100000
                logger.eval_episodes=5 "${WORKER_RUN[@]}")
  recipe "push_cpu_${ENVS}envs" cpu_workers.log 60 "${WORKER[@]}" env.num_envs="$ENVS" env.parallel=true num_threads="$THREADS"
  recipe push_cpu_1env_1thread cpu_workers.log 60 "${WORKER[@]}" env.num_envs=1 num_threads=1  # the goal's baseline
  recipe push_cpu_1env cpu_workers.log 60 "${WORKER[@]}" env.num_envs=1 num_threads="$THREADS"
  # b. the CUDA tests and the fast-update tests on the GPU
  stage tests 150 tests.log "$PY" -m pytest -q --maxfail=3 --durations=15 -p no:cacheprovider "${TESTS[@]}" \
    tests/test_cuda.py tests/training/test_update_step.py
  # p1. the prior run's second seed (the curves against the CPU path's, docs/runs/prior-push-s1.json)
  prior_run 1 cpu_workers.log 150
}

OPEN_ROWS=1000000; [ "$DRY" = 1 ] && OPEN_ROWS=100000
gpu_track &
GPU_PID=$!
cpu_track
wait "$GPU_PID"

log "session end"
echo "== bench tables"; grep -E '^\|' "$OUT/bench.log" || true
echo "== tests"; grep -E '(passed|failed|error)' "$OUT/tests.log" | tail -3 || true
rm -rf "$RUNS"
