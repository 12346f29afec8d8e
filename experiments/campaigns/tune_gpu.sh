#!/usr/bin/env bash
# Issue 20 on the GPU machine, one call: install the carried wheels (.wheels/: mujoco, mujoco-mjx,
# trimesh, evosax, dotmap; the image's jax, flax, optax, pandas, scipy are kept), then run
# experiments/campaigns/tune_gpu.py with the arguments given, under a time limit that leaves the call time to
# pack. Results (with the compilation cache, RUN_DIR/xla_cache) are packed into
# $OUT/tune_gpu.tgz.part-NN and the log is $OUT/log.txt, also when the limit stops the run: every
# phase resumes from what the tarball holds.
#
#   bash experiments/campaigns/tune_gpu.sh [--limit SECONDS] [tune_gpu.py arguments]
#
# To continue in a later call: cat the returned parts into tune_gpu.tgz, unpack it into runs/ here
# and carry runs/tune_gpu (and .wheels) again (64 MiB travel in all: drop runs/tune_gpu/xla_cache if
# it does not fit; that costs only compile time). Set TUNE_XLA_FLAGS to replace the XLA flags below.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
exec > >(tee -a "$OUT/log.txt") 2>&1
LIMIT=540
if [ "${1:-}" = "--limit" ]; then LIMIT=$2; shift 2; fi
if ls .wheels/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-deps --no-compile .wheels/*.whl 2>&1 | grep -v -i warning
fi
# warp-lang (for the held-out sweeps on MJX-Warp), carried in parts as for experiments/gpu_run.sh:
# collected in ~/wp while the machine is held, unpacked into /tmp/site once all four are there.
SITE=/tmp/site; mkdir -p "$SITE" ~/wp
for d in .wa .wb .wc; do [ -d $d ] && cp $d/* ~/wp/; done
if [ ! -d $SITE/warp ] && [ "$(ls ~/wp/wpart_0* 2>/dev/null | wc -l)" -eq 4 ]; then
  cat ~/wp/wpart_0* | xz -d | tar xf - -C $SITE && echo "warp-lang unpacked"
fi
# Compile time dominates a tuning run on the GPU: no autotuning of the many small matrix products
# of the closed loop (the default configurations are used), and no triton gemm rewriting.
FLAGS=${TUNE_XLA_FLAGS-"--xla_gpu_autotune_level=0"}
if ! XLA_FLAGS="$FLAGS" python3 -c "import jax, jax.numpy as jnp; jnp.zeros(2).block_until_ready()" >/dev/null 2>&1; then
  echo "XLA_FLAGS '$FLAGS' refused by this jax: running without them"; FLAGS=""
fi
RUN_DIR=runs/tune_gpu prev=""
for a in "$@"; do if [ "$prev" = "--out" ]; then RUN_DIR=$a; fi; prev=$a; done
# The compilation cache lives in the run folder, so that it travels with the results: a later call
# that carries them back skips XLA's compilation of the same programs (tracing still runs).
export XLA_FLAGS="$FLAGS" PYTHONPATH=$SITE:$PWD PYTHONUNBUFFERED=1 WBC_JAX_CACHE=${WBC_JAX_CACHE:-$RUN_DIR/xla_cache}
nvidia-smi -L || true
python3 -c "import jax, mujoco, evosax; print('jax', jax.__version__, jax.devices(), 'mujoco', mujoco.__version__)"
SECONDS=0
timeout --signal=INT --kill-after=20 "$LIMIT" python3 experiments/campaigns/tune_gpu.py --out "$RUN_DIR" "$@"
rc=$?
echo "tune_gpu.py: exit $rc after ${SECONDS}s (124/130: stopped by the ${LIMIT}s limit; run again to resume)"
# $OUT returns at most 8 files of 16 MiB, 64 MiB in all: the tarball goes back in 15 MiB pieces
# (cat tune_gpu.tgz.part-* > tune_gpu.tgz), without the cache if it would not fit.
du -sh "$RUN_DIR" "$RUN_DIR/xla_cache" 2>/dev/null
tar -czf /tmp/tune_gpu.tgz -C "$(dirname "$RUN_DIR")" "$(basename "$RUN_DIR")"
if [ "$(stat -c %s /tmp/tune_gpu.tgz)" -gt $((56 * 1024 * 1024)) ]; then
  echo "results with the cache exceed 56 MiB: packing them without xla_cache"
  tar -czf /tmp/tune_gpu.tgz --exclude=xla_cache -C "$(dirname "$RUN_DIR")" "$(basename "$RUN_DIR")"
fi
split -b 15M -d /tmp/tune_gpu.tgz "$OUT/tune_gpu.tgz.part-"
ls -la "$OUT"
exit 0
