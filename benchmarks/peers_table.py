"""TSID and our controller side by side: the tables of results/peers from their two JSON files.

    python benchmarks/peers_table.py --tsid results/peers/tsid.json --wbc results/peers/wbc_jax.json \\
        [--out results/peers/side_by_side.md]

Reads the TSID peer's file (``benchmarks/tsid_peer.py``) and ours (``benchmarks/wbc_peer.py``, one
column per gain set) and prints two Markdown tables: the summary (time per tick on one core, the
20 s sinusoid, the stand, the strict envelope by bisection and the full grid) and the envelope of
each push direction (fraction of the LIP bound), with the controller that holds the larger push.
Figures the files lack print as "—". JAX-free.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _get(d: dict, *keys):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def _fmt(value, spec: str, scale: float = 1.0) -> str:
    return "—" if value is None else format(value * scale, spec)


def _pair(a, b, spec: str, scale: float = 1.0) -> str:
    return "—" if a is None else f"{_fmt(a, spec, scale)} ({_fmt(b, spec, scale)})"


def columns(tsid: dict, wbc: dict) -> dict:
    """{column title: the figures of one controller}, TSID first, then each of our gain sets."""
    cols = {
        "TSID": {
            "controller": _get(tsid, "timing", "controller_cpu_us_per_tick"),
            "physics": _get(tsid, "timing", "physics_cpu_us_per_tick"),
            "rtf": _get(tsid, "timing", "real_time_factor_cpu"),
            "sinusoid": tsid.get("sinusoid", {}),
            "stand": tsid.get("stand", {}),
            "envelope": tsid.get("envelope", {}),
            "grid": tsid.get("grid", {}),
        }
    }
    for name, entry in wbc.get("gain_sets", {}).items():
        cols[f"wbc_jax {name}"] = {
            "controller": _get(entry, "timing", "controller_cpu_us_per_tick"),
            "physics": _get(entry, "timing", "physics_cpu_us_per_tick"),
            "rtf": _get(entry, "timing", "real_time_factor_cpu"),
            "sinusoid": entry.get("sinusoid", {}),
            "stand": entry.get("stand", {}),
            "envelope": entry.get("envelope", {}),
            "grid": entry.get("grid", {}),
        }
    for col in cols.values():
        c, p = col["controller"], col["physics"]
        col["loop"] = None if c is None or p is None else c + p
    return cols


def summary_table(cols: dict) -> str:
    rows = [
        ("controller per 10 ms tick, CPU time (us)", lambda c: _fmt(c["controller"], ".0f")),
        ("physics per tick (10 `mj_step`), CPU time (us)", lambda c: _fmt(c["physics"], ".0f")),
        ("closed loop per tick, CPU time (us)", lambda c: _fmt(c["loop"], ".0f")),
        ("real-time factor of the closed loop, CPU time", lambda c: _fmt(c["rtf"], ".1f")),
        (
            "20 s sinusoid: CoM RMSE (max), mm",
            lambda c: _pair(c["sinusoid"].get("com_rmse_m"), c["sinusoid"].get("com_max_err_m"), ".2f", 1e3),
        ),
        ("10 s stand: CoM drift, mm", lambda c: _fmt(c["stand"].get("com_drift_m"), ".3f", 1e3)),
        (
            "strict envelope / LIP bound, median (min), bisection",
            lambda c: _pair(
                c["envelope"].get("fraction_of_bound_median"), c["envelope"].get("fraction_of_bound_min"), ".3f"
            ),
        ),
        ("64 x 32 grid: strict survival", lambda c: _fmt(c["grid"].get("survival_rate"), ".1%")),
        (
            "64 x 32 grid: monotone envelope / LIP bound, median (min)",
            lambda c: _pair(
                c["grid"].get("monotone_fraction_of_bound_median"),
                c["grid"].get("monotone_fraction_of_bound_min"),
                ".3f",
            ),
        ),
    ]
    lines = ["| figure | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
    lines += [f"| {title} | " + " | ".join(fn(c) for c in cols.values()) + " |" for title, fn in rows]
    return "\n".join(lines)


def direction_table(cols: dict) -> str:
    """Per azimuth: each controller's strict envelope (bisection) as a fraction of the LIP bound, the
    controller that holds the largest push, and TSID against our first gain set (the defaults)."""
    names = list(cols)
    ours = names[1] if len(names) > 1 else None
    azimuths = sorted({float(a) for c in cols.values() for a in c["envelope"].get("directions", {})})
    pair = f" TSID vs {ours} |" if ours else ""
    lines = [
        "| azimuth (deg) | " + " | ".join(names) + " | largest |" + pair,
        "|---:|" + "---:|" * len(names) + "---|" + ("---|" if ours else ""),
    ]
    for az in azimuths:
        values = [_get(c["envelope"], "directions", f"{az:g}", "fraction_of_bound") for c in cols.values()]
        known = [(v, n) for v, n in zip(values, names, strict=True) if v is not None]
        best = max(known)[1] if known else "—"
        row = f"| {az:g} | " + " | ".join(_fmt(v, ".3f") for v in values) + f" | {best} |"
        if ours:
            t, w = values[0], values[1]
            row += (
                " — |"
                if t is None or w is None
                else f" {'tie' if abs(t - w) < 1e-9 else ('TSID' if t > w else ours)} |"
            )
        lines.append(row)
    return "\n".join(lines)


def main(argv=None) -> str:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tsid", default=str(ROOT / "results" / "peers" / "tsid.json"))
    p.add_argument("--wbc", default=str(ROOT / "results" / "peers" / "wbc_jax.json"))
    p.add_argument("--out", default=None, help="also write the tables to this Markdown file")
    args = p.parse_args(argv)
    docs = []
    for name in ("tsid", "wbc"):
        path = pathlib.Path(getattr(args, name))
        if not path.is_file():
            raise SystemExit(f"error: --{name}: no such file {path}")
        try:
            docs.append(json.loads(path.read_text()))
        except json.JSONDecodeError as err:
            raise SystemExit(f"error: --{name}: {path} is not JSON ({err})") from None
    cols = columns(*docs)
    text = (
        f"Measured by `{docs[0].get('command', '?')}` ({docs[0].get('date', '?')}) and "
        f"`{docs[1].get('command', '?')}` ({docs[1].get('date', '?')}).\n\n"
        f"{summary_table(cols)}\n\nStrict envelope by direction (fraction of the LIP bound, bisection):\n\n"
        f"{direction_table(cols)}\n"
    )
    if args.out:
        pathlib.Path(args.out).write_text(text)
    sys.stdout.write(text)
    return text


if __name__ == "__main__":
    main()
