"""The gain-tuning problem shared by gradient tuning and its baselines.

    TuneConfig --sample_pushes--> Scenario batch (B,) --objective--> loss (), terms (B,), Metrics (B,)

* the push distribution (:func:`sample_pushes`): azimuth uniform over 360 deg, impulse a
  uniform multiple (``magnitude_range``) of the default gains' envelope or of the feet-in-place
  LIP bound (``push_scale``) in that direction, pushed body among ``train_bodies``, duration
  uniform in ``duration_range``, floor friction, plant mass scale and initial joint noise; batch k of a stream is drawn from ``default_rng([seed, stream,
  k])``, so a resumed run draws the same pushes;
* the tuned parameters and their controls (:class:`Problem`: plain gains, or a
  :class:`~wbc_jax.tuning.algorithms.schedule.GainSchedule` with ``parameterisation == "scheduled"``);
* the differentiable objectives on MJX's JAX implementation (:func:`make_batched_loss`: one gain
  set over B pushes; :func:`make_env_objective`: one push), with the loss of
  :mod:`wbc_jax.tuning.algorithms.loss`. The forward objectives of the searches, on any MJX engine, and the
  sharded gradient programs are in :mod:`wbc_jax.tuning.algorithms.objectives`.

Shapes: ``B`` pushes, ``P`` candidates, ``n = 23`` joints, T ticks.
"""

from __future__ import annotations

import dataclasses
import hashlib

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control.gains import Gains, default_gains, load_gains
from wbc_jax.core import constants, loader
from wbc_jax.jobs import sweep_table
from wbc_jax.robot import model as model_lib
from wbc_jax.sim import executables, mjx_loop, physics, scenario
from wbc_jax.sim import loop as loop_lib
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim.state import Push, Scenario, SimConfig
from wbc_jax.tuning.algorithms import loss as tuning_loss
from wbc_jax.tuning.algorithms import params as tuning_params
from wbc_jax.tuning.algorithms import schedule as gain_schedule
from wbc_jax.tuning.config import NOT_TRAINING, TuneConfig, config_key

# ---------------------------------------------------------------------------------------------
# The push distribution


def load_envelope(path) -> tuple[np.ndarray, np.ndarray]:
    """(azimuths (K,) deg, impulses (K,) N s) of an envelope file: {"azimuth_deg": [...],
    "impulse_ns": [...]}, or the summary.json of ``wbc-jax envelope`` (gain set 0)."""
    try:
        data = loader.read_json(path, "envelope")
    except OSError as err:
        raise ValueError(f"envelope file {path} is unreadable: {err}") from None
    try:  # a summary.json of another job, or any other JSON: named, never a traceback
        if "envelope" in data and "azimuth_deg" not in data:
            env = data["envelope"].get("0", data["envelope"].get(0, {}))
            az = np.array([float(a) for a in env], float)
            imp = np.array([e["impulse_ns"] for e in env.values()], float)
        else:
            az, imp = np.asarray(data.get("azimuth_deg", []), float), np.asarray(data.get("impulse_ns", []), float)
    except (AttributeError, KeyError, TypeError, ValueError):
        az = imp = np.zeros(0)
    if az.size == 0 or az.shape != imp.shape or not np.all(np.isfinite(imp)) or np.any(imp <= 0):
        raise ValueError(
            f"envelope file {path}: needs matching azimuth_deg and positive impulse_ns lists, "
            "or the summary.json of wbc-jax envelope"
        )
    order = np.argsort(az % 360.0)
    return az[order] % 360.0, imp[order]


def envelope_table(tc: TuneConfig, robot: model_lib.Robot) -> tuple[np.ndarray, np.ndarray]:
    """(azimuths (32,) or (K,) deg, impulses N s) that push impulses are scaled by: with
    ``push_scale == "lip"`` the feet-in-place LIP bound over 32 directions; else the default
    envelope per direction: ``tc.envelope``, the robot description's ``default_envelope``, or
    ``envelope_fraction`` x the LIP bound."""
    if tc.push_scale == "lip":
        return _lip_table(robot)
    if tc.envelope is not None:
        return load_envelope(tc.envelope)
    stored = robot.description.asset_path(robot.description.default_envelope)
    if stored is not None and stored.is_file():
        return load_envelope(stored)
    az, bound = _lip_table(robot)
    return az, tc.envelope_fraction * bound


