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
    contact_set=None,
    qpos=None,
):
    """Validate everything (before any compilation) and build the pieces of a run.

    ``stack``: motion tasks (a list of :class:`wbc_jax.tasks.MotionTask` or of mappings, the
    postural task last) between the force task and the postural task; None: the two-level law.
    ``contact_set``: a :class:`wbc_jax.contacts.ContactSet` built with ``robot``
    (:func:`load_scenario`); None: the two feet. ``qpos``: (nq,) initial posture (None: home).

    Returns (rollout, d0, gains, consts, schedule)."""
    ccfg = ctrl_lib.ControllerConfig(forces=forces, postural=postural, **(controller or {}))
    if task not in references.TASKS:
        raise ValueError(f"unknown task {task!r}; valid tasks: {list(references.TASKS)}")
    if contact_set is not None and forces != "qp":
        raise ValueError("a general contact set needs forces='qp' (friction cones at every contact)")
    d0 = rollout_lib.initial_data(robot, qpos)
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
    rollout = rollout_lib.make_rollout(robot, schedule, ccfg, cfg, resolved, contact_set)
    return rollout, d0, gains, consts, schedule


def load_scenario(robot_name: str, tasks_file=None):
    """Robot, motion tasks, contact set and initial posture of a specification file.

    Returns ``(robot, stack, contact_set, qpos)``: without a file (or without ``contacts`` in it)
    the robot is the plain model and contact_set None (the two feet); with ``contacts`` the robot
    is the scene of :func:`wbc_jax.contacts.build_scene` (objects, collision spheres, pairs)."""
    from wbc_jax import contacts as contacts_lib

    robot = model.load_robot(robot_name)
    if not tasks_file:
        return robot, None, None, None
    spec = tasks_lib.load_spec_file(tasks_file)
    qpos = tasks_lib.initial_qpos(robot, spec["initial_posture_deg"])
    contact_set = None
    if spec["contacts"] is not None:
        robot, contact_set = contacts_lib.build_scene(robot_name, spec["contacts"], spec["scene"], qpos)
    elif spec["scene"]:
        raise ValueError(f"{tasks_file}: scene objects need a 'contacts' list (what touches them)")
    return robot, spec["tasks"], contact_set, qpos


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


def contact_tracking(cset, traj: dict, after: float = 1.0) -> dict:
    """Per contact of a general set, over the ticks after ``after`` s: the measured (MuJoCo) and
    commanded normal forces (median, N) and, where a normal force is desired, the max and median of
    |measured - desired|; and the max slip of the contact point (m)."""
    sel = traj["t"] >= min(after, 0.5 * float(traj["t"][-1]))
    out = {}
    for k, (c, sl) in enumerate(zip(cset.contacts, cset.slices(), strict=True)):
        n = traj["contact_normal"][sel, k]
        meas = np.einsum("ti,ti->t", traj["f_meas"][sel, sl.start : sl.start + 3], n)
        cmd = np.einsum("ti,ti->t", traj["f_cmd"][sel, sl.start : sl.start + 3], n)
        entry = {"normal_force_meas_median_n": float(np.median(meas)),
                 "normal_force_cmd_median_n": float(np.median(cmd))}  # fmt: skip
        if math.isfinite(c.normal_force):
            desired = c.normal_force * traj["activation"][sel, k]
            entry["normal_force_desired_n"] = c.normal_force
            entry["normal_force_err_max_n"] = float(np.max(np.abs(meas - desired)))
            entry["normal_force_err_median_n"] = float(np.median(np.abs(meas - desired)))
        p = traj["feet_pos"][:, k]
        entry["max_drift_m"] = float(np.max(np.linalg.norm(p - p[0], axis=1)))
        out[c.name] = entry
    return out


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
      tasks_file: task/contact specification (JSON/YAML, :func:`wbc_jax.tasks.load_spec_file`).
      control_dt: controller period in s, a multiple of the 1 ms physics step (None: 0.01).

    Returns:
      the metrics dict (also printed by the CLI as one JSON line).
    """
    robot, stack, contact_set, qpos = load_scenario(robot_name, tasks_file)
    gains = ctrl_lib.load_gains(gains_file, robot.index.n) if gains_file else None
    rollout, d0, gains, consts, schedule = setup(
        robot, task, duration=duration, forces=forces, postural=postural, gains=gains,
        sim={**({} if solver_iterations is None else {"solver_iterations": int(solver_iterations)}),
             **({} if control_dt is None else {"control_dt": float(control_dt)})},
        stack=stack, contact_set=contact_set, qpos=qpos,
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
    if contact_set is not None:
        result["contacts"] = contact_tracking(contact_set, traj)
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
            if contact_set is None:
                plots.contact_forces(traj, out / "contact_forces.png", title)
            else:
                plots.contact_normal_forces(traj, list(contact_set.names),
                                            [c.dim for c in contact_set.contacts], out / "contact_forces.png", title)
            plots.joint_torques(traj, list(robot.index.joints), out / "torques.png", title)
    return result


def main_json_line(result: dict) -> str:
    return json.dumps(result, separators=(",", ":"))
