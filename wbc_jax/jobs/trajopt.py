"""Trajectory optimisation through MJX: does some torque trajectory recover from this push?

The policy. In a window of T ticks from the push onset (tick k0) the plant gets

.. math::

    \\tau_k = \\mathrm{sat}_{\\pm \\bar\\tau}\\big(\\tau_{WBC}(x_k) + u_k\\big), \\qquad k_0 \\le k < k_0 + T,

with tau_bar (n,) each joint's motor limit (the robot model's actuators, ``RobotIndex.torque_limit``),
and the balancing controller's own torques after it (:class:`wbc_jax.sim.state.Feedforward`). The
decision variables are the knots ``z`` (Kn, n) of u, linear between knots ``knot`` ticks apart
(u = W z, W (T, Kn); ``knot`` 1: every tick free); z = 0 is the controller's own trajectory (the
warm start). The torques applied are every zero-order-hold trajectory at the control rate
(100 Hz) within +-tau_bar over the window that is tau_WBC + u for such a u: with ``knot`` 1 every
one (any trajectory tau is tau_WBC + u with u_k = tau_k - tau_WBC(x_k) along its own states);
with coarser knots the feedforward part is smooth, the feedback part is not, and the search
runs over fewer, better conditioned variables (a restriction: the limit found stays a lower
bound). Written around the controller, a trajectory found in float32 on MJX replays in C MuJoCo
in float64 (:mod:`wbc_jax.jobs.limit_rounds`) as a policy, not as an open loop: the small
differences of the engines meet the controller's feedback instead of growing unchecked.

The cost of one candidate (smooth, with margins inside the strict criterion's thresholds) over the
window and a ``tail`` of controller-only ticks after it, W ticks in all, from the standing state at
the onset (simulated once, the same for every push):

* slip: per sole, relu(|dp| - slip_margin)^2 / slip_margin^2, dp the xy displacement of the
  centre of its CoP rectangle's corners since the onset (the strict test: 2 cm);
* tilt: relu((1 - n . n0) - (1 - cos tilt_margin))^2 / (1 - cos tilt_margin)^2 of each sole's
  normal n against n0 at the onset (the strict test: 5 deg);
* height: relu(height_fraction h0 - z_CoM)^2 / scale^2 (a fall: z_CoM < 0.7 h0);
* capture, over the tail: relu(capture_margin - margin(xi))^2 / scale^2 with xi = c + v / omega
  the instantaneous capture point against the soles' support polygon, and |v_CoM|^2 / speed^2:
  the controller takes over a robot that a linear inverted pendulum says can stop on its feet;
* effort: mean (u / tau_bar)^2 per joint, small: it also pulls a u that the saturation cuts off back
  in range.

The mean of each over the W ticks, weighted (:class:`Cost`), summed: ``total``; the objective is
log(1 + total). Two ways to descend it, each candidate with its own Adam state (optax):

* ``es`` (the default): an evolution-strategies gradient of the objective smoothed at scale sigma:
  2M antithetic samples z +- sigma eps per candidate and step, forward rollouts only, centred
  ranks of their objectives as weights (Salimans et al. 2017, "Evolution strategies as a scalable
  alternative to reinforcement learning"), plus the unperturbed z;
* ``gradient``: the exact gradient through the closed loop (controller and MJX-JAX physics,
  per-tick ``jax.checkpoint``, the contact solver as a fixed-length scan), clipped per candidate
  to ``clip_norm``; a non-finite one is dropped (a zero step).

Why ES by default: near the limit the objective is rough at the scale of useful steps. The soles
roll over their corner spheres, contacts open and close, the controller's force QP changes its
active set; the same z rolled out by two compiled programs (float32) differs by 1 % in the
objective. Measured on the 2-core CPU (forward push of 11 N s, tuned gains, whose own trajectory
tilts a sole by 26 deg): along the exact gradient the objective fell from 6.44 to 5.72 at a step of
3 N m (L2 over the knots), then no step of 3-300 N m along the next gradient descended, while
random directions did; 40 ES steps of 16 samples took the best sample from 6.37 to 0.13, a
trajectory that passes the strict criterion on MJX and in the C MuJoCo replay (sole tilt 4.5 /
4.5 deg, slip 1.4 cm). Forward rollouts are also about 20x cheaper per physics step than rollouts
with gradient on a GPU (docs/limit/README.md).

Every step also keeps, per candidate, the lowest-objective z seen (``best_z``): the strict judge
tests that one.

Shapes: B candidates (directions x impulses), T window ticks, W = T + tail ticks, Kn knots,
n joints, M sample pairs.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax

from wbc_jax.core import constants
from wbc_jax.core.math import safe_norm
from wbc_jax.core.types import pytree_dataclass
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import mjx_loop, physics
from wbc_jax.sim.scenario import Setup
from wbc_jax.sim.state import Feedforward, LossTrace, Push, no_push


@dataclasses.dataclass(frozen=True)
class Cost:
    """Weights and margins of the optimiser's cost (module docstring); lengths in m, angles in deg."""

    slip_margin: float = 0.01
    tilt_margin_deg: float = 3.0
    height_fraction: float = 0.85
    capture_margin: float = 0.01
    end_speed: float = 0.1
    scale: float = 0.02
    w_slip: float = 1.0
    w_tilt: float = 1.0
    w_height: float = 1.0
    w_capture: float = 1.0
    w_speed: float = 0.1
    w_effort: float = 1e-3


