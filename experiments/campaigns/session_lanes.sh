#!/usr/bin/env bash
# Several resumable jobs at once on one held machine of four GPUs (issues 45, 41, 47): each lane runs in a process
# session of its own, so it goes on between device calls while the machine is held, and every call returns what has
# finished. The calls carry the wheels (gpu_run.sh's header) and poll.
#
#   bash experiments/gpu_run.sh setup && bash experiments/campaigns/session_lanes.sh start   # first call (.wa)
#   bash experiments/gpu_run.sh setup && touch /tmp/warp_ready                                 # the call with wpart_02
#   bash experiments/gpu_run.sh setup && touch /tmp/viz_ready                                  # the call with .wr2
#   bash experiments/campaigns/session_lanes.sh poll $OUT [SECONDS]   # wait up to SECONDS, pack results.tgz
#
# Lanes (the GPUs' timings never share a GPU with another job). SESSION_PLAN picks them:
#   four (a machine of 4 GPUs; issue 45): the 131,072-env chest sweep (64 x 32 x 64, one chunk) on 1, 2 and 4 GPUs of
#     both engines, rows merged in /tmp/scaling4_131072: four (JAX on all 4 GPUs from the first call, then Warp once
#     it arrived, 2 runs each), then at once on disjoint GPUs: jax1 (JAX on GPU 0, 3 runs: the repeat floor), warp1
#     (Warp on GPU 1, 3 runs), jax2 (JAX, then Warp, on GPUs 2-3, 2 runs each); scaling ends when all are done;
#   one (one GPU; issue 46): ONE_JOBS (default profile_tick profile_tick_warm: no Warp needed, so no wheels
#     beyond .wa), then ONE_WARP_JOBS once Warp's wheels arrived (default none; e.g. "bench46_warm bench46");
#   two (a machine of 2 or more GPUs; issue 45): scaling (once Warp is there: tune_gpus on one GPU, then on all; its
#     one-GPU half is kept in $OUT/tune_gpus/tune_gpus_one_device.json as soon as it ends, and taken from
#     TUNE_GPUS_SEED, an earlier call's, where that was measured alike: then only the N-GPU half runs).
# Git-less copy: NIGHTLY_COMMIT names the commit in the gpu set's log.
set -uo pipefail
ACTION=${1:?usage: session_lanes.sh start|poll OUT [SECONDS]}
LANES=${SESSION_LANES_DIR:-/tmp/lanes}
REPO=$LANES/repo  # a copy of the checkout: a later call replaces the working tree under a running lane
export PYTHONPATH=/tmp/site:$REPO PYTHONUNBUFFERED=1 TF_CPP_MIN_LOG_LEVEL=3
PLAN=${SESSION_PLAN:-four}
LANE_NAMES="four jax1 warp1 jax2 scaling"; [ "$PLAN" != four ] && LANE_NAMES=scaling

bg() {  # name, shell command: run in a session of its own, its log in $LANES/name/log.txt, then a done file
  local name=$1; shift; mkdir -p "$LANES/$name"
  setsid nohup bash -c "cd $REPO && { $*; }; echo \"rc=\$? \$(date +%T)\" > $LANES/$name/done" \
    > "$LANES/$name/log.txt" 2>&1 < /dev/null &
}
wait_for() { echo "until [ -f $1 ]; do sleep 5; done;"; }

