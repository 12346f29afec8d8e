#!/usr/bin/env bash
# Gradient tuning + CMA-ES and random search at equal simulated steps + held-out pushes, on the
# 2-core CPU at small sizes (`wbc-jax tune`; the GPU sizes: experiments/campaigns/tune_gpu.sh). Writes
# tuned_gains.json, history.csv, {cmaes,random}/history.csv, learning.png, eval.json into
# ${1:-runs/tune_cpu}. XLA's backend optimisation is lowered: the gradient program compiles in
# minutes instead of many (the values are the same; the programs run slower).
set -euo pipefail
cd "$(dirname "$0")/../.."
export JAX_PLATFORMS=cpu
export XLA_FLAGS="--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
wbc-jax tune --out "${1:-runs/tune_cpu}" --steps 4 --batch 4 --horizon 2.0 --population 3 --es-batch 1 \
  --eval-pushes 8 --seed 0 --lr 0.1 "${@:2}"
