"""Where a compiled program's time goes, op by op and source line by source line (issue 46).

    summary = trace_summary.summarize(trace_dir, compiled.as_text(), calls=3, batch=B)

A JAX profiler trace (``jax.profiler.trace(dir, create_perfetto_trace=True)``) holds one event per executed HLO
op (a GPU kernel, or a CPU thunk) with its ``hlo_op`` and ``hlo_module``; the compiled program's HLO text holds each
op's stack frames (file, function, line). Summed per op and attributed to the innermost frame of its call stack,
the trace says which source file and function the device spent its time in. Device events are the GPU's where the
trace has them, else the host CPU's; an event's time is its own (nested events, a CPU while loop's body, are counted
once, in the innermost).
"""

from __future__ import annotations

import collections
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


def op_times(trace_dir: str | pathlib.Path, module: str) -> tuple[str, dict[str, float]]:
    """(timeline, {hlo_op: self time in µs summed over the trace}) of ``module``'s ops: the GPU's events where the
    trace has a GPU timeline, else the host CPU's."""
    paths = sorted(pathlib.Path(trace_dir).rglob("*perfetto_trace.json.gz"))
    if not paths:
        raise FileNotFoundError(
            f"no perfetto_trace.json.gz under {trace_dir} (jax.profiler.trace(..., create_perfetto_trace=True))"
        )
    with gzip.open(paths[-1]) as f:
        data = json.load(f)
    events = data["traceEvents"] if isinstance(data, dict) else data
    names = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
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
            and args.get("hlo_module", module) == module
        ):
            by_thread[(e["pid"], e.get("tid"))].append((float(e["ts"]), float(e["dur"]), args["hlo_op"]))
    totals: dict[str, float] = collections.defaultdict(float)
    for spans in by_thread.values():
        spans.sort(key=lambda s: (s[0], -s[1]))
        stack: list[list] = []  # [end, op, own time]
        for ts, dur, op in spans:
            while stack and stack[-1][0] <= ts:
                end, name, own = stack.pop()
                totals[name] += own
            if stack:
                stack[-1][2] -= dur  # the parent's own time excludes its nested ops
            stack.append([ts + dur, op, dur])
        for _, name, own in stack:
            totals[name] += own
    return timeline, dict(totals)


def summarize(trace_dir, hlo_text: str, *, calls: int, batch: int, top: int = 25) -> dict:
    """µs per environment and call, per source file, per function (``top``) and per opcode, and the ``top`` ops,
    of the program whose compiled HLO text is ``hlo_text``, traced ``calls`` times at ``batch`` environments."""
    module, ops = hlo_sources(hlo_text)
    timeline, times = op_times(trace_dir, module)
    if not times:
        raise ValueError(f"the trace under {trace_dir} has no op of module {module!r}")
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
        "top_ops": ranked(lambda o: f"{o['opcode']} {short(o['file'])}:{o['function']}:{o['line']}")[:top],
    }
