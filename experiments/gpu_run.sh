#!/usr/bin/env bash
# One call on a GPU machine (docs/usage.md, "On a GPU machine"): install the carried wheels next to the
# machine's own jax (never replacing it), then run the jobs named as arguments. Results go to
# $OUT (one folder per job, log.txt), so a call that runs past its limit still returns what finished.
#
#   bash experiments/gpu_run.sh setup check bench sweep agree envelope regrid queue soak race limit limit_root
#
# Carried folders (git-ignored, built by experiments/gpu_wheels.sh; collected in ~/wp while the machine is held):
# .wa/ holds site_small.tar.xz (the Python 3.12 wheels of mujoco 3.17.0 without its filament renderer, mujoco-mjx,
# trimesh, quadprog, evosax, dotmap, unpacked; carry it in every call to a fresh machine), .wb/ .wc/ .wd/ wpart_00..02:
# the three thirds of an xz tar of the warp-lang 1.18.0 wheel's contents (the extra of mujoco-mjx) without its CPU
# compiler, examples and tests (27 MB each: one a call, beside the working tree and a race's state in .ws/). All
# unpack into /tmp/site, beside the machine's own jax (never replacing it).
set -uo pipefail
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
exec > >(tee -a "$OUT/log.txt") 2>&1
SITE=/tmp/site; mkdir -p "$SITE" ~/wp
export PYTHONPATH=$SITE:$PWD PYTHONUNBUFFERED=1 TF_CPP_MIN_LOG_LEVEL=3 WBC_JAX_CACHE=/tmp/xla-cache
for d in .wa .wb .wc .wd .wr .wt1 .wt2 .wt3; do [ -d $d ] && cp $d/* ~/wp/; done
if [ ! -d $SITE/mujoco ] && [ -f ~/wp/site_small.tar.xz ]; then
  xz -dc ~/wp/site_small.tar.xz | tar xf - -C $SITE && echo "wheels unpacked"
fi
if [ ! -d $SITE/warp ] && [ -f ~/wp/wpart_00 ] && [ -f ~/wp/wpart_01 ] && [ -f ~/wp/wpart_02 ]; then
  cat ~/wp/wpart_00 ~/wp/wpart_01 ~/wp/wpart_02 | xz -dc | tar xf - -C $SITE && echo "warp-lang unpacked"
fi
if [ ! -d $SITE/rerun ] && [ -f ~/wp/viz.tar.xz ]; then
  xz -dc ~/wp/viz.tar.xz | tar xf - -C $SITE && echo "rerun and the notebook runner unpacked"
fi
echo "carried so far: $(ls ~/wp | tr '\n' ' ')"; [ -d $SITE/warp ] || echo "no warp yet (needs wpart_00..02)"
run() {  # name, command...: time a job, keep its output
  local name=$1; shift
  mkdir -p "$OUT/$name"; SECONDS=0
  "$@" 2>&1 | tail -c 20000 > "$OUT/$name/stdout.txt"; local rc=${PIPESTATUS[0]}
  echo "job $name: rc=$rc ${SECONDS}s"; tail -n 3 "$OUT/$name/stdout.txt"
}
keep_trace() {  # job: the last traced tick's perfetto trace beside the job's results (a few MB; for a viewer)
  local f; f=$(ls -t /tmp/traces/$1/tick_*/plugins/profile/*/*perfetto_trace.json.gz 2>/dev/null | head -1)
  [ -n "$f" ] && cp "$f" "$OUT/$1/trace_$(basename "$(dirname "$(dirname "$(dirname "$(dirname "$f")")")")").json.gz"
}
profile46() {  # job, flags...: profile_tick at 65,536 envs on the loop's states, traced; the last traced tick kept
  local job=$1; shift
  run $job python3 benchmarks/profile_tick.py --batch 65536 --states loop --out "$OUT/$job" --trace /tmp/traces/$job "$@"
  keep_trace $job
}
bench46_run() {  # job, flags...: the Warp closed loop at 65,536 envs beside the physics alone and C MuJoCo + NumPy
  local job=$1; shift  # on 16 cores (benchmark.py), its rows in $OUT/job/benchmarks.json
  run $job python3 benchmarks/benchmark.py --out "$OUT/$job" --json "$OUT/$job/benchmarks.json" --backends warp \
    --batches 65536 --horizon 0.5 --cpu-baseline-envs 64 --cpu-workers 16 --repeats 2 --skip-equivalence "$@"
}
SW="python3 -m wbc_jax.cli push-sweep --quiet --horizon 3 --push-onset 0.5 --push-duration 0.1 --magnitudes 10 400 64 --directions 32"
for job in "$@"; do
  case "$job" in
    cpu_peer)  # issue 46 on this host's own CPU (an Intel Xeon on these machines; the CI machine is an AMD EPYC):
            # our compiled loop's tick (benchmarks/cpu_loop.py --parts profile) and TSID's (benchmarks/tsid_peer.py)
            # on core 1, alternating, CPU_PEER_RUNS times each. Needs TSID's Python 3.12 wheels, carried in .wt1/
            # (cmeel-boost without its headers, cmeel-assimp, cmeel-zlib), .wt3/ (icub-models, eigenpy) and .wt2/ (tsid,
            # pin, coal, eiquadprog, their other cmeel libraries, and libtsid's files as libtsid-1.10.0.tar.xz: the
            # package index here has no libtsid wheel), 24 MB each, one a call; installed apart in /tmp/site-tsid.
      export JAX_PLATFORMS=cpu  # our loop on this host's CPU even where the job's caller left the GPU visible
      TS=/tmp/site-tsid
      if [ ! -d $TS/cmeel.prefix ]; then
        python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target $TS ~/wp/*.whl \
          && xz -dc ~/wp/libtsid-*.tar.xz | tar xf - -C $TS
      fi
      # The iCub's URDF for Pinocchio (.wt3/): icub_models finds its share/ five folders above its module, as a
      # --prefix install lays it out (under --target its data files are dropped).
      IC=/tmp/icub-prefix
      [ -d $IC/share/iCub ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
        --ignore-installed --prefix $IC ~/wp/icub_models-*.whl
      mkdir -p "$OUT/cpu_peer"; lscpu | grep -E "Model name|^CPU\(s\)|MHz" > "$OUT/cpu_peer/cpu.txt"; uptime >> "$OUT/cpu_peer/cpu.txt"
      for i in $(seq 1 ${CPU_PEER_RUNS:-3}); do
        run cpu_peer_wbc_$i taskset -c 1 python3 benchmarks/cpu_loop.py --parts profile --out "$OUT/cpu_peer/wbc_$i.json"
        # CPU_PEER_QP_ENGINE=eiquadprog (s60): also our loop with that force QP engine (its library from .wa's site)
        [ -n "${CPU_PEER_QP_ENGINE:-}" ] && run cpu_peer_wbc_qp_$i taskset -c 1 python3 benchmarks/cpu_loop.py \
          --parts profile --qp-engine $CPU_PEER_QP_ENGINE --out "$OUT/cpu_peer/wbc_${CPU_PEER_QP_ENGINE}_$i.json"
        # CPU_PEER_ISA=AVX2: also our loop with XLA's code capped at that ISA (AVX-512 may lower an Intel core's clock;
        # on the AMD EPYC the cap changed nothing beyond noise, 2026-11-26), its own compilation cache
        [ -n "${CPU_PEER_ISA:-}" ] && run cpu_peer_wbc_isa_$i env XLA_FLAGS=--xla_cpu_max_isa=$CPU_PEER_ISA \
          WBC_JAX_CACHE=/tmp/xla-cache-isa taskset -c 1 python3 benchmarks/cpu_loop.py --parts profile \
          --out "$OUT/cpu_peer/wbc_isa_${CPU_PEER_ISA}_$i.json"
        PYTHONPATH=$IC/lib/python3.12/site-packages:$TS/cmeel.prefix/lib/python3.12/site-packages:$TS:$PYTHONPATH run cpu_peer_tsid_$i \
          python3 benchmarks/tsid_peer.py --cpu 1 --no-envelope --out "$OUT/cpu_peer/tsid_$i.json"
      done ;;
    cpu_loop_qp)  # issue 46 (s60) on this host's Intel Xeon: our compiled loop's tick with the JAX QP and with
            # eiquadprog (--qp-engine eiquadprog, its library from .wa's site), alternating CPU_PEER_RUNS times on
            # core 1, no TSID wheels needed (TSID's Xeon figures: results/cpu_targets/xeon_s55); JAX_PLATFORMS=cpu
      mkdir -p "$OUT/cpu_loop_qp"; lscpu | grep -E "Model name|^CPU\(s\)" > "$OUT/cpu_loop_qp/cpu.txt"
      for i in $(seq 1 ${CPU_PEER_RUNS:-3}); do
        for e in jax eiquadprog; do
          run cpu_loop_${e}_$i taskset -c 1 python3 benchmarks/cpu_loop.py --parts profile --qp-engine $e \
            --out "$OUT/cpu_loop_qp/${e}_$i.json"
        done
      done ;;
    cpu_stages)  # issue 46 on this host's Intel Xeon, stage by stage: where our controller's tick goes there (on the
            # AMD EPYC it costs 0.81x TSID's, on this Xeon about 1.3x against each run's own physics:
            # results/cpu_targets/xeon_s55); run with JAX_PLATFORMS=cpu. About 210 s (its compiles) on the loaded AMD:
            # a limit of 150 s on the Xeon stopped every run before it printed (2026-11-27), allow 400
      mkdir -p "$OUT/cpu_stages"; lscpu | grep -E "Model name|^CPU\(s\)|Flags" > "$OUT/cpu_stages/cpu.txt"
      # CPU_STAGES_QP_ENGINE=eiquadprog (s60): also the stages with that force QP engine, interleaved
      run cpu_stages taskset -c 1 python3 benchmarks/controller_stages.py --ticks 300 --repeats 5 \
        ${CPU_STAGES_QP_ENGINE:+--qp-engine $CPU_STAGES_QP_ENGINE} --out "$OUT/cpu_stages/controller_stages.json" ;;
    cpu_profile)  # issue 46 on this host's Intel Xeon, op by op: profile_tick at batch 1 on core 1 (the CPU loop's
            # case) with --trace, so profile_tick.json says per source function where the tick's time goes, beside
            # the same run on the AMD EPYC (results/cpu_targets/profile_s56/); run with JAX_PLATFORMS=cpu (175 s on
            # the AMD). At batch 1 the profiler's own cost per op inflates the traced sum (about 2.5x the tick's
            # wall time there): compare the shares between the CPUs, not the sums with the tick
      mkdir -p "$OUT/cpu_profile"; lscpu | grep -E "Model name|^CPU\(s\)" > "$OUT/cpu_profile/cpu.txt"
      run cpu_profile taskset -c 1 python3 benchmarks/profile_tick.py --batch 1 --loop-envs 8 --repeats 20 \
        --trace /tmp/traces/cpu_profile --out "$OUT/cpu_profile" ;;
    cpu_drivers)  # the C MuJoCo engine's two drivers on this host's 16 cores (the 2-core AMD EPYC: the compiled batch
            # program 35 s against 73-83 s for the Python loop on the README main job, BENCHMARKS.md): whether the
            # Python loop's threaded physics wins a batch on many cores. Run with JAX_PLATFORMS=cpu; about 5 minutes
      mkdir -p "$OUT/cpu_drivers"; lscpu | grep -E "Model name|^CPU\(s\)" > "$OUT/cpu_drivers/cpu.txt"
      # the checkout is not installed here: the CLI as a module (s60: `wbc-jax: command not found`)
      run cpu_drivers env WBC_JAX="python3 -m wbc_jax.cli" bash benchmarks/host_loop_drivers.sh \
        "$OUT/cpu_drivers/readme_job.jsonl" 2 ;;
    setup)  # what is there
      nvidia-smi -L; python3 -c "import jax, mujoco; print(jax.__version__, mujoco.__version__, jax.devices())"
      python3 -c "import warp; print('warp', warp.__version__)" 2>&1 | tail -1 ;;
    check)  # same trajectory on warp, jax (GPU, float32) and C MuJoCo (host, float32)
      run check python3 experiments/checks/backend_check.py --backends warp jax mujoco --out "$OUT/check" ;;
    bench)  # closed loop and physics only, warp and jax, against C MuJoCo + NumPy on all 16 cores
      run bench python3 benchmarks/benchmark.py --out "$OUT/bench" --json "$OUT/bench/benchmarks.json" \
        --backends warp jax --batches 16384 65536 --horizon 0.5 --cpu-baseline-envs 64 --cpu-workers 16 \
        --repeats 2 --skip-equivalence ;;
    sweep)  # the 64 x 32 x 8 sweep of results/sweep_h100 on warp, twice in one process (first-run costs)
      run sweep python3 benchmarks/sweep_timing.py --out "$OUT/sweep" --repeats 2 -- \
        --magnitudes 10 400 64 --directions 32 --gain-sets 8 --horizon 3 --chunk-size 16384 --backend warp ;;
    agree)  # default-gain grid (2,048 envs) on warp and on jax: outcomes outside the transition band
      mkdir -p "$OUT/agree"
      for b in ${AGREE_BACKENDS:-warp jax}; do
        run agree_$b $SW --chunk-size 2048 --backend $b --out /tmp/sw/agree_$b
        cp /tmp/sw/agree_$b/summary.json "$OUT/agree/agree_$b.summary.json"
        cp /tmp/sw/agree_$b/survival.png "$OUT/agree/survival_$b.png"
      done
      if [ -f /tmp/sw/agree_jax/summary.json ] && [ -f /tmp/sw/agree_warp/summary.json ]; then
        run agree python3 experiments/checks/island_check.py /tmp/sw/agree_jax /tmp/sw/agree_warp --out "$OUT/agree/islands.json"
      fi ;;
    envelope)  # bisection envelope (32 directions, 8 rounds) against the grid of 'agree', per backend
      for b in ${ENVELOPE_BACKENDS:-warp}; do
        run envelope_$b python3 experiments/checks/envelope_check.py --grid /tmp/sw/agree_$b --out "$OUT/envelope_$b" -- \
          --backend $b
      done ;;
    ab_sweep)  # issue 46 (s62), defaults that the push-sweep CLI does not expose (warp_terms, mass_solve_engine,
            # ritz_engine): the default-gain grid on Warp three times with this checkout and twice with another
            # commit's package carried in AB_SWEEP_DIR (default .wnew: its wbc_jax/, assets linked from here), each
            # compared cell by cell with the first grid (island_check), as was_sweep
      nd=${AB_SWEEP_DIR:-.wnew}; ln -sfn "$PWD/assets" "$nd/assets"; mkdir -p "$OUT/$job"
      for r in cold1 cold2 cold3 new1 new2; do
        case $r in cold*) pp=$SITE:$PWD ;; *) pp=$SITE:$PWD/$nd ;; esac
        run ${job}_$r env PYTHONPATH=$pp $SW --chunk-size 2048 --backend warp --out /tmp/sw/${job}_$r
        cp /tmp/sw/${job}_$r/summary.json "$OUT/$job/$r.summary.json"
      done
      run $job python3 experiments/checks/island_check.py /tmp/sw/${job}_cold1 /tmp/sw/${job}_cold2 \
        /tmp/sw/${job}_cold3 /tmp/sw/${job}_new1 /tmp/sw/${job}_new2 --out "$OUT/$job/islands.json" ;;
    warm_sweep|wqp_sweep|was_sweep)  # issue 46, a setting of the force QP as the default: the default-gain grid
            # (2,048 envs, 3 s) on Warp three times as now (the engine's run-to-run floor) and twice with the setting,
            # each compared cell by cell with the first grid (island_check: differing cells, their distance from its
            # transition band). warm_sweep: --qp-warm-start; wqp_sweep: --qp-engine warp (the QP's interior point as
            # one Warp kernel, s58); was_sweep: --qp-engine warp_active_set (the dual active-set kernel, s60)
      case $job in
        warm_sweep) v=warm f="--qp-warm-start" ;;
        wqp_sweep) v=wqp f="--qp-engine warp" ;;
        was_sweep) v=was f="--qp-engine warp_active_set" ;;
      esac
      mkdir -p "$OUT/$job"
      for r in cold1 cold2 cold3 ${v}1 ${v}2; do
        case $r in cold*) g="" ;; *) g=$f ;; esac
        run ${job}_$r $SW --chunk-size 2048 --backend warp $g --out /tmp/sw/${job}_$r
        cp /tmp/sw/${job}_$r/summary.json "$OUT/$job/$r.summary.json"
      done
      run $job python3 experiments/checks/island_check.py /tmp/sw/${job}_cold1 /tmp/sw/${job}_cold2 \
        /tmp/sw/${job}_cold3 /tmp/sw/${job}_${v}1 /tmp/sw/${job}_${v}2 --out "$OUT/$job/islands.json" ;;
    regrid)  # the grids of 'agree' run again (the engine's run-to-run floor) and kept with their tables
      for b in ${ENVELOPE_BACKENDS:-warp}; do
        run regrid_$b $SW --chunk-size 2048 --backend $b --out /tmp/sw/agree_${b}_2
        run regrid_${b}_islands python3 experiments/checks/island_check.py /tmp/sw/agree_$b /tmp/sw/agree_${b}_2 \
          --out "$OUT/regrid_$b/islands.json"
        for g in agree_$b agree_${b}_2; do
          mkdir -p "$OUT/grids/$g"; cp /tmp/sw/$g/summary.json /tmp/sw/$g/results.parquet "$OUT/grids/$g/"
        done
      done ;;
    queue)  # the 64 x 32 x 8 sweep on warp: plain, with 2 and 4 scenarios per batch slot (fallen robots retired),
            # and plain at chunk 8192
      for q in ${QUEUES:-1 2 4}; do
        run queue_$q python3 benchmarks/sweep_timing.py --out "$OUT/queue_$q" --repeats 2 -- --magnitudes 10 400 64 \
          --directions 32 --gain-sets 8 --horizon 3 --chunk-size 16384 --backend ${QUEUE_BACKEND:-warp} --queue $q
      done
      # the control: the plain sweep compiled at another chunk size (float32 rounding alone)
      run queue_1c python3 benchmarks/sweep_timing.py --out "$OUT/queue_1c" --repeats 1 -- --magnitudes 10 400 64 \
        --directions 32 --gain-sets 8 --horizon 3 --chunk-size 8192 --backend ${QUEUE_BACKEND:-warp}
      run queue_check python3 experiments/checks/queue_check.py "$OUT/queue_1" "$OUT/queue_1c" \
        $(for q in ${QUEUES:-1 2 4}; do [ $q != 1 ] && echo "$OUT/queue_$q"; done) --out "$OUT/queue_check.json" ;;
    scaling_jax|scaling_warp)  # issue 33: the 64 x 32 x 8 sweep on 1 and 2 GPUs, each twice (repeat floor)
      b=${job#scaling_}
      run $job python3 benchmarks/scaling.py --out "$OUT/$job" --gpus 1 2 --backends $b -- \
        --magnitudes 10 400 64 --directions 32 --gain-sets 8 --horizon 3 --chunk-size 16384 --push-onset 0.5 \
        --push-duration 0.1 ;;
    scaling4_jax|scaling4_warp)  # issue 45: 32,768 envs on 1, 2 and 4 GPUs, 3 runs each (repeat floor), under a
            # watchdog (a device stalled 240 s in a chunk: one line naming it, the row's error). SCALING_GPUS: the GPU
            # counts of this call (one GPU's runs stay in /tmp/scaling4 on a warm machine for a later call's comparison).
            # SCALING_GAIN_SETS=32: 65,536 envs (one chunk; /tmp/scaling4_65536, $OUT/${job}_65536); 64: 131,072 (a
            # chunk stalls after 600 s: one GPU of JAX runs it in about 260). CUDA_VISIBLE_DEVICES: the GPUs it uses
            # (calls on disjoint GPUs run at once, their rows merged in one --out); SCALING_REPEATS: runs of each.
      b=${job#scaling4_}; gs=${SCALING_GAIN_SETS:-16}; envs=$((2048 * gs))
      sd=/tmp/scaling4; od=$OUT/$job; [ "$envs" != 32768 ] && { sd=/tmp/scaling4_$envs; od=$OUT/${job}_$envs; }
      run $job python3 benchmarks/scaling.py --out $sd --gpus ${SCALING_GPUS:-1 2 4} --backends $b \
        --repeats ${SCALING_REPEATS:-3} --timeout $((gs > 32 ? 1560 : gs > 16 ? 900 : 560)) -- --magnitudes 10 400 64 \
        --directions 32 --gain-sets $gs --horizon 3 --chunk-size $envs --push-onset 0.5 --push-duration 0.1 \
        --stall-timeout-s $((gs > 32 ? 600 : 240))
      mkdir -p "$od"; cp $sd/scaling.json "$od/"
      find $sd/runs -name timeline.json | tar -czf "$od/timelines.tgz" -T - ;;
    profile_tick)  # issue 46: each stage of the controller tick jitted and vmapped alone at 65,536 envs (no Warp needed),
            # on the benchmark loop's own states (256 pushes, ticks before/in/after the push), then on the synthetic ones
      # --trace: the whole tick's kernels per source file and function, in profile_tick.json (the raw traces stay here)
      profile46 profile_tick
      run profile_tick_synthetic python3 benchmarks/profile_tick.py --batch 65536 --states synthetic \
        --out "$OUT/profile_tick_synthetic" ;;
    bench46)  # issue 46: the Warp closed loop at 65,536 envs beside the physics alone and C MuJoCo + NumPy on 16 cores
      bench46_run bench46 ;;
    bench46_warm)  # issue 46: the same with the force QP warm-started (--qp-warm-start): under vmap the QP's while
            # loop runs the batch's slowest problem's Newton steps (14 after the push against 7.9 in the mean on the
            # CPU, results/cpu_targets/pt46), which a warm start cuts (to 10 at tol 5e-7, results/cpu_targets/qpmax46);
            # run right after bench46 on the same machine
      bench46_run bench46_warm --qp-warm-start ;;
    profile_tick_unrolled|bench46_unrolled)  # issue 46 (s57): the force QP's first QP_UNROLLED_STEPS (default 6)
            # Newton steps written out before its while loop (--qp-unrolled-steps; the same solutions). On the H100 at
            # the loop's precision the tick's traced kernels summed 0.31-0.37 µs per env against 0.58-0.81 timed, and
            # the gap grew by 1.2 ms a tick per Newton step of the batch's slowest QP (results/gpu_h100/s57): each pass
            # of a while loop waits for its predicate on the host. profile_tick's trace now says where the GPU waits
            # (device_idle); QP_WARM=1 adds --qp-warm-start. Run beside profile_tick / bench46 on the same machine
      u="--qp-unrolled-steps ${QP_UNROLLED_STEPS:-6}${QP_WARM:+ --qp-warm-start}"
      case $job in profile_tick_unrolled) profile46 $job $u ;; bench46_unrolled) bench46_run $job $u ;; esac ;;
    profile_tick_wqp|bench46_wqp)  # issue 46 (s58): the force QP's interior point as one Warp kernel, one thread per
            # problem (--qp-engine warp, wbc_jax/control/qp_warp.py), where XLA ran 20 library kernels a Newton step
            # (batched LU, triangular solves, top_k) on the H100. Run beside profile_tick / bench46 on the same machine
      case $job in
        profile_tick_wqp) profile46 $job --qp-engine warp ;;
        bench46_wqp) bench46_run $job --qp-engine warp ;;
      esac ;;
    profile_tick_was|bench46_was)  # issue 46 (s60): the force QP by the dual active-set method as one Warp kernel
            # (--qp-engine warp_active_set, wbc_jax/control/qp_active_set_kernel.py): at most n rows active, so a few
            # rank-k solves where the interior point factorises an (n + n) Newton matrix over all 38 rows per step
      case $job in
        profile_tick_was) profile46 $job --qp-engine warp_active_set ;;
        bench46_was) bench46_run $job --qp-engine warp_active_set ;;
      esac ;;
    loop_trace46)  # issue 46 (s61): the Warp closed loop at 65,536 envs traced, kernels summed per JAX scope per tick
            # (benchmarks/loop_trace.py): the active-set QP with the terms off step1 and without, so the split's own
            # cost shows (it saved 0.049 of the terms' 0.21 µs per environment and tick); the traces stay on the machine.
            # LOOP_TRACE_VARIANTS picks them (default "was_split was"; was_split_msw: with the Warp M solve too, s62;
            # was_split_msw_ritz: and the Warp Ritz decomposition)
      for v in ${LOOP_TRACE_VARIANTS:-was_split was}; do
        f="--qp-engine warp_active_set"
        case $v in was_split) f="$f --warp-terms step1" ;; was_split_msw) f="$f --warp-terms step1 --mass-solve-engine warp" ;;
          was_split_msw_ritz) f="$f --warp-terms step1 --mass-solve-engine warp --ritz-engine warp" ;; esac
        run loop_trace46_$v python3 benchmarks/loop_trace.py --batch 65536 --backend warp $f --out /tmp/loop_trace/$v \
          --depth ${LOOP_TRACE_DEPTH:-3}
        mkdir -p "$OUT/loop_trace46"; cp /tmp/loop_trace/$v/loop_trace.json "$OUT/loop_trace46/$v.json"
        # LOOP_TRACE_KEEP=1 (s62): the trace itself too (trace_summary.py by_scope at any depth, off the machine)
        [ -n "${LOOP_TRACE_KEEP:-}" ] && cp "$(ls -t /tmp/loop_trace/$v/trace/plugins/profile/*/*perfetto_trace.json.gz | head -1)" \
          "$OUT/loop_trace46/$v.trace.json.gz"
      done ;;
    projector_cost)  # issue 46 (s62): the stable postural projector's parts (Householder QR or Gram-Schmidt basis, the
            # small and the whole eigh, the certified Ritz projector), 65,536 environments (benchmarks/projector_cost.py)
      run $job python3 benchmarks/projector_cost.py --batch 65536 --repeats 5 --out "$OUT/$job/projector_cost.json" ;;
    mass_solve_cost)  # issue 46 (s61): the torque law's M solve by JAX (batched potrf + trsm) and by one Warp tile kernel
            # (wbc_jax/control/cholesky_warp.py), 65,536 environments, µs per environment and their agreement
      run $job python3 benchmarks/mass_solve_cost.py --batch 65536 --repeats 5 --out "$OUT/$job/mass_solve_cost.json" ;;
    bench46_msw|bench46_was_split_msw|profile_tick_msw)  # issue 46 (s61): bench46 with the M solve as one Warp tile
            # kernel (--mass-solve-engine warp); _was_split: with the active-set QP and the terms off step1 too. Run
            # beside bench46 / bench46_was_split on the same machine. profile_tick_msw: the tick's stages and trace with
            # the tile kernel and the active-set QP (against profile_tick_was)
      case $job in
        profile_tick_msw) profile46 $job --qp-engine warp_active_set --mass-solve-engine warp ;;
        bench46_msw) bench46_run $job --mass-solve-engine warp ;;
        bench46_was_split_msw) bench46_run $job --warp-terms step1 --qp-engine warp_active_set --mass-solve-engine warp ;;
      esac ;;
    bench46_ritz)  # issue 46 (s62): bench46_was_split_msw with the postural projector's Ritz decomposition as one Warp
            # kernel too (--ritz-engine warp, wbc_jax/control/ritz_warp.py: the QR's forming of Q and the small eigh
            # cost 0.061 µs per environment and tick in the loop trace). Run beside bench46_was_split_msw on one machine
      bench46_run $job --warp-terms step1 --qp-engine warp_active_set --mass-solve-engine warp --ritz-engine warp ;;
    bench46_split|bench46_was_split)  # issue 46 (s60): the controller's dynamics terms read off MuJoCo Warp's step1
            # (--warp-terms step1, wbc_jax/sim/warp_split.py) instead of MJX-JAX's 0.21 µs per env a tick; _was_split
            # with the active-set QP too. Run beside bench46 / bench46_was on the same machine
      case $job in
        bench46_split) bench46_run $job --warp-terms step1 ;;
        bench46_was_split) bench46_run $job --warp-terms step1 --qp-engine warp_active_set ;;
      esac ;;
    gpu_tests_qp|gpu_tests_warp)  # the Warp engines' tests on the GPU: gpu_tests_qp the force QP's `gpu` tests
            # (s60); gpu_tests_warp every test of the QP engines and of the split step (tests/test_warp_split.py)
      files="tests/test_qp_warp.py tests/test_qp_active_set.py tests/test_cholesky_warp.py tests/test_ritz_warp.py"
      case $job in gpu_tests_qp) sel="-m gpu" ;; gpu_tests_warp) sel=""; files="$files tests/test_warp_split.py" ;; esac
      run $job env JAX_PLATFORMS=cuda,cpu python3 -m pytest -q -p no:cacheprovider -o addopts="" $sel $files ;;
    profile_tick_cbuf|bench46_cbuf)  # issue 46 (s57): profile_tick / bench46 with XLA's command buffers taking while
            # loops and conditionals too (CUDA graph conditional nodes: the predicate stays on the GPU), CBUF_TYPES
            # (default below). The tick has one QP while loop and four batch_any conds on its path, and at 65,536
            # envs the H100 waited about 1.5-1.8 ms a tick per such pause (results/gpu_h100/s57); QP_UNROLLED_STEPS adds
            # --qp-unrolled-steps. Run beside profile_tick / bench46 on the same machine
      u="${QP_UNROLLED_STEPS:+--qp-unrolled-steps $QP_UNROLLED_STEPS}"
      x="--xla_gpu_enable_command_buffer=${CBUF_TYPES:-FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL}"
      case $job in
        profile_tick_cbuf) XLA_FLAGS="$x" profile46 $job $u ;;
        bench46_cbuf) XLA_FLAGS="$x" bench46_run $job $u ;;
      esac
      echo "$x" > "$OUT/$job/xla_flags.txt" ;;
    warp_terms_cost)  # issue 46 (s58): what the controller's dynamics terms would cost from MuJoCo Warp before building
            # it: MJX-JAX's dynamics.terms against one MJX-Warp forward and one step at 65,536 envs (µs per env)
      run $job python3 benchmarks/warp_terms_cost.py --batch 65536 --out "$OUT/$job/warp_terms_cost.json" ;;
    profile_tick_warm)  # issue 46 (qpmax46): profile_tick at 65,536 envs with the force QP warm-started at its own
            # float32 tolerance (qp.WARM_START_TOL_FLOAT32, 5e-7; one-foot's acceptance within 0.03 %): the batch's
            # slowest QP's Newton steps and the force stage's µs before, in and after the push, beside profile_tick's
      profile46 profile_tick_warm --qp-warm-start ;;
    tune_gpus)  # issue 45: the tune job's gradient step and a CMA-ES generation at the race's settings on 1 GPU and on
            # all of them (loss, gradient, their difference, step seconds, speed-up). A call cut off by its limit
            # leaves the compiled programs in $WBC_JAX_CACHE: the same call on the warm machine goes on from them.
      run tune_gpus env XLA_FLAGS="${TUNE_GPUS_XLA_FLAGS---xla_gpu_autotune_level=0}" timeout ${TUNE_GPUS_WALL:-560} \
        python3 experiments/checks/tune_gpus_check.py --out "$OUT/tune_gpus" ${TUNE_GPUS_FLAGS:-} ;;
    scaling4_warp_diag)  # issue 45: why 4 GPUs of Warp ran 4x slower than one (BENCHMARKS.md, "Why 4 GPUs of Warp
            # were slower"). The 32,768-env sweep at a 0.7 s horizon, 2 runs each, one scaling.json per variant in
            # $OUT/$job/VARIANT.json (copied as each ends: a call cut short keeps the variants done). DIAG_VARIANTS:
            # base (1 and 4 GPUs, as measured), graphs0 (4 GPUs, Warp's graph cache unbounded), processes (4 GPUs as
            # 4 jax.distributed processes), switch (4 GPUs, thread switch interval DIAG_SWITCH_MS), three (3 GPUs);
            # graphjax (1 and 4 GPUs, XLA captures the step's graphs: --warp-graph-mode jax) when named.
      D="--magnitudes 10 400 64 --directions 32 --gain-sets 16 --horizon 0.7 --chunk-size 32768 --push-onset 0.5
         --push-duration 0.1 --stall-timeout-s 240"
      mkdir -p "$OUT/$job"
      for v in ${DIAG_VARIANTS:-base graphs0 processes switch three}; do
        case $v in
          base) a="--gpus 1 4"; s="" ;;
          graphs0) a="--gpus 4"; s="--warp-graph-cache 0" ;;
          processes) a="--gpus 4 --launch processes"; s="" ;;
          switch) a="--gpus 4 --switch-interval-ms ${DIAG_SWITCH_MS:-0.1}"; s="" ;;
          three) a="--gpus 3"; s="" ;;
          graphjax) a="--gpus 1 4"; s="--warp-graph-mode jax" ;;
          *) echo "scaling4_warp_diag: unknown variant $v (valid: base graphs0 processes switch three graphjax)"
             continue ;;
        esac
        run $job python3 benchmarks/scaling.py --out /tmp/diag/$v $a --backends warp --repeats 2 \
          --timeout 240 -- $D $s
        [ -f /tmp/diag/$v/scaling.json ] && cp /tmp/diag/$v/scaling.json "$OUT/$job/$v.json"
        python3 -c "import json,sys; [print('$v', r['gpus'], r.get('launch'), r.get('run_s_each'), r.get('error', ''),
          {k: v['graphs'] for k, v in (r.get('warp_graphs_last_run') or {}).items()},
          r.get('custom_calls_per_program')) for r in
          json.load(open(sys.argv[1]))['rows']]" /tmp/diag/$v/scaling.json 2>&1 | tail -n 4
      done ;;
    limit|limit_root)  # issue 37: the physical limit of push recovery, 32 directions, pushes of 0.1 s at 0.5 s (limit:
            # chest; limit_root: root_link). Time-capped (LIMIT_TIME s from the job's start: no new round, the round
            # in flight stops at its next judge, its C MuJoCo replays still run) and written into $OUT round by round,
            # so a cut-off call returns the rounds finished; the same command with the same --out resumes.
            # LIMIT_FLAGS: extra flags (later ones win), e.g. a tiny CPU test.
      # The run folder lives in /tmp/limit_<body> (restored from .ws/limit_<body>.tgz, carried from the last call)
      # and comes back packed as $OUT/limit_<body>.tgz (a call returns at most 8 files).
      body=chest; [ "$job" = limit_root ] && body=root_link
      if [ ! -d /tmp/limit_$body ] && [ -f .ws/limit_$body.tgz ]; then tar -xzf .ws/limit_$body.tgz -C /tmp; fi
      run $job env XLA_FLAGS="${LIMIT_XLA_FLAGS---xla_gpu_autotune_level=0}" timeout ${LIMIT_WALL:-510} \
        python3 -m wbc_jax.cli limit --quiet --body $body --directions 32 \
        --gains experiments/gains/tuned_gradient.json --envelopes results/limit/envelopes/*_$body/summary.json \
        --candidates 3 --rounds 3 --iterations 30 --judge-every 5 --es-pairs 8 --window 0.5 --tail 0.2 \
        --time-limit ${LIMIT_TIME:-390} --out /tmp/limit_$body ${LIMIT_FLAGS:-}
      tar -czf "$OUT/limit_$body.tgz" -C /tmp limit_$body ;;
    gputests)  # the tests marked gpu (their log goes to results/ with the device)
      run gputests env JAX_PLATFORMS=cuda,cpu python3 -m pytest -q -n 0 -m gpu -p no:cacheprovider tests ;;
    race)  # issue 35 in about 8 minutes: gradient throughput (new, old settings), gradient quality, the race if
           # time is left; everything in $OUT/race (summary.json, race_gpu.tgz): experiments/campaigns/race_gpu.sh
      run race env XLA_FLAGS="${RACE_XLA_FLAGS---xla_gpu_autotune_level=0}" \
        bash experiments/campaigns/race_gpu.sh "$OUT/race" ;;
    soak)  # hostile scenarios on warp
      run soak python3 experiments/checks/soak.py --envs ${SOAK_ENVS:-1000000} --chunk 65536 --horizon ${SOAK_HORIZON:-0.5} \
        --backend warp --out "$OUT/soak" ;;
  esac
done
