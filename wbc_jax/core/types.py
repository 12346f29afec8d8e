"""Shared types, the frame/symbol legend and the pytree dataclass helper.

Frames and symbols (jaxsim-style ASCII names):

* ``W``: world frame, z up; ``B``: the floating base (the model's root body);
  ``l_sole``/``r_sole``: the sole frames of the URDF (x forward, z up); ``G[W]``: the CoM
  with world axes (centroidal frame).
* ``nu`` (6+n,): the **mixed** velocity ``[W_v_B, W_omega_B, s_dot]``: base-origin linear
  velocity and base angular velocity, both in world axes, then the joint velocities in the
  controller's joint order. MuJoCo's free joint stores the angular velocity in base axes:
  :func:`wbc_jax.robot.dynamics.mixed_velocity` is the one place that converts.
* ``M`` (6+n, 6+n) mass matrix, ``h`` (6+n,) Coriolis + gravity, ``J_feet`` (2, 6, 6+n)
  sole Jacobians (rows: linear, angular), ``Jdot_nu_feet`` (2, 6), ``A_G`` (6, 6+n) centroidal
  momentum matrix, ``L_G`` (6,) centroidal momentum ``[linear; angular about the CoM]``.
* Wrenches are ``[force; moment]``, applied at the sole origin, in world axes.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

import jax

from wbc_jax.core.options import option  # noqa: F401  (job-config fields, declared there)

Array = jax.Array
T = TypeVar("T")


def static_field(**kwargs: Any) -> Any:
    """A dataclass field that is pytree metadata (hashable, not traced)."""
    return dataclasses.field(metadata={"static": True}, **kwargs)


def pytree_dataclass(cls: type[T]) -> type[T]:
    """Frozen dataclass registered as a JAX pytree.

    Fields are leaves unless declared with :func:`static_field`; ``replace`` is added.
    """
    cls = dataclasses.dataclass(frozen=True)(cls)
    fields = dataclasses.fields(cls)
    data = [f.name for f in fields if not f.metadata.get("static", False)]
    meta = [f.name for f in fields if f.metadata.get("static", False)]
    jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)
    cls.replace = lambda self, **kw: dataclasses.replace(self, **kw)  # type: ignore[attr-defined]
    return cls