def _lip_table(robot: model_lib.Robot) -> tuple[np.ndarray, np.ndarray]:
    """(azimuths (32,) deg, the feet-in-place LIP bound m omega d (32,) N s)."""
    az = np.arange(32) * 360.0 / 32
    bound = sweep_table.lip_bound(robot, az)
    return az, np.array([bound[float(a)]["impulse_bound_ns"] for a in az])


def interp_periodic(az_table: np.ndarray, values: np.ndarray, az) -> np.ndarray:
    """Linear interpolation over azimuth (deg, period 360) of a table (K,)."""
    xp = np.concatenate([az_table - 360.0, az_table, az_table + 360.0])
    return np.interp(np.asarray(az, float) % 360.0, xp, np.tile(values, 3))


def batch_rng(seed: int, stream: int, k: int) -> np.random.Generator:
    """The generator of batch ``k`` of a stream (0: training, 1: CMA-ES, 2: random search, 3:
    held-out, 4: prediction check): reproducible and independent of what ran before."""
    return np.random.default_rng([int(seed), int(stream), int(k)])


def sample_pushes(
    tc: TuneConfig, robot: model_lib.Robot, table, rng: np.random.Generator, size: int, dtype=np.float32
) -> tuple[Scenario, dict]:
    """``size`` pushes of the training distribution (module docstring): (Scenario with a leading
    axis of ``size`` (its gains are the robot's defaults, unused by the objectives), numpy columns)."""
    n = robot.index.n
    az = rng.uniform(0.0, 360.0, size)
    impulse = rng.uniform(*tc.magnitude_range, size) * interp_periodic(*table, az)
    body = np.array([robot.index.pushable_body_id(b) for b in tc.train_bodies])[
        rng.integers(0, len(tc.train_bodies), size)
    ]
    duration = rng.uniform(*tc.duration_range, size)
    friction, mass = rng.uniform(*tc.friction_range, size), rng.uniform(*tc.mass_range, size)
    offsets = rng.normal(scale=tc.joint_noise, size=(size, n)) if tc.joint_noise else np.zeros((size, n))
    return pushes_at(robot, az, impulse, body, duration, tc.push_onset, friction, mass, offsets, dtype)


def pushes_at(robot, az, impulse, body, duration, onset, friction, mass, offsets, dtype=np.float32):
    """Scenarios (B,) of horizontal pushes: azimuth (B,) deg, impulse (B,) N s, body ids (B,),
    duration (B,) s, onset () s, plant friction and mass scale (B,), joint offsets (B, n)."""
    az, impulse, duration = (np.asarray(x, float) for x in (az, impulse, duration))
    B = az.size
    u = np.stack([np.cos(np.deg2rad(az)), np.sin(np.deg2rad(az)), np.zeros(B)], 1)
    base = default_gains(robot.description)
    scen = Scenario(
        push=Push(
            force=((impulse / duration)[:, None] * u)[:, None, :].astype(dtype),
            onset=np.full((B, 1), onset, dtype),
            duration=duration[:, None].astype(dtype),
            body=np.asarray(body, np.int32).reshape(B, 1),
        ),
        gains=jax.tree_util.tree_map(lambda x: np.broadcast_to(np.asarray(x, dtype), (B,) + np.shape(x)), base),
        joint_offset=np.asarray(offsets, dtype),
        friction=np.asarray(friction, dtype),
        mass_scale=np.asarray(mass, dtype),
    )
    cols = {
        "azimuth_deg": az,
        "impulse_ns": impulse,
        "magnitude_n": impulse / duration,
        "duration_s": duration,
        "body": np.asarray(body),
        "friction": np.asarray(friction, float),
        "mass_scale": np.asarray(mass, float),
    }
    return scen, cols


