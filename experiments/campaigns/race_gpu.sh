#!/usr/bin/env bash
# Issue 35 on one GPU in one call of about 8 minutes (experiments/gpu_run.sh race), in priority order,
# each part under its own time cap so that a call cut short still returns what finished:
#
#   a. gradient throughput at the new settings (--solver-gradient implicit, --checkpoint tick, batch
#      $RACE_BATCH, 2,048): `wbc-jax tune --phases train` (compile + $RACE_STEPS (2) steps: train_info.json,
#      history.csv with each step's time), then at the old settings (--solver-gradient unrolled,
#      batch 1,024) when $RACE_OLD_NEED seconds are left (else the before is results/tuning/train_info.json);
#   b. gradient quality on the same program (phase quality, --quality-directions 0: no other compile),
#      then phase profile (the per-tick parts, implicit against unrolled solver gradients);
#   c. the race at a $RACE_BUDGET s wall budget per method, with its sets also kept at $RACE_SNAPSHOTS s
#      (e.g. RACE_BUDGET=600 RACE_SNAPSHOTS="120 300": the issue's 2, 5 and 10 minutes) (gradient on jax,
#      CMA-ES and random search on --search-backend auto: Warp where installed; the hybrid: the gradient
#      refining CMA-ES's set at half of each budget for the other half, CMA-ES keeping its sets at those
#      halves for it) with the held-out evaluation and race.json / race.png, when $RACE_C_NEED seconds are
#      left (a later call with the same $RACE_RUNS resumes it; the hybrid costs a fourth budget of time).
#
#   bash experiments/campaigns/race_gpu.sh OUT_DIR   # TINY=1: tiny sizes (CPU check); RACE_PARTS="new profile old race"
#
# Writes OUT_DIR/summary.json (experiments/campaigns/race_fold.py: the figures and their provenance) and
# OUT_DIR/race_gpu.tgz (every run folder, less checkpoints' caches). Fold into results/ with
#   python experiments/campaigns/race_fold.py --from <returned OUT_DIR or the tgz> --docs results/tuning/race_h100
set -uo pipefail
OUT_DIR=${1:?usage: race_gpu.sh OUT_DIR}
mkdir -p "$OUT_DIR"
RUNS=${RACE_RUNS:-/tmp/race_runs}
LIMIT=${RACE_LIMIT:-450}
T0=$SECONDS
left() { echo $((LIMIT - (SECONDS - T0))); }
TUNE=(python3 -m wbc_jax.cli tune --quiet)
if [ -n "${TINY:-}" ]; then
  # The whole job at tiny sizes: flags, paths and imports, not figures.
  B=4 STEPS=2 BUDGET=${RACE_BUDGET:-20}
  COMMON=(--horizon 0.3 --push-onset 0.05 --duration-range 0.05 0.1 --eval-horizon 0.3 --population 2 --es-batch 1
          --eval-pushes 2 --push-scale lip --magnitude-range 0.3 1.0)
  HELD=(--grid-magnitudes 20 200 3 --grid-directions 2 --variation-magnitudes 2 --variation-directions 2
        --variations l_hand --grid-onset 0.1 --grid-horizon 0.4 --one-foot-onset 7.5 --one-foot-horizon 7.7
        --sinusoid-s 0.3)
  OLD_B=4
else
  B=${RACE_BATCH:-2048} STEPS=${RACE_STEPS:-2} BUDGET=${RACE_BUDGET:-120}
  COMMON=(--horizon 2 --lr 0.1 --push-scale lip --magnitude-range 0.3 1.0
          --init-gains assets/gains/com_critical_100.json --population 16 --es-batch 60)
  HELD=(--chunk-size 16384)
  OLD_B=1024
fi
cap() {  # seconds for a part: its cap, or what is left less a margin to pack, whichever is smaller
  local want=$1 l; l=$(( $(left) - 25 )); echo $(( want < l ? want : l ))
}
PARTS=" ${RACE_PARTS:-new profile old race} "  # e.g. RACE_PARTS=race: the race alone, in a call of its own
part() {  # name, cap seconds, command...: run under timeout (SIGINT: files already written stay whole)
  local name=$1 secs=$2; shift 2
  if [[ "$PARTS" != *" $name "* ]]; then echo "part $name: not asked for (RACE_PARTS)"; return; fi
  if [ "$secs" -lt 20 ]; then echo "part $name: skipped (${secs}s left)"; return; fi
  local t=$SECONDS
  timeout --signal=INT --kill-after=15 "$secs" "$@"
  echo "part $name: rc=$? $((SECONDS - t))s (cap ${secs}s; 124/130: stopped by the cap)"
}
nvidia-smi -L 2>/dev/null || true
python3 -c "import jax, mujoco; print('jax', jax.__version__, jax.devices(), 'mujoco', mujoco.__version__)"
python3 -c "import warp; print('warp', warp.__version__)" 2>/dev/null || echo "no warp: searches on MJX-JAX"
NEW=(--batch "$B" --quality-pushes "$B" --quality-directions 0 --solver-gradient implicit --checkpoint tick)
# a + b: one compile of the gradient program for training steps and the quality figures.
part new "$(cap ${RACE_NEW_CAP:-330})" "${TUNE[@]}" --out "$RUNS/new" --phases train quality --steps "$STEPS" \
  "${NEW[@]}" "${COMMON[@]}"
part profile "$(cap ${RACE_PROFILE_CAP:-120})" "${TUNE[@]}" --out "$RUNS/new" --phases profile --steps "$STEPS" \
  "${NEW[@]}" "${COMMON[@]}"
if [ "$(left)" -ge "${RACE_OLD_NEED:-330}" ]; then
  part old "$(cap 330)" "${TUNE[@]}" --out "$RUNS/old" --phases train --steps 2 --batch "$OLD_B" \
    --quality-pushes "$OLD_B" --solver-gradient unrolled --checkpoint tick "${COMMON[@]}"
else
  echo "part old: skipped ($(left)s left; the before is results/tuning/train_info.json)"
fi
if [ "$(left)" -ge "${RACE_C_NEED:-600}" ]; then
  read -r -a SNAPSHOTS <<< "${RACE_SNAPSHOTS:-}"  # wall times [s] within the budget: more race budgets
  RACE=(--out "$RUNS/race" --budget-s "$BUDGET" --snapshots-s "${SNAPSHOTS[@]}" --steps 100000 --batch "$B"
        --quality-pushes "$B" --no-wall-budget --search-backend auto "${COMMON[@]}" "${HELD[@]}")
  part race "$(cap 100000)" "${TUNE[@]}" "${RACE[@]}" --phases train cmaes random hybrid heldout report
else
  echo "part race: skipped ($(left)s left; needs ${RACE_C_NEED:-600}s: run it in a call of its own)"
fi
python3 experiments/campaigns/race_fold.py --from "$RUNS" --summary "$OUT_DIR/summary.json"
echo "fold: rc=$?"
tar -czf "$OUT_DIR/race_gpu.tgz" -C "$(dirname "$RUNS")" --exclude='*/heldout/*/*.parquet' "$(basename "$RUNS")"
ls -la "$OUT_DIR"
