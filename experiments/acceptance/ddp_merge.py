"""Merge crocoddyl cross-check files of one optimiser (experiments/acceptance/ddp_limit.py runs, e.g. one
direction per process on a many-core host) into one file (issue 43).

    python experiments/acceptance/ddp_merge.py --into results/limit/ddp_chest_cop08.json /tmp/ddp/chest_*.json

Every source must have the target's config except ``directions`` (another setting is another optimiser: a
file of its own, limit_table.ddp_label), and a direction present twice must have the same content. The result
holds the union of the directions, ``config.directions`` sorted, the commands concatenated, and ``wall_s`` the
sum of the parts' wall times beside ``parts`` ({file, wall_s, device, provenance} each: parts that ran in
parallel are not serial time). The ``<file>_witness.npz`` torques (keys "azimuth:impulse") are merged the same
way. A source already merged (its sha256 among the parts) is skipped, so a rerun changes nothing. Both files
are written atomically, after every check passed.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import zipfile

import numpy as np

from wbc_jax.core import io, loader, provenance
from wbc_jax.jobs import limit_ddp

FIELDS = ("what", "commands", "config", "directions", "wall_s", "provenance")  # what ddp_limit.py writes


def _checked(name: str, doc) -> dict:
    if not isinstance(doc, dict) or any(k not in doc for k in FIELDS):
        missing = next((k for k in FIELDS if not isinstance(doc, dict) or k not in doc), FIELDS[0])
        raise ValueError(
            f"{name}: not a crocoddyl cross-check file (no field {missing!r}; ddp_limit.py writes {', '.join(FIELDS)})"
        )
    return doc


def _first_difference(a, b, field: str) -> str:
    """The dotted name of the first field where ``a`` and ``b`` differ (they do differ)."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in [*a, *(k for k in b if k not in a)]:
            if key not in a or key not in b or a[key] != b[key]:
                return _first_difference(a.get(key), b.get(key), f"{field}.{key}")
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            if x != y:
                return _first_difference(x, y, f"{field}[{i}]")
    return field


def _part(name: str, doc: dict, sha256: str | None) -> dict:
    prov = doc["provenance"] or {}
    part = {"file": pathlib.Path(name).name, "wall_s": doc["wall_s"], "device": (prov.get("device") or {}).get("label")}
    return {**part, "sha256": sha256, "provenance": prov} if sha256 else {**part, "provenance": prov}


def merge(into: str, target: dict | None, sources: list[tuple[str, dict, str]]) -> tuple[dict, list[str]]:
    """(the merged file, the sources skipped as already merged) of ``target`` (None: a new file named
    ``into``) and ``sources`` [(name, file, its sha256)]; ValueError (one line naming the file and the
    field) for a config other than the target's but for directions, or a direction of other content."""
    if target is None and not sources:
        raise ValueError(f"--into {into} does not exist and no source was given")
    base = _checked(into, target) if target is not None else _checked(*sources[0][:2])
    config = limit_ddp.stored_config(base["config"])
    directions = dict(target["directions"]) if target is not None else {}
    origin = dict.fromkeys(directions, into)
    if target is None:
        parts = []
    else:
        parts = list(target.get("parts") or [_part(pathlib.Path(into).name, target, None)])
    merged_shas = {p.get("sha256") for p in parts} - {None}
    commands, azimuths, skipped = list(base["commands"] if target is not None else []), set(), []
    azimuths.update(float(a) for a in (target["config"]["directions"] if target is not None else []))
    inputs = {}
    for part in parts:
        inputs.update((part["provenance"] or {}).get("inputs") or {})
    for name, doc, sha in sources:
        _checked(name, doc)
        if sha in merged_shas:
            skipped.append(name)
            continue
        if doc["what"] != base["what"]:
            raise ValueError(f"{name}: field 'what' differs from {into}'s: another optimiser, a file of its own")
        theirs = limit_ddp.stored_config(doc["config"])
        for field in [*config, *(k for k in theirs if k not in config)]:
            if field != "directions" and config.get(field) != theirs.get(field):
                raise ValueError(
                    f"{name}: config.{field} is {theirs.get(field)!r}, {into} has {config.get(field)!r}: only "
                    "config.directions may differ between parts of one optimiser's file"
                )
        for az, row in doc["directions"].items():
            if az in directions and directions[az] != row:
                raise ValueError(
                    f"{name}: {_first_difference(row, directions[az], f'directions.{az}')} differs from "
                    f"{origin[az]}'s: one run per direction, or the same content"
                )
            directions[az], origin[az] = row, origin.get(az, name)
        for key, entry in ((doc["provenance"] or {}).get("inputs") or {}).items():
            if key in inputs and inputs[key].get("sha256") != entry.get("sha256"):
                raise ValueError(
                    f"{name}: provenance.inputs.{key} has sha256 {str(entry.get('sha256'))[:12]}..., another part "
                    f"{str(inputs[key].get('sha256'))[:12]}...: the parts ran with different {key} files"
                )
            inputs[key] = entry
        azimuths.update(float(a) for a in doc["config"]["directions"])
        commands += doc["commands"]
        parts.append(_part(name, doc, sha))
        merged_shas.add(sha)
    config["directions"] = sorted(azimuths | {float(a) for a in directions})
    record = {**provenance.record(argv=[], with_device=False), "inputs": inputs}  # the command: main's
    merged = {
        "what": base["what"],
        "commands": commands,
        "config": config,
        "directions": {a: directions[a] for a in sorted(directions, key=float)},
        "wall_s": round(sum(p["wall_s"] for p in parts), 1),
        "parts": parts,
        "provenance": record,
    }
    return merged, skipped


