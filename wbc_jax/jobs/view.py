"""``wbc-jax view``: a run on disk as a rerun recording (:mod:`wbc_jax.report.recording` draws it).

A ``balance`` run (``trajectory.npz``) is logged as is; env I of a push sweep (``results.parquet``
+ ``summary.json``) is first re-simulated with trajectory recording from its stored scenario
(:func:`wbc_jax.jobs.sweep.replay_env`).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import zipfile

import numpy as np

from wbc_jax.core import io, loader
from wbc_jax.core.options import check_options, option
from wbc_jax.jobs import runs
from wbc_jax.jobs.sweep_config import MAX_ENVS
from wbc_jax.report.recording import check_trajectory, log_trajectory, scene_boxes
from wbc_jax.robot.robots import DEFAULT_ROBOT, describe
from wbc_jax.sim.state import SimConfig


@dataclasses.dataclass(frozen=True)
class ViewConfig:
    """What ``wbc-jax view`` shows (its CLI flags are generated from these fields)."""

    run_dir: str = option("", "output folder of a balance run or a push sweep", positional=True)
    env: int | None = option(None, "sweep env to re-simulate and show", ge=0, le=MAX_ENVS)
    out: str | None = option(None, ".rrd file (default RUN_DIR/rollout.rrd or env_I.rrd)")
    spawn: bool = option(False, "open a rerun viewer instead of a file")

    def check(self) -> None:
        """The declared ranges, then the run folder: its kind, and ``env`` against it."""
        check_options(self)
        if self.spawn and self.out is not None:
            raise ValueError("--out and --spawn exclude each other: write a file or open a viewer")
        if self.out is not None and runs.check_out_path(self.out) and pathlib.Path(self.out).is_dir():
            raise ValueError(f"--out {self.out} is a folder; give a .rrd file name")
        if self.out is not None and not self.out.endswith(".rrd"):
            raise ValueError(
                f"--out {self.out}: give a .rrd file name (view writes a rerun recording, never a run's own files)"
            )
        kind = run_kind(self.run_dir)
        if kind == "balance" and self.env is not None:
            raise ValueError(f"{self.run_dir} is a balance run (one trajectory): --env applies to sweeps only")
        if kind == "sweep":
            size = _sweep_size(pathlib.Path(self.run_dir))
            if self.env is None:
                raise ValueError(
                    f"{self.run_dir} is a push sweep of {size} envs: choose one with --env I, I in 0..{size - 1}"
                )
            if self.env >= size:
                raise ValueError(f"--env {self.env} is out of range: this sweep has envs 0..{size - 1}")
            from wbc_jax.jobs.sweep import load_sweep

            load_sweep(self.run_dir)  # a summary.json of something else: named before anything compiles
        check_untouched(pathlib.Path(self.run_dir), kind)
        if not self.spawn:
            check_recording_path(recording_path(self.run_dir, self.out, kind, self.env), self.out is not None)


def default_config() -> ViewConfig:
    return ViewConfig()


def recording_path(run_dir, out: str | None, kind: str, env: int | None) -> pathlib.Path:
    """Where the recording goes: ``out``, or RUN_DIR/rollout.rrd (a balance run), RUN_DIR/env_I.rrd."""
    if out is not None:
        return pathlib.Path(out)
    return pathlib.Path(run_dir) / ("rollout.rrd" if kind == "balance" else f"env_{env}.rrd")


def check_recording_path(path: pathlib.Path, given: bool = True) -> None:
    """The recording can be written at ``path`` (``given``: by --out, else the default in the run's
    folder): one line naming it and the problem otherwise."""
    flag = "--out" if given else "the recording (give --out FILE.rrd elsewhere)"
    runs.probe_writable(path, runs.check_out_path(path, flag), flag)


def check_untouched(run_dir: pathlib.Path, kind: str) -> None:
    """A run is shown only as it was written: its result files as the run recorded them (sha256 in
    run.json), and for a sweep (re-simulated from its config) its input files as they were."""
    if not (run_dir / runs.MANIFEST).exists():
        return
    own = ("trajectory.npz",) if kind == "balance" else ("results.parquet", "summary.json")
    for name in own:
        why = runs.output_changed(run_dir / name)
        if why is not None:
            raise ValueError(f"view {run_dir}: {why}; rerun the {kind} with the same --out")
    changed = runs.changed_inputs(run_dir) if kind == "sweep" else []
    if changed:
        raise ValueError(
            f"view {run_dir}: its input files changed since it ran ({'; '.join(changed)}): a replay "
            "would not show that run; rerun the sweep"
        )


def run_kind(run_dir: str | pathlib.Path) -> str:
    """``"balance"`` (trajectory.npz) or ``"sweep"`` (results.parquet + summary.json); the run
    kind of the folder's run.json when it has one (an envelope or tuning run has no trajectory
    to show: refused, naming it)."""
    run_dir = pathlib.Path(run_dir)
    if not str(run_dir) or not run_dir.exists():
        raise FileNotFoundError(f"run directory {run_dir} does not exist")
    if not run_dir.is_dir():
        raise ValueError(f"{run_dir} is a file; give the output folder of a balance run or a push sweep")
    manifest = run_dir / runs.MANIFEST
    if manifest.exists():
        try:
            kind = json.loads(io.read_text(manifest, "run manifest")).get("kind")
        except (json.JSONDecodeError, AttributeError):
            kind = None
        if kind not in (None, "balance", "sweep"):
            raise ValueError(
                f"{run_dir} holds {runs.with_article(kind)} run, which keeps no "
                "trajectories; view shows a balance run or one env of a push sweep (run wbc-jax balance "
                "or push-sweep with its settings)"
            )
    if (run_dir / "trajectory.npz").exists():
        return "balance"
    if (run_dir / "results.parquet").exists():
        return "sweep"
    if (run_dir / "summary.json").exists() or (run_dir / "parts").exists():
        raise FileNotFoundError(
            f"{run_dir / 'results.parquet'} is missing: the sweep has not finished; rerun it with the same --out"
        )
    raise FileNotFoundError(
        f"{run_dir} is neither a balance run (no trajectory.npz) nor a finished push sweep "
        f"(no results.parquet); found: {sorted(p.name for p in run_dir.iterdir())[:5]}"
    )


def _sweep_size(run_dir: pathlib.Path) -> int:
    import pandas as pd

    try:
        return len(pd.read_parquet(run_dir / "results.parquet", columns=["env"]))
    except Exception as err:  # a truncated or foreign file: name it, whatever pyarrow raises
        raise ValueError(
            f"{run_dir / 'results.parquet'} is unreadable ({type(err).__name__}); rerun the sweep"
        ) from None


def _read_npz(path: pathlib.Path) -> dict:
    try:
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:  # truncated or not an npz
        raise ValueError(f"{path} is unreadable ({err}); rerun the balance job") from None


def load_run(run_dir: str | pathlib.Path, env: int | None = None) -> tuple[dict, dict]:
    """The trajectory of a run dir and how to draw it.

    Returns:
      (traj dict, info {"kind", "robot", "push_body", "joints", "name", "contacts", "dims", "boxes"}).

    Raises:
      FileNotFoundError / ValueError: unknown dir, missing files, env given for a balance run or
        missing / out of range for a sweep.
    """
    from wbc_jax.jobs import sweep
    from wbc_jax.sim import scenario

    run_dir = pathlib.Path(run_dir)
    kind = run_kind(run_dir)
    check_untouched(run_dir, kind)
    if kind == "balance":
        if env is not None:
            raise ValueError(f"{run_dir} is a balance run (one trajectory): --env applies to sweeps only")
        traj = _read_npz(run_dir / "trajectory.npz")
        metrics = run_dir / "metrics.json"
        config = loader.read_json(metrics, "balance metrics").get("config", {}) if metrics.exists() else {}
        robot = config.get("robot", DEFAULT_ROBOT)  # a run of before --robot: the default robot's
        joints = [str(j) for j in traj.pop("joints", describe(robot).joints)]
        names = [str(c) for c in traj.pop("contact_names", ["left", "right"])]
        dims = [int(d) for d in traj.pop("contact_dims", [6] * len(names))]
        boxes = {}
        tasks = config.get("tasks")
        if tasks:
            boxes = scene_boxes(scenario.load_scene(robot, tasks).robot)
        return traj, {
            "kind": kind,
            "robot": robot,
            "push_body": SimConfig.push_body,
            "joints": joints,
            "name": "rollout",
            "contacts": names,
            "dims": dims,
            "boxes": boxes,
        }
    if env is None:
        size = _sweep_size(run_dir)
        raise ValueError(f"{run_dir} is a push sweep of {size} envs: choose one with --env I, I in 0..{size - 1}")
    st, traj, _, _ = sweep.replay_env(run_dir, env)
    cset = st.loop.contact_set
    return traj, {
        "kind": kind,
        "robot": st.robot.index.robot,
        "push_body": st.loop.cfg.push_body,
        "joints": list(st.robot.index.joints),
        "name": f"env_{env}",
        "contacts": list(cset.names),
        "dims": [c.dim for c in cset.contacts],
        "boxes": scene_boxes(st.robot),
    }


def view(
    run_dir: str | pathlib.Path, env: int | None = None, *, out: str | pathlib.Path | None = None, spawn: bool = False
) -> pathlib.Path | None:
    """Log a run (or sweep env) to rerun: write ``out`` (default RUN_DIR/rollout.rrd or
    RUN_DIR/env_I.rrd) or, with ``spawn``, open a viewer. Returns the .rrd path (None if spawned)."""
    try:
        import rerun as rr
    except ImportError:
        raise ImportError('wbc-jax view needs rerun-sdk: pip install -e ".[viz]"') from None

    run_dir = pathlib.Path(run_dir)
    traj, info = load_run(run_dir, env)
    check_trajectory(traj)  # before a file or viewer is opened
    rec = rr.RecordingStream("wbc_jax", recording_id=f"{run_dir.resolve()}:{info['name']}")
    if spawn:
        rec.spawn()
        path = None
    else:
        path = recording_path(run_dir, out, info["kind"], env)
        if path.exists() and path.is_dir():
            raise ValueError(f"--out {path} is a folder; give a .rrd file name")
        check_recording_path(path, out is not None)
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(path))
    log_trajectory(
        rec,
        traj,
        robot=info["robot"],
        push_body=info["push_body"],
        joints=info["joints"],
        contacts=info["contacts"],
        dims=info["dims"],
        boxes=info["boxes"],
    )
    rec.flush()
    if path is not None:
        rec.disconnect()
    return path
