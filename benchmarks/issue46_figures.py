"""Issue 46's figures against its targets, gathered into results/issue46_targets.json from the runs' own result files
(the issue names its benchmarks.json under docs/, which the repository keeps in results/: one row per measured
setting with its command and device; this file says, row by row and round by round, whether the targets hold).

    python benchmarks/issue46_figures.py [--out results/issue46_targets.json]

- ``gpu``: each closed-loop row of benchmark.py on one H100 (``--batches 65536``, the four settings of one machine),
  with its command and device, the controller's share of the loop (1 - closed loop / physics alone) and whether the
  issue's GPU target holds (>= 6,000,000 steps/s and the controller <= 25 %).
- ``cpu``: per CPU, round by round, our compiled loop's tick and controller's part (benchmarks/cpu_loop.py
  ``--parts profile``) beside TSID's tick and controller (benchmarks/tsid_peer.py) where TSID ran in the same run,
  and whether the CPU target holds there (our tick <= TSID's and our controller <= TSID's); without TSID in the same
  run, ``target_met`` is null (not measured). ``median``: each figure's median over a CPU's rounds beside TSID, and the
  target on those medians.

The inputs' paths and sha256 are in ``provenance.inputs``. The figures are the files' own; nothing is measured here.
"""

import argparse
import json
import pathlib
import statistics

from wbc_jax.core import io, provenance

ROOT = pathlib.Path(__file__).resolve().parents[1]
GPU_TARGET_STEPS = 6_000_000
GPU_TARGET_SHARE = 0.25
GPU_RUNS = {  # folder: the runs of one machine
    "results/gpu_h100/s61/machine_a": ("bench46_was_split", "bench46_was", "bench46_split", "bench46"),
    "results/gpu_h100/s62/machine_a": (
        "bench46_was_split_msw",
        "bench46_was_split",
        "bench46_was_split_msw_r2",
        "bench46_was_split_r2",
    ),
    "results/gpu_h100/s62/machine_c": (
        "bench46_was_split_msw_xfrc",
        "bench46_was_split_msw",
        "bench46_was_split_msw_xfrc_r2",
    ),
    "results/gpu_h100/s63/machine_0": ("bench46_ritz", "bench46_was_split_msw"),
    # new: 7d17fb9 (keep_sound), old: dde4e26, alternating (its README)
    "results/gpu_h100/s63/machine_a": ("new1", "old1", "new2", "new3", "old2"),
    # the command with every engine at its default (0377830: the auto engines on a GPU)
    "results/gpu_h100/s63/machine_c": ("bench46_r1", "bench46_r2"),
}
CPU_RUNS = {  # folder, our engines, TSID beside them (tsid_timing_<round>.json) or not
    "AMD EPYC (2 cores, the CI machine's kind), core 1": ("results/cpu_targets/eq61", ("jax", "eiquadprog"), True),
    "Intel Xeon (a GPU host's 16 cores), core 1": ("results/cpu_targets/xeon_s61", ("jax", "eiquadprog"), False),
    "Intel Xeon (a GPU host's 16 cores), core 1, beside TSID, a GPU sweep on cores 2-15": (
        "results/cpu_targets/xeon_s62",
        ("jax", "eiquadprog"),
        True,
    ),
    "Intel Xeon (a GPU host's 16 cores), core 1, beside TSID, the host idle": (
        "results/cpu_targets/xeon_s62_idle",
        ("jax", "eiquadprog"),
        True,
    ),
    # 0377830, the default engine (auto: eiquadprog), the machine otherwise idle
    "AMD EPYC (2 cores, the CI machine's kind), core 1, s63": ("results/cpu_targets/amd_s63", ("eiquadprog",), True),
}


