"""The multi-host path with two processes on one machine (issue: several GPUs / hosts).

    python experiments/multihost_check.py --out runs/multihost [--devices-per-process 2]

Runs the same small push sweep (MJX 'jax' backend on CPU devices) three ways: one process with
2 x D devices, and two processes of D devices each, joined by ``jax.distributed.initialize()``
(coordinator on localhost, Gloo collectives), so that the batch is sharded over the global
mesh of all four devices. The results tables must be identical. On several hosts the same
commands run with the coordinator's address and each host's ``--process-id``; see the README.
Writes multihost.json into --out.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent

SWEEP = ["push-sweep", "--magnitudes", "20", "300", "4", "--directions", "2", "--horizon", "0.6",
         "--push-onset", "0.1", "--chunk-size", "8", "--backend", "jax", "--quiet"]  # fmt: skip

WORKER = """
import os, sys
import jax
jax.config.update("jax_cpu_collectives_implementation", "gloo")
n, pid, port = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
if n > 1:
    jax.distributed.initialize(coordinator_address=f"localhost:{port}", num_processes=n, process_id=pid)
from wbc_jax import cli
sys.exit(cli.main(sys.argv[4:]))
"""


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="runs/multihost")
    p.add_argument("--devices-per-process", type=int, default=2)
    p.add_argument("--port", default="12356")
    args = p.parse_args(argv)
    out = pathlib.Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    D = args.devices_per_process

    def env(devices: int) -> dict:
        return {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": f"--xla_force_host_platform_device_count={devices}",
                "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}  # fmt: skip

    single = subprocess.run([sys.executable, "-c", WORKER, "1", "0", args.port, *SWEEP, "--out", str(out / "single")],
                            env=env(2 * D), capture_output=True, text=True, timeout=3000)  # fmt: skip
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, "2", str(i), args.port, *SWEEP, "--out", str(out / "two")],
                              env=env(D), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]  # fmt: skip
    outs = [proc.communicate(timeout=3000) for proc in procs]
    import pandas as pd

    ok = single.returncode == 0 and all(proc.returncode == 0 for proc in procs)
    result = {"single_process_rc": single.returncode, "two_process_rc": [proc.returncode for proc in procs]}
    if ok:
        a = pd.read_parquet(out / "single" / "results.parquet")
        b = pd.read_parquet(out / "two" / "results.parquet")
        s_single = json.loads(single.stdout.strip().splitlines()[-1])
        s_two = json.loads(outs[0][0].strip().splitlines()[-1])
        result.update({
            "identical_results": bool(a.equals(b)), "envs": int(len(a)),
            "devices": {"single_process": s_single["n_devices"], "two_processes": s_two["n_devices"]},
        })  # fmt: skip
    else:
        result["stderr"] = [single.stderr[-2000:], *[o[1][-2000:] for o in outs]]
    result["command"] = "python experiments/multihost_check.py " + " ".join(sys.argv[1:] if argv is None else argv)
    (out / "multihost.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result), flush=True)
    return result


if __name__ == "__main__":
    main()
