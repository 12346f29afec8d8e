#!/usr/bin/env bash
# The README's main job (`wbc-jax push-sweep`, 12 environments, C MuJoCo) with each driver of the C MuJoCo engine,
# each from a fresh compilation cache (first run: the native step's build, tracing and compiling included) and again
# with that cache (second run), alternating; one JSON line per run, with the sweep's device, versions and provenance
# (its command and input files). Usage: bash benchmarks/host_loop_drivers.sh OUT.jsonl [REPEATS]
# WBC_JAX: the command that runs the CLI (default wbc-jax, the installed entry point; a checkout that is not
# installed, as on the device machines: WBC_JAX='python3 -m wbc_jax.cli').
set -euo pipefail
out=$1; reps=${2:-2}
: > "$out"
for rep in $(seq 1 "$reps"); do
  for driver in python compiled; do
    cache=$(mktemp -d)
    for run in first second; do
      dir=$(mktemp -d)/sweep
      start=$(date +%s.%N)
      WBC_JAX_CACHE=$cache ${WBC_JAX:-wbc-jax} push-sweep --host-loop "$driver" --out "$dir" --quiet > /dev/null
      end=$(date +%s.%N)
      python3 - "$driver" "$rep" "$run" "$start" "$end" "$dir" >> "$out" <<'PY'
import json, sys
driver, rep, run, start, end, folder = sys.argv[1:]
s = json.load(open(f"{folder}/summary.json"))
print(json.dumps({"driver": driver, "repeat": int(rep), "run": run, "command_wall_s": round(float(end) - float(start), 1),
                  "compile_s": s["compile_s"], "run_s": s["run_s"], "survival": s.get("survival_rate"),
                  "device": s["device"], "versions": s["versions"], "provenance": s["provenance"]}))
PY
    done
  done
done
cat "$out"
