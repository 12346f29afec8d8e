"""The memory a batch holds against :func:`wbc_jax.sim.runner.memory_estimate`, which every sweep and
envelope checks before allocating a chunk (issue 34: a chunk too large for the machine is refused
with the estimate, not killed by the kernel).

    python experiments/checks/memory_estimate.py --backends mujoco jax --batches 1 8        # a CPU
    python experiments/checks/memory_estimate.py --backends jax warp --batches 1024 16384   # a GPU

Per backend and batch B: C MuJoCo, the resident memory (RSS) added by B stepped MjData (the
engine's per-environment state); MJX, the compiled closed loop's buffers (XLA's memory analysis:
arguments, outputs, temporaries) and on a GPU the device's peak bytes in use; each per environment,
against the estimate's per-environment bytes. Writes memory_estimate.json (with provenance) into
--out.

The check (:func:`failures`): no measurement above the estimate; exit status 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

from wbc_jax.core import checks, io, provenance
from wbc_jax.sim import runner

BAR = "no measured bytes per environment above runner.memory_estimate's"


def _rss() -> int:
    for line in pathlib.Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise OSError("no /proc/self/status")


def host_bytes_per_env(batch: int, steps: int = 50) -> float:
    """RSS added per environment by ``batch`` C MuJoCo MjData of the iCub stepped ``steps`` times."""
    import mujoco

    from wbc_jax.robot import model

    m = model.load_mj_model("icub")
    before = _rss()
    datas = []
    for _ in range(batch):
        d = mujoco.MjData(m)
        d.qpos[:] = m.key("home").qpos
        for _ in range(steps):
            mujoco.mj_step(m, d)
        datas.append(d)
    return (_rss() - before) / batch


def mjx_bytes_per_env(backend: str, batch: int) -> dict:
    """The compiled sweep program's buffers per environment (and the device's peak, on a GPU)."""
    import jax

    from wbc_jax.jobs import sweep, sweep_config
    from wbc_jax.sim import loop as loop_lib
    from wbc_jax.sim import scenario

    cfg = sweep_config.SweepConfig(
        magnitudes=(20.0,),
        directions=tuple(np.linspace(0, 360, batch, endpoint=False)),
        horizon=0.2,
        push_onset=0.05,
        push_duration=0.05,
        backend=backend,
        chunk_size=batch,
        out=None,
    )
    dtype = scenario.float_dtype()
    base = sweep.base_gains(cfg, 23, dtype)
    st = sweep.make_setup(cfg, base)
    scen, _ = sweep.build_scenarios(cfg, base, 23, dtype)
    before = set(loop_lib.PROGRAMS)
    runner.run(st, scen, batch_size=batch)
    (key,) = set(loop_lib.PROGRAMS) - before
    per_device = loop_lib.PROGRAMS[key].compiled.values()  # per_device.PerDevice: one program per device
    compiled = sum(
        ma.temp_size_in_bytes + ma.argument_size_in_bytes + ma.output_size_in_bytes
        for ma in (c.memory_analysis() for c in per_device)
    )
    out = {"compiled_per_env": compiled / batch, "estimate_per_env": runner.memory_estimate(st, batch)["per_env"]}
    stats = jax.devices()[0].memory_stats() if jax.devices()[0].platform != "cpu" else None
    if stats and "peak_bytes_in_use" in stats:
        out["device_peak_per_env"] = stats["peak_bytes_in_use"] / batch
    return out


def failures(result: dict) -> list[str]:
    """One line per measurement above its estimate; none measured is a failure too."""
    if not result.get("rows"):
        return ["nothing was measured"]
    return [
        f"{r['backend']} batch {r['batch']}: measured {r['measured_over_estimate']:g} x the estimate"
        for r in result["rows"]
        if r["measured_over_estimate"] > 1.0
    ]


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0], epilog=f"Check: {BAR}; exit status 1 otherwise.")
    p.add_argument("--backends", nargs="+", default=["mujoco", "jax"], choices=["mujoco", "jax", "warp"])
    p.add_argument("--batches", nargs="+", type=int, default=[1, 8])
    p.add_argument("--out", default="runs/memory_estimate")
    args = p.parse_args(argv)
    rows = []
    for backend in args.backends:
        for batch in args.batches:
            if backend == "mujoco":
                measured = {"rss_per_env": host_bytes_per_env(batch)}
                estimate = runner.HOST_ENV_BYTES
            else:
                measured = mjx_bytes_per_env(backend, batch)
                estimate = measured.pop("estimate_per_env")
            rows.append(
                {
                    "backend": backend,
                    "batch": batch,
                    **{k: round(v) for k, v in measured.items()},
                    "estimate_per_env": round(estimate),
                    "measured_over_estimate": round(max(measured.values()) / estimate, 3),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    result = {
        "rows": rows,
        "mjx_env_factor": runner.MJX_ENV_FACTOR,
        "host_env_bytes": runner.HOST_ENV_BYTES,
        "device": provenance.device_label(),
        "provenance": provenance.record(),
    }
    result["check"] = checks.verdict(failures(result), BAR)
    io.atomic_write_json(pathlib.Path(args.out) / "memory_estimate.json", result)
    return result


if __name__ == "__main__":
    sys.exit(checks.exit_status(main()))
