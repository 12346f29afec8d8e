"""The programs of gain tuning, data-parallel over their batch axis.

    make_rollout_grads(problem)        params_b (B, ...), scen (B,) -> values (B,), grads (B, ...), terms, Metrics
    make_population_objective(problem) params (P, ...), scen (b,)   -> objective (P,), terms (P, b), Metrics (P, b)
    DevicePrograms(core, mesh, ...)    ``core`` over the batch axis, one program per device of the mesh

The gradient program takes one parameter vector per rollout (the estimators of
:mod:`wbc_jax.tuning.algorithms.estimators` perturb them), so each rollout's reverse-mode gradient is its own
and a diverging rollout neither poisons nor steers the step. The population objective runs the P
candidates x b pushes as one flat batch of P b rollouts with per-rollout gains, on the problem's
engine (``jax``, or ``warp`` whose contact buffer is shared by the batch of one program), and
averages each candidate's objective over its pushes (common random numbers).

Several devices (:func:`wbc_jax.sim.runner.device_mesh`: every local GPU): each device runs its share
of the batch as a single-device program from a host thread of its own, as the push-sweep does
(:class:`DevicePrograms` over :class:`wbc_jax.sim.per_device.PerDevice`, under the watchdog; BENCHMARKS.md,
"Several GPUs of one host": MJX-Warp's foreign call has no partitioning rule, and a two-GPU
``shard_map`` program crashed XLA). Per-rollout values and gradients come back to the host in batch
order, and the step's reductions (the robust mean, each candidate's mean) run over the whole batch on
one device, so the result is the one-device result up to the rollouts' own float rounding.
"""

from __future__ import annotations

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from wbc_jax.sim import executables, physics, runner, warp_graphs, watchdog
from wbc_jax.sim.per_device import PerDevice
from wbc_jax.tuning.algorithms import loss as tuning_loss
from wbc_jax.tuning.algorithms import problem as tp

AXIS = "batch"


def mesh_of(mesh: Mesh | None = None) -> Mesh:
    """``mesh``, or the runner's mesh of every batch device."""
    return runner.device_mesh() if mesh is None else mesh


def _identity(*args):
    return args


def _same(out):
    return out


