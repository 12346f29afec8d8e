"""What a result file records of its origin: the command, the device, the package version and the
contents (sha256) of every input file, in one format for every job and script.

    record(inputs={"gains": "experiments/gains/x.json"}) -> {"command": ..., "device": ...,
        "version": ..., "date": ..., "inputs": {"gains": {"path": ..., "sha256": ...}}}

:func:`check_inputs` reads such a record back and names every input of the repository whose file
has changed since, so a figure whose gains file was later overwritten is caught;
:func:`mentioned_files` lists the repository files a result names anywhere (its command, config,
notes), so a gains file named without its sha256 is caught too (tests/test_provenance.py runs both
over every result file in results/). Results recorded before results/ was split from docs/ name
``docs/<path>``: :func:`current_path` reads that as ``results/<path>``, so their records stay as written.
"""

from __future__ import annotations

import datetime
import hashlib
import os
import pathlib
import re
import shlex
import sys
import time

from wbc_jax.core.assets import ASSETS

# The repository's top folder (the package lives in REPO_ROOT / "wbc_jax").
REPO_ROOT = pathlib.Path(__file__).resolve().parents[2]
_IMPORTED = time.time()


def process_started() -> float:
    """When this process started (``time.time()`` seconds): from /proc on Linux (10 ms ticks),
    elsewhere when this module was imported. Jobs report the seconds from it to their first tick."""
    try:
        fields = pathlib.Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        uptime = float(pathlib.Path("/proc/uptime").read_text().split()[0])
        return time.time() - (uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError, AttributeError):
        return _IMPORTED


def sha256(path) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def sha256_bytes(data: bytes) -> str:
    """Hex sha256 of bytes (a file's contents at some commit)."""
    return hashlib.sha256(data).hexdigest()


def display_path(path) -> str:
    """A path as results name it: relative to the repository when inside it, else absolute. The
    package data is ``assets/...`` wherever it is installed (a wheel's copy or the checkout's)."""
    p = pathlib.Path(path).resolve()
    for root, prefix in ((ASSETS.resolve(), "assets/"), (REPO_ROOT, "")):
        try:
            return prefix + p.relative_to(root).as_posix()
        except ValueError:
            pass
    return p.as_posix()


def current_path(relative: str) -> str:
    """Where a recorded repository path lies now: generated results were under docs/ until issue 44
    moved them to results/ (same sub-path); docs/ keeps only the written pages (.md)."""
    head, _, rest = relative.partition("/")
    return f"results/{rest}" if head == "docs" and not rest.endswith(".md") else relative


def _repository_file(base: pathlib.Path, relative: str) -> pathlib.Path:
    """The file of a recorded relative path (:func:`current_path`): ``assets/...`` is the package data
    when ``base`` is this package's repository (an installed wheel has no repository around its data)."""
    relative = current_path(relative)
    head, _, rest = relative.partition("/")
    return ASSETS / rest if head == "assets" and base == REPO_ROOT else base / relative


def command(argv: list[str] | None = None) -> str:
    """The command line that is running, as a user would type it again: ``wbc-jax JOB ...`` for the
    command-line jobs, ``python SCRIPT ...`` for scripts (paths relative to the repository)."""
    argv = list(sys.argv if argv is None else argv)
    if not argv:
        return ""
    prog = pathlib.Path(argv[0])
    if prog.name in ("wbc-jax", "__main__.py") or prog.name.startswith("wbc_jax"):
        head = ["wbc-jax"]
    elif prog.suffix == ".py":
        head = ["python", display_path(prog)]
    else:
        head = [prog.name]
    return shlex.join([*head, *argv[1:]])


def script_argv(script, argv: list[str] | None = None) -> list[str]:
    """The command line of a script's ``main(argv)``: ``sys.argv`` when it runs from the shell
    (argv None), else the script's path and ``argv``; for :func:`command` and :func:`record`."""
    return list(sys.argv) if argv is None else [str(script), *argv]


def cpu_name() -> str:
    """The host CPU's model name."""
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return platform.processor() or platform.machine() or "CPU"


