"""The ``balance`` job: one closed-loop run of the controller, with metrics, trajectory and plots."""

from __future__ import annotations

import json
import math
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax import controller as ctrl_lib
from wbc_jax import dynamics, io, model, plots, references
from wbc_jax import tasks as tasks_lib
from wbc_jax import rollout as rollout_lib

CHUNK_SECONDS = 1.0  # progress granularity: one compiled chunk of ticks


def setup(
    robot: model.Robot,
    task: str,
    *,
    duration: float | None,
    forces: str = "qp",
    postural: str = "stable",
    gains: ctrl_lib.Gains | None = None,
    sim: dict | None = None,
    controller: dict | None = None,
    stack=None,
):
    """Validate everything (before any compilation) and build the pieces of a run.

    ``stack``: motion tasks (a list of :class:`wbc_jax.tasks.MotionTask` or of mappings, the
    postural task last) between the force task and the postural task; None: the two-level law.

    Returns (rollout, d0, gains, consts, schedule)."""
    ccfg = ctrl_lib.ControllerConfig(forces=forces, postural=postural, **(controller or {}))
    if task not in references.TASKS:
        raise ValueError(f"unknown task {task!r}; valid tasks: {list(references.TASKS)}")
    d0 = rollout_lib.initial_data(robot)
    resolved = None if stack is None else tasks_lib.resolve(robot, stack, np.asarray(d0.qpos))
    dtype = d0.qpos.dtype
    gains = ctrl_lib.default_gains(robot.index.n, dtype) if gains is None else gains
    ctrl_lib.validate_gains(gains, robot.index.n)
    t0 = dynamics.terms(robot.mjx_model, d0, robot.index)
    schedule = references.make_schedule(
        task, com0=np.asarray(t0.W_p_CoM), s0=np.asarray(t0.s),
        left_sole=np.asarray(t0.W_p_feet[0]), joints=robot.index.joints, duration=duration,
    )  # fmt: skip
    cfg = rollout_lib.SimConfig(duration=schedule.duration, **(sim or {}))
    consts = ctrl_lib.constants_at_reference(t0, ccfg)
    return rollout_lib.make_rollout(robot, schedule, ccfg, cfg, resolved), d0, gains, consts, schedule


def run_chunked(rollout, mx, d0, gains, consts, push, *, progress: bool = True):
    """Run a rollout in compiled chunks of ~1 s, with a progress bar. Returns (metrics, traj)."""
    from tqdm.auto import tqdm

    per_chunk = max(1, int(round(CHUNK_SECONDS / rollout.cfg.control_dt)))
    n_ticks = rollout.n_ticks
    chunk = jax.jit(rollout.chunk, static_argnames="n_ticks")
    carry = jax.jit(rollout.init)(mx, d0)
    pieces = []
    k = 0
    with tqdm(total=n_ticks * rollout.cfg.control_dt, unit="sim s", disable=not progress,
              bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} sim s [{elapsed}<{remaining}]") as bar:  # fmt: skip
        while k < n_ticks:
            n = min(per_chunk, n_ticks - k)
            carry, traj = chunk(mx, gains, consts, push, carry, k, n_ticks=n)
            jax.block_until_ready(carry[2])
            pieces.append(jax.tree_util.tree_map(np.asarray, traj))
            k += n
            bar.update(n * rollout.cfg.control_dt)
    traj = {
        name: np.concatenate([getattr(p, name) for p in pieces])
        for name in pieces[0].__dataclass_fields__
    }
    return carry[2], traj


def task_tracking(stack, traj: dict, after: float = 0.0) -> dict:
    """Per motion task: RMSE and max of the error norm (m, or the vee orientation error) over the
    ticks after ``after`` s, from the trajectory's ``task_err`` columns (stack order)."""
    sel = traj["t"] >= after
    out, col = {}, 0
    for task in stack.tasks:
        rows = len(task.kp)
        e = np.linalg.norm(traj["task_err"][sel, col : col + rows], axis=1)
        out[task.name] = {"rmse": float(np.sqrt(np.mean(e**2))), "max": float(e.max())}
        col += rows
    return out


