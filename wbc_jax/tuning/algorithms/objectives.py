"""The programs of gain tuning, data-parallel over their batch axis.

    make_rollout_grads(problem)        params_b (B, ...), scen (B,) -> values (B,), grads (B, ...), terms, Metrics
    make_population_objective(problem) params (P, ...), scen (b,)   -> objective (P,), terms (P, b), Metrics (P, b)
    data_parallel(fn, mesh)            fn over the batch axis of every argument and output, one shard per device

The gradient program takes one parameter vector per rollout (the estimators of
:mod:`wbc_jax.tuning.algorithms.estimators` perturb them), so each rollout's reverse-mode gradient is its own
and a diverging rollout neither poisons nor steers the step. The population objective runs the P
candidates x b pushes as one flat batch of P b rollouts with per-rollout gains, on the problem's
engine (``jax``, or ``warp`` whose contact buffer is shared by the batch of one program), and
averages each candidate's objective over its pushes (common random numbers).

Several devices (:func:`wbc_jax.sim.runner.device_mesh`): ``jax.shard_map`` runs each device's shard
of the batch; per-rollout values and gradients come back as shards of the whole batch, and the
step's reductions (the robust mean, each candidate's mean) run over the whole batch, so the result
is the one-device result up to the order of floating-point sums.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from wbc_jax.sim import physics, runner
from wbc_jax.tuning.algorithms import loss as tuning_loss
from wbc_jax.tuning.algorithms import problem as tp

AXIS = "batch"


def mesh_of(mesh: Mesh | None = None) -> Mesh:
    """``mesh``, or the runner's mesh of every batch device."""
    return runner.device_mesh() if mesh is None else mesh


def data_parallel(fn, mesh: Mesh | None = None, *, replicated: int = 0):
    """``fn`` (leading batch axis on every argument and output, but the last ``replicated`` arguments,
    which every device gets whole) run shard by shard: each device runs ``fn`` on its part of the
    batch (the batch must divide by the device count)."""
    mesh = mesh_of(mesh)
    if mesh.devices.size == 1:
        return fn

    def sharded(*args):
        n = len(args) - replicated
        specs = (PartitionSpec(AXIS),) * n + (PartitionSpec(),) * replicated
        return jax.shard_map(fn, mesh=mesh, in_specs=specs, out_specs=PartitionSpec(AXIS), check_vma=False)(*args)

    return sharded


def shard(tree, mesh: Mesh | None = None):
    """Put a batch (leading axis) on the mesh's devices, split along the batch when it divides."""
    mesh = mesh_of(mesh)
    B = int(jax.tree_util.tree_leaves(tree)[0].shape[0])
    if mesh.devices.size > 1 and B % mesh.devices.size == 0:
        return jax.device_put(tree, NamedSharding(mesh, PartitionSpec(AXIS)))
    return jax.device_put(tree)


def make_rollout_grads(problem: tp.Problem, mesh: Mesh | None = None):
    """Per-rollout value and gradient, unjitted: ``fn(params_b {group: (B, ...)}, scen (B,)) ->
    (values (B,), grads {group: (B, ...)}, terms {name: (B,)}, Metrics (B,))``; data-parallel over
    the mesh; MJX's solver differentiated as ``--solver-gradient`` says while it is traced."""
    env_objective = tp.make_env_objective(problem)

    def fn(params_b, scen):
        with physics.gradient_solver(problem.tc.solver_gradient, problem.iterations):
            per_env = jax.vmap(jax.value_and_grad(env_objective, has_aux=True))
            (values, (terms, metrics)), grads = per_env(params_b, scen)
        return values, grads, terms, metrics

    return data_parallel(fn, mesh)


def padded_size(n: int, mesh: Mesh | None = None) -> int:
    """``n`` rounded up to a multiple of the device count."""
    d = int(mesh_of(mesh).devices.size)
    return n + (-n) % d


def make_population_objective(problem: tp.Problem, population: int, pushes: int, mesh: Mesh | None = None):
    """Forward objective of ``population`` candidates on the same ``pushes`` pushes, on the problem's
    engine, unjitted: ``fn(params {group: (P, ...)}, scen (b,)) -> (objective (P,), terms {name: (P, b)},
    Metrics (P, b))``. One flat batch of P b rollouts (padded to the device count), data-parallel."""
    mesh = mesh_of(mesh)
    n_env = population * pushes
    size = padded_size(n_env, mesh)
    env = tp.rollout_fn(problem, batch=size // int(mesh.devices.size))
    dtype = problem.setup.dtype

    def flat(controls, reg, scen):
        return jax.vmap(env)(controls, reg, scen)

    run = data_parallel(flat, mesh)

    def fn(params, scen):
        controls, reg = jax.vmap(lambda p: tp.controls_cast(problem, p))(params)
        take = lambda x: jnp.repeat(x, pushes, axis=0)  # noqa: E731  env e: candidate e // b, push e % b
        tile = lambda x: jnp.tile(jnp.asarray(x), (population,) + (1,) * (jnp.ndim(x) - 1))  # noqa: E731
        per_env = (
            jax.tree_util.tree_map(take, controls),
            None if reg is None else jax.tree_util.tree_map(take, reg),
            jax.tree_util.tree_map(tile, scen),
        )
        per_env = jax.tree_util.tree_map(lambda x: _pad(x, size), per_env)
        per_env = (
            tp.cast(dtype, per_env[0]),
            per_env[1] if per_env[1] is None else tp.cast(dtype, per_env[1]),
            per_env[2],
        )
        terms, metrics = run(*per_env)
        unflat = lambda x: x[:n_env].reshape((population, pushes) + x.shape[1:])  # noqa: E731
        terms, metrics = jax.tree_util.tree_map(unflat, (terms, metrics))
        return tuning_loss.batch_objective_rows(terms["total"], problem.lc), terms, metrics

    return fn


def _pad(x, size: int):
    """Pad a batch (leading axis) to ``size`` with copies of its last row."""
    n = x.shape[0]
    if n == size:
        return x
    return jnp.concatenate([x, jnp.repeat(x[-1:], size - n, axis=0)])


def cast_batch(tree, dtype):
    """Float leaves of a numpy batch in ``dtype`` (the closed loop's)."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x, dtype) if np.asarray(x).dtype.kind == "f" else x, tree)
