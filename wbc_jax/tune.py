"""[experiments] Gradient-based gain tuning through the differentiable closed loop (issue 5).

The pipeline (brax-APG shape)::

    params --(bounded map)--> Gains --vmap(rollout with a LossTrace)--> smooth loss
           <--(adam, clipped, NaN-guarded)-- grad

Differentiation: reverse mode (``jax.value_and_grad``) through the whole ``lax.scan`` of the
closed loop: MJX physics with the model's contact solver (Newton, 4 iterations), 4 corner spheres
per foot (foot boxes gave NaN gradients, measured.md), the contact QP through its implicit
(custom_jvp, transposed) derivative, and ``jax.checkpoint`` on each 10 ms control tick, so memory
grows with the horizon only by one carry per tick. Forward mode would cost one pass per gain (52
of them); reverse mode costs one backward pass for all of them.

MJX's Newton loop is a ``lax.while_loop`` (not reverse-differentiable) unless iterations == 1.
Measured here: with iterations = 1 the closed loop is chaotic (float64, 0.35 s after a 50 N push:
the loss went 50.2 -> 1.2 when kp_com changed by 1e-6 relative; contact chatter, saturated
torques), while with 4 iterations it is smooth (0.04611 -> 0.04611). So, while the tuning
program is traced, :func:`wbc_jax.physics.fixed_iteration_solver` swaps that one ``while_loop``
for MJX's own scan-based ``_while_loop_scan`` with the same iteration bound: identical values
(the scan does no-ops once the loop condition is false), reverse-differentiable.

The loss is smooth in the gains wherever the contact set does not switch: a running mean of the
CoM tracking error, the torque effort and two fall surrogates (capture point outside the
feet's bounding box, CoM height drop), with weights in :class:`LossConfig`. The Metrics of the
rollout (max / flags) are used for evaluation only.

Shapes: ``B`` scenarios per batch, ``T`` control ticks, ``n = 23`` joints, ``F = 8`` foot
contact spheres, ``P`` tuned parameters (52).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import math
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax import io, physics, runs, scenario, sweep
from wbc_jax import model as model_lib
from wbc_jax import rollout as rollout_lib
from wbc_jax.constants import GAIN_FIELDS, GRAVITY
from wbc_jax.gains import Gains, default_gains, gains_to_dict
from wbc_jax.types import Array, option, pytree_dataclass

# Tuned gain groups; ki_com stays at its WBC value (0: no CoM integral) and is not tuned.
TUNED_FIELDS = ("kp_com", "kd_com", "kp_ang", "ki_ang", "kp_postural", "kd_postural")


# ---------------------------------------------------------------------------------------------
# Bounded parameterisation


@pytree_dataclass
class GainBounds:
    """Per-entry bounds of the tuned gains: lo/hi dicts {field: (k,)} with 0 < lo < hi."""

    lo: dict
    hi: dict


def default_bounds(base: Gains, factor: float = 4.0) -> GainBounds:
    """Bounds [base / factor, base * factor] for each tuned gain (per axis / per joint)."""
    if not factor > 1.0:
        raise ValueError(f"bound factor must be > 1, got {factor}")
    lo = {k: jnp.asarray(getattr(base, k)) / factor for k in TUNED_FIELDS}
    hi = {k: jnp.asarray(getattr(base, k)) * factor for k in TUNED_FIELDS}
    for k in TUNED_FIELDS:
        if not np.all(np.asarray(lo[k]) > 0):
            raise ValueError(f"tuned gain {k} must be positive in the base gains to be bounded")
    return GainBounds(lo=lo, hi=hi)


def params_to_gains(params: dict, bounds: GainBounds, base: Gains) -> Gains:
    """Unconstrained params {field: (k,)} -> Gains, each tuned entry in (lo, hi).

    gain = exp(log lo + sigmoid(p) (log hi - log lo)): positive, bounded, log-scaled (a gain
    doubles as easily as it halves); with symmetric bounds p = 0 is the geometric mid-point."""
    out = {}
    for k in GAIN_FIELDS:
        if k in TUNED_FIELDS:
            llo, lhi = jnp.log(bounds.lo[k]), jnp.log(bounds.hi[k])
            out[k] = jnp.exp(llo + jax.nn.sigmoid(params[k]) * (lhi - llo))
        else:
            out[k] = jnp.asarray(getattr(base, k))
    return Gains(**out)


def gains_to_params(gains: Gains, bounds: GainBounds) -> dict:
    """Inverse of :func:`params_to_gains` (gains clipped strictly inside the bounds)."""
    out = {}
    for k in TUNED_FIELDS:
        llo, lhi = jnp.log(bounds.lo[k]), jnp.log(bounds.hi[k])
        u = (jnp.log(jnp.asarray(getattr(gains, k))) - llo) / (lhi - llo)
        u = jnp.clip(u, 1e-6, 1 - 1e-6)
        out[k] = jnp.log(u) - jnp.log1p(-u)
    return out


# ---------------------------------------------------------------------------------------------
# Smooth loss


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Weights and scales of the smooth objective (per tick, averaged over ticks and scenarios).

    Attributes:
      w_com: weight of |CoM - CoM_ref|^2 / com_scale^2.
      w_effort: weight of mean_j (tau_j / torque_scale)^2.
      w_capture: weight of sum over the 4 sides of relu(-margin)^2 / capture_scale^2, margin of
        the instantaneous capture point xi = x + v / omega inside the xy bounding box of the foot
        contact spheres (feet in place: xi outside means a LIP cannot stop).
      w_height: weight of relu(height_frac h0 - h)^2 / capture_scale^2 (CoM dropping).
    """

    w_com: float = 1.0
    w_effort: float = 0.1
    w_capture: float = 1.0
    w_height: float = 1.0
    com_scale: float = 0.02
    torque_scale: float = 60.0
    capture_scale: float = 0.02
    height_frac: float = 0.9

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"LossConfig.{f.name} must be finite and >= 0, got {v}")
        for name in ("com_scale", "torque_scale", "capture_scale", "height_frac"):
            if not getattr(self, name) > 0:
                raise ValueError(f"LossConfig.{name} must be positive")


