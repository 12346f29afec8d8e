#!/usr/bin/env bash
# One call on the GPU machine (see README): install the carried wheels without touching the
# machine's jax, then run the jobs named as arguments. Results are packed into
# $OUT/results.tar.gz (the device tool returns at most 8 files).
set -uo pipefail
python3 -m pip install -q --no-deps .wheels/*.whl 2>&1 | grep -v WARNING
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_FLAGS=--xla_gpu_triton_gemm_any=true
nvidia-smi -L
python3 -c "import jax; print(jax.__version__, jax.devices())"
R=/tmp/results; mkdir -p $R
sweep() {  # name, extra args
  local name=$1; shift
  python3 -m wbc_jax.cli push-sweep --out /tmp/sweeps/$name --quiet "$@" | tee $R/$name.json
  mkdir -p $R/$name && cp /tmp/sweeps/$name/{summary.json,survival.png,envelope.png,results.parquet} $R/$name/
}
for job in "$@"; do
  case "$job" in
    sweep)  # the acceptance sweep: 64 magnitudes x 32 directions x 8 gain sets, 3 s
      sweep main --magnitudes 10 400 64 --directions 32 --gain-sets 8 --horizon 3 --chunk-size 16384 ;;
    variants)  # same 32 x 16 grid for each controller variant
      for v in "qp stable" "analytic stable" "qp seed"; do
        set -- $v
        sweep "grid-$1-$2" --magnitudes 10 320 32 --directions 16 --horizon 3 --chunk-size 512 \
          --forces $1 --postural $2
      done ;;
    bench)
      python3 experiments/benchmark.py --out $R/bench --batches 1024 16384 65536 --horizon 1.0 \
        --iterations 4 ;;
    bench-iters)
      python3 experiments/benchmark.py --out $R/bench_iters --batches 16384 --horizon 1.0 \
        --iterations 2 1 ;;
    baseline)
      python3 experiments/benchmark.py --out $R/bench_cpu --batches 1 --horizon 1.0 \
        --iterations 4 --cpu-baseline-envs 256 ;;
  esac
done
tar -czf $OUT/results.tar.gz -C $R .