case "$ACTION" in
  start)
    [ -d "$REPO" ] && { echo "lanes already started in $LANES"; exit 1; }
    mkdir -p "$REPO" && cp -r . "$REPO/" && rm -rf "$REPO"/.w[a-z]*
    cd "$REPO" || exit 1
    G="OUT=$LANES/scaling/out"
    if [ "$PLAN" = one ]; then
      W=${ONE_WARP_JOBS-}  # jobs that need Warp's wheels (e.g. "bench46_warm bench46"): after /tmp/warp_ready
      # ONE_PAR_JOBS (untimed on the GPU, e.g. "was_sweep gpu_tests_warp") after those, on cores 2.. while ONE_CPU_JOBS
      # (e.g. cpu_peer: core 1, once the call carrying TSID's last wheels touched /tmp/tsid_ready) run beside them
      P=${ONE_PAR_JOBS-}; C=${ONE_CPU_JOBS-}; after=""
      [ -n "$C" ] && after="{ $(wait_for /tmp/tsid_ready) OUT=$LANES/cpu/out bash experiments/gpu_run.sh $C; } &"
      [ -n "$P" ] && after="$after OUT=$LANES/par/out taskset -c 2-$(($(nproc) - 1)) bash experiments/gpu_run.sh $P;"
      bg scaling "$G bash experiments/gpu_run.sh ${ONE_JOBS-profile_tick profile_tick_warm} \
        ${W:+; $(wait_for /tmp/warp_ready) $G bash experiments/gpu_run.sh $W}; $after wait"
      sleep 2; echo "lanes started ($(nproc) cores, plan one): $(ls "$LANES")"; exit 0
    fi
    if [ "$PLAN" = two ]; then
      # An earlier one-GPU half (TUNE_GPUS_SEED): the check reuses it where measured alike (device kind, flags).
      SEED=${TUNE_GPUS_SEED-results/tuning/tune_gpus_h200x2_s56/tune_gpus_one_device.json}
      mkdir -p "$LANES/scaling/out/tune_gpus"; [ -n "$SEED" ] && cp "$SEED" "$LANES/scaling/out/tune_gpus/"
      bg scaling "$(wait_for /tmp/warp_ready) \
        TUNE_GPUS_FLAGS='${TUNE_GPUS_FLAGS:---repeats 2}' TUNE_GPUS_WALL=${TUNE_GPUS_WALL:-1500} $G bash experiments/gpu_run.sh tune_gpus"
      sleep 2; echo "lanes started ($(nproc) cores, plan two): $(ls "$LANES")"; exit 0
    fi
    S="SCALING_GAIN_SETS=64"; L=$LANES; F=$(wait_for $L/four/done)
    bg four "$S SCALING_GPUS=4 SCALING_REPEATS=2 OUT=$L/four/out bash experiments/gpu_run.sh scaling4_jax; \
      $(wait_for /tmp/warp_ready) $S SCALING_GPUS=4 SCALING_REPEATS=2 OUT=$L/four/out bash experiments/gpu_run.sh scaling4_warp"
    bg jax1 "$F CUDA_VISIBLE_DEVICES=0 $S SCALING_GPUS=1 OUT=$L/jax1/out bash experiments/gpu_run.sh scaling4_jax"
    bg warp1 "$F CUDA_VISIBLE_DEVICES=1 $S SCALING_GPUS=1 OUT=$L/warp1/out bash experiments/gpu_run.sh scaling4_warp"
    bg jax2 "$F CUDA_VISIBLE_DEVICES=2,3 $S SCALING_GPUS=2 SCALING_REPEATS=2 OUT=$L/jax2/out \
      bash experiments/gpu_run.sh scaling4_jax scaling4_warp"
    bg scaling "$(wait_for $L/jax1/done) $(wait_for $L/jax2/done) $(wait_for $L/warp1/done) \
      mkdir -p $L/scaling/out && cp /tmp/scaling4_131072/scaling.json $L/scaling/out/"
    sleep 2; echo "lanes started ($(nproc) cores): $(ls "$LANES")" ;;
  poll)
    OUT=${2:?poll OUT [SECONDS]}; WAIT=${3:-0}; SECONDS=0
    while [ $SECONDS -lt "$WAIT" ] && [ ! -f "$LANES/scaling/done" ]; do sleep 10; done
    for name in $LANE_NAMES; do
      echo "--- $name $(cat "$LANES/$name/done" 2>/dev/null)"; tail -n 4 "$LANES/$name/log.txt" | cut -c1-220
    done
    nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader; uptime
    mkdir -p "$OUT"
    tar -czf "$OUT/results.tgz" -C / tmp/scaling4/scaling.json tmp/scaling4_65536/scaling.json tmp/scaling4_131072/scaling.json \
      "${LANES#/}"/repo/results/nightly/gpu.log $(cd / && ls -d "${LANES#/}"/*/log.txt "${LANES#/}"/*/out "${LANES#/}"/*/done 2>/dev/null) 2>/dev/null
    ls -la "$OUT" ;;
esac
