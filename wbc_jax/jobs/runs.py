"""Run directories: where a job writes, checked first, bound to what made its results.

Every job's output folder holds ``run.json``: the job kind and a fingerprint of everything that
determines the results (the full config, a content hash of each input file and of the robot
model, the package version). A job refuses a folder that is a file, is not writable, holds a
run of another kind, or holds a run of its kind made with other inputs (naming the difference),
before anything is loaded or compiled: nothing is overwritten by a run with other settings. A
resumable job (sweep, tune) continues a run of the same fingerprint; the others redo it.

Inputs are compared by content (an input file by its sha256 wherever the config names it) and
outputs by what they change: the folder's own path and whether plots are drawn are no part of a
fingerprint, so a run resumes from a copy of its folder, under another spelling of --out or with
its input files by other paths. Each result file a run writes (sweep parts, tables, summaries, a
limit search's checkpoint) has its sha256 recorded in ``run.json`` (``outputs``): a file edited,
or copied in from another run, is not the run's own (:func:`output_changed`) and is recomputed or
refused, never merged nor shown.
"""

from __future__ import annotations

import json
import os
import pathlib
import tempfile

from wbc_jax.core import io, provenance

MANIFEST = "run.json"


# Fields that say where results go, not what they are: a run moved, copied or written without its
# plots resumes (the job decides what to redo for them).
OUTPUT_ONLY = ("out", "plots")
# A fingerprint's record of where its input files were: written to the manifest, never compared (the
# same file by another path, or a copied folder, is the same input).
INPUT_PATHS = "inputs"
NAME_MAX = 255  # bytes of one path component on Linux file systems (ENAMETOOLONG beyond)


def fingerprint(config: dict, files, robot: str) -> dict:
    """What determines a run's results: the config (its ``robot`` among its fields) without its
    output-only fields, each input file (paths in ``files``; None skipped) as its contents' sha256
    wherever the config names it (a path, or NAME=PATH), the robot's model file and the package
    version; a ``qp_engine`` of ``auto`` as the engine it names here (:func:`wbc_jax.control.qp.resolve_engine`).
    ``inputs`` records the resolved path of each file (kept in the manifest, not compared)."""
    from wbc_jax import __version__
    from wbc_jax.robot.robots import describe

    if config.get("qp_engine") == "auto":  # the force QP engine it names here (as a backend's "auto")
        from wbc_jax.control import qp

        steps = config.get("qp_unrolled_steps") or 0
        config = {**config, "qp_engine": qp.resolve_engine("auto", config.get("qp_warm_start") is True, steps)}
    contents = {str(f): _content(f) for f in files if f}

    def canonical(value):
        if isinstance(value, dict):
            return {k: canonical(v) for k, v in value.items() if k not in OUTPUT_ONLY}
        if isinstance(value, (list, tuple)):
            return [canonical(v) for v in value]
        if isinstance(value, str) and value in contents:
            return contents[value]
        if isinstance(value, str) and value.partition("=")[2] in contents:  # --sets NAME=FILE
            name, _, path = value.partition("=")
            return f"{name}={contents[path]}"
        return value

    model = describe(robot).model_path
    return {
        "config": canonical(json.loads(json.dumps(config, default=str))),
        "model": provenance.sha256(model) if model is not None and model.exists() else None,
        "version": __version__,
        INPUT_PATHS: {_resolved(f): contents[str(f)] for f in files if f},
    }


def _content(path) -> str:
    path = pathlib.Path(path)
    return f"sha256:{provenance.sha256(path)}" if path.is_file() else f"missing:{path}"


def _resolved(path) -> str:
    try:
        return str(pathlib.Path(path).resolve())
    except (OSError, RuntimeError):  # a symlink loop: named as given
        return str(path)


def check_out_path(path, flag: str = "--out") -> pathlib.Path:
    """``path`` as a place to write, each problem in one line naming ``flag``: a name component
    longer than the file system takes, a symlink to nothing or in a loop, a parent that is a file.
    Returns the nearest folder that exists (where :func:`probe_writable` writes)."""
    path = pathlib.Path(path)
    for part in path.parts:
        if len(os.fsencode(part)) > NAME_MAX:
            raise ValueError(
                f"{flag} {str(path)[:60]}...: a name of {len(os.fsencode(part))} bytes; names are at "
                f"most {NAME_MAX} bytes"
            )
    try:
        probe = path.absolute()
        while not probe.exists():
            if probe.is_symlink():
                raise ValueError(
                    f"{flag} {path}: {probe} is a symlink to a missing target or in a loop; give a "
                    "folder that exists or can be made"
                )
            probe = probe.parent
        if probe != path.absolute() and not probe.is_dir():
            raise ValueError(f"{flag} {path}: {probe} is a file, not a folder; give a path under a folder")
    except OSError as err:  # ELOOP, EACCES on the way
        raise ValueError(f"{flag} {path}: cannot be reached ({err.strerror}); give another path") from None
    return probe


def probe_writable(path: pathlib.Path, probe: pathlib.Path, flag: str) -> None:
    """A file can be made in the folder ``probe`` (on the way to ``path``): checked by making one, as
    ``os.access`` says yes to root everywhere (a read-only mount, /proc)."""
    try:
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as err:
        raise ValueError(f"{flag} {path}: cannot write in {probe} ({err.strerror}); give a writable folder") from None


