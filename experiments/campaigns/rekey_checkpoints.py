"""Re-key a tuning run's checkpoints after an input file moved (companion of upgrade_run.py).

    python experiments/campaigns/rekey_checkpoints.py RUN_DIR --init-gains NEW_PATH [--dry-run]

A checkpoint records the short hash of the tuning config that wrote it (tuning/config.config_key), and
that hash covers the ``--init-gains`` path as typed. After the hand-set gains moved to
assets/gains/, upgrade_run.py rewrote the run's record (inputs by content) but every checkpoint still
carried the old hash, so a phase that loads one (CMA-ES giving the hybrid its sets at half of each
budget) refused the folder as "another tuning config". This recomputes both hashes a run uses (the
training key, less NOT_TRAINING; the searches' key, less baselines.NOT_SEARCH) from the run's
config.json, checks that they are the ones its checkpoints hold, and swaps in the hashes of the same
config with ``--init-gains`` at NEW_PATH, whose content must be the one the run recorded. Exits 1 on any
mismatch, changing nothing.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pathlib
import sys

import numpy as np

from wbc_jax.core import io, provenance
from wbc_jax.jobs import runs
from wbc_jax.tuning.algorithms.baselines import NOT_SEARCH
from wbc_jax.tuning.config import NOT_TRAINING


def _key(dicts: list[dict], exclude) -> str:
    """tuning/config.config_key over the config dicts (as written in config.json)."""
    blob = json.dumps([{k: v for k, v in d.items() if k not in exclude} for d in dicts], sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def swaps(run_dir: pathlib.Path, new_init_gains: str) -> dict[str, str]:
    """{old hash: new hash} for the run's training and search keys with ``--init-gains`` at the new path."""
    config = json.loads((run_dir / "config.json").read_text())
    tune, loss = config["tune"], config["loss"]
    recorded = json.loads((run_dir / runs.MANIFEST).read_text())["fingerprint"]["config"]["tune"]["init_gains"]
    if not pathlib.Path(new_init_gains).is_file():
        raise ValueError(f"--init-gains {new_init_gains} is not a file")
    if recorded != f"sha256:{provenance.sha256(new_init_gains)}":
        raise ValueError(f"--init-gains {new_init_gains} differs from the content the run recorded ({recorded})")
    moved = {**tune, "init_gains": new_init_gains}
    return {
        _key([tune, loss], NOT_TRAINING): _key([moved, loss], NOT_TRAINING),
        _key([tune], NOT_SEARCH): _key([moved], NOT_SEARCH),
    }


def rekey(run_dir, new_init_gains: str, *, dry_run: bool = False) -> list[tuple[str, str, str]]:
    """Re-key every checkpoint.npz under ``run_dir``; returns [(path, old key, new key)]."""
    run_dir = pathlib.Path(run_dir)
    table = swaps(run_dir, new_init_gains)
    done = []
    for path in sorted(run_dir.rglob("checkpoint.npz")):
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        old = str(arrays.get("key", ""))
        parts = old.split("-")
        if not parts or parts[0] not in table or any(p in table.values() for p in parts):
            raise ValueError(f"{path}: key {old!r} is not one of this run's config ({', '.join(table)})")
        new = "-".join(table.get(p, p) for p in parts)
        done.append((str(path), old, new))
        if not dry_run:
            arrays["key"] = np.asarray(new)
            recorded = runs.output_changed(path) is None and runs.run_root(path) is not None
            io.atomic_save_npz(path, **arrays)
            if recorded:  # the run's own file before: still its own after
                runs.record_output(path)
    return done


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dir", type=pathlib.Path)
    ap.add_argument("--init-gains", required=True)
    ap.add_argument("--dry-run", action="store_true")
    args = ap.parse_args(argv)
    try:
        done = rekey(args.run_dir, args.init_gains, dry_run=args.dry_run)
    except (OSError, KeyError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    for path, old, new in done:
        print(f"{path}: {old} -> {new}{' (dry run)' if args.dry_run else ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
