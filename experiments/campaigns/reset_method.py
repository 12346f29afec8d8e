"""Take one method's results out of a tuning run folder, so that its phase runs afresh on resume.

    python experiments/campaigns/reset_method.py RUN_DIR --method hybrid [--dry-run]

A tuning run never overwrites a gain file (tuning/store.write_once), so a phase whose results must be
measured again (the race's hybrid after the compile-cache fix: its three budgets spent 69-225 s of
their halves compiling) needs its sets taken out first. This removes the method's folder
(``<method>/``), its gain files (``gains/<method>.json``, ``gains/<method>_t<s>.json``), their
entries in ``gains/provenance.json`` and every recorded output under those paths in ``run.json``.
The held-out tables need nothing: their parts are keyed by the sets they evaluated, so the next
``--phases heldout`` evaluates the new sets (and the group they share) afresh. The other methods'
files stay as they are. Exits 1 when RUN_DIR is not a tuning run or holds nothing of the method.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import re
import shutil
import sys

from wbc_jax.core import io
from wbc_jax.jobs import runs
from wbc_jax.tuning.orchestration import race


def method_files(run_dir: pathlib.Path, method: str) -> tuple[list[pathlib.Path], list[str]]:
    """(the files and folders of ``method`` in ``run_dir``, its set names in gains/provenance.json)."""
    pattern = re.compile(rf"^{re.escape(method)}(_t[0-9.]+)?$")
    index_path = run_dir / "gains" / "provenance.json"
    index = json.loads(index_path.read_text()) if index_path.exists() else {}
    names = sorted(n for n in index if pattern.match(n))
    paths = [p for p in sorted((run_dir / "gains").glob(f"{method}*.json")) if pattern.match(p.stem)]
    if (run_dir / method).is_dir():
        paths.append(run_dir / method)
    return paths, names


def reset(run_dir: pathlib.Path, method: str, *, dry_run: bool = False) -> dict:
    """Remove ``method``'s results from the tuning run ``run_dir`` (module docstring); returns what was
    (or, with ``dry_run``, would be) removed: {"paths", "sets", "outputs"}."""
    run_dir = pathlib.Path(run_dir)
    manifest_path = run_dir / runs.MANIFEST
    if method not in race.METHODS:
        raise ValueError(f"--method {method!r} is not a race method; valid: {', '.join(race.METHODS)}")
    try:
        record = json.loads(manifest_path.read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{manifest_path} is not a run record ({err})") from None
    if record.get("kind") != "tune":
        raise ValueError(f"{run_dir} is a {record.get('kind')!r} run, not a tuning run")
    paths, names = method_files(run_dir, method)
    if not paths and not names:
        raise ValueError(f"{run_dir} holds no results of {method}")
    keys = [p.relative_to(run_dir).as_posix() for p in paths]
    outputs = record.get(runs.OUTPUTS, {})
    dropped = sorted(k for k in outputs if any(k == key or k.startswith(key + "/") for key in keys))
    if not dry_run:
        index_path = run_dir / "gains" / "provenance.json"
        if names:
            index = json.loads(index_path.read_text())
            io.atomic_write_json(index_path, {k: v for k, v in index.items() if k not in names})
        for path in paths:
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        if dropped:
            record[runs.OUTPUTS] = {k: v for k, v in outputs.items() if k not in dropped}
            io.atomic_write_json(manifest_path, record)
    return {"paths": keys, "sets": names, "outputs": dropped}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dir", type=pathlib.Path)
    ap.add_argument("--method", required=True)
    ap.add_argument("--dry-run", action="store_true")
    args = ap.parse_args(argv)
    try:
        done = reset(args.run_dir, args.method, dry_run=args.dry_run)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    verb = "would remove" if args.dry_run else "removed"
    print(
        f"{verb}: {len(done['paths'])} paths ({', '.join(done['paths'])}), sets {', '.join(done['sets'])}, "
        f"{len(done['outputs'])} recorded outputs"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
