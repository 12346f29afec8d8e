"""The rigid-contact constraints of a contact set, its wrench map and measured wrenches.

Each contact's wrench (world axes, at the contact point) must satisfy ``C f <= b``: the linearised
friction cone, torsion, the unilateral row ``f_n >= fz_min`` and, for surface contacts, the CoP
rectangle (Nori et al. 2015; the WBC ``computeRigidContactConstraints``). The rows of a contact are
named by :func:`constraint_rows`. ``A`` (:func:`wrench_map`) maps the stacked wrenches to the rate
of the centroidal momentum; :func:`measured_wrenches` reads back what the simulator applied.

Every function takes a :class:`wbc_jax.robot.contacts.ContactSet` (static) and arrays of one state.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax.numpy as jnp
import numpy as np

from wbc_jax.core.constants import GRAVITY
from wbc_jax.core.math import skew
from wbc_jax.core.types import Array
from wbc_jax.robot.contacts import ContactParams, ContactSet

# Accepted violation of each contact's constraints, relative to its normal force, by precision
# {float64: 8 bytes, float32: 4}: the interior-point solution meets them ~1e3 times better.
VIOLATION_TOL = {8: 1e-9, 4: 1e-4}

# ---------------------------------------------------------------------------------------------
# Constraints of one contact


@dataclasses.dataclass(frozen=True)
class ConstraintRows:
    """Row ranges of one contact's constraints ``C f <= b`` (contact frame).

    cone: linearised friction cone; torsion: |tau_z| <= mu_t f_z (surface only); unilateral: the
    row ``-f_z <= -fz_min``; cop: the CoP rectangle (surface only). ``count``: rows in all."""

    cone: slice
    torsion: slice
    unilateral: int
    cop: slice
    count: int


def constraint_rows(params: ContactParams, contact_type: str = "surface") -> ConstraintRows:
    """The named rows of :func:`contact_constraints` for these parameters and contact type."""
    edges = 4 * (params.n_points - 1)
    if contact_type == "point":
        return ConstraintRows(slice(0, edges), slice(edges, edges), edges, slice(edges + 1, edges + 1), edges + 1)
    return ConstraintRows(slice(0, edges), slice(edges, edges + 2), edges + 2, slice(edges + 3, edges + 7), edges + 7)


def contact_constraints(params: ContactParams, contact_type: str = "surface") -> tuple[np.ndarray, np.ndarray]:
    """Rigid-contact constraints ``C f <= b`` of one contact's wrench in its CONTACT frame.

    Same constraint set as WBC ``wbc.computeRigidContactConstraints(mu, numberOfPoints, mu_t,
    footSize, fZmin)`` and the same row order (:func:`constraint_rows`):

    * cone (E = 4 (n_points - 1) rows, 12 by default): a regular E-gon *inscribed* in the circle
      of radius ``mu f_z``, vertices at ``t_i = i d``, ``d = (pi/2) / (n_points - 1)``. Each edge
      is ``n_e . (f_x, f_y) <= mu cos(d/2) f_z`` with ``n_e`` the unit outward normal and
      ``cos(d/2)`` the apothem. WBC writes the same half-planes as ``y - k x - q`` with the
      slope/offset of the edge line: its rows are ours times ``1/|n_e,y|`` (same set).
    * torsion: ``tau_z - mu_t f_z <= 0``, ``-tau_z - mu_t f_z <= 0``.
    * unilateral: ``-f_z <= -fz_min``.
    * cop: ``x_min f_z + tau_y <= 0``, ``-x_max f_z - tau_y <= 0``, ``y_min f_z - tau_x <= 0``,
      ``-y_max f_z + tau_x <= 0``, i.e. ``x_min <= -tau_y/f_z <= x_max`` and
      ``y_min <= tau_x/f_z <= y_max``.

    A ``point`` contact (a 3-D force) keeps the cone and the unilateral row.

    Returns:
      ``(C, b)``: float64 numpy arrays, (E+7, 6) and (E+7,) for a surface contact
      (``f = [f_x, f_y, f_z, tau_x, tau_y, tau_z]``), (E+1, 3) and (E+1,) for a point contact.
    """
    n_edges = 4 * (params.n_points - 1)
    step = 0.5 * np.pi / (params.n_points - 1)
    mid = step * (np.arange(n_edges) + 0.5)  # edge midpoints' angles
    apothem = np.cos(0.5 * step)
    cone = np.zeros((n_edges, 6))
    cone[:, 0] = np.cos(mid)
    cone[:, 1] = np.sin(mid)
    cone[:, 2] = -params.mu * apothem
    (x_min, x_max), (y_min, y_max) = params.foot_size
    #                  f_x  f_y  f_z            tau_x tau_y tau_z
    torsion = np.array([[0.0, 0.0, -params.mu_t, 0.0, 0.0, 1.0], [0.0, 0.0, -params.mu_t, 0.0, 0.0, -1.0]])
    unilateral = np.array([[0.0, 0.0, -1.0, 0.0, 0.0, 0.0]])
    cop = np.array(
        [
            [0.0, 0.0, x_min, 0.0, 1.0, 0.0],
            [0.0, 0.0, -x_max, 0.0, -1.0, 0.0],
            [0.0, 0.0, y_min, -1.0, 0.0, 0.0],
            [0.0, 0.0, -y_max, 1.0, 0.0, 0.0],
        ]
    )
    rows = constraint_rows(params, contact_type)
    if contact_type == "point":
        C = np.concatenate([cone, unilateral])[:, :3]
    else:
        C = np.concatenate([cone, torsion, unilateral, cop])
    b = np.zeros(rows.count)
    b[rows.unilateral] = -params.fz_min
    return C, b


@functools.cache
def _contact_frame_rows(cset: ContactSet) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(C (M, D), b (M,), block_contact (D / 3,), unilateral (K,))``: every contact's constraints
    on its wrench in its own frame, block-diagonal (:func:`contact_constraints`); the contact of
    each 3-vector (force, moment) of the stacked wrenches; the unilateral row of each contact."""
    parts = [contact_constraints(c.params, c.type) for c in cset.contacts]
    C = np.zeros((sum(len(b) for _, b in parts), cset.dim))
    r, unilateral = 0, []
    for (C_k, b_k), c, sl in zip(parts, cset.contacts, cset.slices(), strict=True):
        C[r : r + len(b_k), sl] = C_k
        unilateral.append(r + constraint_rows(c.params, c.type).unilateral)
        r += len(b_k)
    block_contact = np.concatenate([np.full(c.dim // 3, k) for k, c in enumerate(cset.contacts)])
    return C, np.concatenate([b for _, b in parts]), block_contact, np.asarray(unilateral)


def constraint_products(cset: ContactSet, W_R: Array, X: Array) -> Array:
    """``C X`` (M, ...) for stacked world-axes wrenches X (D, ...) and the world-axes ``C`` of
    :func:`constraints`, without building C: each force and moment of X rotated into its contact
    frame (W_R (K, 3, 3): contact frame -> world), then the contact-frame rows (constants).
    Two products in all, whatever the number of contacts."""
    C_local, _, block_contact, _ = _contact_frame_rows(cset)
    blocks = X.reshape(len(block_contact), 3, -1)
    local = jnp.einsum("bij,bic->bjc", W_R[block_contact], blocks).reshape(X.shape)
    return jnp.asarray(C_local, X.dtype) @ local


def constraint_bounds(cset: ContactSet, fz_min_scale: Array) -> Array:
    """b (M,) of :func:`constraints`: each contact's minimum normal force times ``fz_min_scale`` (K,)."""
    _, b, _, _ = _contact_frame_rows(cset)
    return jnp.asarray(b, fz_min_scale.dtype) * fz_min_scale[constraint_contact(cset)]


def constraints(cset: ContactSet, W_R: Array, fz_min_scale: Array) -> tuple[Array, Array]:
    """Block-diagonal ``C`` (M, D), ``b`` (M,) of all contacts, world axes (``C f``:
    :func:`constraint_products`, without building C).

    Args:
      cset: the contact set. W_R: (K, 3, 3) contact frames.
      fz_min_scale: (K,) multiplies each contact's minimum normal force (the activation when the
        violation of a contact being released is measured; 1 in the QPs).
    """
    return constraint_products(cset, W_R, jnp.eye(cset.dim, dtype=W_R.dtype)), constraint_bounds(cset, fz_min_scale)


def constraint_contact(cset: ContactSet) -> np.ndarray:
    """(M,) the contact of each row of :func:`constraints`."""
    return np.concatenate([np.full(constraint_rows(c.params, c.type).count, k) for k, c in enumerate(cset.contacts)])


def wrench_map(cset: ContactSet, W_p: Array, W_p_CoM: Array) -> Array:
    """A (6, D): contact wrenches (world axes, at the contact points W_p (K, 3)) -> rate of the
    centroidal momentum about the CoM: ``A_k = [I3 0; S(p_k - x_CoM) I3]`` (a point contact: the
    first three columns)."""
    dtype = W_p.dtype
    blocks = []
    for k, c in enumerate(cset.contacts):
        force = jnp.concatenate([jnp.eye(3, dtype=dtype), skew(W_p[k] - W_p_CoM)])
        if c.dim == 6:
            moment = jnp.concatenate([jnp.zeros((3, 3), dtype), jnp.eye(3, dtype=dtype)])
            blocks.append(jnp.concatenate([force, moment], axis=1))
        else:
            blocks.append(force)
    return jnp.concatenate(blocks, axis=1)


def gravity_wrench(mass: float, dtype=jnp.float32) -> Array:
    """f_grav (6,): the weight as a centroidal wrench."""
    return jnp.array([0.0, 0.0, -mass * GRAVITY, 0.0, 0.0, 0.0], dtype=dtype)


def normal_force_rows(cset: ContactSet, W_R: Array) -> tuple[Array, Array]:
    """S (k, D), F (k,): ``S f`` = the normal forces of the k contacts that have a desired one F."""
    dtype = W_R.dtype
    rows, targets = [], []
    for k, (c, sl) in enumerate(zip(cset.contacts, cset.slices(), strict=True)):
        if math.isnan(c.normal_force):
            continue
        rows.append(jnp.zeros(cset.dim, dtype).at[sl.start : sl.start + 3].set(W_R[k][:, 2]))
        targets.append(jnp.asarray(c.normal_force, dtype))
    if not rows:
        return jnp.zeros((0, cset.dim), dtype), jnp.zeros(0, dtype)
    return jnp.stack(rows), jnp.stack(targets)


def normal_forces(cset: ContactSet, f: Array, W_R: Array) -> Array:
    """(K,) the normal force of each contact's wrench in f (D,)."""
    return jnp.stack([W_R[k][:, 2] @ f[sl.start : sl.start + 3] for k, sl in enumerate(cset.slices())])


def contact_violation(cset: ContactSet, f: Array, W_R: Array, activation: Array) -> Array:
    """(K,) each contact's ``max(C_k f_k - b_k, 0) / max(f_n,k, fz_min,k)``: its constraint
    violation relative to its own normal force (dimensionless). The minimum normal force is scaled
    by the activation (a contact being released may go down to zero)."""
    Cf = constraint_products(cset, W_R, f)
    excess = jnp.maximum(Cf - constraint_bounds(cset, activation.astype(f.dtype)), 0.0)
    owner = constraint_contact(cset)
    fn = -Cf[_contact_frame_rows(cset)[3]]  # the unilateral rows: -f_n <= -fz_min
    fz_min = jnp.asarray([c.params.fz_min for c in cset.contacts], f.dtype)
    # Each contact's largest excess (>= 0), one reduction over the rows for all contacts.
    per_contact = jnp.max(jnp.where(owner[None, :] == np.arange(len(cset.contacts))[:, None], excess, 0.0), axis=1)
    return per_contact / jnp.maximum(fn, fz_min)


def violation(cset: ContactSet, f: Array, W_R: Array, activation: Array) -> Array:
    """Max of :func:`contact_violation` over the active contacts (activation (K,) > 0)."""
    return jnp.max(jnp.where(activation > 0, contact_violation(cset, f, W_R, activation), 0.0))


def row_weights(cset: ContactSet) -> np.ndarray | None:
    """(M,) weights of the constraint rows in the QP solver's scaled problem
    (:func:`wbc_jax.control.qp.solve_qp`'s ``row_weight``): ``max_j fz_min_j / fz_min_k`` for the rows of
    contact k, so each contact's constraints are met to the same tolerance relative to its own
    smallest normal force (a hand's 1 N next to the feet's 10 N). None when every contact has the
    same fz_min (the two feet: the solver's unit rows, unchanged)."""
    fz_min = np.array([c.params.fz_min for c in cset.contacts])
    if np.all(fz_min == fz_min[0]):
        return None
    return (fz_min.max() / fz_min)[constraint_contact(cset)]


def measured_wrenches(
    cset: ContactSet, contact_pos: Array, contact_force: Array, contact_geom: Array, ngeom: int, W_p: Array
) -> Array:
    """The contact wrenches (D,) that the simulator applies on each contact (world axes, at the
    contact points W_p (K, 3); a point contact: the force only), summed over its collision geoms.

    Args:
      contact_pos: (C, 3) contact points; contact_force: (C, 3) world-axes force on geom 2 of each
        pair (zero for slots that do not touch); contact_geom: (C, 2) geom ids; ngeom: geom count.
    """
    owner = np.full(ngeom, -1)
    for k, c in enumerate(cset.contacts):
        owner[list(c.geoms)] = k
    # The force is on geom 2; the collision pipeline may order a pair either way (a sphere on a
    # box comes out as (sphere, box)), so find the robot's side of each contact.
    owner = jnp.asarray(owner)
    first, second = owner[contact_geom[:, 0]], owner[contact_geom[:, 1]]
    who = jnp.maximum(first, second)
    forces = jnp.where((second >= 0)[:, None], contact_force, -contact_force)
    out = []
    for k, c in enumerate(cset.contacts):
        F = jnp.where((who == k)[:, None], forces, 0.0)
        wrench = jnp.concatenate([F.sum(0), jnp.cross(contact_pos - W_p[k], F).sum(0)])
        out.append(wrench[: c.dim])
    return jnp.concatenate(out)


# ---------------------------------------------------------------------------------------------
# Formulations