METHODS = ("es", "gradient")


@pytree_dataclass
class OptState:
    """The optimiser's batch (B candidates): knots z (B, Kn, n) N m, Adam's state, the random key;
    the lowest-objective knots seen best_z (B, Kn, n) and their objective best_f (B,); the knots
    that passed the strict judge pass_z (B, Kn, n), whether (B,) and at which step (B,) (-1)."""

    z: jax.Array
    adam: optax.OptState
    key: jax.Array
    best_z: jax.Array
    best_f: jax.Array
    pass_z: jax.Array
    passed: jax.Array
    passed_step: jax.Array


def knot_matrix(T: int, knot: int) -> np.ndarray:
    """W (T, Kn): u = W z is linear between knots every ``knot`` ticks (Kn = ceil((T - 1) / knot)
    + 1; the last knot at or after the window's last tick)."""
    Kn = -(-(T - 1) // knot) + 1
    t = np.arange(T) / knot
    return np.maximum(0.0, 1.0 - np.abs(t[:, None] - np.arange(Kn)[None, :]))


def terms(trace: LossTrace, u, window: int, cost: Cost, motor_limit) -> dict:
    """The cost terms {name: ()} of one candidate's trace (W ticks: the window, then the tail), its
    torques u (T, n) and the motor limits (n,) N m that scale the effort per joint."""
    W = trace.com.shape[0]
    F = trace.support_xy.shape[1]
    centre = trace.support_xy.reshape(W, 2, F // 2, 2).mean(2)  # (W, 2 soles, 2)
    slip = safe_norm(centre - centre[0], axis=-1)
    slip_pen = jnp.sum(jax.nn.relu(slip - cost.slip_margin) ** 2, -1) / cost.slip_margin**2
    c_margin = 1.0 - math.cos(math.radians(cost.tilt_margin_deg))
    one_minus_cos = 1.0 - jnp.einsum("wfi,fi->wf", trace.foot_normal, trace.foot_normal[0])
    tilt_pen = jnp.sum(jax.nn.relu(one_minus_cos - c_margin) ** 2, -1) / c_margin**2
    h0 = trace.com_height0[0]
    height_pen = jax.nn.relu(cost.height_fraction * h0 - trace.com[:, 2]) ** 2 / cost.scale**2
    tail = slice(window, W) if W > window else slice(W - 1, W)
    omega = jnp.sqrt(constants.GRAVITY / h0)
    xi = trace.com[tail, :2] + trace.com_vel[tail, :2] / omega
    margin = jax.vmap(metrics_lib.polygon_margin)(trace.support_xy[tail], xi)
    capture = jnp.mean(jax.nn.relu(cost.capture_margin - margin) ** 2) / cost.scale**2
    speed = jnp.mean(jnp.sum(trace.com_vel[tail] ** 2, -1)) / cost.end_speed**2
    out = {
        "slip": jnp.mean(slip_pen),
        "tilt": jnp.mean(tilt_pen),
        "height": jnp.mean(height_pen),
        "capture": capture,
        "speed": speed,
        "effort": jnp.mean((u / motor_limit) ** 2),
    }
    out["total"] = sum(getattr(cost, f"w_{k}") * v for k, v in out.items())
    return out


class Optimiser:
    """Batched trajectory optimisation of one closed loop (a :class:`~wbc_jax.sim.scenario.Setup`
    with a LossTrace, MJX-JAX physics; per-tick checkpointing for ``gradient``).

    Args:
      setup: the closed loop (its gains drive tau_WBC).
      onset_tick: k0, the window's first tick (the push onset rounded down to a tick).
      window, tail: ticks optimised, and controller-only ticks after them in the cost.
      method: one of :data:`METHODS` (module docstring).
      knot: ticks between the knots of u; learning_rate: Adam's step (N m); clip_norm: the
        per-candidate gradient clip (``gradient``); pairs, sigma: antithetic sample pairs per
        candidate and their spread (N m) (``es``); cost: :class:`Cost`.
    """

    def __init__(
        self,
        setup: Setup,
        onset_tick: int,
        window: int,
        tail: int,
        *,
        method: str = "es",
        learning_rate: float,
        clip_norm: float = 10.0,
        knot: int = 1,
        pairs: int = 8,
        sigma: float = 2.0,
        cost: Cost = Cost(),
    ):
        if not (setup.loop.trace is not None and setup.loop.backend == "jax"):
            raise ValueError("the optimiser needs a closed loop with a LossTrace on the 'jax' backend")
        if method not in METHODS:
            raise ValueError(f"unknown optimiser method {method!r}; valid: {list(METHODS)}")
        self.setup, self.k0, self.window, self.tail, self.cost = setup, int(onset_tick), int(window), int(tail), cost
        self.method, self.pairs, self.sigma = method, int(pairs), float(sigma)
        self.n = setup.robot.index.n
        self.motor_limit = np.asarray(setup.robot.index.torque_limit, float)  # (n,) N m: the effort's scale
        self.W = knot_matrix(self.window, knot)
        self.iterations = int(setup.robot.mj_model.opt.iterations)
        clip = [optax.clip_by_global_norm(clip_norm)] if method == "gradient" else []
        self.adam = optax.chain(*clip, optax.adam(learning_rate))
        self.plant = physics.device_model(setup.robot.mj_model, "jax", setup.loop.cfg.physics)
        self._programs: dict = {}

    @property
    def rollouts_per_step(self) -> int:
        """Rollouts of the window and tail per candidate and step."""
        return 2 * self.pairs + 1 if self.method == "es" else 1

    def standing(self):
        """The carry (physics data, loop state, physics_ok) at the onset tick: the robot standing,
        unpushed, from the initial posture (one run, shared by every candidate)."""
        st, loop = self.setup, self.setup.loop
        if "standing" not in self._programs:

            def run(qpos, gains):
                carry = mjx_loop.start(loop, qpos)
                if self.k0 == 0:
                    return carry
                return mjx_loop.chunk(loop, self.plant, gains, no_push(qpos.dtype), carry, 0, self.k0)[0]

            self._programs["standing"] = jax.jit(run)
        return self._programs["standing"](jnp.asarray(st.qpos0, st.dtype), st.gains)

    def torques(self, z):
        """u (..., T, n) of knots z (..., Kn, n)."""
        xp = jnp if isinstance(z, jax.Array) else np
        return xp.einsum("tk,...kn->...tn", xp.asarray(self.W, z.dtype), z)

    def objective(self, z, push: Push, carry0):
        """(log1p(total) (), terms {name: ()}) of one candidate: knots z (Kn, n), its push, the
        standing carry (unbatched)."""
        loop = self.setup.loop
        u = self.torques(z)
        ff = Feedforward(start=jnp.asarray(self.k0, jnp.int32), torque=u)
        carry = mjx_loop.touch(carry0, jnp.sum(z))  # every carry leaf batched (and tangent) from the start
        _, trace = mjx_loop.chunk(loop, self.plant, self.setup.gains, push, carry, self.k0, self.window + self.tail, ff)
        t = terms(trace, u, self.window, self.cost, jnp.asarray(self.motor_limit, u.dtype))
        return jnp.log1p(t["total"]), t

    def init(self, z0, seed: int = 0) -> OptState:
        """The optimiser's state from warm starts z0 (B, Kn, n)."""
        z0 = jnp.asarray(z0, self.setup.dtype)
        B = z0.shape[0]
        return OptState(
            z=z0,
            adam=jax.vmap(self.adam.init)(z0),
            key=jax.random.split(jax.random.key(seed), B),
            best_z=z0,
            best_f=jnp.full(B, jnp.inf, z0.dtype),
            pass_z=z0,
            passed=jnp.zeros(B, bool),
            passed_step=jnp.full(B, -1, jnp.int32),
        )

    def step(self, state: OptState, push: Push, carry0):
        """One Adam step of every candidate: (state, objective at z (B,), terms {name: (B,)} at z).
        Compiled once per batch shape."""
        key = ("step", state.z.shape)
        if key not in self._programs:
            run = self._es_step if self.method == "es" else self._gradient_step
            if self.method == "gradient":
                with physics.fixed_iteration_solver(self.iterations):
                    self._programs[key] = jax.jit(run).lower(state, push, carry0).compile()
            else:
                self._programs[key] = jax.jit(run).lower(state, push, carry0).compile()
        return self._programs[key](state, push, carry0)

    def _gradient_step(self, state: OptState, push: Push, carry0):
        grad = jax.vmap(jax.value_and_grad(self.objective, has_aux=True), in_axes=(0, 0, None))
        (obj, t), g = grad(state.z, push, carry0)
        finite = jnp.all(jnp.isfinite(g), axis=(1, 2)) & jnp.isfinite(obj)
        g = jnp.where(finite[:, None, None], g, 0.0)
        state = _keep_best(state, state.z, obj)
        updates, adam = jax.vmap(self.adam.update)(g, state.adam, state.z)
        return state.replace(z=state.z + updates, adam=adam), obj, t

    def _es_step(self, state: OptState, push: Push, carry0):
        B, M = state.z.shape[0], self.pairs
        keys = jax.vmap(jax.random.split)(state.key)
        eps = jax.vmap(lambda k: jax.random.normal(k, (M, *state.z.shape[1:]), state.z.dtype))(keys[:, 1])
        zs = jnp.concatenate(
            [state.z[:, None], state.z[:, None] + self.sigma * eps, state.z[:, None] - self.sigma * eps], 1
        )  # (B, 2M + 1, Kn, n)
        pushes = jax.tree_util.tree_map(lambda x: jnp.repeat(x, 2 * M + 1, 0), push)
        flat = zs.reshape(B * (2 * M + 1), *zs.shape[2:])
        f, t = jax.vmap(self.objective, in_axes=(0, 0, None))(flat, pushes, carry0)
        f = f.reshape(B, 2 * M + 1)
        f_ok = jnp.where(jnp.isfinite(f), f, jnp.inf)  # a diverged sample ranks last
        i = jnp.argmin(f_ok, 1)
        state = _keep_best(state, zs[jnp.arange(B), i], f_ok[jnp.arange(B), i])
        g = jax.vmap(es_gradient, in_axes=(0, 0, None))(f_ok[:, 1:], eps, self.sigma)
        updates, adam = jax.vmap(self.adam.update)(g, state.adam, state.z)
        t0 = jax.tree_util.tree_map(lambda x: x.reshape(B, 2 * M + 1)[:, 0], t)
        return state.replace(z=state.z + updates, adam=adam, key=keys[:, 0]), f[:, 0], t0


def es_gradient(f, eps, sigma: float):
    """(Kn, n) the antithetic evolution-strategies gradient of the objectives f (2M,) of the
    samples z + sigma eps (the first M) and z - sigma eps (the last M), eps (M, Kn, n): weights
    are the centred ranks of f, in [-1/2, 1/2] (a sample's size does not matter, only its rank)."""
    M = eps.shape[0]
    ranks = jnp.argsort(jnp.argsort(f)).astype(eps.dtype) / (2 * M - 1) - 0.5
    w = ranks[:M] - ranks[M:]
    return jnp.einsum("m,m...->...", w, eps) / (M * sigma)


def _keep_best(state: OptState, z, f) -> OptState:
    """The state with z (B, Kn, n) kept as best_z where its objective f (B,) is lower."""
    better = f < state.best_f
    return state.replace(
        best_z=jnp.where(better[:, None, None], z, state.best_z), best_f=jnp.where(better, f, state.best_f)
    )


def record_passes(state: OptState, passed: np.ndarray, z, step: int) -> OptState:
    """The state with the knots z (B, Kn, n) kept as the passing ones of the candidates that
    ``passed`` (B,) the strict judge after ``step`` steps."""
    passed = jnp.asarray(passed, bool)
    return state.replace(
        pass_z=jnp.where(passed[:, None, None], jnp.asarray(z, state.z.dtype), state.pass_z),
        passed=state.passed | passed,
        passed_step=jnp.where(passed, step, state.passed_step),
    )


def warm_starts(tested: list, B_index, Kn: int, n: int) -> np.ndarray:
    """Warm starts (len(B_index), Kn, n): per candidate (direction d, impulse J), the knots of the
    verified trajectory of direction d with the largest impulse below J, else zeros. ``tested``:
    per direction, a list of (impulse, knots or None) of verified candidates."""
    out = np.zeros((len(B_index), Kn, n))
    for b, (d, J) in enumerate(B_index):
        below = [(imp, u) for imp, u in tested[d] if u is not None and imp < J]
        if below:
            out[b] = max(below, key=lambda x: x[0])[1]
    return out
