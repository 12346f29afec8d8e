#!/usr/bin/env bash
# Several resumable jobs at once on one held machine of four GPUs and many CPU cores (issues 42, 43, 45, 41): each
# lane runs in a process session of its own, so it goes on between device calls while the machine is held, and
# every call returns what has finished (docs/tuning/README.md, "The race, complete").
#
#   bash experiments/gpu_run.sh setup && bash experiments/campaigns/session_lanes.sh start   # first call (.wa .wx)
#   bash experiments/gpu_run.sh setup && touch /tmp/warp_ready                                 # the call with wpart_02
#   bash experiments/gpu_run.sh setup && touch /tmp/viz_ready                                  # the call with .wr
#   bash experiments/campaigns/session_lanes.sh poll $OUT [SECONDS]   # wait up to SECONDS, pack results.tgz
#
# Lanes: GPU 0 and 1: phase quality of the race (64 antithetic directions) for the per-axis gains and the schedule,
# each in a fresh run folder; GPU 2: the gpu test set (.ci/nightly gpu; waits for Warp and the .wr wheels); GPU 3:
# phase profile at batch 16,384 (JAX only); CPU: the crocoddyl cross-check of the limit (experiments/acceptance/
# ddp_limit.py, one process per direction on a core of its own, then --recheck) for the directions not yet run;
# then, once the GPU lanes are done, the 4-GPU scaling jobs of gpu_run.sh (scaling4_warp, then scaling4_jax).
# .wx/ddpsite.tar.xz: crocoddyl 3.2.1 and pinocchio 4.0.0 for Python 3.12 (cmeel wheels, unpacked, headers removed).
set -uo pipefail
ACTION=${1:?usage: session_lanes.sh start|poll OUT [SECONDS]}
LANES=${SESSION_LANES_DIR:-/tmp/lanes}
REPO=$LANES/repo  # a copy of the checkout: a later call replaces the working tree under a running lane
DDP_SITE=/tmp/ddpsite/cmeel.prefix/lib/python3.12/site-packages
export PYTHONPATH=/tmp/site:$REPO PYTHONUNBUFFERED=1 TF_CPP_MIN_LOG_LEVEL=3
CHEST="11.25 22.5 33.75 56.25 67.5 78.75 101.25 112.5 236.25 247.5 258.75 281.25 292.5 303.75 326.25 337.5 348.75"
ROOT_LINK="0.0 11.25 22.5 45.0 56.25 67.5 78.75 90.0 101.25 123.75 135.0 146.25 157.5 168.75 180.0 191.25 213.75
  225.0 236.25 247.5 258.75 281.25 292.5 303.75 315.0 326.25 337.5 348.75"
GPU_LANES="quality_gains quality_scheduled gpuset profile"

bg() {  # name, shell command: run in a session of its own, its log in $LANES/name/log.txt, then a done file
  local name=$1; shift; mkdir -p "$LANES/$name"
  setsid nohup bash -c "cd $REPO && { $*; }; echo \"rc=\$? \$(date +%T)\" > $LANES/$name/done" \
    > "$LANES/$name/log.txt" 2>&1 < /dev/null &
}
wait_for() { echo "until [ -f $1 ]; do sleep 5; done"; }

quality() {  # gpu, param, snapshots
  echo "$(wait_for /tmp/warp_ready); CUDA_VISIBLE_DEVICES=$1 RACE_PARAM=$2 RACE_RUNS=/tmp/race_q RACE_PHASES=quality \
    RACE_FLAGS='--quality-directions 64' RACE_SNAPSHOTS='$3' RACE_RESTORE=0 RACE_PACK_CACHE=0 RACE_CAP=1700 \
    bash experiments/campaigns/race_piece.sh $LANES/quality_$2/out"
}

ddp() {  # body, azimuth, core: a job file: the bisection (3 tests, CoP x0.8), then the limit replayed alone
  local f=/tmp/ddp/$1_$2 run
  run="taskset -c $3 nice -n 5 env JAX_PLATFORMS=cpu CUDA_VISIBLE_DEVICES= OMP_NUM_THREADS=1"
  run="$run PYTHONPATH=$DDP_SITE:/tmp/site:$REPO python3 experiments/acceptance/ddp_limit.py --body $1"
  run="$run --cop-scale 0.8 --tests 3 --batch 1 --directions $2 --out $f.json"
  printf 'cd %s\n%s > %s.log 2>&1 && %s --recheck >> %s.log 2>&1\necho "%s %s rc=$? $(date +%%T)"\n' \
    "$REPO" "$run" "$f" "$run" "$f" "$1" "$2" > "/tmp/ddp/job_$1_$2.sh"
}

