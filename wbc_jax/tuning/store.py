"""What a tuning run keeps on disk: checkpoints (atomic, keyed to the config), history tables, and the
gain files it writes, each once.

A campaign never overwrites a gain file: :func:`write_controls` writes ``NAME.json`` into the run's
``gains/`` folder, accepts the same contents again (a resumed run) and refuses other contents; each
file's origin (method, step or generation, simulated steps, wall time, the command and device) goes
into ``gains/provenance.json`` beside it, since a gains file holds gains only.
"""

from __future__ import annotations

import csv
import io as _io
import json
import pathlib
import zipfile

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control.gains import Gains, gains_to_dict
from wbc_jax.core import io, provenance


def save_checkpoint(path: pathlib.Path, state, step: int, key: str, **extra) -> None:
    """state (a pytree) + step + config key (+ extra arrays), atomically."""
    leaves = jax.tree_util.tree_leaves(state)
    io.atomic_save_npz(
        path,
        step=np.asarray(step),
        key=np.asarray(key),
        **{f"leaf_{i:04d}": np.asarray(x) for i, x in enumerate(leaves)},
        **{f"extra_{k}": np.asarray(v) for k, v in extra.items()},
    )


def load_checkpoint(path: pathlib.Path, like, key: str):
    """(state shaped like ``like``, step, extra {name: array}) of a checkpoint of config ``key``."""
    try:
        with np.load(path) as z:
            stored = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise ValueError(f"{path} is unreadable ({err}); remove it to restart") from None
    if "key" not in stored or str(stored["key"]) != key:
        raise ValueError(f"{path} belongs to another tuning config; use another --out")
    treedef = jax.tree_util.tree_structure(like)
    like_leaves = jax.tree_util.tree_leaves(like)
    try:
        leaves = [jnp.asarray(stored[f"leaf_{i:04d}"], dtype=jnp.asarray(x).dtype) for i, x in enumerate(like_leaves)]
    except KeyError as err:
        raise ValueError(f"{path} lacks {err}; remove it to restart") from None
    extra = {k[len("extra_") :]: v for k, v in stored.items() if k.startswith("extra_")}
    return jax.tree_util.tree_unflatten(treedef, leaves), int(stored["step"]), extra


def write_csv(path: pathlib.Path, rows: list, columns) -> None:
    buf = _io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(columns), extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    io.atomic_write_bytes(path, buf.getvalue().encode())


def read_csv(path: pathlib.Path) -> list:
    with open(path) as fh:
        return list(csv.DictReader(fh))


def rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def controls_dict(controls) -> dict:
    """The JSON of a tuned gain set: a gains file's dict for :class:`Gains`, a schedule's
    :meth:`to_dict` otherwise (:class:`wbc_jax.tuning.algorithms.schedule.GainSchedule`)."""
    if isinstance(controls, Gains):
        return gains_to_dict(controls)
    return controls.to_dict()


def write_once(path: pathlib.Path, data: dict) -> bool:
    """Write JSON ``data`` to ``path`` unless the file is there; the same contents again are accepted
    (returns False), other contents are an error: a campaign never overwrites a result."""
    path = pathlib.Path(path)
    blob = json.loads(json.dumps(data, default=io.jsonable))
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            old = None
        if old != blob:
            raise ValueError(
                f"{path} exists with other contents; a tuning run never overwrites a gain file: use another --out"
            )
        return False
    io.atomic_write_json(path, blob)
    return True


def set_name(method: str, seconds: float | None = None) -> str:
    """A tuned set's name: ``method`` (at the race's budget, or without one), ``method_t<seconds>`` at a
    snapshot time of the race."""
    return method if seconds is None else f"{method}_t{seconds:g}"


def write_controls(
    folder: pathlib.Path, name: str, controls, reg, origin: dict, *, regularisation: bool, inputs: dict | None = None
) -> dict:
    """``folder/NAME.json`` (and ``NAME_regularisation.json`` when ``regularisation``), written once, and
    their origin in ``folder/provenance.json`` (with the run's ``inputs`` files and their sha256). Returns
    {"gains": path, "regularisation": path or None}."""
    folder = pathlib.Path(folder)
    path = folder / f"{name}.json"
    write_once(path, controls_dict(controls))
    reg_path = None
    if regularisation:
        reg_path = folder / f"{name}_regularisation.json"
        write_once(reg_path, dict(zip(("pinv_damping", "kp_postural_reg"), np.asarray(reg, float).tolist())))
    index_path = folder / "provenance.json"
    index = json.loads(index_path.read_text()) if index_path.exists() else {}
    entry = {**origin, "sha256": provenance.sha256(path), "provenance": provenance.record(inputs)}
    if name not in index or index[name].get("sha256") != entry["sha256"]:
        index[name] = entry
        io.atomic_write_json(index_path, index)
    return {"gains": str(path), "regularisation": None if reg_path is None else str(reg_path)}
