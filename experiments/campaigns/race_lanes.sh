#!/usr/bin/env bash
# The race's remaining pieces (issue 42) on a host of several GPUs: one lane of race_piece.sh steps per GPU, run in
# the background in a process session of their own, so that they go on between device calls while the machine is
# held (docs/tuning/README.md, "Lanes"). Each step resumes like race_piece.sh; a lane that needs the Warp engine
# (held-out evaluation, the quality phase's population program) waits for /tmp/warp_ready, which the call that
# finishes unpacking warp-lang touches.
#
#   bash experiments/gpu_run.sh setup && bash experiments/campaigns/race_lanes.sh start   # first call (.wa, .ws)
#   bash experiments/gpu_run.sh setup && touch /tmp/warp_ready                              # the call with wpart_02
#   bash experiments/campaigns/race_lanes.sh poll $OUT [SECONDS]   # wait up to SECONDS for the lanes, pack run folders
#   bash experiments/campaigns/race_lanes.sh cache $OUT            # the compiled programs, in 15 MiB parts
#
# Lanes (GPU: steps): 0: per-axis hybrid, then its held-out evaluation and report; 1: the schedule's hybrid afresh
# (experiments/campaigns/reset_method.py: its first run spent its halves compiling), held out and reported; 2 and 3:
# a copy of each run folder for phase profile (JAX only), then phase quality (64 antithetic directions on Warp).
# Race budgets 2, 5 and 10 minutes (RACE_SNAPSHOTS="120 300": the hybrid's parents are CMA-ES at 60, 150, 300 s).
set -uo pipefail
ACTION=${1:?usage: race_lanes.sh start|poll OUT [SECONDS]|cache OUT}
LANES=${RACE_LANES_DIR:-/tmp/lanes}
REPO=$LANES/repo  # a copy of the checkout: a later call replaces the working tree under a running lane
export LANES REPO PYTHONPATH=/tmp/site:$REPO RACE_SNAPSHOTS=${RACE_SNAPSHOTS:-120 300} RACE_PACK_CACHE=0 RACE_CAP=${RACE_CAP:-3000}

lane() {  # gpu, name, steps...: each step "PARAM|RUNS|PHASES|FLAGS|NEEDS_WARP"
  local gpu=$1 name=$2; shift 2
  for step in "$@"; do
    IFS='|' read -r param runs phases flags warp <<< "$step"
    if [ "$warp" = warp ]; then until [ -f /tmp/warp_ready ]; do sleep 5; done; fi
    if [ "$phases" = reset ]; then
      tar -xzf "$REPO/.ws/race_$param.tgz" -C "$runs" && python3 "$REPO/experiments/campaigns/reset_method.py" \
        "$runs/$param" --method hybrid; continue
    fi
    echo "== $(date +%T) lane $name: $param $phases"
    CUDA_VISIBLE_DEVICES=$gpu RACE_PARAM=$param RACE_RUNS=$runs RACE_PHASES=$phases RACE_FLAGS=$flags \
      RACE_STATE=$REPO/.ws bash "$REPO/experiments/campaigns/race_piece.sh" "$LANES/$name/out" 2>&1 | grep -v '^\s*$'
  done
  echo "== $(date +%T) lane $name: done"; touch "$LANES/$name/done"
}

case "$ACTION" in
  start)
    [ -d "$REPO" ] && { echo "lanes already started in $LANES"; exit 1; }
    mkdir -p "$REPO" /tmp/race_runs /tmp/race_q && cp -r . "$REPO/" && rm -rf "$REPO"/.w[a-e]
    cd "$REPO" || exit 1
    for name in gains scheduled profile_gains profile_scheduled; do mkdir -p "$LANES/$name"; done
    Q="--quality-directions 64"
    setsid nohup bash -c "$(declare -f lane); lane 0 gains 'gains|/tmp/race_runs|hybrid||' \
      'gains|/tmp/race_runs|heldout report||warp'" > "$LANES/gains/log.txt" 2>&1 < /dev/null &
    setsid nohup bash -c "$(declare -f lane); lane 1 scheduled 'scheduled|/tmp/race_runs|reset||' \
      'scheduled|/tmp/race_runs|hybrid||' 'scheduled|/tmp/race_runs|heldout report||warp'" \
      > "$LANES/scheduled/log.txt" 2>&1 < /dev/null &
    setsid nohup bash -c "$(declare -f lane); lane 2 profile_gains 'gains|/tmp/race_q|profile||' \
      'gains|/tmp/race_q|quality|$Q|warp'" > "$LANES/profile_gains/log.txt" 2>&1 < /dev/null &
    setsid nohup bash -c "$(declare -f lane); lane 3 profile_scheduled 'scheduled|/tmp/race_q|profile||' \
      'scheduled|/tmp/race_q|quality|$Q|warp'" > "$LANES/profile_scheduled/log.txt" 2>&1 < /dev/null &
    sleep 2; echo "lanes started: $(ls "$LANES")" ;;
  poll)
    OUT=${2:?poll OUT [SECONDS]}; WAIT=${3:-0}; SECONDS=0
    while [ $SECONDS -lt "$WAIT" ] && [ "$(ls "$LANES"/*/done 2>/dev/null | wc -l)" -lt 4 ]; do sleep 10; done
    for name in gains scheduled profile_gains profile_scheduled; do
      echo "--- $name $([ -f "$LANES/$name/done" ] && echo DONE)"; tail -n 4 "$LANES/$name/log.txt" | cut -c1-220
    done
    nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
    mkdir -p "$OUT"
    tar -czf "$OUT/race_runs.tgz" -C /tmp race_runs 2>/dev/null
    tar -czf "$OUT/race_q.tgz" -C /tmp race_q 2>/dev/null
    tar -czf "$OUT/lane_logs.tgz" -C "$LANES" gains/log.txt scheduled/log.txt profile_gains/log.txt \
      profile_scheduled/log.txt 2>/dev/null
    ls -la "$OUT" ;;
  cache)
    OUT=${2:?cache OUT}; mkdir -p "$OUT"
    GPU=$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1 | tr -c 'A-Za-z0-9\n' '_')
    KEY=xla_${GPU}_jax$(python3 -c 'import jax; print(jax.__version__)')
    tar -czf - -C /tmp/xla-cache . | split -b 15M -d -a 2 - "$OUT/$KEY.tgz." && ls -la "$OUT" ;;
esac
