"""Bring a run folder written before issue 41's class 8 (inputs by content) to today's run record.

    python experiments/campaigns/upgrade_run.py RUN_DIR [--dry-run]

Before, a run's fingerprint named each input file by its path (``files``: path -> sha256) and its
manifest recorded no result file; today the config names an input by its content (``sha256:<hex>``),
``inputs`` keeps where it lay, and ``outputs`` holds every result file's sha256 (jobs/runs.py). A
folder of the old kind is refused on resume once an input moved (the race's per-axis run after the
hand-set gains moved to wbc_jax/assets/gains/), and its parts would not count as its own. This
rewrites run.json: every path the old record names is replaced by the content it recorded (each path
must have one sha256), and the files now in the folder are adopted as the run's outputs: run it only
on a folder that came unchanged from its own job (e.g. unpacked from race_piece.sh's archive). A resume
with other inputs is then still refused, naming them. Exits 1 when the folder is not an old-kind run.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

from wbc_jax.core import io, provenance
from wbc_jax.jobs import runs


def upgraded(record: dict, run_dir: pathlib.Path) -> dict:
    """The run.json of today for the old-kind ``record`` of ``run_dir`` (ValueError: not an old kind)."""
    fp = record.get("fingerprint")
    if not isinstance(fp, dict) or "files" not in fp or runs.INPUT_PATHS in fp:
        raise ValueError(f"{run_dir}/{runs.MANIFEST} is not a record of the old kind (a 'files' map, no 'inputs')")
    files = fp["files"]

    def canonical(value):
        if isinstance(value, dict):
            return {k: canonical(v) for k, v in value.items()}
        if isinstance(value, list):
            return [canonical(v) for v in value]
        if isinstance(value, str) and value in files:
            return f"sha256:{files[value]}"
        if isinstance(value, str) and value.partition("=")[2] in files:  # --sets NAME=FILE
            name, _, path = value.partition("=")
            return f"{name}=sha256:{files[path]}"
        return value

    new_fp = {k: v for k, v in fp.items() if k != "files"}
    new_fp["config"] = canonical(fp["config"])
    new_fp[runs.INPUT_PATHS] = dict(files)  # where they lay then (kept, never compared)
    outputs = {
        f.relative_to(run_dir).as_posix(): provenance.sha256(f)
        for f in sorted(run_dir.rglob("*"))
        if f.is_file() and f.name != runs.MANIFEST
    }
    return {**record, "fingerprint": new_fp, runs.OUTPUTS: outputs}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir", help="the run folder (holding run.json)")
    p.add_argument("--dry-run", action="store_true", help="print what would change, write nothing")
    args = p.parse_args(argv)
    run_dir = pathlib.Path(args.run_dir)
    try:
        record = json.loads((run_dir / runs.MANIFEST).read_text())
        new = upgraded(record, run_dir)
    except (OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(
        json.dumps(
            {
                "run": str(run_dir),
                "inputs": new["fingerprint"][runs.INPUT_PATHS],
                "outputs_adopted": len(new[runs.OUTPUTS]),
                "written": not args.dry_run,
            }
        )
    )
    if not args.dry_run:
        io.atomic_write_json(run_dir / runs.MANIFEST, new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
