"""MuJoCo Warp's step in its two phases, ``step1`` (positions and velocities: kinematics, the mass matrix and its
factor, the bias forces) and ``step2`` (actuation, the constraint solve, integration), as JAX calls on MJX-Warp data
(issue 46).

Why: on a GPU the controller's dynamics terms computed in MJX-JAX are a large part of its tick (BENCHMARKS.md), while
the tick's first physics step computes the same quantities at the same state a moment later.
Split there, the controller reads them off ``step1``'s data (:func:`wbc_jax.robot.dynamics.terms_from_split`), and
``step2`` finishes the step with its torques: C MuJoCo's ``mj_step1``/``mj_step2`` contract, which the C MuJoCo engine
already uses (wbc_jax/sim/native.py). MJX wraps only ``step`` and ``forward``; each phase here is MJX's own ``step``
wrapper (its foreign-call shim, fields in and out, batching rule) with ``mujoco_warp.step1`` or ``step2`` called in
place of ``mujoco_warp.step``: the same arguments and outputs, a superset of what each phase touches. ``step2(step1(d))``
equals ``mjx.step(d)`` bit for bit (tests/test_warp_split.py). Needs warp-lang; MJX 3.17.0's generated wrapper.

    phases() -> (step1, step2), each (mjx.Model, mjx.Data) -> mjx.Data of the Warp implementation, vmappable
"""

from __future__ import annotations

import functools
import types

import jax

TERMS = ("jax", "step1")
"""Where the controller's dynamics terms come from on the ``warp`` backend (``PhysicsConfig.warp_terms``): ``jax``
(MJX-JAX's ``dynamics.terms`` at the state) or ``step1`` (read off :func:`phases`' first phase of the tick's first
step by ``dynamics.terms_from_split``: the same terms to float32 rounding without a kinematics pass of their own;
not with a perturbed plant, whose dynamics the controller must not see)."""

TERMS_CHOICES = ("auto",) + TERMS
"""What ``PhysicsConfig.warp_terms`` takes: a source of :data:`TERMS`, or ``auto`` (:func:`resolve_terms`)."""


def resolve_terms(choice: str, backend: str, perturbed: bool) -> str:
    """The source of the controller's terms that ``choice`` names on ``backend``: itself, or for ``auto`` ``step1`` on
    the ``warp`` backend with an unperturbed plant (the loop's faster source there, BENCHMARKS.md, issue 46), else
    ``jax``."""
    if choice != "auto":
        return choice
    return "step1" if backend == "warp" and not perturbed else "jax"


def _rebound(fn, **names):
    """``fn`` with some of its module's global names bound to other objects (its code and annotations unchanged)."""
    scope = dict(fn.__globals__)
    scope.update(names)
    new = types.FunctionType(fn.__code__, scope, fn.__name__, fn.__defaults__, fn.__closure__)
    new.__annotations__ = dict(fn.__annotations__)
    new.__kwdefaults__ = fn.__kwdefaults__
    return new


def _phase(warp_fn):
    import mujoco.mjx.third_party.mujoco_warp as mjwarp
    import mujoco.mjx.warp.forward as mjx_warp_forward
    from mujoco.mjx.warp import ffi

    library = types.SimpleNamespace(**{k: getattr(mjwarp, k) for k in dir(mjwarp) if not k.startswith("__")})
    library.step = warp_fn  # what MJX's step shim calls
    shim = ffi.format_args_for_warp(_rebound(mjx_warp_forward._step_shim.__wrapped__, mjwarp=library))
    impl = _rebound(mjx_warp_forward._step_jax_impl, _step_shim=shim)

    @jax.custom_batching.custom_vmap
    @ffi.marshal_jax_warp_callable
    def call(m, d):
        return impl(m, d)

    @call.def_vmap
    @ffi.marshal_custom_vmap
    def _(axis_size, is_batched, m, d):
        return call(m, d), is_batched[1]

    return call


@functools.cache
def phases():
    """(step1, step2): MuJoCo Warp's two phases of a step as JAX calls (module docstring); built once per process."""
    import mujoco.mjx.third_party.mujoco_warp as mjwarp

    return _phase(mjwarp.step1), _phase(mjwarp.step2)