# ---------------------------------------------------------------------------------------------
# The problem: closed loop with a tuning trace, bounds, objectives


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """What the objectives close over: configs, robot, the tuning loop, the start and bounds of the
    search, the default envelope table, the physics steps of one rollout."""

    tc: TuneConfig
    lc: tuning_loss.LossConfig
    setup: scenario.Setup
    loop: loop_lib.ClosedLoop
    base: Gains
    reg0: np.ndarray
    init: Gains
    bounds: tuning_params.Bounds
    table: tuple
    iterations: int

    @property
    def robot(self) -> model_lib.Robot:
        return self.setup.robot

    @property
    def steps_per_rollout(self) -> int:
        """Physics steps of one rollout (the unit of the simulation budget)."""
        return self.loop.n_ticks * self.loop.n_sub

    @property
    def scheduled(self) -> bool:
        return self.tc.parameterisation == "scheduled"

    def init_params(self) -> dict:
        """The unconstrained start of the search: {group: (k,)}, or for a schedule {"base": {group:
        (k,)}, "weights": {group: (k, F)}} (weights 0: the plain start)."""
        plain = tuning_params.controls_to_params(
            self.init, self.reg0, self.bounds, regularisation=self.tc.tune_regularisation
        )
        return gain_schedule.init_params(plain) if self.scheduled else plain

    @property
    def key(self) -> str:
        """Checkpoints belong to this: the configs and the envelope table the pushes scale with."""
        table = hashlib.sha256(np.asarray(self.table, float).tobytes()).hexdigest()[:8]
        return f"{config_key(self.tc, self.lc, exclude=NOT_TRAINING)}-{table}"

    def program_identity(self, mesh=None) -> tuple:
        """What shapes this problem's compiled programs besides their arguments' shapes (the key parts of
        :func:`wbc_jax.sim.executables.compiled`, which loads a program compiled by an earlier phase or
        process instead of tracing it again): every tuning and loss setting, the loop, the constants the
        objectives close over (start, bounds, envelope table), the tuning code and the device mesh."""
        consts = jax.tree_util.tree_leaves(
            (self.base, self.reg0, self.init, self.bounds.lo, self.bounds.hi, self.table)
        )
        digest = hashlib.sha256(b"".join(np.asarray(x).tobytes() for x in consts)).hexdigest()
        devices = None if mesh is None else (repr(mesh.shape), [str(d) for d in mesh.devices.flat])
        return (
            config_key(self.tc, self.lc, exclude=("out", "phases")),
            self.loop.structure_key,
            digest,
            self.iterations,
            executables.source_digest(("tuning",)),
            devices,
        )

    def regularisation(self, reg) -> np.ndarray:
        """(2,) Reg.pinvDamp, Reg.KP_postural of a controls dict (None: the controller's)."""
        if reg is None:
            return np.asarray(self.reg0, float)
        return np.array([float(reg[k]) for k in tuning_params.REGULARISATION])

    def controls(self, params: dict):
        """(Gains or GainSchedule, regularisation dict or None) of unconstrained params (differentiable)."""
        if self.scheduled:
            origin = np.asarray(self.setup.qpos0[:2], float)
            return gain_schedule.from_params(params, self.bounds, self.base.ki_com, origin), None
        return tuning_params.params_to_controls(params, self.bounds, self.base)


def checkpoint_setting(name: str):
    """The tuning loop's ``remat`` (:func:`wbc_jax.sim.loop.compose`) of a ``--checkpoint`` choice."""
    return {"tick": True, "none": False, "dots": "checkpoint_dots"}[name]


