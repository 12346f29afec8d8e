"""Where a compiled program's time goes, op by op and source line by source line (issue 46).

    summary = trace_summary.summarize(trace_dir, compiled.as_text(), calls=3, batch=B)

A JAX profiler trace (``jax.profiler.trace(dir, create_perfetto_trace=True)``) holds one event per executed HLO
op (a GPU kernel, or a CPU thunk) with its ``hlo_op`` and ``hlo_module``; the compiled program's HLO text holds each
op's stack frames (file, function, line). Summed per op and attributed to the innermost frame of its call stack,
the trace says which source file and function the device spent its time in. Device events are the GPU's where the
trace has them, else the host CPU's; an event's time is its own (nested events, a CPU while loop's body, are counted
once, in the innermost). On a GPU, ``device_idle`` adds where the device waited between its kernels within a call
(a while loop's predicate read by the host, a library's host work, launch gaps), beside the ops' own time.
"""

from __future__ import annotations

import collections
import functools
import gzip
import json
import pathlib
import re

_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*\S+.*?\s([\w\-]+)\(")
_FRAME_ID = re.compile(r"stack_frame_id=(\d+)")
_TABLE_ROW = re.compile(r"^(\d+)\s+(.*)$")


def hlo_sources(hlo_text: str) -> tuple[str, dict[str, dict]]:
    """(module name, {instruction name: {"opcode", "file", "function", "line"}}) from a compiled HLO text with its
    stack-frame tables (FileNames, FunctionNames, FileLocations, StackFrames); the frame is the op's innermost."""
    lines = hlo_text.splitlines()
    module = lines[0].split()[1].rstrip(",") if lines and lines[0].startswith("HloModule") else ""
    tables: dict[str, dict[int, str]] = {}
    current = None
    for line in lines:
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            current = tables.setdefault(line, {})
            continue
        row = _TABLE_ROW.match(line) if current is not None else None
        if row:
            current[int(row.group(1))] = row.group(2).strip()
        elif current is not None and not line.strip():
            current = None
    files = {k: v.strip('"') for k, v in tables.get("FileNames", {}).items()}
    functions = {k: v.strip('"') for k, v in tables.get("FunctionNames", {}).items()}
    locations = {k: dict(re.findall(r"(\w+)=(\d+)", v)) for k, v in tables.get("FileLocations", {}).items()}
    frames = {k: dict(re.findall(r"(\w+)=(\d+)", v)) for k, v in tables.get("StackFrames", {}).items()}

    def frame_source(frame_id: int) -> dict:
        loc = locations.get(int(frames.get(frame_id, {}).get("file_location_id", 0)), {})
        return {
            "file": files.get(int(loc.get("file_name_id", 0)), "?"),
            "function": functions.get(int(loc.get("function_name_id", 0)), "?"),
            "line": int(loc.get("line", 0)),
        }

    ops = {}
    for line in lines:
        m = _INSTRUCTION.match(line)
        if not m:
            continue
        frame = _FRAME_ID.search(line)
        source = frame_source(int(frame.group(1))) if frame else {"file": "?", "function": "?", "line": 0}
        ops[m.group(1)] = {"opcode": m.group(2), **source}
    return module, ops


def _events(trace_dir: str | pathlib.Path) -> tuple[list[dict], dict[int, str]]:
    """(the trace's events, {pid: process name}) of the newest perfetto trace under ``trace_dir`` (or that file: a
    trace kept apart, gpu_run.sh keep_trace)."""
    where = pathlib.Path(trace_dir)
    paths = [where] if where.is_file() else sorted(where.rglob("*perfetto_trace.json.gz"))
    if not paths:
        raise FileNotFoundError(
            f"no perfetto_trace.json.gz under {trace_dir} (jax.profiler.trace(..., create_perfetto_trace=True))"
        )
    stat = paths[-1].stat()
    return _load(str(paths[-1]), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=2)
def _load(path: str, mtime_ns: int, size: int) -> tuple[list[dict], dict[int, str]]:
    """One trace file parsed once for the summaries that read it (keyed by its path, time and size)."""
    with gzip.open(path) as f:
        data = json.load(f)
    events = data["traceEvents"] if isinstance(data, dict) else data
    names = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    return events, names


def same_module(traced: str, module: str) -> bool:
    """Whether a trace event's ``hlo_module`` names ``module``: the same name, or it with a suffix of XLA's
    (``jit_tick.1``, ``jit_tick(3)``): runtimes differ in how they name a module's executions."""
    return traced == module or (traced.startswith(module) and traced[len(module) : len(module) + 1] in (".", "("))


def modules_in(trace_dir: str | pathlib.Path) -> list[str]:
    """The ``hlo_module`` names of the trace's events that carry an ``hlo_op`` (what a failed match found)."""
    events, _ = _events(trace_dir)
    return sorted({str((e.get("args") or {}).get("hlo_module")) for e in events if "hlo_op" in (e.get("args") or {})})


def op_times(trace_dir: str | pathlib.Path, module: str) -> tuple[str, dict[str, float]]:
    """(timeline, {hlo_op: self time in µs summed over the trace}) of ``module``'s ops: the GPU's events where the
    trace has a GPU timeline, else the host CPU's."""
    events, names = _events(trace_dir)
    gpu = {pid for pid, name in names.items() if name.startswith("/device:GPU")}
    timeline = "gpu" if gpu else "cpu"
    keep = gpu or {pid for pid, name in names.items() if name.startswith("/host:CPU")}
    by_thread = collections.defaultdict(list)
    for e in events:
        args = e.get("args") or {}
        if (
            e.get("ph") == "X"
            and e.get("pid") in keep
            and "hlo_op" in args
            and same_module(args.get("hlo_module", module), module)
        ):
            by_thread[(e["pid"], e.get("tid"))].append((float(e["ts"]), float(e["dur"]), args["hlo_op"]))
    totals: dict[str, float] = collections.defaultdict(float)
    for spans in by_thread.values():
        spans.sort(key=lambda s: (s[0], -s[1]))
        stack: list[list] = []  # [end, op, own time]
        for ts, dur, op in spans:
            # An op nests in the open one only where it ends inside it (a CPU while thunk and its body's thunks);
            # one that starts before the open op's end but ends after it follows it: on a GPU stream the kernels
            # run one after another, and their clock's rounding overlaps neighbours by a fraction of a µs
            # (the kept trace in results/gpu_h100/s58/machine_a/u14/profile_tick_cbuf).
            while stack and (stack[-1][0] <= ts or ts + dur > stack[-1][0]):
                end, name, own = stack.pop()
                totals[name] += own
            if stack:
                stack[-1][2] -= dur  # the parent's own time excludes its nested ops
            stack.append([ts + dur, op, dur])
        for _, name, own in stack:
            totals[name] += own
    return timeline, dict(totals)


def device_idle(trace_dir: str | pathlib.Path, calls: int, label=lambda op: op, top: int = 10) -> dict | None:
    """Where the GPU waits within each call (None without a GPU timeline): every GPU event (kernels, copies, with
    or without an HLO op) merged into busy intervals, split into ``calls`` calls where the program's first op runs
    again (else at the ``calls - 1`` longest pauses), and per call its span, busy and idle µs; the idle time summed per
    pair (the op that ends before a pause, the op that starts after it; ``label`` names an op), and the device
    events that carry no HLO op (a library's copies, say) per name."""
    events, names = _events(trace_dir)
    gpu = {pid for pid, name in names.items() if name.startswith("/device:GPU")}
    spans = sorted(
        (float(e["ts"]), float(e["ts"]) + float(e["dur"]), (e.get("args") or {}).get("hlo_op"), e.get("name", "?"))
        for e in events
        if e.get("ph") == "X" and e.get("pid") in gpu and float(e.get("dur", 0)) > 0
    )
    if not spans:
        return None
    merged: list[list] = []  # [start, end, the first op, the last op, the first event's raw op]
    for start, end, op, name in spans:
        tag = label(op) if op else f"(no op) {name}"
        if merged and start <= merged[-1][1]:
            if end > merged[-1][1]:
                merged[-1][1], merged[-1][3] = end, tag
        else:
            merged.append([start, end, tag, tag, op])
    # A call starts where the program's first op runs again, if that op runs once a call; else (an op in a loop)
    # at the calls - 1 longest pauses (a GPU can wait longer inside a call than between two).
    starts = [i for i, seg in enumerate(merged) if seg[4] is not None and seg[4] == merged[0][4]]
    if len(starts) == calls:
        cuts = [i - 1 for i in starts[1:]]
    else:
        pauses = [(merged[i + 1][0] - merged[i][1], i) for i in range(len(merged) - 1)]
        cuts = sorted(i for _, i in sorted(pauses, reverse=True)[: max(calls - 1, 0)])
    groups, first = [], 0
    for i in cuts + [len(merged) - 1]:
        groups.append(merged[first : i + 1])
        first = i + 1
    by_pair: dict[str, float] = collections.defaultdict(float)
    span = busy = 0.0
    for g in groups:
        span += g[-1][1] - g[0][0]
        busy += sum(seg[1] - seg[0] for seg in g)
        for a, b in zip(g, g[1:]):
            by_pair[f"{a[3]} -> {b[2]}"] += b[0] - a[1]
    unattributed: dict[str, float] = collections.defaultdict(float)
    for start, end, op, name in spans:
        if not op:
            unattributed[name] += end - start
    n = max(len(groups), 1)
    return {
        "calls_found": len(groups),
        "span_us_per_call": round(span / n, 1),
        "busy_us_per_call": round(busy / n, 1),
        "idle_us_per_call": round((span - busy) / n, 1),
        "idle_share": round((span - busy) / span, 4) if span > 0 else 0.0,
        "pauses_per_call": round(sum(len(g) - 1 for g in groups) / n, 1),
        "largest_idle": [
            {"between": k, "us_per_call": round(v / n, 2)} for k, v in sorted(by_pair.items(), key=lambda kv: -kv[1])
        ][:top],
        "events_without_op": [
            {"name": k, "us_per_call": round(v / n, 2)} for k, v in sorted(unattributed.items(), key=lambda kv: -kv[1])
        ][:top],
    }


def summarize(trace_dir, hlo_text: str, *, calls: int, batch: int, top: int = 25) -> dict:
    """µs per environment and call, per source file, per function (``top``) and per opcode, and the ``top`` ops,
    of the program whose compiled HLO text is ``hlo_text``, traced ``calls`` times at ``batch`` environments."""
    module, ops = hlo_sources(hlo_text)
    timeline, times = op_times(trace_dir, module)
    if not times:
        found = modules_in(trace_dir)
        raise ValueError(
            f"the trace under {trace_dir} has no op of module {module!r}; its events with an hlo_op name the modules "
            f"{found[:8]}"
        )
    scale = 1.0 / (calls * batch)

    def ranked(key) -> list[dict]:
        groups: dict[str, float] = collections.defaultdict(float)
        for op, us in times.items():
            groups[key(ops.get(op, {"opcode": "?", "file": "?", "function": "?", "line": 0}))] += us
        total = sum(groups.values())
        return [
            {"name": name, "us_per_env": round(us * scale, 5), "share": round(us / total, 4)}
            for name, us in sorted(groups.items(), key=lambda kv: -kv[1])
        ]

    def short(path: str) -> str:
        for anchor in ("wbc_jax/", "mujoco/", "jax/"):
            if anchor in path:
                return anchor + path.split(anchor, 1)[1]
        return path

    return {
        "timeline": timeline,
        "module": module,
        "calls": calls,
        "total_us_per_env": round(sum(times.values()) * scale, 5),
        "ops_traced": len(times),
        "ops_without_source": sum(1 for op in times if op not in ops),
        "by_file": ranked(lambda o: short(o["file"])),
        "by_function": ranked(lambda o: f"{short(o['file'])}:{o['function']}")[:top],
        "by_opcode": ranked(lambda o: o["opcode"]),
        "top_ops": ranked(lambda o: op_label(o, "?", short))[:top],
        "device_idle": device_idle(trace_dir, calls, label=lambda op: op_label(ops.get(op), op, short)),
    }


def op_label(source: dict | None, op: str, short=lambda path: path) -> str:
    """``opcode file:function:line`` of an op with a source, else its HLO name."""
    if not source:
        return op
    return f"{source['opcode']} {short(source['file'])}:{source['function']}:{source['line']}"


def by_scope(trace_dir: str | pathlib.Path, module: str, calls: int, batch: int, depth: int = 1) -> dict:
    """A kept trace summed without the program's HLO text: ``module``'s GPU events a call, and µs per environment
    and call of its ops per the JAX scope that named them (the events' ``name``: ``jit(tick)/vmap(torque_law)/...`` -> ``vmap(torque_law)``;
    ``depth`` scopes below the program's: 3 gives ``vmap(torque_law)/jit(_cho_solve)/triangular_solve``, the
    library call by the function that made it; fusions that XLA named itself are ``(fusion)``), their total, and
    ``device_idle``."""
    events, names = _events(trace_dir)
    gpu = {pid for pid, name in names.items() if name.startswith("/device:GPU")}
    _, times = op_times(trace_dir, module)
    scope_of: dict[str, str] = {}
    for e in events:
        args = e.get("args") or {}
        if e.get("pid") in gpu and "hlo_op" in args and args["hlo_op"] not in scope_of:
            parts = str(args.get("name", "")).split("/")
            inner = "/".join(parts[1 : 1 + depth])
            scope_of[args["hlo_op"]] = inner if len(parts) > 2 else ("(fusion)" if "name" not in args else parts[0])
    scale = 1.0 / (calls * batch)
    scopes: dict[str, float] = collections.defaultdict(float)
    for op, t in times.items():
        scopes[scope_of.get(op, "(fusion)")] += t * scale
    kernels = sum(
        1
        for e in events
        if e.get("ph") == "X"
        and e.get("pid") in gpu
        and same_module(str((e.get("args") or {}).get("hlo_module")), module)
    )
    return {
        "total_us_per_env": round(sum(times.values()) * scale, 5),
        "kernels_per_call": round(kernels / calls, 1),
        "by_scope": {k: round(v, 5) for k, v in sorted(scopes.items(), key=lambda kv: -kv[1])},
        "device_idle": device_idle(trace_dir, calls),
    }


def by_kernel(trace_dir: str | pathlib.Path, module: str, calls: int, batch: int, top: int = 40) -> dict:
    """``module``'s GPU events summed per kernel (the event's own name: a Warp kernel, a cuBLAS or cuSOLVER routine,
    an XLA fusion, a copy), µs per environment and call with launches per call, the ``top`` largest; and the device's
    busy time, the union of all its events (copies on a copy engine overlap the kernels: the sum over-counts them)."""
    events, names = _events(trace_dir)
    gpu = {pid for pid, name in names.items() if name.startswith("/device:GPU")}
    times: dict[str, float] = collections.defaultdict(float)
    launches: collections.Counter = collections.Counter()
    for e in events:
        args = e.get("args") or {}
        if e.get("ph") == "X" and e.get("pid") in gpu and same_module(str(args.get("hlo_module")), module):
            times[e.get("name", "?")] += float(e["dur"])
            launches[e.get("name", "?")] += 1
    scale = 1.0 / (calls * batch)
    idle = device_idle(trace_dir, calls)
    return {
        "sum_us_per_env": round(sum(times.values()) * scale, 5),
        "busy_us_per_env": round(idle["busy_us_per_call"] * calls * scale, 5) if idle else None,
        "kernels": [
            {"name": k[:120], "us_per_env": round(v * scale, 5), "launches": round(launches[k] / calls, 1)}
            for k, v in sorted(times.items(), key=lambda kv: -kv[1])[:top]
        ],
    }


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="A kept perfetto trace summed per JAX scope (by_scope).")
    parser.add_argument("trace", help="a folder holding a *perfetto_trace.json.gz, or the file itself")
    parser.add_argument("--module", default="jit_tick")
    parser.add_argument("--calls", type=int, default=3, help="calls of the program in the trace")
    parser.add_argument("--batch", type=int, default=65536, help="environments of a call")
    parser.add_argument("--depth", type=int, default=1, help="scopes below the program's in each key (3: the op)")
    a = parser.parse_args()
    if a.depth < 1:
        parser.error(f"--depth must be a whole number >= 1, got {a.depth}")
    summary = by_scope(a.trace, a.module, a.calls, a.batch, a.depth)
    if summary["device_idle"]:
        summary["device_idle"] = {k: v for k, v in summary["device_idle"].items() if not isinstance(v, list)}
    print(json.dumps(summary, indent=1))