def device() -> dict:
    """The devices JAX computes on: platform, their kind (the GPU's name, or the CPU's model), how
    many (across processes after jax.distributed) and the host's cores."""
    import jax

    devices = jax.devices()
    first = devices[0]
    kind = cpu_name() if first.platform == "cpu" else first.device_kind
    return {
        "platform": first.platform,
        "kind": kind,
        "count": len(devices),
        "processes": jax.process_count(),
        "host_cores": os.cpu_count(),
    }


def device_label(info: dict | None = None) -> str:
    """One line for a device record: 'NVIDIA H100 80GB HBM3 x2 (gpu)', 'AMD EPYC, 2 cores (cpu)'."""
    info = device() if info is None else info
    if info["platform"] == "cpu":
        return f"{info['kind']}, {info['host_cores']} cores (cpu)"
    count = f" x{info['count']}" if info["count"] > 1 else ""
    return f"{info['kind']}{count} ({info['platform']})"


def record(inputs: dict | None = None, *, argv: list[str] | None = None, with_device: bool = True) -> dict:
    """The provenance of a result: command, device, package version, date (UTC) and, for each
    named input file (None: skipped), its path and sha256."""
    from wbc_jax import __version__

    out = {
        "command": command(argv),
        "version": __version__,
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
    }
    if with_device:
        info = device()
        out["device"] = {**info, "label": device_label(info)}
    out["inputs"] = {
        name: {"path": display_path(path), "sha256": sha256(path)}
        for name, path in (inputs or {}).items()
        if path is not None and pathlib.Path(path).is_file()
    }
    return out


def in_repository(path: str) -> bool:
    """Is a recorded path one of the repository's files (relative, not under the ignored runs/)?"""
    p = pathlib.PurePosixPath(path)
    return not p.is_absolute() and p.parts[:1] != ("runs",)


def check_inputs(result: dict, base: pathlib.Path = REPO_ROOT) -> list[str]:
    """The inputs of a recorded result (its ``provenance.inputs``) that the repository holds and
    whose files now differ or are gone: one line each, empty when the record still reproduces.
    (Inputs outside the repository, e.g. a run folder's gains, are named by sha256 only.)"""
    problems = []
    for name, entry in (result.get("provenance", {}).get("inputs") or {}).items():
        if not in_repository(entry["path"]):
            continue
        path = _repository_file(base, entry["path"])
        if not path.is_file():
            problems.append(f"{name}: {entry['path']} is missing")
        elif sha256(path) != entry["sha256"]:
            problems.append(f"{name}: {entry['path']} has changed since (sha256 {entry['sha256'][:12]}...)")
    return problems


# A repository file named in a result's text: experiments/..., results/..., assets/... or docs/... (results
# recorded before issue 44; relative, or absolute with the repository's folder before it), ending in .json,
# .yaml or .yml.
_FOLDERS = ("experiments", "results", "assets", "docs")
_NAMED_FILE = re.compile(
    r"(?<![\w./-])((?:/[\w.-]+)*/?(?:experiments|results|assets|docs)/[\w./-]*?\.(?:json|ya?ml))(?![\w-])"
)


def _relative(token: str) -> str:
    if not token.startswith("/"):
        return token
    return token[min(i for i in (token.find(f"/{f}/") for f in _FOLDERS) if i >= 0) + 1 :]


def mentioned_files(result) -> set[str]:
    """Repository paths (experiments/..., results/..., assets/...; .json, .yaml) named in any string of a result,
    absolute spellings made relative, results under docs/ by their place now (:func:`current_path`): the files its
    command, config and notes refer to."""
    found = set()

    def walk(x):
        if isinstance(x, dict):
            for v in x.values():
                walk(v)
        elif isinstance(x, list):
            for v in x:
                walk(v)
        elif isinstance(x, str):
            found.update(current_path(_relative(t)) for t in _NAMED_FILE.findall(x))

    walk(result)
    return found


def spellings(text: str, path: str) -> set[str]:
    """The substrings of ``text`` that name the repository file ``path`` (relative or absolute, or under docs/
    as results recorded before issue 44 name it)."""
    return {t for t in _NAMED_FILE.findall(text) if current_path(_relative(t)) == path}