case "$ACTION" in
  start)
    [ -d "$REPO" ] && { echo "lanes already started in $LANES"; exit 1; }
    mkdir -p "$REPO" /tmp/race_q /tmp/ddp && cp -r . "$REPO/" && rm -rf "$REPO"/.w[a-z]
    if [ -f .wx/ddpsite.tar.xz ] && [ ! -d /tmp/ddpsite ]; then xz -dc .wx/ddpsite.tar.xz | tar xf - -C /tmp; fi
    PYTHONPATH=$DDP_SITE:$PYTHONPATH python3 -c "import crocoddyl, pinocchio; print('crocoddyl', crocoddyl.__version__, 'pinocchio', pinocchio.__version__)"
    cd "$REPO" || exit 1
    bg quality_gains "$(quality 0 gains '60 120 150 300')"
    bg quality_scheduled "$(quality 1 scheduled '120 300')"
    bg gpuset "$(wait_for /tmp/warp_ready); $(wait_for /tmp/viz_ready); CUDA_VISIBLE_DEVICES=2 \
      NIGHTLY_COMMIT=${NIGHTLY_COMMIT:-} WBC_JAX_CACHE=/tmp/xla-gpuset bash .ci/nightly gpu"
    bg profile "CUDA_VISIBLE_DEVICES=3 RACE_PARAM=gains RACE_RUNS=/tmp/race_p RACE_PHASES=profile \
      RACE_FLAGS='--batch 16384 --quality-pushes 16384' RACE_RESTORE=0 RACE_PACK_CACHE=0 RACE_CAP=900 \
      bash experiments/campaigns/race_piece.sh $LANES/profile/out"
    # The crocoddyl directions, one process per core from core 16 up (cores 0-15 serve the GPU lanes' host work).
    cores=$(nproc); core=16
    for az in $CHEST; do ddp chest "$az" $core; core=$(( core + 1 < cores ? core + 1 : 16 )); done
    for az in $ROOT_LINK; do ddp root_link "$az" $core; core=$(( core + 1 < cores ? core + 1 : 16 )); done
    bg ddp "ls /tmp/ddp/job_*.sh | xargs -P $(( cores - 16 )) -n 1 bash"
    waits=""; for n in $GPU_LANES; do waits="$waits $(wait_for "$LANES/$n/done");"; done
    bg scaling "$waits OUT=$LANES/scaling/out bash experiments/gpu_run.sh scaling4_warp scaling4_jax"
    sleep 2; echo "lanes started ($(nproc) cores, $(( cores - 16 )) for crocoddyl): $(ls "$LANES")" ;;
  poll)
    OUT=${2:?poll OUT [SECONDS]}; WAIT=${3:-0}; SECONDS=0
    while [ $SECONDS -lt "$WAIT" ] && [ ! -f "$LANES/scaling/done" ]; do sleep 10; done
    for name in $GPU_LANES ddp scaling; do
      echo "--- $name $(cat "$LANES/$name/done" 2>/dev/null)"; tail -n 3 "$LANES/$name/log.txt" | cut -c1-200
    done
    echo "crocoddyl: $(ls /tmp/ddp/*.json 2>/dev/null | wc -l) files, $(grep -c 'rc=' "$LANES/ddp/log.txt") of $(ls /tmp/ddp/job_*.sh | wc -l) directions finished"
    nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader; uptime
    mkdir -p "$OUT"
    tar -czf "$OUT/results.tgz" -C / tmp/race_q tmp/race_p tmp/ddp tmp/scaling4/scaling.json \
      "${LANES#/}"/repo/results/nightly/gpu.log $(cd / && ls -d "${LANES#/}"/*/log.txt "${LANES#/}"/*/out "${LANES#/}"/*/done 2>/dev/null) 2>/dev/null
    ls -la "$OUT" ;;
esac