def loss_terms(trace: rollout_lib.LossTrace, lc: LossConfig) -> dict:
    """Per-scenario loss terms (each a scalar, mean over the T ticks) from one LossTrace.

    Args: trace: fields (T, ...) as emitted by the rollout. Returns {com, effort, capture,
    height, total}, each ()."""
    err = trace.com - trace.com_ref  # (T, 3)
    com = jnp.mean(jnp.sum(err**2, -1)) / lc.com_scale**2
    effort = jnp.mean((trace.tau / lc.torque_scale) ** 2)
    h0 = trace.com_height0  # (T,)
    omega = jnp.sqrt(GRAVITY / h0)[:, None]
    xi = trace.com[:, :2] + trace.com_vel[:, :2] / omega  # (T, 2)
    lo, hi = jnp.min(trace.support_xy, 1), jnp.max(trace.support_xy, 1)  # (T, 2)
    margins = jnp.concatenate([xi - lo, hi - xi], -1)  # (T, 4)
    capture = jnp.mean(jnp.sum(jax.nn.relu(-margins) ** 2, -1)) / lc.capture_scale**2
    height = jnp.mean(jax.nn.relu(lc.height_frac * h0 - trace.com[:, 2]) ** 2) / lc.capture_scale**2
    total = lc.w_com * com + lc.w_effort * effort + lc.w_capture * capture + lc.w_height * height
    return {"com": com, "effort": effort, "capture": capture, "height": height, "total": total}


