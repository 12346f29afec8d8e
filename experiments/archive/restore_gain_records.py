"""Which gains each recorded result (results/) was made with, from the repository's history (issue 32, 2026-11-25).

    python experiments/archive/restore_gain_records.py [--dry-run]

A later campaign overwrote experiments/gains/tuned_*.json, so a result that named one of them by path no longer
said which gains it had measured. For every result JSON of results/ that names a gains file of the repository (in its
command, its config, its gain sets) and does not yet record its sha256: the commit that wrote the result (the oldest
commit, following renames, whose copy of the file is today's), that gains file's contents at that commit, and:

- the contents are today's: the result records the file's path and sha256 (``provenance.inputs``);
- they differ: the result is pointed at a file of the repository that holds those contents (every name of the old
  path in the result is replaced), or at a new file ``experiments/gains/{name}_{commit}.json`` written with them.

The held-out evaluations of experiments/campaigns/tune_gpu.py name only the hand-set file: the tuned sets came from the
run's folder and were copied to experiments/gains/ (docs/tuning/README.md). ``EVALUATED`` names those copies; each is
recorded only if the Nava 2016 damping ratios the result holds for that set (``nava_2016[set].zeta_com``) are the
file's, K_D,CoM / (2 sqrt(K_P,CoM)).

``provenance.check_inputs`` then holds each result to those files; tests/test_provenance.py runs it over results/.
Needs git and the repository's history. One run did the repair; run again, it finds nothing left to do.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

from wbc_jax.core import io, loader, provenance

ROOT = pathlib.Path(__file__).resolve().parents[2]


EVALUATED = {  # result: {gain set: the copy in experiments/gains/ of the run's gains file}
    "results/tuning/heldout.json": {"gradient": "tuned_gradient", "cmaes": "tuned_cmaes", "random": "tuned_random"},
    "results/tuning/keep_tracking/heldout.json": {
        "gradient": "tuned_gradient_keep_tracking",
        "cmaes": "tuned_cmaes_keep_tracking",
        "random": "tuned_random_keep_tracking",
    },
    "results/tuning/envelope_scaled/before_margin_fix/heldout.json": {
        "gradient": "tuned_gradient_envelope_scaled",
        "cmaes": "tuned_cmaes_envelope_scaled",
        "random": "tuned_random_envelope_scaled",
    },
    "results/tuning/from_critical/heldout.json": {"gradient": "tuned_gradient_from_critical"},
}


def git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, check=True).stdout


def blob(commit: str, path: str) -> bytes | None:
    proc = subprocess.run(["git", "-C", str(ROOT), "show", f"{commit}:{path}"], capture_output=True)
    return proc.stdout if proc.returncode == 0 else None


def writing_commit(path: str) -> str:
    """The oldest commit, following renames, from which the file at ``path`` has today's contents."""
    today = (ROOT / path).read_bytes()
    lines = git("log", "--follow", "--format=@%H", "--name-only", "--", path).split("\n")
    history, commit = [], None
    for line in lines:
        if line.startswith("@"):
            commit = line[1:]
        elif line.strip() and commit:
            history.append((commit, line.strip()))
            commit = None
    found = None
    for commit, name in history:  # newest first
        if blob(commit, name) != today:
            break
        found = commit
    if found is None:
        raise ValueError(f"{path}: today's contents are not committed; commit the result first")
    return found


def gains_files() -> dict[str, str]:
    """{sha256: path} of every gains file of the repository (experiments/, results/, assets/)."""
    out = {}
    for folder in ("experiments", "results", "assets"):
        for p in sorted((ROOT / folder).rglob("*.json")):
            if loader.is_gains_file(p):
                out.setdefault(provenance.sha256(p), provenance.display_path(p))
    return out


def replace_strings(value, old: str, new: str):
    """``value`` with every string's ``old`` (and absolute spellings ending in it) replaced by ``new``."""
    if isinstance(value, dict):
        return {k: replace_strings(v, old, new) for k, v in value.items()}
    if isinstance(value, list):
        return [replace_strings(v, old, new) for v in value]
    if isinstance(value, str):
        for spelled in sorted(provenance.spellings(value, old), key=len, reverse=True):
            value = value.replace(spelled, new)
    return value