def check_output_dir(path, kind: str, fp: dict | None = None) -> pathlib.Path:
    """Fail early if ``path`` cannot hold a ``kind`` run: it is a file, it holds a run of another
    kind (or files of something else), a run of this kind whose fingerprint differs from ``fp``
    (None: not compared), or it cannot be written."""
    if path is None:
        return None
    path = pathlib.Path(path)
    probe = check_out_path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"--out {path} is a file; give a folder for the {kind} run")
    manifest = path / MANIFEST
    if manifest.exists():
        record = _read_manifest(path)
        found = record.get("kind")
        if found != kind:
            raise ValueError(
                f"--out {path} holds {with_article(found)} run; {with_article(kind)} run needs its own folder"
            )
        if fp is not None:
            old = record.get("fingerprint")
            names = {sha: where for where, sha in (fp.get(INPUT_PATHS) or {}).items()}
            diff = differences(_compared(old if isinstance(old, dict) else {}), _compared(fp), names=names)
            if diff:
                raise ValueError(
                    f"--out {path} holds {with_article(kind)} run made with other inputs "
                    f"({'; '.join(diff)}); use another --out, or remove the folder to start over"
                )
    elif path.is_dir():
        others = sorted(p.name for p in path.iterdir() if not p.name.startswith("."))
        if others:
            raise ValueError(
                f"--out {path} is not empty and holds no {MANIFEST} (found {others[:5]}); give a new or empty folder"
            )
    probe_writable(path, probe, "--out")
    return path


def _read_manifest(run_dir: pathlib.Path) -> dict:
    try:
        record = json.loads((run_dir / MANIFEST).read_text())
        if not isinstance(record, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError, UnicodeDecodeError) as err:
        raise ValueError(f"--out {run_dir}: its {MANIFEST} is unreadable ({err}); use another folder") from None
    return record


def _compared(fp: dict) -> dict:
    return {k: v for k, v in fp.items() if k != INPUT_PATHS}


def with_article(kind) -> str:
    """A run kind with its article: 'a sweep', 'an envelope'."""
    return f"{'an' if str(kind)[:1] in 'aeiou' else 'a'} {kind}"


def differences(old: dict, new: dict, prefix: str = "", names: dict | None = None) -> list[str]:
    """Human-readable differences between two fingerprints (``names``: an input file's path by its
    contents' entry, to name a file whose contents changed)."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key, "<absent>"), new.get(key, "<absent>")
        name = f"{prefix}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            out += differences(a, b, name + ".", names)
        elif a != b:
            if key == "model" or all(str(x).startswith(("sha256:", "missing:")) for x in (a, b)):
                where = (names or {}).get(b)
                out.append(f"{name}{f' ({where})' if where else ''}: contents changed")
            else:
                out.append(f"{name}: {a!r} -> {b!r}")
    return out


def claim_output_dir(path, kind: str, fp: dict, *, resume: bool = False) -> bool:
    """Bind ``path`` to a ``kind`` run with fingerprint ``fp``; a folder holding a run with
    another fingerprint is refused, naming the differences (:func:`check_output_dir`). Returns
    True when a run of the same fingerprint is there and ``resume`` (the job continues it; where
    its inputs now lie is recorded), else False (the job writes the folder afresh: the record of
    its outputs starts empty)."""
    path = check_output_dir(path, kind, fp)
    if (path / MANIFEST).exists() and resume:
        record = _read_manifest(path)
        if record.get("fingerprint", {}).get(INPUT_PATHS) != fp.get(INPUT_PATHS):  # a moved input or a copied folder
            io.atomic_write_json(path / MANIFEST, {**record, "fingerprint": fp})
        return True
    path.mkdir(parents=True, exist_ok=True)
    io.atomic_write_json(path / MANIFEST, {"kind": kind, "fingerprint": fp, OUTPUTS: {}})
    return False


# ---------------------------------------------------------------------------------------------
# The sha256 of each result file a run wrote, in its manifest: a part or table changed (edited, or
# copied from another run) is not taken for the run's own.

OUTPUTS = "outputs"
_ROOT_DEPTH = 3  # a result file lies at most this many folders below its run's manifest


def run_root(path) -> pathlib.Path | None:
    """The run folder (the one holding run.json) of a result file, None outside any run."""
    for parent in list(pathlib.Path(path).absolute().parents)[:_ROOT_DEPTH]:
        if (parent / MANIFEST).is_file():
            return parent
    return None


def _key(root: pathlib.Path, path) -> str:
    return pathlib.Path(path).absolute().relative_to(root).as_posix()


def record_output(path) -> None:
    """Record the sha256 of the result file ``path``, just written, in its run's manifest (no run:
    nothing to record)."""
    root = run_root(path)
    if root is None:
        return
    record = _read_manifest(root)
    record.setdefault(OUTPUTS, {})[_key(root, path)] = provenance.sha256(path)
    io.atomic_write_json(root / MANIFEST, record)


def output_changed(path) -> str | None:
    """Why the result file ``path`` is not its run's own (None: it is, or it lies in no run):
    missing, never recorded (copied in, or written before the run recorded it), or changed since."""
    path = pathlib.Path(path)
    root = run_root(path)
    if root is None:
        return None if path.exists() else f"{path} is missing"
    recorded = _read_manifest(root).get(OUTPUTS, {}).get(_key(root, path))
    if not path.is_file():
        return f"{path} is missing"
    if recorded is None:
        return f"{path} is not recorded in {root / MANIFEST} (copied in, or written by an older version)"
    if provenance.sha256(path) != recorded:
        return f"{path} changed since the run wrote it (its sha256 differs from {root / MANIFEST})"
    return None


def changed_inputs(run_dir) -> list[str]:
    """The input files of the run in ``run_dir`` that are gone or changed since it ran, one line each."""
    fp = _read_manifest(pathlib.Path(run_dir)).get("fingerprint", {})
    problems = []
    for where, content in (fp.get(INPUT_PATHS) or {}).items():
        now = _content(where)
        if now != content:
            problems.append(f"{where} {'is gone' if now.startswith('missing:') else 'has changed'} since the run")
    return problems