def force_task_error(traj: dict, after: float = 1.0) -> dict:
    """How well MuJoCo's contact wrenches realise the commanded ones (ticks after ``after`` s).

    Returns the median and 95th percentile over ticks of |f_meas - f_cmd| / |f_cmd| (both feet
    stacked) and of the momentum-rate error |Ldot_meas - Ldot*| / (m g)."""
    sel = traj["t"] >= min(after, 0.5 * float(traj["t"][-1]))
    df = np.linalg.norm(traj["f_meas"][sel] - traj["f_cmd"][sel], axis=1)
    rel = df / np.maximum(np.linalg.norm(traj["f_cmd"][sel], axis=1), 1e-9)
    dL = np.linalg.norm(traj["Ldot_meas"][sel] - traj["Ldot_star"][sel], axis=1)
    return {
        "force_rel_err_median": float(np.median(rel)),
        "force_rel_err_p95": float(np.percentile(rel, 95)),
        "momentum_rate_err_median_n": float(np.median(dL)),
    }


def run(
    task: str = "stand",
    *,
    duration: float | None = None,
    forces: str = "qp",
    postural: str = "stable",
    out: str | pathlib.Path | None = None,
    gains_file: str | None = None,
    push: dict | None = None,
    robot_name: str = "icub",
    progress: bool = True,
    plots_on: bool = True,
    solver_iterations: int | None = None,
    tasks_file: str | None = None,
    control_dt: float | None = None,
) -> dict:
    """Run the balance job; write metrics.json, trajectory.npz and PNG plots into ``out``.

    Args:
      push: optional ``{"force": [fx, fy, fz] N, "onset": s, "duration": s}`` on the chest.
      solver_iterations: MJX Newton iterations (None: the model's, 4).
      tasks_file: task specification (JSON/YAML, :func:`wbc_jax.tasks.load_stack_file`).
      control_dt: controller period in s, a multiple of the 1 ms physics step (None: 0.01).

    Returns:
      the metrics dict (also printed by the CLI as one JSON line).
    """
    robot = model.load_robot(robot_name)
    gains = ctrl_lib.load_gains(gains_file, robot.index.n) if gains_file else None
    stack = tasks_lib.load_stack_file(tasks_file) if tasks_file else None
    rollout, d0, gains, consts, schedule = setup(
        robot, task, duration=duration, forces=forces, postural=postural, gains=gains,
        sim={**({} if solver_iterations is None else {"solver_iterations": int(solver_iterations)}),
             **({} if control_dt is None else {"control_dt": float(control_dt)})},
        stack=stack,
    )
    dtype = d0.qpos.dtype
    if push:
        force = np.asarray(push["force"], float).reshape(3)
        onset, dur = float(push["onset"]), float(push["duration"])
        if not (np.all(np.isfinite(force)) and onset >= 0 and dur >= 0):
            raise ValueError(f"push needs a finite force and non-negative onset/duration: {push}")
        push_tree = rollout_lib.Push(
            force=jnp.asarray(force[None], dtype), onset=jnp.asarray([onset], dtype),
            duration=jnp.asarray([dur], dtype),
        )  # fmt: skip
        push_end = onset + dur
    else:
        push_tree, push_end = rollout_lib.no_push(dtype), 0.0
    start = time.time()
    metrics, traj = run_chunked(rollout, robot.mjx_model, d0, gains, consts, push_tree, progress=progress)
    wall = time.time() - start
    result = {"task": task, "forces": forces, "postural": postural, "duration_s": schedule.duration,
              "solver_iterations": int(robot.mj_model.opt.iterations if solver_iterations is None
                                       else solver_iterations),
              "control_dt_s": rollout.cfg.control_dt}  # fmt: skip
    result.update(rollout_lib.summarize(metrics, push_end))
    result.update(force_task_error(traj))
    if rollout.stack is not None:
        result["tasks"] = task_tracking(rollout.stack, traj)
    result["wall_time_s"] = round(wall, 2)
    result["device"] = str(jax.devices()[0])
    result = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in result.items()}
    if out is not None:
        out = pathlib.Path(out)
        io.atomic_write_json(out / "metrics.json", {**result, "gains": ctrl_lib.gains_to_dict(gains), "push": push})
        io.atomic_save_npz(out / "trajectory.npz", joints=np.array(robot.index.joints), **traj)
        if plots_on:
            title = f"{task}, forces={forces}, postural={postural}"
            plots.com_tracking(traj, out / "com.png", title)
            plots.contact_forces(traj, out / "contact_forces.png", title)
            plots.joint_torques(traj, list(robot.index.joints), out / "torques.png", title)
    return result


def main_json_line(result: dict) -> str:
    return json.dumps(result, separators=(",", ":"))