# ---------------------------------------------------------------------------------------------
# Scenarios and batched, differentiable rollouts


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """A tuning run (defaults: a few minutes on a 2-core CPU); the CLI flags of ``wbc-jax tune``
    are generated from these fields.

    Attributes:
      steps: optimiser steps. batch: scenarios per step. horizon: s per rollout.
      seed: seeds the training scenario pool and the minibatches.
      lr: adam learning rate (on the unconstrained params). clip_norm: global-norm clipping.
      bound_factor: gains stay within [default / f, default * f].
      train_magnitudes (N) x train_directions (deg): the training pool; push_onset/duration (s).
      joint_noise: std (rad) of the initial joint offsets of the pool.
      solver_iterations / eval_solver_iterations: MJX contact solver iterations in training /
        held-out evaluation (None: the model's 4, as in push sweeps; see the module docstring).
      eval_magnitudes x eval_directions, eval_seed: the held-out set (disjoint from training).
      eval_horizon: s per held-out rollout. baseline: run the random-search baseline.
    """

    out: str = option("runs/tune", "output folder (resumes a run there)")
    steps: int = option(12, "optimiser steps")
    batch: int = option(4, "push scenarios per step")
    horizon: float = option(1.0, "seconds per training rollout")
    seed: int = option(0, "training scenarios seed")
    lr: float = option(0.1, "adam learning rate")
    clip_norm: float = option(1.0, "global-norm gradient clipping")
    bound_factor: float = option(4.0, "gains stay within [default / f, default * f]")
    train_magnitudes: tuple[float, ...] = option((50.0, 70.0, 90.0), "training push forces [N]", nargs="+")
    train_directions: tuple[float, ...] = option(
        (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0), "training push azimuths [deg]", nargs="+"
    )
    push_onset: float = option(0.2, "push start [s]")
    push_duration: float = option(0.1, "push length [s]")
    joint_noise: float = option(0.01, "initial joint noise std [rad]")
    solver_iterations: int | None = option(None, "contact solver iterations in training (default: the model's)")
    eval_solver_iterations: int | None = option(None, "contact solver iterations in evaluation")
    eval_magnitudes: tuple[float, ...] = option((55.0, 65.0, 80.0, 95.0), "held-out push forces [N]", nargs="+")
    eval_directions: tuple[float, ...] = option((22.5, 112.5, 202.5, 292.5), "held-out push azimuths [deg]", nargs="+")
    eval_seed: int = option(1000, "held-out scenarios seed")
    eval_horizon: float = option(1.5, "seconds per held-out rollout")
    baseline: bool = option(True, "run the random-search baseline")

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        for name in ("steps", "batch"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"--{name} must be a whole number >= 1, got {value!r}")
        for name in ("horizon", "lr", "clip_norm", "eval_horizon", "push_duration"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"--{name.replace('_', '-')} must be positive and finite, got {v!r}")
        if not (math.isfinite(self.push_onset) and self.push_onset >= 0):
            raise ValueError(f"--push-onset must be >= 0, got {self.push_onset}")
        if not self.bound_factor > 1.0:
            raise ValueError(f"--bound-factor must be > 1, got {self.bound_factor}")
        if self.horizon <= self.push_onset + self.push_duration:
            raise ValueError(f"--horizon {self.horizon} s must end after the push "
                             f"({self.push_onset} + {self.push_duration} s)")  # fmt: skip
        if self.eval_horizon <= self.push_onset + self.push_duration:
            raise ValueError(f"--eval-horizon {self.eval_horizon} s must end after the push")
        if self.batch > len(self.train_magnitudes) * len(self.train_directions):
            raise ValueError(f"--batch {self.batch} is larger than the training pool "
                             f"({len(self.train_magnitudes)} magnitudes x {len(self.train_directions)} directions)")  # fmt: skip
        train = {(m, d) for m in self.train_magnitudes for d in self.train_directions}
        held = {(m, d) for m in self.eval_magnitudes for d in self.eval_directions}
        if train & held:
            raise ValueError(f"held-out scenarios overlap the training ones: {sorted(train & held)}")

    def sweep_config(self, held_out: bool = False) -> sweep.SweepConfig:
        """The push scenarios as a :class:`sweep.SweepConfig` (training pool or held-out set)."""
        return sweep.SweepConfig(
            magnitudes=self.eval_magnitudes if held_out else self.train_magnitudes,
            directions=self.eval_directions if held_out else self.train_directions,
            push_onset=self.push_onset, push_duration=self.push_duration,
            joint_noise=self.joint_noise, seed=self.eval_seed if held_out else self.seed,
            horizon=self.eval_horizon if held_out else self.horizon,
            solver_iterations=self.eval_solver_iterations if held_out else self.solver_iterations,
            backend="jax", out=None,
        )  # fmt: skip


def default_config() -> TuneConfig:
    return TuneConfig()