def evaluated(result: dict, rel: str) -> list[str]:
    """The gains files of EVALUATED for this result, each checked against the damping ratios it records."""
    files = []
    for name, stem in EVALUATED.get(rel, {}).items():
        path = f"experiments/gains/{stem}.json"
        g = json.loads((ROOT / path).read_text())
        zeta = [kd / (2.0 * kp**0.5) for kp, kd in zip(g["kp_com"], g["kd_com"])]
        if not all(abs(a - b) <= 1e-6 * abs(b) for a, b in zip(zeta, result["nava_2016"][name]["zeta_com"])):
            raise ValueError(f"{rel}: set {name!r} was not evaluated with {path} (its CoM damping ratios differ)")
        files.append(path)
    return files


def repair(path: pathlib.Path, known: dict[str, str], dry_run: bool) -> dict | None:
    raw = path.read_text()
    result = json.loads(raw)
    if not isinstance(result, dict):
        return None
    recorded = {e["path"] for e in (result.get("provenance", {}).get("inputs") or {}).values()}
    named = sorted(
        p for p in provenance.mentioned_files(result) if p not in recorded and loader.is_gains_file(ROOT / p)
    )
    checked = [p for p in evaluated(result, provenance.display_path(path)) if p not in recorded]
    if not named and not checked:
        return None
    commit = writing_commit(provenance.display_path(path))
    inputs, moved = {}, {}
    for name in named:
        then = blob(commit, name)
        if then is None:
            raise ValueError(f"{path}: {name} did not exist at {commit[:7]}, the commit that wrote it")
        sha = provenance.sha256_bytes(then)
        target = name
        if sha != provenance.sha256(ROOT / name):
            target = known.get(sha)
            if target is None:
                stem = pathlib.Path(name).stem
                target = f"experiments/gains/{stem}_{commit[:7]}.json"
                if not dry_run:
                    io.write_new_json(ROOT / target, json.loads(then))
                known[sha] = target
            moved[name] = target
            result = replace_strings(result, name, target)
        inputs[f"gains:{pathlib.Path(target).stem}"] = {"path": target, "sha256": sha}
    for name in checked:  # today's files, checked against the result's own damping ratios
        inputs[f"gains:{pathlib.Path(name).stem}"] = {"path": name, "sha256": provenance.sha256(ROOT / name)}
    date = git("log", "-1", "--format=%ad", "--date=short", commit).strip()
    note = (
        f"the gains files' contents at {commit[:7]} ({date}), the commit that wrote this result; "
        "recorded on 2026-11-25 by experiments/archive/restore_gain_records.py"
    )
    if checked:
        note += (
            "; the tuned sets evaluated (" + ", ".join(checked) + ") by their CoM damping ratios, which this "
            "result records under nava_2016"
        )
    if moved:
        # The old names without their folder: a path here would name the overwritten file again.
        note += "; the sets were named " + ", ".join(
            f"{pathlib.Path(a).name} (overwritten since; these contents: {pathlib.Path(b).name})"
            for a, b in moved.items()
        )
    entry = result.setdefault("provenance", {})
    entry.setdefault("inputs", {}).update(inputs)
    entry["inputs_restored"] = note
    if not dry_run:
        indent = len(raw.splitlines()[1]) - len(raw.splitlines()[1].lstrip()) if raw.count("\n") > 1 else 2
        io.atomic_write_bytes(path, (json.dumps(result, indent=indent or 2) + "\n").encode())
    return {"result": provenance.display_path(path), "commit": commit[:7], "inputs": inputs, "moved": moved}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dry-run", action="store_true", help="show what would change, write nothing")
    args = p.parse_args(argv)
    known = gains_files()
    for path in sorted((ROOT / "results").rglob("*.json")):
        done = repair(path, known, args.dry_run)
        if done:
            print(json.dumps(done), flush=True)
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (ValueError, FileExistsError, subprocess.CalledProcessError) as err:
        sys.exit(f"error: {err}")
