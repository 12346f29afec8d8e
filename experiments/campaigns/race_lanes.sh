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
# Lanes (GPU: steps): 0: the per-axis run's checkpoints re-keyed (rekey_checkpoints.py), CMA-ES's sets at half of
# each budget and the hybrid, then its held-out evaluation and report; 1: the schedule's hybrid afresh
# (reset_method.py: its first run spent its halves compiling), held out and reported; 2: phase profile (JAX only) on
# a copy of each run folder; 3: phase quality (64 antithetic directions on Warp) in a fresh folder per
# parameterisation. Processes started from a device call die with it unless they start a session of their own.
set -uo pipefail
ACTION=${1:?usage: race_lanes.sh start|lane GPU NAME STEP...|poll OUT [SECONDS]|cache OUT}
LANES=${RACE_LANES_DIR:-/tmp/lanes}
REPO=$LANES/repo  # a copy of the checkout: a later call replaces the working tree under a running lane
export LANES REPO PYTHONPATH=/tmp/site:$REPO RACE_PACK_CACHE=0 RACE_CAP=${RACE_CAP:-3000}

lane() {  # gpu, name, steps...: each step "PARAM|RUNS|PHASES|FLAGS|NEEDS_WARP|SNAPSHOTS|RESTORE"
  local gpu=$1 name=$2; shift 2
  for step in "$@"; do
    IFS='|' read -r param runs phases flags warp snaps restore <<< "$step"
    if [ "$warp" = warp ]; then until [ -f /tmp/warp_ready ]; do sleep 5; done; fi
    case "$phases" in
      reset)  # the schedule's hybrid afresh: its first run spent its halves compiling
        tar -xzf "$REPO/.ws/race_$param.tgz" -C "$runs" && python3 "$REPO/experiments/campaigns/reset_method.py" \
          "$runs/$param" --method hybrid; continue ;;
      rekey)  # the per-axis run's checkpoints, keyed before the hand-set gains moved to assets/gains/
        tar -xzf "$REPO/.ws/race_$param.tgz" -C "$runs" && python3 "$REPO/experiments/campaigns/rekey_checkpoints.py" \
          "$runs/$param" --init-gains assets/gains/com_critical_100.json; continue ;;
    esac
    echo "== $(date +%T) lane $name: $param $phases"
    CUDA_VISIBLE_DEVICES=$gpu RACE_PARAM=$param RACE_RUNS=$runs RACE_PHASES=$phases RACE_FLAGS=$flags \
      RACE_SNAPSHOTS=$snaps RACE_RESTORE=${restore:-1} RACE_STATE=$REPO/.ws \
      bash "$REPO/experiments/campaigns/race_piece.sh" "$LANES/$name/out" 2>&1 | grep -v '^\s*$'
  done
  echo "== $(date +%T) lane $name: done"; touch "$LANES/$name/done"
}

NAMES="gains scheduled profile quality"
case "$ACTION" in
  start)
    [ -d "$REPO" ] && { echo "lanes already started in $LANES"; exit 1; }
    mkdir -p "$REPO" /tmp/race_runs /tmp/race_q /tmp/race_q2 && cp -r . "$REPO/" && rm -rf "$REPO"/.w[a-e]
    cd "$REPO" || exit 1
    for name in $NAMES; do mkdir -p "$LANES/$name"; done
    # Each run folder's snapshots are part of its fingerprint: the per-axis run's 60 120 150 300, the schedule's
    # 120 300. The quality phase runs in fresh folders (its --quality-directions is part of a run's fingerprint too).
    PA="60 120 150 300"; SC="120 300"; Q="--quality-directions 64"
    start_lane() { setsid nohup bash -c "$(declare -f lane); lane $*" > "$LANES/$2/log.txt" 2>&1 < /dev/null & }
    start_lane 0 gains "'gains|/tmp/race_runs|rekey'" "'gains|/tmp/race_runs|cmaes hybrid|||$PA'" \
      "'gains|/tmp/race_runs|heldout report||warp|$PA'"
    start_lane 1 scheduled "'scheduled|/tmp/race_runs|reset'" "'scheduled|/tmp/race_runs|hybrid|||$SC'" \
      "'scheduled|/tmp/race_runs|heldout report||warp|$SC'"
    start_lane 2 profile "'gains|/tmp/race_q|profile|||$PA'" "'scheduled|/tmp/race_q|profile|||$SC'"
    start_lane 3 quality "'gains|/tmp/race_q2|quality|$Q|warp|$PA|0'" "'scheduled|/tmp/race_q2|quality|$Q|warp|$SC|0'"
    sleep 2; echo "lanes started: $(ls "$LANES")" ;;
  lane)  # one lane again (after start): race_lanes.sh lane GPU NAME 'STEP' ...
    cd "$REPO" || exit 1; shift; mkdir -p "$LANES/$2"; rm -f "$LANES/$2/done"
    q=(); for a in "$@"; do q+=("'$a'"); done
    setsid nohup bash -c "$(declare -f lane); lane ${q[*]}" >> "$LANES/$2/log.txt" 2>&1 < /dev/null &
    sleep 1; echo "lane $2 started on GPU $1" ;;
  poll)
    OUT=${2:?poll OUT [SECONDS]}; WAIT=${3:-0}; SECONDS=0
    while [ $SECONDS -lt "$WAIT" ] && [ "$(ls "$LANES"/*/done 2>/dev/null | wc -l)" -lt 4 ]; do sleep 10; done
    for name in $NAMES; do
      echo "--- $name $([ -f "$LANES/$name/done" ] && echo DONE)"; tail -n 4 "$LANES/$name/log.txt" | cut -c1-220
    done
    nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
    mkdir -p "$OUT"
    tar -czf "$OUT/race_runs.tgz" -C /tmp race_runs 2>/dev/null
    tar -czf "$OUT/race_q.tgz" -C /tmp race_q race_q2 2>/dev/null
    (cd "$LANES" && tar -czf "$OUT/lane_logs.tgz" ./*/log.txt 2>/dev/null)
    ls -la "$OUT" ;;
  cache)
    OUT=${2:?cache OUT}; mkdir -p "$OUT"
    GPU=$(nvidia-smi --query-gpu=name --format=csv,noheader | head -1 | tr -c 'A-Za-z0-9\n' '_')
    KEY=xla_${GPU}_jax$(python3 -c 'import jax; print(jax.__version__)')
    tar -czf - -C /tmp/xla-cache . | split -b 15M -d -a 2 - "$OUT/$KEY.tgz." && ls -la "$OUT" ;;
esac