def _witnesses(path: pathlib.Path) -> dict[str, np.ndarray]:
    if not path.exists():
        return {}
    try:
        with np.load(path) as data:
            return {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise ValueError(f"{path}: not a readable witness file (.npz of torques; {err})") from None


def merge_witnesses(into: str, target: dict[str, np.ndarray], sources: list[tuple[str, dict]]) -> dict:
    """``target``'s witness torques {"azimuth:impulse": array} with every source's; ValueError (one line)
    where a key holds other torques in two files."""
    merged, origin = dict(target), dict.fromkeys(target, into)
    for name, arrays in sources:
        for key, torques in arrays.items():
            if key in merged and not (
                merged[key].shape == torques.shape and np.array_equal(merged[key], torques, equal_nan=True)
            ):
                raise ValueError(f"{name}: witness {key} holds other torques than {origin[key]}'s: one run per key")
            merged[key], origin[key] = torques, origin.get(key, name)
    return merged


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--into", required=True, help="the merged file (created if missing), e.g. results/limit/ddp_X.json"
    )
    parser.add_argument("sources", nargs="+", help="ddp_limit.py files of the same optimiser")
    args = parser.parse_args(argv)
    into = pathlib.Path(args.into)
    try:
        same = [s for s in args.sources if into.exists() and pathlib.Path(s).resolve() == into.resolve()]
        if same:
            raise ValueError(f"{same[0]}: is --into itself; give the files to merge into it")
        target = loader.read_json(into, "crocoddyl cross-check") if into.exists() else None
        sources = []
        for s in args.sources:
            doc = loader.read_json(s, "crocoddyl cross-check")
            sources.append((s, doc, provenance.sha256(s)))
        merged, skipped = merge(str(into), target, sources)
        merged_now = [s for s in dict.fromkeys(args.sources) if s not in skipped]
        witnesses = merge_witnesses(
            str(limit_ddp.witness_path(into)),
            _witnesses(limit_ddp.witness_path(into)),
            [(str(limit_ddp.witness_path(s)), _witnesses(limit_ddp.witness_path(s))) for s in merged_now],
        )
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"ddp_merge: {err}")
    merged["provenance"]["command"] = provenance.command(provenance.script_argv(__file__, argv))
    if witnesses:
        io.atomic_save_npz(limit_ddp.witness_path(into), **witnesses)
    io.atomic_write_json(into, merged)
    print(
        f"{into}: {len(merged['directions'])} directions, {len(merged['parts'])} parts "
        f"(wall_s {merged['wall_s']} summed), {len(witnesses)} witnesses"
        + (f"; already merged, skipped: {', '.join(skipped)}" if skipped else "")
    )


if __name__ == "__main__":
    main()
