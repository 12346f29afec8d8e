"""The ``balance`` job: one closed-loop run of the controller, with metrics,
trajectory and plots."""

from __future__ import annotations

import dataclasses
import math
import pathlib
import time

import jax
import numpy as np

from wbc_jax.control import references
from wbc_jax.control.controller import ControllerConfig
from wbc_jax.control.flags import ControllerFlags
from wbc_jax.control.gains import gains_to_dict, load_gains
from wbc_jax.core import constants as limits
from wbc_jax.core import io, options, provenance
from wbc_jax.core.options import check_options, flat_dict, nested, option
from wbc_jax.jobs import grids, runs
from wbc_jax.robot.robots import robot_option
from wbc_jax.sim import host_loop, physics, runner, scenario
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim.state import HOST_LOOPS, SimConfig


@dataclasses.dataclass(frozen=True)
class BalanceConfig:
    """A balance run (the CLI flags of ``wbc-jax balance`` are generated from these fields, and
    their declared ranges are checked by :meth:`check`)."""

    robot: str = robot_option()
    task: str = option("stand", "balance task", choices=references.TASKS)
    duration: float | None = option(
        None,
        "seconds (default: the task's: stand 10, sinusoid 20, one-foot 16)",
        gt=0.0,
        le=limits.MAX_HORIZON_S,
        unit="s",
    )
    controller: ControllerFlags = nested(ControllerFlags())
    gains: str | None = option(
        None, "gains JSON file (default: the robot's, wbc_jax/robot/<name>.py)", metavar="FILE", input_file=True
    )
    push_force: tuple[float, float, float] | None = option(
        None,
        "push on the trunk (the robot's 'trunk' body), world axes [N]",
        nargs=3,
        metavar=("FX", "FY", "FZ"),
        ge=-limits.MAX_PUSH_N,
        le=limits.MAX_PUSH_N,
        unit="N",
    )
    push_onset: float = grids.push_onset_option(1.0)
    push_duration: float = grids.push_duration_option()
    control_dt: float = option(
        0.01, "controller period [s], a multiple of the 1 ms physics step", ge=0.001, le=0.1, unit="s"
    )
    solver_iterations: int | None = option(
        None, "contact solver Newton iterations (default: the model's, 4)", ge=1, le=limits.MAX_SOLVER_ITERATIONS
    )
    backend: str = option("auto", "physics engine (auto: C MuJoCo on a CPU, MJX on a GPU)", choices=physics.BACKENDS)
    host_loop: str = option(
        "auto",
        "C MuJoCo engine: the horizon as one compiled program, or a Python loop of ticks (auto: compiled "
        "where the native step builds)",
        choices=HOST_LOOPS,
    )
    out: str | None = option("runs/balance", "output folder")
    plots: bool = option(True, "write PNG plots")

    def check(self) -> None:
        """Every check that compiles nothing: the declared ranges, then what ties the flags together."""
        check_options(self)
        duration = self.duration or references.DEFAULT_DURATIONS[self.task]
        if self.push_force is not None and self.push_onset + self.push_duration >= duration:
            raise ValueError(
                f"the push (--push-onset {self.push_onset:g} + --push-duration {self.push_duration:g} s) "
                f"must end inside the run (--duration {duration:g} s)"
            )
        physics.resolve_backend(self.backend)
        self.controller_config()
        runs.check_output_dir(self.out, "balance", self.fingerprint())

    def fingerprint(self) -> dict:
        # The engine as it resolves here (auto on a CPU is mujoco): the same run whichever was named.
        return runs.fingerprint(
            {**flat_dict(self), "backend": physics.resolve_backend(self.backend)},
            [self.gains, self.controller.tasks],
            self.robot,
        )

    def controller_config(self, base: ControllerConfig | None = None) -> ControllerConfig:
        """``base`` (default: the defaults) with this run's controller settings."""
        return self.controller.config(base)


def default_config() -> BalanceConfig:
    return BalanceConfig()


def make_setup(cfg: BalanceConfig, controller: ControllerConfig | None = None) -> scenario.Setup:
    """Scene, controller and closed loop of a balance run (checked, nothing compiled).
    ``controller``: further controller settings (forces, postural and angular_weight_soft come from
    ``cfg``)."""
    scene = scenario.load_scene(cfg.robot, cfg.controller.tasks)
    dtype = scenario.float_dtype()
    gains = load_gains(cfg.gains, scene.robot.index.n, dtype) if cfg.gains else None
    sim = SimConfig(
        control_dt=cfg.control_dt,
        record=True,
        host_loop=cfg.host_loop,
        physics=physics.PhysicsConfig(backend=cfg.backend, solver_iterations=cfg.solver_iterations),
    )
    return scenario.setup(
        cfg.task,
        duration=cfg.duration,
        controller=cfg.controller_config(controller),
        sim=sim,
        gains=gains,
        scene=scene,
    )