def make_problem(
    tc: TuneConfig,
    lc: tuning_loss.LossConfig | None = None,
    *,
    horizon: float | None = None,
    checkpoint: bool | str | None = None,
    backend: str = "jax",
) -> Problem:
    """Check the inputs (gains file inside the bounds, bodies) and build the tuning closed loop
    (stand task, perturbed plant, a :class:`~wbc_jax.tuning.algorithms.loss.TuneTrace` per tick, the gain
    schedule evaluated at each tick with ``parameterisation == "scheduled"``). ``horizon``: seconds
    (default ``tc.horizon``); ``checkpoint``: the loop's ``remat`` (default from
    ``tc.checkpoint``); ``backend``: the physics engine (gradients need ``jax``)."""
    dtype = scenario.float_dtype()
    robot = model_lib.load_robot(tc.robot)
    # The effort and saturation terms scale each joint's torque by its motor limit (the robot's model).
    lc = (tuning_loss.LossConfig() if lc is None else lc).with_motor_limits(robot.index.torque_limit)
    for b in tc.train_bodies:
        robot.index.pushable_body_id(b)
    base = default_gains(robot.description, dtype)
    reg0 = tuning_params.default_regularisation()
    bounds = tuning_params.default_bounds(base, tc.bound_factor, tc.zeta_range, reg0)
    if tc.keep_tracking:
        bounds = tuning_params.tracking_bounds(
            bounds, base, constants.TRACKING_KP_COM_FLOOR, constants.TRACKING_YAW_FRACTION
        )
    init = base
    if tc.init_gains is not None:
        init = load_gains(tc.init_gains, robot.index.n, dtype)
        tuning_params.check_in_bounds(init, reg0, bounds, source=f"--init-gains {tc.init_gains}")
    table = envelope_table(tc, robot)
    sim = SimConfig(
        record=False,
        push_body=tc.train_bodies[0],
        perturb_plant=True,
        physics=physics.PhysicsConfig(
            backend=backend, solver_iterations=tc.solver_iterations, ls_iterations=tc.ls_iterations
        ),
    )
    st = scenario.setup(
        "stand",
        duration=tc.horizon if horizon is None else horizon,
        sim=sim,
        gains=base,
        controller=tc.controller.config(),
        scene=scenario.load_scene(tc.robot, tc.controller.tasks),
    )
    loop = tuning_loss.tuning_loop(st.loop, checkpoint_setting(tc.checkpoint) if checkpoint is None else checkpoint)
    if tc.parameterisation == "scheduled":
        loop = gain_schedule.scheduled_loop(loop)
    iterations = tc.solver_iterations or int(robot.mj_model.opt.iterations)
    return Problem(
        tc=tc,
        lc=lc,
        setup=st,
        loop=loop,
        base=base,
        reg0=reg0,
        init=init,
        bounds=bounds,
        table=table,
        iterations=iterations,
    )


def with_backend(problem: Problem, backend: str) -> Problem:
    """The same problem on another physics engine (forward objectives: searches, window starts)."""
    if problem.loop.backend == backend:
        return problem
    return make_problem(
        problem.tc, problem.lc, horizon=problem.setup.loop.cfg.duration, checkpoint=False, backend=backend
    )


# The carry seeding of :func:`rollout` (one implementation, shared with the limit job's optimiser).
_touch = mjx_loop.touch


def rollout(loop: loop_lib.ClosedLoop, plant, qpos, gains, push, reg=None, seed=None):
    """:func:`wbc_jax.sim.mjx_loop.rollout` with, when ``seed`` is given (a scalar that varies
    along the vmapped batch and depends on the differentiated parameters), every leaf of the
    initial carry made to depend on it (:func:`wbc_jax.sim.mjx_loop.touch`: the same values, a
    shorter trace)."""
    carry = mjx_loop.start(loop, qpos)
    if reg:
        carry = (carry[0], carry[1].replace(controller=carry[1].controller.replace(**reg)), carry[2])
    if seed is not None:
        carry = mjx_loop.touch(carry, seed)
    (d, state, ok), records = mjx_loop.chunk(loop, plant, gains, push, carry, 0, loop.n_ticks)
    return metrics_lib.final(state.metrics, ok), records


SEED_CARRY = True  # see :func:`rollout`; False: the closed loop's own rollout (measurements)