class DevicePrograms:
    """``post(core(*pre(*args)))``, ``core`` mapping the leading batch axis of its batched arguments to the
    leading batch axis of its outputs, on every device of ``mesh``.

    One device: one jitted program of the three (the single-device path). Several: ``pre`` on the
    default device; each device's share of ``core``'s batch (the batch divides by the device count) as a
    program of its own (:class:`~wbc_jax.sim.per_device.PerDevice`), every call under a
    :class:`~wbc_jax.sim.watchdog.Watchdog` (a stalled device is a one-line
    :class:`~wbc_jax.sim.watchdog.DeviceStalled` naming it and the call); the shares gathered on the
    host in batch order; ``post`` on the default device, over the whole batch.

    Args:
      core: the per-device function (its batched arguments' local shares -> outputs with the batch axis).
      mesh: the 1-D batch mesh (default :func:`wbc_jax.sim.runner.device_mesh`).
      batched: per argument of ``core``: True if split along the batch axis, False if each device takes it whole.
      pre, post: what runs before and after ``core`` on one device (``pre`` returns ``core``'s arguments).
      unit: what the stall error calls a call of this program ("gradient program call").
      stall_timeout_s: a call's bound on a device (``--stall-timeout-s``; None: the watchdog's default,
        from this program's slowest finished call). simulate_stall: the watchdog's test hook (call, device).
    """

    def __init__(
        self,
        core,
        mesh: Mesh | None,
        batched: tuple[bool, ...],
        *,
        pre=None,
        post=None,
        unit: str = "tuning program call",
        stall_timeout_s: float | None = None,
        simulate_stall: tuple[int, int] | None = None,
    ):
        self.mesh = mesh_of(mesh)
        self.n_devices = int(self.mesh.devices.size)
        self.batched, self.unit = batched, unit
        self.stall_timeout_s, self.simulate_stall = stall_timeout_s, simulate_stall
        pre = _identity if pre is None else pre
        finish = _same if post is None else post

        @functools.wraps(core if pre is _identity else pre)  # the arguments' names: part of the lowered text
        def fn(*args):
            return finish(core(*pre(*args)))

        # Named as the single-device program always was: its lowered text, the persistent cache's key, stays.
        fn.__name__ = fn.__qualname__ = "fn"

        self.whole = fn
        if self.n_devices == 1:
            self.program = jax.jit(fn)
        else:
            self.pre = None if pre is _identity else jax.jit(pre)
            self.post = None if post is None else jax.jit(post)
            self.program = PerDevice(core, self.mesh, batched)
        self.compiled = False
        self.calls = 0
        self.finished_s: list[float] = []  # each finished call's seconds: the default stall bound
        self.ran_on: list[str] = []  # the devices whose share of the last call finished

    def watch(self) -> watchdog.Watchdog:
        """The watchdog of the next call."""
        bound = watchdog.stall_bound(self.stall_timeout_s, self.finished_s)
        return watchdog.Watchdog(self.calls, bound, simulate_stall=self.simulate_stall, unit=self.unit)

    def _place(self, core_args) -> list:
        """``core``'s arguments as :class:`PerDevice` takes them: batched ones split over the mesh, the
        others host values (each device copies them whole)."""
        host = lambda tree: jax.tree_util.tree_map(np.asarray, tree)  # noqa: E731
        sharding = NamedSharding(self.mesh, PartitionSpec(AXIS))
        placed = []
        for arg, batched in zip(core_args, self.batched, strict=True):
            if arg is None:
                placed.append(None)
            elif batched:
                size = int(jax.tree_util.tree_leaves(arg)[0].shape[0])
                if size % self.n_devices:
                    raise ValueError(f"a batch of {size} does not split over {self.n_devices} devices")
                placed.append(jax.device_put(host(arg), sharding))
            else:
                placed.append(host(arg))
        return placed

    def _core_args(self, args) -> tuple:
        return args if self.pre is None else self.pre(*args)

    def eval_shape(self, *args):
        """The outputs' shapes and dtypes for ``args`` (a compiled one-device program's own, with no trace)."""
        if self.compiled and self.n_devices == 1:
            return self.program.out_info
        return jax.eval_shape(self.whole, *args)

    def compile(self, *args, saved_as: tuple[str, tuple] | None = None) -> float:
        """Compile for ``args`` (each device's program, on several); returns the seconds spent (0 when
        compiled already).

        ``saved_as`` = (name, key parts): on one device, the program is loaded from
        :func:`wbc_jax.sim.executables.compiled` when an earlier phase or process compiled it under that key,
        else compiled and kept there. JAX's persistent cache skips only XLA's compile; this skips the trace
        too (tracing the reverse-mode closed loop took 190 of the gradient program's 230 s on a 2-core CPU).
        On several devices each device's program is traced and compiled (the persistent cache as ever)."""
        if self.compiled:
            return 0.0
        t0 = time.perf_counter()
        if self.n_devices == 1 and saved_as is not None:
            name, key_parts = saved_as
            jitted = self.program
            self.program = executables.compiled(name, key_parts, args, lambda: runner.lower_fresh(jitted, *args))
        elif self.n_devices == 1:
            self.program = runner.compile_ahead(self.program, *args)  # keyed by the program alone
        else:  # as runner.lower_fresh: each device's lowered text (its persistent-cache key) is the program's alone
            jax.clear_caches()
            self.program.compile(*self._place(self._core_args(args)), watch=self.watch())
            # MJX-Warp's graphs: 32 per device (tracing set Warp's shared 32 again; a no-op without Warp), as a sweep
            warp_graphs.bound(None, self.n_devices)
        self.compiled = True
        return time.perf_counter() - t0

    def __call__(self, *args):
        if self.n_devices == 1:
            self.ran_on = [watchdog.device_label(self.mesh.devices.flat[0])]
            return self.program(*args)
        self.compile(*args)
        core_args = self._place(self._core_args(args))
        watch = self.watch()
        self.calls += 1
        t0 = time.perf_counter()
        out = self.program(*core_args, watch=watch, to_host=True)
        self.finished_s.append(time.perf_counter() - t0)
        self.ran_on = [r["device"] for r in watch.rows if r["phase"] == "run" and r["finished"]]
        return out if self.post is None else self.post(out)


