#!/usr/bin/env bash
# One call on the GPU machine (see README): install the carried wheels without touching the
# machine's jax, then run the jobs named as arguments. After each job the results so far are
# packed into $OUT/results.tar.gz and the log is in $OUT/log.txt, so a call that runs past its
# time limit still returns what finished.
set -uo pipefail
exec > >(tee -a $OUT/log.txt) 2>&1
python3 -m pip install -q --no-deps .wheels/*.whl 2>&1 | grep -v WARNING
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 XLA_FLAGS=--xla_gpu_triton_gemm_any=true
nvidia-smi -L
python3 -c "import jax; print(jax.__version__, jax.devices())"
R=/tmp/results; mkdir -p $R
pack() { tar -czf $OUT/results.tar.gz -C $R . ; }
sweep() {  # name, extra args
  local name=$1; shift
  SECONDS=0
  python3 -m wbc_jax.cli push-sweep --out /tmp/sweeps/$name --quiet "$@" | tee $R/$name.json
  echo "job $name: ${SECONDS}s"
  mkdir -p $R/$name && cp /tmp/sweeps/$name/{summary.json,survival.png,envelope.png,results.parquet} $R/$name/
  pack
}
for job in "$@"; do
  case "$job" in
    sweep)  # the acceptance sweep: 64 magnitudes x 32 directions x 8 gain sets, 3 s
      sweep main --magnitudes 10 400 64 --directions 32 --gain-sets 8 --horizon 3 --chunk-size 16384 ;;
    variants)  # same 32 x 16 grid (512 envs, one chunk) for each controller variant
      for v in "qp stable" "analytic stable" "qp seed"; do
        set -- $v
        sweep "grid-$1-$2" --magnitudes 10 320 32 --directions 16 --horizon 3 --chunk-size 512 \
          --forces $1 --postural $2
      done ;;
    islands)  # are the survival islands of the acceptance sweep numerical artefacts? The default-gain
              # grid (64 magnitudes x 32 directions) with the sweep's settings, with 8 solver
              # iterations, and in float64
      sweep islands-it4 --magnitudes 10 400 64 --directions 32 --horizon 3 --chunk-size 2048
      sweep islands-it8 --magnitudes 10 400 64 --directions 32 --horizon 3 --chunk-size 2048 --solver-iterations 8
      export JAX_ENABLE_X64=1
      sweep islands-f64 --magnitudes 10 400 64 --directions 32 --horizon 3 --chunk-size 2048
      unset JAX_ENABLE_X64 ;;
    one-foot)  # the same grid, pushed while balancing on the left foot (one-foot task, 7-9 s)
      sweep grid-one-foot --task one-foot --push-onset 7.5 --horizon 9 \
        --magnitudes 10 320 32 --directions 16 --chunk-size 512 ;;
    bench)  # trajectory check, GPU closed loop over batch sizes, then the CPU baseline on 1,
            # 4 and all 16 cores (scaling)
      python3 experiments/benchmark.py --out $R/bench --batches 1 1024 16384 65536 --horizon 0.5 \
        --iterations 4 --cpu-baseline-envs 64 --cpu-workers 1 4 16; pack ;;
    bench-large)  # the largest batch that fits: 262,144 and 1,048,576 environments, then doublings
                  # until one fails (0.05 s horizon: memory, not the horizon, decides what fits)
      python3 experiments/benchmark.py --out $R/bench_large --batches 262144 1048576 --horizon 0.05 \
        --push-onset 0.0 --push-duration 0.02 --iterations 4 --find-largest 1 --skip-physics-only --skip-equivalence; pack ;;
    bench-iters)  # fewer Newton iterations at batch 65,536, each against the CPU baseline with the
                  # same iteration count on all 16 cores (balance figures: experiments/solver_iterations.py)
      python3 experiments/benchmark.py --out $R/bench_iters --batches 65536 --horizon 0.5 \
        --iterations 2 1 --skip-physics-only --skip-equivalence --cpu-baseline-envs 64 --cpu-workers 16; pack ;;
    balance-iters)  # the controller issue's balance figures with 2 and 1 Newton iterations (one env each)
      for it in 2 1; do
        python3 experiments/balance_acceptance.py --only stand sinusoid push-qp --solver-iterations $it \
          --out /tmp/acceptance --summary $R/balance_iterations.json; pack
      done ;;
    multi-gpu)  # the same closed loop on one GPU, then sharded over all local GPUs (a Mesh over the
                # batch axis, wbc_jax.sweep.device_mesh), in one call: the scaling over GPUs
      for devs in 0 all; do
        if [ $devs = all ]; then unset CUDA_VISIBLE_DEVICES; else export CUDA_VISIBLE_DEVICES=$devs; fi
        python3 experiments/benchmark.py --out $R/mgpu_$devs --batches 131072 --horizon 0.35 \
          --iterations 4 --skip-physics-only --skip-equivalence; pack
      done
      unset CUDA_VISIBLE_DEVICES ;;
  esac
done
pack