def make_batched_loss(robot_name: str, scfg: sweep.SweepConfig, lc: LossConfig, *, checkpoint: bool = True,
                      controller=None):  # fmt: skip
    """Differentiable batched objective (unjitted; the caller jits / differentiates).

    Returns ``fn(gains, scen, regularisation=None) -> (loss (), terms {name: (B,)}, Metrics with
    a (B,) axis)``: the closed loop of the sweep's environments (joint offsets, per-env plant)
    vmapped over the Scenario batch (its ``gains`` field is ignored; ``gains`` is shared), with a
    LossTrace, on MJX's JAX implementation. ``regularisation``: optional ``{"pinv_damping": (),
    "kp_postural_reg": ()}`` overriding the controller's Reg.pinvDamp and Reg.KP_postural
    (differentiable). ``controller``: further controller settings (a ControllerConfig)."""
    st = sweep.make_setup(scfg, robot_name=robot_name, loss_trace=True, checkpoint=checkpoint, controller=controller)
    loop = st.loop
    dtype = st.dtype
    qpos0 = jnp.asarray(st.qpos0, dtype)
    nominal = physics.device_model(st.robot.mj_model, "jax", loop.cfg.physics)
    iterations = scfg.solver_iterations or int(st.robot.mj_model.opt.iterations)

    def env(gains, regularisation, scen):
        plant = physics.plant_model(nominal, scen.friction, scen.mass_scale) if loop.cfg.perturb_plant else nominal
        metrics, trace = loop.rollout(plant, loop.initial_qpos(qpos0, scen.joint_offset), gains, scen.push,
                                      controller_overrides=regularisation)  # fmt: skip
        return loss_terms(trace, lc), metrics

    def fn(gains, scen, regularisation=None):
        gains = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), gains)
        reg = None if regularisation is None else {k: jnp.asarray(v, dtype) for k, v in regularisation.items()}
        with physics.fixed_iteration_solver(iterations):
            terms, metrics = jax.vmap(env, in_axes=(None, None, 0))(gains, reg, scen)
        return jnp.mean(terms["total"]), terms, metrics

    return fn