def run(
    cfg: BalanceConfig | None = None, *, progress: bool = True, controller: ControllerConfig | None = None, **overrides
) -> dict:
    """Run the balance job; write metrics.json, trajectory.npz and PNG plots into ``cfg.out``
    (None: nothing written). ``overrides``: fields of :class:`BalanceConfig`; ``controller``:
    further controller settings (hierarchy damping, ...).

    Returns:
      the metrics dict (also printed by the CLI as one JSON line).
    """
    from tqdm.auto import tqdm

    cfg = options.replace(default_config() if cfg is None else cfg, **overrides)
    cfg.check()
    st = make_setup(cfg, controller)
    out = None if cfg.out is None else pathlib.Path(cfg.out)
    if out is not None:
        runs.claim_output_dir(out, "balance", cfg.fingerprint())
    push, push_end = None, 0.0
    if cfg.push_force is not None:
        push = scenario.make_push(cfg.push_force, cfg.push_onset, cfg.push_duration, st.dtype)
        push_end = cfg.push_onset + cfg.push_duration
    loop = st.loop
    start = time.time()
    with tqdm(total=loop.n_ticks, unit="tick", disable=not progress, desc=f"{cfg.task} ({st.backend})") as bar:
        result_run = runner.run(st, scenario.single(st, push), on_tick=lambda k: bar.update(k - bar.n))
    wall = time.time() - start
    metrics = jax.tree_util.tree_map(lambda x: x[0], result_run.metrics)
    traj = {name: np.asarray(v)[0] for name, v in dataclasses.asdict(result_run.records).items()}
    result = {
        "task": cfg.task,
        "forces": cfg.controller.forces,
        "postural": cfg.controller.postural,
        "duration_s": loop.cfg.duration,
        "solver_iterations": int(cfg.solver_iterations or st.robot.mj_model.opt.iterations),
        "control_dt_s": loop.cfg.control_dt,
        "backend": st.backend,
        "host_loop": host_loop.driver(loop) if st.backend == "mujoco" else None,
    }
    result.update(metrics_lib.summarize(metrics, push_end))
    result.update(force_task_error(traj))
    if loop.controller.stack is not None:
        result["tasks"] = task_tracking(loop.controller.stack, traj)
    if st.scene.tasks_file is not None:
        result["contacts"] = contact_tracking(loop.contact_set, traj)
    result["compile_s"] = round(result_run.compile_s, 2)
    result["started_s"] = round(result_run.started - provenance.process_started(), 2)  # process start to first tick
    result["loop_s"] = round(result_run.run_s, 2)
    result["real_time_factor"] = round(loop.cfg.duration / result_run.run_s, 3) if result_run.run_s > 0 else None
    result["wall_time_s"] = round(wall, 2)
    result["device"] = provenance.device_label()
    result = _jsonable(result)
    if out is not None:
        io.atomic_write_json(
            out / "metrics.json",
            {
                **result,
                "gains": gains_to_dict(st.gains),
                "provenance": provenance.record({"gains": cfg.gains, "tasks": cfg.controller.tasks}),
                "config": flat_dict(cfg),
                "controller": dataclasses.asdict(st.loop.controller.config),
            },
        )
        io.atomic_save_npz(
            out / "trajectory.npz",
            joints=np.array(st.robot.index.joints),
            contact_names=np.array(loop.contact_set.names),
            contact_dims=np.array([c.dim for c in loop.contact_set.contacts]),
            **traj,
        )
        for name in ("metrics.json", "trajectory.npz"):
            runs.record_output(out / name)
        if cfg.plots:
            from wbc_jax.report import plots  # matplotlib: imported after the simulation

            title = f"{cfg.robot} {cfg.task}, forces={cfg.controller.forces}, postural={cfg.controller.postural}"
            plots.com_tracking(traj, out / "com.png", title)
            plots.contact_forces(
                traj,
                list(loop.contact_set.names),
                [c.dim for c in loop.contact_set.contacts],
                out / "contact_forces.png",
                title,
            )
            plots.joint_torques(traj, list(st.robot.index.joints), out / "torques.png", title)
    return result


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (np.generic, np.ndarray)):
        value = value.item() if np.ndim(value) == 0 else value.tolist()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


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
    """How well the simulator's contact wrenches realise the commanded ones (ticks after ``after``
    s): median and 95th percentile over ticks of |f_meas - f_cmd| / |f_cmd| (all contacts
    stacked) and the median momentum-rate error |Ldot_meas - Ldot*| (N)."""
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
    """Per contact, over the ticks after ``after`` s: the measured (simulator) and commanded normal
    forces (median, N) and, where a normal force is desired, the max and median of
    |measured - desired|; and the max drift of the contact point (m)."""
    sel = traj["t"] >= min(after, 0.5 * float(traj["t"][-1]))
    out = {}
    for k, (c, sl) in enumerate(zip(cset.contacts, cset.slices(), strict=True)):
        n = traj["contact_normal"][sel, k]
        meas = np.einsum("ti,ti->t", traj["f_meas"][sel, sl.start : sl.start + 3], n)
        cmd = np.einsum("ti,ti->t", traj["f_cmd"][sel, sl.start : sl.start + 3], n)
        entry = {
            "normal_force_meas_median_n": float(np.median(meas)),
            "normal_force_cmd_median_n": float(np.median(cmd)),
        }
        if math.isfinite(c.normal_force):
            desired = c.normal_force * traj["activation"][sel, k]
            entry["normal_force_desired_n"] = c.normal_force
            entry["normal_force_err_max_n"] = float(np.max(np.abs(meas - desired)))
            entry["normal_force_err_median_n"] = float(np.median(np.abs(meas - desired)))
        p = traj["contact_pos"][:, k]
        entry["max_drift_m"] = float(np.max(np.linalg.norm(p - p[0], axis=1)))
        out[c.name] = entry
    return out
