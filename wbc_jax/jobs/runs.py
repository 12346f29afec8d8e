"""Run directories: where a job writes, checked first, bound to what made its results.

Every job's output folder holds ``run.json``: the job kind and a fingerprint of everything that
determines the results (the full config, a content hash of each input file and of the robot
model, the package version). A job refuses a folder that is a file, is not writable, holds a
run of another kind, or holds a run of its kind made with other inputs (naming the difference),
before anything is loaded or compiled: nothing is overwritten by a run with other settings. A
resumable job (sweep, tune) continues a run of the same fingerprint; the others redo it.
"""

from __future__ import annotations

import json
import os
import pathlib
import tempfile

from wbc_jax.core import io, provenance

MANIFEST = "run.json"


def fingerprint(config: dict, files=(), robot: str = "icub") -> dict:
    """What determines a run's results: the config, the contents of its input files (paths that
    are None are skipped), the robot model file and the package version."""
    from wbc_jax import __version__
    from wbc_jax.robot.model import ROBOTS

    contents = {}
    for f in files:
        if f:
            path = pathlib.Path(f)
            contents[str(f)] = provenance.sha256(path) if path.is_file() else None
    model = ROBOTS.get(robot)
    return {
        "config": json.loads(json.dumps(config, default=str)),
        "files": contents,
        "model": provenance.sha256(model) if model is not None and model.exists() else None,
        "version": __version__,
    }


def check_output_dir(path, kind: str, fp: dict | None = None) -> pathlib.Path:
    """Fail early if ``path`` cannot hold a ``kind`` run: it is a file, it holds a run of another
    kind (or files of something else), a run of this kind whose fingerprint differs from ``fp``
    (None: not compared), or it cannot be written."""
    if path is None:
        return None
    path = pathlib.Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"--out {path} is a file; give a folder for the {kind} run")
    manifest = path / MANIFEST
    if manifest.exists():
        try:
            found = json.loads(manifest.read_text()).get("kind")
        except (json.JSONDecodeError, UnicodeDecodeError, AttributeError) as err:
            raise ValueError(f"--out {path}: its {MANIFEST} is unreadable ({err}); use another folder") from None
        if found != kind:
            raise ValueError(
                f"--out {path} holds {with_article(found)} run; {with_article(kind)} run needs its own folder"
            )
        if fp is not None:
            old = json.loads(manifest.read_text()).get("fingerprint")
            diff = differences(old if isinstance(old, dict) else {}, fp)
            if diff:
                raise ValueError(f"--out {path} holds {with_article(kind)} run made with other inputs "
                                 f"({'; '.join(diff)}); use another --out, or remove the folder to start over")  # fmt: skip
    elif path.is_dir():
        others = sorted(p.name for p in path.iterdir() if not p.name.startswith("."))
        if others:
            raise ValueError(
                f"--out {path} is not empty and holds no {MANIFEST} (found {others[:5]}); give a new or empty folder"
            )
    # Writable: the folder itself, or the nearest existing parent.
    probe = path
    while not probe.exists():
        probe = probe.parent
    if not os.access(probe, os.W_OK | os.X_OK):
        raise ValueError(f"--out {path}: {probe} is not writable")
    try:
        probe.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as err:
        raise ValueError(f"--out {path}: cannot write there ({err})") from None
    return path


def with_article(kind) -> str:
    """A run kind with its article: 'a sweep', 'an envelope'."""
    return f"{'an' if str(kind)[:1] in 'aeiou' else 'a'} {kind}"


def differences(old: dict, new: dict, prefix: str = "") -> list[str]:
    """Human-readable differences between two fingerprints."""
    out = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key, "<absent>"), new.get(key, "<absent>")
        name = f"{prefix}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            out += differences(a, b, name + ".")
        elif a != b:
            if key in ("model",) or prefix.startswith("files"):
                out.append(f"{name}: contents changed")
            else:
                out.append(f"{name}: {a!r} -> {b!r}")
    return out


def claim_output_dir(path, kind: str, fp: dict, *, resume: bool = False) -> bool:
    """Bind ``path`` to a ``kind`` run with fingerprint ``fp``; a folder holding a run with
    another fingerprint is refused, naming the differences (:func:`check_output_dir`). Returns
    True when a run of the same fingerprint is there and ``resume`` (the job continues it), else
    False (the job writes the folder afresh)."""
    path = check_output_dir(path, kind, fp)
    manifest = path / MANIFEST
    if manifest.exists():
        return resume
    path.mkdir(parents=True, exist_ok=True)
    io.atomic_write_json(manifest, {"kind": kind, "fingerprint": fp})
    return False
