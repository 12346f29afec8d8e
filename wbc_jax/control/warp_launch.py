"""What the controller's Warp engines share (:mod:`wbc_jax.control.qp_warp_kernel`,
:mod:`wbc_jax.control.qp_active_set_kernel`, :mod:`wbc_jax.control.cholesky_warp`, :mod:`wbc_jax.control.ritz_warp`):
Warp imported with a one-line error naming the fix where warp-lang is missing, and a kernel launch over a batch of
problems that stays one launch under ``vmap``."""

import importlib.util

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap


def installed() -> bool:
    """Whether warp-lang is installed (without importing it)."""
    return importlib.util.find_spec("warp") is not None


def gpu_default() -> bool:
    """Whether JAX's default device is a GPU and warp-lang is installed: where the controller's ``auto`` engines name
    the Warp kernels (measured faster there, BENCHMARKS.md, issue 46; on the CPU a Warp kernel called from XLA goes
    through Python)."""
    return jax.default_backend() == "gpu" and installed()


def warp_module():
    """The ``warp`` module, imported where a Warp engine is first built (warp-lang is an optional extra)."""
    try:
        import warp as wp
    except ImportError as e:  # pragma: no cover - the message is what matters
        raise ImportError(
            "the controller's Warp engines (qp_engine 'warp' or 'warp_active_set', mass_solve_engine or ritz_engine "
            "'warp') need warp-lang: pip install 'wbc_jax[cuda]' (or use the engines 'jax')"
        ) from e
    return wp


def one_launch_under_vmap(flat):
    """``flat`` (arrays whose leading axes are problems -> a tuple of arrays, one kernel launch over them all) as a
    function that stays one launch under ``vmap``: the vmapped axis joins the problems, unbatched arguments broadcast
    to it."""

    @custom_vmap
    def batched(*args):
        return flat(*args)

    @batched.def_vmap
    def _(axis_size, in_batched, *args):
        args = [a if b else jnp.broadcast_to(a, (axis_size,) + a.shape) for a, b in zip(args, in_batched)]
        out = batched(*args)
        return out, tuple(True for _ in out)

    return batched
