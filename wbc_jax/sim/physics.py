"""The physics backends, and the only module that touches MJX internals.

Three engines step the same MuJoCo model:

* ``jax``: MJX's JAX implementation. Differentiable; the engine of gradient tuning and the
  reference the others are checked against (tests/test_mjx_physics.py, tests/test_rollout.py).
* ``warp``: MJX's Warp implementation (``impl='warp'``, CUDA GPUs, warp-lang installed:
  ``pip install -e ".[cuda]"``). Not differentiable; fast batched forward runs on a GPU.
* ``mujoco``: C MuJoCo (``mujoco.mj_step``) on the host CPU, one ``MjData`` per environment,
  environments stepped in threads. The controller stays the jitted JAX function; only the
  physics leaves XLA. The forward engine on a CPU (laptops, Jupyter, CI).

``auto`` picks ``warp`` on a CUDA GPU with warp-lang, ``jax`` on another accelerator, and
``mujoco`` on a CPU; gradient tuning always uses ``jax``. The controller and the rollout see
(qpos, qvel), the contact slots of :func:`contacts` and a model from :func:`plant_model`; solver
settings, contact-force reads and the solver-loop swap for reverse mode live here.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from wbc_jax.control import warp_launch
from wbc_jax.core import mjx as mjx_device
from wbc_jax.core.constants import DIVERGED_SPEED
from wbc_jax.core.mjx import mjx
from wbc_jax.core.types import Array
from wbc_jax.sim import warp_graphs, warp_split

BACKENDS = ("auto", "jax", "warp", "mujoco")
FLOOR_GEOM = 0  # the floor is the model's first geom (the model builders of assets/; tested)
_WARP_INSTALL = 'pip install -e ".[cuda]" (warp-lang, the extra of mujoco-mjx)'


@dataclasses.dataclass(frozen=True)
class PhysicsConfig:
    """Which engine steps the plant, and its contact-solver settings.

    Attributes:
      backend: one of :data:`BACKENDS`.
      solver_iterations / ls_iterations: Newton / line-search iterations (None: the model's).
      warp_graph_mode: who captures MJX-Warp's CUDA graphs (:data:`warp_graphs.GRAPH_MODES`): ``warp`` (MJX's default
        on a GPU), ``jax`` (XLA, within its own command buffers), ``none``.
      warp_graph_cache: CUDA graphs each Warp foreign call keeps, for all devices together (:mod:`wbc_jax.sim.warp_graphs`;
        0: no bound; None: Warp's 32 per device). No program or result changes: out of the repr (``structure_key``).
      warp_terms: the terms' source on ``warp``, :data:`warp_split.TERMS_CHOICES` (``auto``: the loop resolves it).
    """

    backend: str = "auto"
    solver_iterations: int | None = None
    ls_iterations: int | None = None
    warp_graph_mode: str = "warp"
    warp_graph_cache: int | None = dataclasses.field(default=None, repr=False, compare=False)
    warp_terms: str = "auto"

    def __post_init__(self):
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown physics backend {self.backend!r}; valid: {list(BACKENDS)}")
        if self.warp_terms not in warp_split.TERMS_CHOICES:
            raise ValueError(f"unknown warp_terms {self.warp_terms!r}; valid: {list(warp_split.TERMS_CHOICES)}")
        for name in ("solver_iterations", "ls_iterations"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be a positive integer or None, got {value!r}")
        warp_graphs.check(self.warp_graph_cache, self.warp_graph_mode)


def has_cuda() -> bool:
    return any(d.platform == "gpu" for d in jax.devices())


def has_warp() -> bool:
    return warp_launch.installed()


def warp_on_cpu() -> bool:
    """``WBC_JAX_WARP_ON_CPU=1``: let ``--backend warp`` run on the CPU (Warp's CPU kernels; for
    testing the Warp path without a GPU)."""
    return os.environ.get("WBC_JAX_WARP_ON_CPU") == "1"


def resolve_backend(name: str, *, differentiable: bool = False) -> str:
    """The concrete backend for ``name`` on this machine; a clear error if it cannot run here."""
    if name not in BACKENDS:
        raise ValueError(f"unknown physics backend {name!r}; valid: {list(BACKENDS)}")
    if differentiable:
        if name not in ("auto", "jax"):
            raise ValueError(f"gradients need the 'jax' physics backend (MJX's JAX implementation), got {name!r}")
        return "jax"
    if name == "auto":
        if has_cuda():
            return "warp" if has_warp() else "jax"
        return "jax" if jax.default_backend() != "cpu" else "mujoco"
    if name == "warp":
        missing = [
            what for what, ok in (("a CUDA GPU", has_cuda() or warp_on_cpu()), ("warp-lang", has_warp())) if not ok
        ]
        if missing:
            raise ValueError(
                f"the 'warp' physics backend needs {' and '.join(missing)} (devices here: "
                f"{[str(d) for d in jax.devices()]}); install with {_WARP_INSTALL}, or use "
                "--backend jax or mujoco"
            )
    return name


def solver_model(mx: mjx.Model, cfg: PhysicsConfig) -> mjx.Model:
    """The MJX model with the solver overrides of ``cfg``."""
    opt = mx.opt
    if cfg.solver_iterations is not None:
        opt = opt.replace(iterations=int(cfg.solver_iterations))
    if cfg.ls_iterations is not None:
        opt = opt.replace(ls_iterations=int(cfg.ls_iterations))
    return mx.replace(opt=opt)


def solver_mj_model(m: mujoco.MjModel, cfg: PhysicsConfig) -> mujoco.MjModel:
    """A copy of the C model with the solver overrides of ``cfg``; C MuJoCo never resets an
    environment on its own (diverged ones are flagged by the rollout)."""
    m = copy.copy(m)
    if cfg.solver_iterations is not None:
        m.opt.iterations = int(cfg.solver_iterations)
    if cfg.ls_iterations is not None:
        m.opt.ls_iterations = int(cfg.ls_iterations)
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_AUTORESET
    return m


def state_ok(qpos, qvel):
    """() True while the state is finite and its speeds physical (below
    :data:`wbc_jax.core.constants.DIVERGED_SPEED`); numpy or JAX arrays alike."""
    xp = jnp if isinstance(qpos, jax.Array) else np
    # max |qvel| < DIVERGED_SPEED is False for a NaN or infinite speed: no separate finiteness check.
    return xp.all(xp.isfinite(qpos)) & (xp.max(xp.abs(qvel)) < DIVERGED_SPEED)


def floor_pairs(pair_geom1: np.ndarray, pair_geom2: np.ndarray) -> np.ndarray:
    """(npair,) bool: the contact pairs with the floor (scene objects keep their own friction)."""
    return (np.asarray(pair_geom1) == FLOOR_GEOM) | (np.asarray(pair_geom2) == FLOOR_GEOM)


def plant_model(mx: mjx.Model, friction: Array, mass_scale: Array) -> mjx.Model:
    """The simulated plant of one environment: floor friction (sliding) and scaled masses."""
    floor = floor_pairs(mx.pair_geom1, mx.pair_geom2)
    return mx.replace(
        pair_friction=mx.pair_friction.at[floor, :2].set(friction),
        body_mass=mx.body_mass * mass_scale,
        body_inertia=mx.body_inertia * mass_scale,
    )


def plant_mj_model(m: mujoco.MjModel, friction: float, mass_scale: float) -> mujoco.MjModel:
    """:func:`plant_model` for a C model (a copy)."""
    m = copy.copy(m)
    floor = floor_pairs(m.pair_geom1, m.pair_geom2)
    m.pair_friction[floor, :2] = friction
    m.body_mass[:] = m.body_mass * mass_scale
    m.body_inertia[:] = m.body_inertia * mass_scale
    return m


# ---------------------------------------------------------------------------------------------
# MJX (jax, warp): models, data, steps, contact slots


def device_model(robot_mj: mujoco.MjModel, backend: str, cfg: PhysicsConfig) -> mjx.Model:
    """The MJX model of a plant for an MJX backend, with the solver overrides."""
    if backend == "warp":
        from mujoco.mjx.third_party.mujoco_warp._src.types import OverflowType
        from warp import JaxCallableGraphMode

        mode = JaxCallableGraphMode[cfg.warp_graph_mode.upper()]
        mx = solver_model(mjx_device.put_model(robot_mj, impl="warp", graph_mode=mode), cfg)
        # Buffer overflows are reported (they would drop contacts or constraints); reaching the
        # solver's iteration cap is normal for fallen robots (as in C MuJoCo) and is not.
        quiet = ~(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS)
        impl = mx.opt._impl.replace(warn_overflow=int(mx.opt._impl.warn_overflow) & int(quiet))
        return mx.replace(opt=mx.opt.replace(_impl=impl))
    return solver_model(mjx_device.put_model(robot_mj), cfg)


def constraint_rows_bound(m: mujoco.MjModel) -> int:
    """Most constraint rows one environment can have: 2 (condim - 1) per contact pair (pyramidal
    cones, one contact per sphere pair), the limited joints, the dofs with friction loss and the
    equality constraints (6 rows at most each)."""
    rows = int(np.sum(2 * (np.maximum(m.pair_dim, 1) - 1))) if m.npair else 0
    return rows + int(np.sum(m.jnt_limited)) + int(np.sum(m.dof_frictionloss > 0)) + 6 * int(m.neq)


def device_data(
    robot_mj: mujoco.MjModel, backend: str, cfg: PhysicsConfig, qpos, dtype=None, batch: int = 1
) -> mjx.Data:
    """MJX data at ``qpos`` with zero velocity, for one environment of an MJX backend.

    Warp keeps the contacts of all ``batch`` environments in one buffer: it is sized for every
    contact pair of every environment (each pair of spheres and planes/boxes makes one contact at
    most), and the constraint rows per environment likewise, so neither can overflow."""
    if backend == "warp":
        d = mjx_device.make_data(
            robot_mj, impl="warp", naconmax=batch * max_contacts(robot_mj), njmax=constraint_rows_bound(robot_mj)
        )
    else:
        d = mjx_device.make_data(robot_mj)
    return d.replace(qpos=jnp.asarray(qpos, d.qpos.dtype if dtype is None else dtype))


def step(m: mjx.Model, d: mjx.Data, ctrl: Array, xfrc: Array) -> mjx.Data:
    """One physics step of an MJX backend with joint torques ``ctrl`` (nu,) and body wrenches
    ``xfrc`` (nbody, 6)."""
    return mjx.step(m, d.replace(ctrl=ctrl, xfrc_applied=xfrc))


def contacts(m: mjx.Model, d: mjx.Data) -> tuple[Array, Array, Array]:
    """MJX's contact slots after a step (JAX implementation): points (C, 3), the world-axes force
    on geom 2 of each pair (C, 3; zero where the geoms are apart) and the geom ids (C, 2)."""
    from mujoco.mjx._src import support

    if not hasattr(d._impl, "contact"):
        raise ValueError(
            "recording measured contact wrenches needs the 'jax' or 'mujoco' physics backend "
            f"(this data is of {type(d._impl).__name__})"
        )
    contact = d._impl.contact
    # efc addresses are static (numpy) in MJX: loop over the (few) contact slots.
    forces = jnp.stack([support.contact_force(m, d, i, to_world_frame=True)[:3] for i in range(contact.dist.shape[0])])
    return contact.pos, jnp.where((contact.dist <= 0)[:, None], forces, 0.0), contact.geom


@contextlib.contextmanager
def fixed_iteration_solver(max_iter: int):
    """While tracing inside this context, MJX's constraint-solver ``lax.while_loop`` runs as a
    fixed-length ``lax.scan`` of ``max_iter`` guarded iterations (MJX's ``_while_loop_scan``,
    which it already uses for its line search): same values, reverse mode works. Only the
    ``jax`` name seen by ``mujoco.mjx._src.solver`` is replaced, and restored on exit."""
    from mujoco.mjx._src import solver

    class _Lax:
        def __getattr__(self, name):
            return getattr(jax.lax, name)

        @staticmethod
        def while_loop(cond, body, init):
            return solver._while_loop_scan(cond, body, init, max_iter)

    class _Jax:
        lax = _Lax()

        def __getattr__(self, name):
            return getattr(jax, name)

    original = solver.jax
    solver.jax = _Jax()
    try:
        yield
    finally:
        solver.jax = original


SOLVER_GRADIENTS = ("implicit", "unrolled")


@contextlib.contextmanager
def implicit_solver():
    """While tracing inside this context, MJX's constraint solver (JAX implementation, Newton, pyramidal
    cones) is differentiated implicitly instead of through its iterations.

    The solver minimises the convex cost of MuJoCo's soft constraints over the acceleration a,
    ``C(a) = 1/2 (M a - f_smooth) . (a - a_smooth) + 1/2 sum_active D_i (J_i a - aref_i)^2``; at its
    minimum a*, g(a*) = M a* - f_smooth + J^T D_act (J a* - aref) = 0. Here the solver runs on
    stop-gradient inputs (its early-exiting ``while_loop``, no tangents), and the result is
    ``a = a* - H^-1 g(a*)`` with H = M + J^T D_act J and the active set held fixed: one more Newton step
    of the same cost, whose value is a* to the solver's tolerance and whose derivative is the
    implicit-function theorem's, da/dtheta = -H^-1 dg/dtheta (M, f_smooth, J, D and aref all depend on
    the state and the torques). The backward pass is then two Cholesky solves with H and products with
    M and J per physics step, instead of the reverse pass of every Newton and line-search iteration.
    The constraint forces follow from a with the same active set.

    Joint friction loss (Talos's motors; MJX's ``_update_constraint``): a friction-loss row is
    quadratic while |J a - aref| < f / D and linear beyond, its force then the constant -+f (no
    curvature); which rows are linear is held fixed at a* as the active set is."""
    from mujoco.mjx._src import solver, support
    from mujoco.mjx._src.types import DisableBit

    original = solver.solve

    def solve(m, d):
        impl = d._impl
        if m.opt.cone != mujoco.mjtCone.mjCONE_PYRAMIDAL or np.any(np.asarray(m._impl.tendon_hasfrictionloss)):
            raise ValueError("the implicit solver gradient needs pyramidal cones and no tendon friction loss")
        sg = lambda t: jax.tree_util.tree_map(jax.lax.stop_gradient, t)  # noqa: E731
        a_star = jax.lax.stop_gradient(original(m, sg(d)).qacc)  # the plant model carries no tangents here
        J, aref = impl.efc_J, impl.efc_aref
        jaref = jax.lax.stop_gradient(J @ a_star - aref)
        active = (jaref < 0).at[: impl.ne + impl.nf].set(True)
        floss = jnp.zeros_like(aref)
        if np.any(np.asarray(m._impl.dof_hasfrictionloss)) and not m.opt.disableflags & DisableBit.FRICTIONLOSS:
            f = impl.efc_frictionloss
            r = 1.0 / (impl.efc_D + (impl.efc_D == 0.0) * mujoco.mjMINVAL)
            linear_neg = (jaref <= -r * f) & (f > 0)
            linear_pos = (jaref >= r * f) & (f > 0)
            active = active & ~linear_neg & ~linear_pos
            floss = linear_neg * f - linear_pos * f
        w = impl.efc_D * active

        def force(a):
            return -w * (J @ a - aref) + floss

        g = support.mul_m(m, d, a_star) - d.qfrc_smooth - J.T @ force(a_star)
        H = jax.lax.stop_gradient(support.full_m(m, d) + (J.T * w) @ J)
        factor = jax.scipy.linalg.cho_factor(0.5 * (H + H.T))
        a = a_star - jax.scipy.linalg.cho_solve(factor, g)
        f = force(a)
        return d.tree_replace({"qacc": a, "qfrc_constraint": J.T @ f, "_impl.efc_force": f})

    solver.solve = solve
    try:
        yield
    finally:
        solver.solve = original


def gradient_solver(kind: str, iterations: int):
    """The context that makes MJX's solver reverse-differentiable while a program is traced: ``implicit``
    (:func:`implicit_solver`) or ``unrolled`` (:func:`fixed_iteration_solver` with ``iterations``)."""
    if kind == "implicit":
        return implicit_solver()
    if kind == "unrolled":
        return fixed_iteration_solver(iterations)
    raise ValueError(f"unknown solver gradient {kind!r}; valid: {list(SOLVER_GRADIENTS)}")


# ---------------------------------------------------------------------------------------------
# C MuJoCo on the host


class HostBatch:
    """B environments of C MuJoCo, stepped in threads (``mj_step`` releases the GIL).

    Args:
      models: one C model per environment (plants may differ), or one shared.
      qpos: (B, nq) initial positions (zero velocity).
      threads: worker threads (None: the CPU count).
    """

    def __init__(self, models, qpos: np.ndarray, threads: int | None = None):
        qpos = np.asarray(qpos, float)
        self.B = qpos.shape[0]
        self.models = list(models) if isinstance(models, (list, tuple)) else [models] * self.B
        if len(self.models) != self.B:
            raise ValueError(f"{len(self.models)} models for {self.B} environments")
        self.data = [mujoco.MjData(m) for m in self.models]
        for m, d, q in zip(self.models, self.data, qpos, strict=True):
            d.qpos[:] = q
            mujoco.mj_forward(m, d)
        self.threads = max(1, min(threads or os.cpu_count() or 1, self.B))
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        self._lock = threading.Lock()
        self.diverged = np.zeros(self.B, bool)
        self.checked = np.zeros(self.B, bool)  # state known sound (checked after the last step)

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """(qpos (B, nq), qvel (B, nv))."""
        return np.stack([d.qpos for d in self.data]), np.stack([d.qvel for d in self.data])

    def step(self, ctrl: np.ndarray, xfrc: np.ndarray) -> None:
        """Advance every environment by ``xfrc.shape[1]`` physics steps with torques ``ctrl``
        (B, nu) held and body wrenches ``xfrc`` (B, steps, nbody, 6). An environment whose state
        becomes non-finite is restored to its state before the call and marked in ``diverged``."""
        ctrl = np.asarray(ctrl, float)
        xfrc = np.asarray(xfrc, float)
        steps = xfrc.shape[1]
        ctrl_ok = np.all(np.isfinite(ctrl), axis=1)
        # Where each env's wrenches change between steps: runs of equal wrenches go in one call.
        changes = np.any(xfrc[:, 1:] != xfrc[:, :-1], axis=(2, 3))

        def run(envs):
            for i in envs:
                m, d = self.models[i], self.data[i]
                if self.diverged[i]:
                    continue
                if not (ctrl_ok[i] and (self.checked[i] or state_ok(d.qpos, d.qvel))):
                    self.diverged[i] = True  # flagged before C MuJoCo warns about it
                    continue
                saved = (d.time, d.qpos.copy(), d.qvel.copy(), d.qacc_warmstart.copy())
                d.ctrl[:] = ctrl[i]
                bounds = [0, *(np.flatnonzero(changes[i]) + 1), steps]
                for j, k in zip(bounds[:-1], bounds[1:]):
                    d.xfrc_applied[:] = xfrc[i, j]
                    mujoco.mj_step(m, d, nstep=k - j)
                self.checked[i] = True  # the state below is checked
                if not state_ok(d.qpos, d.qvel):
                    d.time, d.qpos[:], d.qvel[:], d.qacc_warmstart[:] = saved
                    mujoco.mj_forward(m, d)
                    self.diverged[i] = True

        if self._pool is None:
            run(range(self.B))
        else:
            chunks = np.array_split(np.arange(self.B), self.threads)
            list(self._pool.map(run, chunks))

    def contacts(self, max_contacts: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Contact slots of every environment, padded to ``max_contacts``: points (B, C, 3),
        world-axes forces on geom 2 (B, C, 3), geom ids (B, C, 2) (padding: zero force, geom 0)."""
        pos = np.zeros((self.B, max_contacts, 3))
        force = np.zeros((self.B, max_contacts, 3))
        geom = np.zeros((self.B, max_contacts, 2), np.int64)
        f6 = np.zeros(6)
        for i, (m, d) in enumerate(zip(self.models, self.data, strict=True)):
            n = min(d.ncon, max_contacts)
            for c in range(n):
                con = d.contact[c]
                if con.dist > 0:
                    continue
                mujoco.mj_contactForce(m, d, c, f6)
                frame = con.frame.reshape(3, 3)
                # mj_contactForce: the force in the contact frame, on geom 2 (as MJX's).
                force[i, c] = frame.T @ f6[:3]
                pos[i, c] = con.pos
                geom[i, c] = con.geom
        return pos, force, geom


def max_contacts(m: mujoco.MjModel) -> int:
    """An upper bound of simultaneous contacts: one per contact pair (the model's contacts are
    explicit pairs of spheres and planes/boxes, at most one contact each)."""
    return max(int(m.npair), 1)


def steps_per_tick(control_dt: float, physics_dt: float) -> int:
    n_sub = int(round(control_dt / physics_dt))
    if n_sub < 1 or abs(n_sub * physics_dt - control_dt) > 1e-9 or not math.isfinite(control_dt):
        raise ValueError(f"control_dt {control_dt} must be a positive multiple of the physics timestep {physics_dt}")
    return n_sub
