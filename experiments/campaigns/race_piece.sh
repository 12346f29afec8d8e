#!/usr/bin/env bash
# One resumable piece of the race (issue 42) in one device call: restore the run folder and JAX's compiled programs
# from the carried state folder, run `wbc-jax tune` on the race's phases until a time cap, pack both back into
# OUT_DIR. The next call (on the same machine or a fresh one) carries what came back and goes on; a piece stopped by
# its cap loses at most the step in flight (the tune job checkpoints every step and generation).
#
#   bash experiments/gpu_run.sh setup && RACE_PHASES="train cmaes" RACE_CAP=500 \
#     bash experiments/campaigns/race_piece.sh $OUT/race
#
# State (RACE_STATE, default .ws/, git-ignored): race_<param>.tgz (the run folder)
# and xla_<gpu>_jax<version>.tgz.NN (JAX's persistent cache and the saved executables of WBC_JAX_CACHE, split in
# 15 MiB parts: a device call returns files of at most 16 MiB). The cache is keyed by GPU name and jax version: a
# program compiled on an H100 is not loaded on an H200 (JAX's own cache key holds the device kind too).
# After a call: mkdir -p .ws && cp <returned race dir>/* .ws/  (docs/tuning/README.md, "Compile once").
set -uo pipefail
OUT_DIR=${1:?usage: race_piece.sh OUT_DIR}
mkdir -p "$OUT_DIR"
STATE=${RACE_STATE:-.ws}
PARAM=${RACE_PARAM:-gains}
PHASES=${RACE_PHASES:-train cmaes random heldout report}
CAP=${RACE_CAP:-500}
BUDGET=${RACE_BUDGET:-600}
SNAPSHOTS=${RACE_SNAPSHOTS:-60 120 150 300}  # the per-axis run's; a new run: "120 300" (the hybrid adds the halves)
RUNS=${RACE_RUNS:-/tmp/race_runs}  # RACE_RESTORE=0: a fresh run folder (e.g. to time a compile from the carried cache)
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 TF_CPP_MIN_LOG_LEVEL=3 WBC_JAX_CACHE=/tmp/xla-cache
export XLA_FLAGS=${RACE_XLA_FLAGS---xla_gpu_autotune_level=0}
GPU=$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1 | tr -c 'A-Za-z0-9\n' '_')
KEY=xla_${GPU:-cpu}_jax$(python3 -c 'import jax; print(jax.__version__)')
mkdir -p "$RUNS"
if [ "${RACE_RESTORE:-1}" = 1 ] && [ ! -d "$RUNS/$PARAM" ] && [ -f "$STATE/race_$PARAM.tgz" ]; then
  tar -xzf "$STATE/race_$PARAM.tgz" -C "$RUNS" && echo "restored $RUNS/$PARAM from $STATE"
fi
if [ ! -d "$WBC_JAX_CACHE" ] && ls "$STATE/$KEY.tgz."* >/dev/null 2>&1; then
  mkdir -p "$WBC_JAX_CACHE" && cat "$STATE/$KEY.tgz."* | tar -xzf - -C "$WBC_JAX_CACHE" \
    && echo "restored the compiled programs ($(du -sh "$WBC_JAX_CACHE" | cut -f1)) from $STATE/$KEY.tgz.*"
fi
# The race's flags (docs/tuning/README.md, "The race"): 2, 5 and 10 minute budgets from one 10-minute run per
# method (snapshots at 120 and 300 s; 60 and 150 s are the hybrid's halves), implicit solver gradient, a tick
# checkpoint, batch 2,048 of 2 s rollouts, the held-out grid in chunks of 16,384.
SECONDS=0
# shellcheck disable=SC2086
timeout --signal=INT --kill-after=20 "$CAP" python3 -m wbc_jax.cli tune --quiet --out "$RUNS/$PARAM" \
  --phases $PHASES --parameterisation "$PARAM" --budget-s "$BUDGET" --snapshots-s $SNAPSHOTS \
  --steps 100000 --batch 2048 --quality-pushes 2048 --no-wall-budget --search-backend auto \
  --solver-gradient implicit --checkpoint tick --horizon 2 --lr 0.1 --push-scale lip --magnitude-range 0.3 1.0 \
  --init-gains assets/gains/com_critical_100.json --population 16 --es-batch 60 --chunk-size 16384 \
  ${RACE_FLAGS:-}
echo "tune: rc=$? ${SECONDS}s (cap ${CAP}s; 124/130: stopped by the cap, resumes in the next piece)"
for m in gradient cmaes random hybrid; do
  [ -f "$RUNS/$PARAM/$m/history.csv" ] && echo "$m: $(($(wc -l < "$RUNS/$PARAM/$m/history.csv") - 1)) rows, last: $(tail -n 1 "$RUNS/$PARAM/$m/history.csv" | cut -c1-160)"
done
ls "$RUNS/$PARAM"
tar -czf "$OUT_DIR/race_$PARAM.tgz" -C "$RUNS" "$PARAM"
# RACE_PACK_CACHE=0: leave the compiled programs on the machine (race_lanes.sh packs them once, at the end)
[ "${RACE_PACK_CACHE:-1}" = 1 ] && tar -czf - -C "$WBC_JAX_CACHE" . | split -b 15M -d -a 2 - "$OUT_DIR/$KEY.tgz."
ls -la "$OUT_DIR"