def gpu_rows(inputs: dict) -> list[dict]:
    rows = []
    for folder, run in ((folder, run) for folder, runs in GPU_RUNS.items() for run in runs):
        path = ROOT / folder / run / "benchmarks.json"
        inputs[f"{folder}/{run}"] = path
        for r in json.loads(path.read_text()):
            share = 1.0 - r["closed_loop_steps_per_s"] / r["physics_only_steps_per_s"]
            rows.append(
                {
                    "setting": {
                        k: r.get(k, "jax") for k in ("qp_engine", "warp_terms", "mass_solve_engine", "ritz_engine")
                    },
                    "device": r["device"],
                    "machine": folder,
                    "run": run,
                    "date": r["date"],
                    "batch": r["batch"],
                    "closed_loop_steps_per_s": round(r["closed_loop_steps_per_s"]),
                    "physics_only_steps_per_s": round(r["physics_only_steps_per_s"]),
                    "controller_share": round(share, 4),
                    "cpu_baseline_steps_per_s": round(r["cpu_baseline_steps_per_s"]),
                    "cpu_baseline_workers": r["cpu_baseline_workers"],
                    "ratio": round(r["ratio"], 2),
                    "target_met": r["closed_loop_steps_per_s"] >= GPU_TARGET_STEPS and share <= GPU_TARGET_SHARE,
                    "command": r["command"],
                }
            )
    return rows


def cpu_rounds(folder: str, engines: tuple[str, ...], with_tsid: bool, inputs: dict) -> list[dict]:
    base = ROOT / folder
    rounds = []
    for i in range(1, 10):
        files = {e: base / f"{e}_{i}.json" for e in engines}
        files = {e: p if p.exists() else base / f"cpu_loop_{e}_{i}.json" for e, p in files.items()}
        if not all(p.exists() for p in files.values()):
            break
        row: dict = {"round": i, "ours": {}}
        for e, p in files.items():
            inputs[f"{folder}/{p.name}"] = p
            loop = json.loads(p.read_text())["profile"]["compiled_loop"]
            row["ours"][e] = {
                "tick_us": loop["per_tick_wall_us"],
                "controller_us": loop["rest_cpu_us"],
                "physics_us": loop["physics_cpu_us"],
            }
        tsid = base / f"tsid_timing_{i}.json"
        if with_tsid and tsid.exists():
            inputs[f"{folder}/{tsid.name}"] = tsid
            t = json.loads(tsid.read_text())["timing"]
            row["tsid"] = {
                "tick_us": round(t["controller_us_per_tick"] + t["physics_us_per_tick"], 1),
                "controller_us": t["controller_us_per_tick"],
                "physics_us": t["physics_us_per_tick"],
            }
            row["target_met"] = {
                e: ours["tick_us"] <= row["tsid"]["tick_us"] and ours["controller_us"] <= row["tsid"]["controller_us"]
                for e, ours in row["ours"].items()
            }
        else:
            row["tsid"] = None
            row["target_met"] = None  # TSID did not run beside it: not measured
        rounds.append(row)
    return rounds


def _with_medians(run: dict) -> dict:
    """``run`` with ``median``: each figure's median over the rounds beside TSID (a core's speed moves between
    rounds on these hosts; the median is the figure one slow round does not decide) and the target on those."""
    rounds = [r for r in run["rounds"] if r["tsid"] is not None]
    if not rounds:
        run["median"] = None
        return run
    med = {
        "ours": {
            e: {k: float(statistics.median(r["ours"][e][k] for r in rounds)) for k in ("tick_us", "controller_us")}
            for e in rounds[0]["ours"]
        },
        "tsid": {k: float(statistics.median(r["tsid"][k] for r in rounds)) for k in ("tick_us", "controller_us")},
        "rounds": len(rounds),
    }
    med["target_met"] = {
        e: o["tick_us"] <= med["tsid"]["tick_us"] and o["controller_us"] <= med["tsid"]["controller_us"]
        for e, o in med["ours"].items()
    }
    run["median"] = med
    return run


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=str(ROOT / "results" / "issue46_targets.json"))
    a = p.parse_args(argv)
    inputs: dict = {}
    result = {
        "issue": 46,
        "gpu_target": {"closed_loop_steps_per_s": GPU_TARGET_STEPS, "controller_share_max": GPU_TARGET_SHARE},
        "gpu": gpu_rows(inputs),
        "cpu": {
            cpu: _with_medians({"folder": folder, "rounds": cpu_rounds(folder, engines, with_tsid, inputs)})
            for cpu, (folder, engines, with_tsid) in CPU_RUNS.items()
        },
    }
    result["provenance"] = provenance.record(inputs, argv=provenance.script_argv(__file__, argv), with_device=False)
    io.atomic_write_json(pathlib.Path(a.out), result)
    print(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