def rollout_fn(problem: Problem, n_ticks: int | None = None, *, batch: int = 1):
    """env(gains, reg, scen) -> (loss terms {name: ()}, Metrics) of one push on the problem's engine
    (``gains``: a Gains or a GainSchedule; ``batch``: the environments run together, Warp's contact
    buffer). On ``jax`` the carry is seeded (:func:`rollout`, :data:`SEED_CARRY`)."""
    loop, st = problem.loop, problem.setup
    qpos0 = jnp.asarray(st.qpos0, st.dtype)
    nominal = physics.device_model(st.robot.mj_model, loop.backend, loop.cfg.physics)
    seeded = SEED_CARRY and loop.backend == "jax"

    def env(gains, reg, scen):
        plant = physics.plant_model(nominal, scen.friction, scen.mass_scale)
        qpos = loop.initial_qpos(qpos0, scen.joint_offset)
        if seeded:
            seed = scen.friction + sum(jnp.sum(x) for x in jax.tree_util.tree_leaves((gains, reg)))
            metrics, trace = rollout(loop, plant, qpos, gains, scen.push, reg, seed)
        else:
            metrics, trace = mjx_loop.rollout(
                loop, plant, qpos, gains, scen.push, controller_overrides=reg, batch=batch
            )
        return tuning_loss.loss_terms(trace, problem.lc, n_ticks, loop.cfg.control_dt), metrics

    return env


def cast(dtype, tree):
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), tree)


def make_batched_loss(problem: Problem, *, n_ticks: int | None = None, fixed_solver: bool = True):
    """Batched objective of one gain set (unjitted; jit / differentiate it):
    ``fn(gains, reg, scen) -> (objective (), terms {name: (B,)}, Metrics (B,))``; ``reg``:
    {"pinv_damping": (), "kp_postural_reg": ()} or None (the controller's). ``fixed_solver``: MJX's
    solver made reverse-differentiable as ``tc.solver_gradient`` says (False: its own loop, forward
    only). ``n_ticks``: the loss on the first ticks only (prediction checks)."""
    env = rollout_fn(problem, n_ticks)
    dtype = problem.setup.dtype

    def fn(gains, reg, scen):
        gains, reg = cast(dtype, gains), None if reg is None else cast(dtype, reg)
        if fixed_solver:
            with physics.gradient_solver(problem.tc.solver_gradient, problem.iterations):
                terms, metrics = jax.vmap(env, in_axes=(None, None, 0))(gains, reg, scen)
        else:
            terms, metrics = jax.vmap(env, in_axes=(None, None, 0))(gains, reg, scen)
        return tuning_loss.batch_objective(terms["total"], problem.lc), terms, metrics

    return fn


def controls_cast(problem: Problem, params: dict):
    """(Gains or GainSchedule, regularisation dict or None) of unconstrained params, in the closed
    loop's dtype."""
    dtype = problem.setup.dtype
    gains, reg = problem.controls(params)
    return cast(dtype, gains), None if reg is None else cast(dtype, reg)


def make_env_objective(problem: Problem):
    """Objective of one push as a function of the unconstrained parameters (unjitted; the training
    step vmaps its gradient over the batch, so that each rollout's gradient can be checked and
    clipped on its own): ``fn(params {group: (k,)}, scen) -> (objective (), (terms {name: ()},
    Metrics))``. Trace it inside :func:`wbc_jax.sim.physics.gradient_solver` for reverse mode."""
    env = rollout_fn(problem, None)

    def fn(params, scen):
        terms, metrics = env(*controls_cast(problem, params), scen)
        return tuning_loss.env_objective(terms["total"], problem.lc), (terms, metrics)

    return fn


def survival_stats(metrics) -> dict:
    """Strict survival and the lax upright rate of a batch's Metrics (host side)."""
    cols = metrics_lib.summarize(jax.tree_util.tree_map(lambda x: np.asarray(x).reshape(-1), metrics))
    return {
        "survival_rate": float(np.mean(cols["survived"])),
        "upright_rate": float(np.mean(cols["upright"])),
        "qp_infeasible_rate": float(np.mean(np.asarray(cols["qp_infeasible_ticks"]) > 0)),
    }


def constants_used() -> dict:
    """The survival thresholds (for reports)."""
    return dict(constants.SURVIVAL_CRITERION)