def select(scen: rollout_lib.Scenario, rows: np.ndarray) -> rollout_lib.Scenario:
    """Rows of a Scenario batch (numpy indexing)."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[rows], scen)


# ---------------------------------------------------------------------------------------------
# Optimiser with a NaN guard


def make_optimizer(lr: float, clip_norm: float):
    """adam after global-norm clipping; non-finite gradients are skipped and counted.

    ``optax.apply_if_finite`` leaves params and adam state unchanged on a NaN/inf gradient and
    counts it (``notfinite_count``, ``total_notfinite``)."""
    import optax

    return optax.apply_if_finite(
        optax.chain(optax.clip_by_global_norm(clip_norm), optax.adam(lr)), max_consecutive_errors=10**9
    )


def skipped_count(opt_state) -> int:
    """Total number of skipped (non-finite) gradients so far."""
    return int(opt_state.total_notfinite)


def make_train_step(loss_fn, bounds: GainBounds, base: Gains, optimizer):
    """One optimiser step, jitted: (params, opt_state, scen) -> (params, opt_state, loss,
    terms {name: ()}, grad_norm, finite)."""
    import optax

    def objective(params, scen):
        loss, terms, _ = loss_fn(params_to_gains(params, bounds, base), scen)
        return loss, jax.tree_util.tree_map(jnp.mean, terms)

    @jax.jit
    def step(params, opt_state, scen):
        (loss, terms), grad = jax.value_and_grad(objective, has_aux=True)(params, scen)
        finite = jnp.all(jnp.asarray([jnp.all(jnp.isfinite(g)) for g in jax.tree_util.tree_leaves(grad)]))
        updates, opt_state = optimizer.update(grad, opt_state, params)
        params = optax.apply_updates(params, updates)
        return params, opt_state, loss, terms, optax.global_norm(grad), finite

    return step


# ---------------------------------------------------------------------------------------------
# Training loop: checkpoint/resume, history CSV, progress bar

HISTORY_COLUMNS = ("step", "loss", "com", "effort", "capture", "height", "grad_norm", "finite",
                   "skipped_total", "step_s", "rss_mb")  # fmt: skip


def _rss_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def minibatches(tc: TuneConfig, pool_size: int) -> np.ndarray:
    """(steps, batch) row indices into the training pool: seeded, without replacement per step."""
    rng = np.random.default_rng(tc.seed + 1)
    return np.stack([rng.choice(pool_size, tc.batch, replace=False) for _ in range(tc.steps)])


def _write_history(path: pathlib.Path, rows: list) -> None:
    import io as _io

    buf = _io.StringIO()
    w = csv.DictWriter(buf, fieldnames=HISTORY_COLUMNS)
    w.writeheader()
    w.writerows(rows)
    io.atomic_write_bytes(path, buf.getvalue().encode())


def _save_checkpoint(path: pathlib.Path, state, step: int, key: str) -> None:
    leaves = jax.tree_util.tree_leaves(state)
    io.atomic_save_npz(path, step=np.asarray(step), key=np.asarray(key),
                       **{f"leaf_{i:04d}": np.asarray(x) for i, x in enumerate(leaves)})  # fmt: skip


def _load_checkpoint(path: pathlib.Path, like, key: str):
    import zipfile

    try:
        with np.load(path) as z:
            stored = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise ValueError(f"{path} is unreadable ({err}); remove it to restart the tuning run") from None
    if "key" not in stored or str(stored["key"]) != key:
        raise ValueError(f"{path} belongs to another tuning config; use another --out")
    treedef = jax.tree_util.tree_structure(like)
    like_leaves = jax.tree_util.tree_leaves(like)
    try:
        leaves = [jnp.asarray(stored[f"leaf_{i:04d}"], dtype=jnp.asarray(x).dtype) for i, x in enumerate(like_leaves)]
    except KeyError as err:
        raise ValueError(f"{path} lacks {err}; remove it to restart the tuning run") from None
    return jax.tree_util.tree_unflatten(treedef, leaves), int(stored["step"])


def config_key(tc: TuneConfig, lc: LossConfig) -> str:
    import hashlib

    blob = json.dumps({"tune": dataclasses.asdict(tc), "loss": dataclasses.asdict(lc)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def train(robot: model_lib.Robot, tc: TuneConfig, lc: LossConfig, out, *, progress: bool = True,
          step_fn=None):  # fmt: skip
    """Gradient tuning into ``out``: checkpoint.npz (resumable), history.csv, tuned_gains.json.

    Returns (tuned Gains, history rows, {compile_s, XLA memory analysis of the step in MiB})."""
    from tqdm.auto import tqdm

    out = pathlib.Path(out)
    base = default_gains(robot.index.n)
    bounds = default_bounds(base, tc.bound_factor)
    pool, _ = sweep.build_scenarios(tc.sweep_config(), base, robot.index.n, scenario.float_dtype())
    batches = minibatches(tc, int(np.asarray(pool.friction).shape[0]))
    optimizer = make_optimizer(tc.lr, tc.clip_norm)
    params = gains_to_params(base, bounds)
    state = (params, optimizer.init(params))
    key = config_key(tc, lc)
    ckpt, hist_path = out / "checkpoint.npz", out / "history.csv"
    start, rows = 0, []
    if ckpt.exists():
        state, start = _load_checkpoint(ckpt, state, key)
        with open(hist_path) as fh:
            rows = list(csv.DictReader(fh))[:start]
    if step_fn is None:
        step_fn = make_train_step(make_batched_loss(robot.index.robot, tc.sweep_config(), lc), bounds, base, optimizer)
    compile_s, memory = 0.0, {}
    if start < tc.steps and hasattr(step_fn, "lower"):  # ahead-of-time: compile timed apart
        t0 = time.perf_counter()
        compiled = step_fn.lower(*state, select(pool, batches[start])).compile()
        compile_s = time.perf_counter() - t0
        ma = compiled.memory_analysis()
        if ma is not None:
            memory = {"temp_mb": ma.temp_size_in_bytes / 2**20, "argument_mb": ma.argument_size_in_bytes / 2**20,
                      "output_mb": ma.output_size_in_bytes / 2**20}  # fmt: skip
        step_fn = compiled
    with tqdm(total=tc.steps, initial=start, unit="step", disable=not progress) as bar:
        for k in range(start, tc.steps):
            scen = select(pool, batches[k])
            t0 = time.perf_counter()
            params, opt_state, loss, terms, gnorm, finite = step_fn(*state, scen)
            jax.block_until_ready(params)
            dt = time.perf_counter() - t0
            state = (params, opt_state)
            rows.append({"step": k, "loss": float(loss), **{n: float(terms[n]) for n in
                         ("com", "effort", "capture", "height")}, "grad_norm": float(gnorm),
                         "finite": bool(finite), "skipped_total": skipped_count(opt_state),
                         "step_s": round(dt, 3), "rss_mb": round(_rss_mb(), 1)})  # fmt: skip
            _save_checkpoint(ckpt, state, k + 1, key)
            _write_history(hist_path, rows)
            bar.set_postfix(loss=f"{float(loss):.4g}", skipped=skipped_count(opt_state))
            bar.update(1)
    tuned = params_to_gains(state[0], bounds, base)
    io.atomic_write_json(out / "tuned_gains.json", gains_to_dict(tuned))
    return tuned, rows, {"compile_s": round(compile_s, 2), **memory}


# ---------------------------------------------------------------------------------------------
# Gradient-free baseline and held-out evaluation


def random_search(robot, tc: TuneConfig, lc: LossConfig, *, sigma: float = 0.5, progress: bool = True):
    """(1+1) random search (hill climbing) in the same bounded parameter space, with the same
    rollout budget as :func:`train` (steps x batch): ``steps`` candidates (the first is the
    default), each scored on the same ``batch`` training scenarios (the first minibatch).

    Returns (best Gains, list of (candidate, loss, best_so_far))."""
    from tqdm.auto import tqdm

    base = default_gains(robot.index.n)
    bounds = default_bounds(base, tc.bound_factor)
    pool, _ = sweep.build_scenarios(tc.sweep_config(), base, robot.index.n, scenario.float_dtype())
    scen = select(pool, minibatches(tc, int(np.asarray(pool.friction).shape[0]))[0])
    loss_fn = make_batched_loss(robot.index.robot, tc.sweep_config(), lc, checkpoint=False)
    f = jax.jit(lambda p, s: loss_fn(params_to_gains(p, bounds, base), s)[0])
    rng = np.random.default_rng(tc.seed + 2)
    best = gains_to_params(base, bounds)
    best_loss, log = math.inf, []
    for k in tqdm(range(tc.steps), disable=not progress, unit="cand"):
        cand = best if k == 0 else {n: v + sigma * rng.standard_normal(v.shape) for n, v in best.items()}
        loss = float(f(cand, scen))
        if math.isfinite(loss) and loss < best_loss:
            best, best_loss = cand, loss
        log.append((k, loss, best_loss))
    return params_to_gains(best, bounds, base), log


def evaluate(robot, tc: TuneConfig, lc: LossConfig, gain_sets: dict) -> dict:
    """Held-out evaluation of named gain sets on ``tc.sweep_config(held_out=True)``.

    The closed loop of a push sweep (model's solver, joint offsets, per-env plant), with the
    smooth objective computed alongside; survival and envelope from ``rollout.summarize`` +
    ``sweep.summarize_table``. Returns {name: {objective, survival_rate, envelope, com_rmse_m,
    effort_rms_nm, peak_torque_nm, ...}}."""
    import pandas as pd

    scfg = tc.sweep_config(held_out=True)
    base = default_gains(robot.index.n)
    scen, cols = sweep.build_scenarios(scfg, base, robot.index.n, scenario.float_dtype())
    f = jax.jit(make_batched_loss(robot.index.robot, scfg, lc, checkpoint=False))
    push_end = scfg.push_onset + scfg.push_duration
    results = {}
    for name, gains in gain_sets.items():
        t0 = time.perf_counter()
        loss, terms, metrics = f(gains, scen)
        mcols = rollout_lib.summarize(metrics, push_end)
        table = pd.DataFrame({**cols, **mcols})
        summary = sweep.summarize_table(table, scfg, robot)
        results[name] = {
            "objective": float(loss),
            **{f"objective_{k}": float(np.mean(v)) for k, v in terms.items() if k != "total"},
            "survival_rate": summary["survival_rate"],
            "n_envs": summary["n_envs"],
            "nan_envs": summary["nan_envs"],
            "envelope_largest_survived_impulse_ns": {
                str(az): e["largest_survived_impulse_ns"] for az, e in summary["envelope"].items()},
            "envelope_mean_impulse_ns": float(np.mean(
                [e["largest_survived_impulse_ns"] for e in summary["envelope"].values()])),
            "com_rmse_m": float(np.mean(mcols["com_rmse_m"])),
            "effort_rms_nm": float(np.mean(np.sqrt(np.asarray(terms["effort"])) * lc.torque_scale)),
            "max_abs_torque_nm": float(np.mean(mcols["max_abs_torque_nm"])),
            "upright_rate": summary["upright_rate"],
            "wall_s": round(time.perf_counter() - t0, 2),
        }  # fmt: skip
    return results


def loss_plot(rows: list, rs_log: list, batch: int, path) -> None:
    """loss.png: gradient-tuning loss per step and the random search's best-so-far, against the
    number of rollouts spent."""
    from matplotlib.figure import Figure  # no pyplot: leaves a notebook's inline backend alone

    fig = Figure(figsize=(6, 3.5))
    ax = fig.subplots()
    ax.plot([(int(r["step"]) + 1) * batch for r in rows], [float(r["loss"]) for r in rows], "o-",
            label="gradient (adam), minibatch loss")  # fmt: skip
    if rs_log:
        ax.plot([(k + 1) * batch for k, _, _ in rs_log], [b for _, _, b in rs_log], "s-",
                label="random search, best so far")  # fmt: skip
    ax.set_xlabel("rollouts")
    ax.set_ylabel("smooth objective")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    pathlib.Path(path).parent.mkdir(parents=True, exist_ok=True)
    buf = __import__("io").BytesIO()
    fig.savefig(buf, dpi=110, format="png")
    io.atomic_write_bytes(pathlib.Path(path), buf.getvalue())


def run(cfg: TuneConfig | None = None, *, lc: LossConfig | None = None, progress: bool = True,
        robot_name: str = "icub", **overrides) -> dict:  # fmt: skip
    """The ``tune`` job: train, gradient-free baseline, held-out evaluation; writes
    tuned_gains.json, history.csv, loss.png, eval.json into ``cfg.out``. Returns eval.json's dict.
    ``overrides``: fields of :class:`TuneConfig`."""
    tc = dataclasses.replace(default_config() if cfg is None else cfg, **overrides)
    baseline = tc.baseline
    out = pathlib.Path(tc.out)
    lc = LossConfig() if lc is None else lc
    runs.check_output_dir(out, "tune")
    robot = model_lib.load_robot(robot_name)
    runs.claim_output_dir(out, "tune", runs.fingerprint({"tune": dataclasses.asdict(tc), "loss": dataclasses.asdict(lc),
                                                         "dtype": str(scenario.float_dtype())}), resume=True)
    t0 = time.perf_counter()
    tuned, rows, compile_info = train(robot, tc, lc, out, progress=progress)
    train_s = time.perf_counter() - t0
    sets = {"default": default_gains(robot.index.n), "gradient": tuned}
    rs_log = []
    if baseline:
        t0 = time.perf_counter()
        sets["random_search"], rs_log = random_search(robot, tc, lc, progress=progress)
        rs_s = time.perf_counter() - t0
        io.atomic_write_json(out / "random_search_gains.json", gains_to_dict(sets["random_search"]))
    loss_plot(rows, rs_log, tc.batch, out / "loss.png")
    t0 = time.perf_counter()
    results = evaluate(robot, tc, lc, sets)
    steady = [float(r["step_s"]) for r in rows]
    report = {
        "held_out": results,
        "improvement_over_default": {
            name: 1.0 - results[name]["objective"] / results["default"]["objective"]
            for name in results if name != "default"},
        "budget_rollouts": {"gradient": tc.steps * tc.batch,
                            "random_search": tc.steps * tc.batch if baseline else 0},
        "gradient_cost": {"horizon_s": tc.horizon, "batch": tc.batch,
                          **{f"xla_{k}": v for k, v in compile_info.items()},
                          "step_s_median": float(np.median(steady)) if steady else None,
                          "peak_rss_mb": max(float(r["rss_mb"]) for r in rows) if rows else None},
        "skipped_nonfinite_gradients": int(rows[-1]["skipped_total"]) if rows else 0,
        "train_s": round(train_s, 1),
        "random_search_s": round(rs_s, 1) if baseline else None,
        "eval_s": round(time.perf_counter() - t0, 1),
        "random_search_log": rs_log,
        "config": {"tune": dataclasses.asdict(tc), "loss": dataclasses.asdict(lc)},
        "device": str(jax.devices()[0]),
        "versions": {"jax": jax.__version__, "mujoco": __import__("mujoco").__version__},
    }  # fmt: skip
    io.atomic_write_json(out / "eval.json", report)
    return report


def report_line(report: dict) -> dict:
    """The one-line JSON summary of a tuning report (the CLI prints it)."""
    keys = ("objective", "survival_rate", "com_rmse_m", "effort_rms_nm")
    return {name: {k: r[k] for k in keys} for name, r in report["held_out"].items()}
