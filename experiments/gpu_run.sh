#!/usr/bin/env bash
# One call on the GPU machine (see README): install the carried wheels without touching the
# machine's jax, then run what the first argument names. Results go to $OUT (small files only).
set -uo pipefail
python3 -m pip install -q --no-deps .wheels/*.whl 2>&1 | grep -v WARNING
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_FLAGS=--xla_gpu_triton_gemm_any=true
nvidia-smi -L
python3 -c "import jax; print(jax.__version__, jax.devices())"
case "$1" in
  sweep)
    python3 -m wbc_jax.cli push-sweep --magnitudes 10 400 64 --directions 32 --gain-sets 8 \
      --horizon 3 --chunk-size 16384 --out /tmp/sweep_main --quiet
    mkdir -p $OUT/sweep_main && cp /tmp/sweep_main/{summary.json,survival.png,envelope.png,results.parquet} $OUT/sweep_main/
    ;;
  bench)
    shift
    python3 experiments/benchmark.py --out $OUT/bench "$@"
    ;;
esac