def make_rollout_grads(problem: tp.Problem, mesh: Mesh | None = None) -> DevicePrograms:
    """Per-rollout value and gradient: ``fn(params_b {group: (B, ...)}, scen (B,)) -> (values (B,),
    grads {group: (B, ...)}, terms {name: (B,)}, Metrics (B,))``, one program per device of the mesh;
    MJX's solver differentiated as ``--solver-gradient`` says while it is traced."""
    env_objective = tp.make_env_objective(problem)

    def fn(params_b, scen):
        with physics.gradient_solver(problem.tc.solver_gradient, problem.iterations):
            per_env = jax.vmap(jax.value_and_grad(env_objective, has_aux=True))
            (values, (terms, metrics)), grads = per_env(params_b, scen)
        return values, grads, terms, metrics

    return DevicePrograms(
        fn, mesh, (True, True), unit="gradient program call", stall_timeout_s=problem.tc.stall_timeout_s
    )


def padded_size(n: int, mesh: Mesh | None = None) -> int:
    """``n`` rounded up to a multiple of the device count."""
    d = int(mesh_of(mesh).devices.size)
    return n + (-n) % d


def make_population_objective(
    problem: tp.Problem, population: int, pushes: int, mesh: Mesh | None = None
) -> DevicePrograms:
    """Forward objective of ``population`` candidates on the same ``pushes`` pushes, on the problem's
    engine: ``fn(params {group: (P, ...)}, scen (b,)) -> (objective (P,), terms {name: (P, b)},
    Metrics (P, b))``. One flat batch of P b rollouts (padded to the device count), one program per
    device; each candidate's mean over its pushes on one device."""
    mesh = mesh_of(mesh)
    n_env = population * pushes
    size = padded_size(n_env, mesh)
    env = tp.rollout_fn(problem, batch=size // int(mesh.devices.size))
    dtype = problem.setup.dtype

    def flat(controls, reg, scen):
        return jax.vmap(env)(controls, reg, scen)

    def spread(params, scen):
        controls, reg = jax.vmap(lambda p: tp.controls_cast(problem, p))(params)
        take = lambda x: jnp.repeat(x, pushes, axis=0)  # noqa: E731  env e: candidate e // b, push e % b
        tile = lambda x: jnp.tile(jnp.asarray(x), (population,) + (1,) * (jnp.ndim(x) - 1))  # noqa: E731
        per_env = (
            jax.tree_util.tree_map(take, controls),
            None if reg is None else jax.tree_util.tree_map(take, reg),
            jax.tree_util.tree_map(tile, scen),
        )
        per_env = jax.tree_util.tree_map(lambda x: _pad(x, size), per_env)
        return (
            tp.cast(dtype, per_env[0]),
            per_env[1] if per_env[1] is None else tp.cast(dtype, per_env[1]),
            per_env[2],
        )

    def objective(out):
        unflat = lambda x: x[:n_env].reshape((population, pushes) + x.shape[1:])  # noqa: E731
        terms, metrics = jax.tree_util.tree_map(unflat, out)
        return tuning_loss.batch_objective_rows(terms["total"], problem.lc), terms, metrics

    return DevicePrograms(
        flat,
        mesh,
        (True, True, True),
        pre=spread,
        post=objective,
        unit="population program call",
        stall_timeout_s=problem.tc.stall_timeout_s,
    )


def _pad(x, size: int):
    """Pad a batch (leading axis) to ``size`` with copies of its last row."""
    n = x.shape[0]
    if n == size:
        return x
    return jnp.concatenate([x, jnp.repeat(x[-1:], size - n, axis=0)])


def cast_batch(tree, dtype):
    """Float leaves of a numpy batch in ``dtype`` (the closed loop's)."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x, dtype) if np.asarray(x).dtype.kind == "f" else x, tree)
