"""[contact forces] The momentum rate distributed over the contact set: constraints, wrench map, QPs.

The momentum task asks for ``L_dot* - f_grav = A f`` with ``f`` (D,) the stacked contact wrenches
(world axes, at the contact points). The WBC balancing controller (robotology whole-body-controllers,
seed paper) picks, among the wrenches that realise it, those that minimise the joint torques,
inside each contact's rigid-contact constraints::

    minimise_f  |tau_model + Sigma f|^2 + w_n |S_n f - F_n|^2
    subject to  A f = L_dot* - f_grav        (f = f1 + Z y,  Z a basis of null(A), as in WBC)
                C f <= b                     (friction cone, torsion, CoP, f_n >= fz_min)

(``w_n |S_n f - F_n|^2``: desired normal forces, a hand pressing a table, Nori et al. 2015). When
a push asks for a momentum rate that no feasible wrench realises, the equality becomes the
leading cost term instead (the soft momentum QP): ``min |A f - w|^2 + c (the cost above)``,
always feasible (its angular rows optionally weighed down: ``angular_weight_soft``). ``analytic``
is the seed paper's C++: the same least-squares torque minimisation without inequality constraints.

Contact switching (the one-foot blend of codyco ``torqueBalancing``, for any contact set): with
activations a_k, the engaged contacts (a_k > 0) and the fully active ones (a_k = 1) each get the
formulation above, restricted to them, and ``f = w f_engaged + (1 - w) f_active`` with
``w = min a_k`` over the engaged contacts, so the wrenches stay continuous while a contact is
loaded or unloaded. With the two feet and one of them ramping this is WBC's blend of the two-feet
QP and the one-foot QP.

Every function takes a :class:`wbc_jax.contacts.ContactSet` (static) and arrays of one state;
the constraint rows of a contact are named by :func:`constraint_rows`.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
from jax import lax

from wbc_jax import qp
from wbc_jax.constants import GRAVITY
from wbc_jax.contacts import ContactParams, ContactSet
from wbc_jax.math import batch_any, skew
from wbc_jax.types import Array

FORCE_MODES = ("qp", "analytic")
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


def world_constraints(C_local: np.ndarray | Array, b: np.ndarray | Array, W_R: Array) -> tuple[Array, Array]:
    """Constraints of a world-axes wrench (force, moment: each rotated by ``W_R'``) from those in the
    contact frame. C_local: (m, 6) or (m, 3); W_R: (3, 3) contact frame -> world."""
    R = jnp.asarray(W_R)
    C_local = jnp.asarray(C_local, R.dtype)
    blocks = [C_local[:, k : k + 3] @ R.T for k in range(0, C_local.shape[1], 3)]
    return jnp.concatenate(blocks, axis=1), jnp.asarray(b, R.dtype)


def constraints(cset: ContactSet, W_R: Array, fz_min_scale: Array) -> tuple[Array, Array]:
    """Block-diagonal ``C`` (M, D), ``b`` (M,) of all contacts, world axes.

    Args:
      cset: the contact set. W_R: (K, 3, 3) contact frames.
      fz_min_scale: (K,) multiplies each contact's minimum normal force (the activation when the
        violation of a contact being released is measured; 1 in the QPs).
    """
    dtype = W_R.dtype
    blocks, bs = [], []
    for k, c in enumerate(cset.contacts):
        C_local, b_local = contact_constraints(c.params, c.type)
        unilateral = constraint_rows(c.params, c.type).unilateral
        C_w, b_w = world_constraints(C_local, b_local, W_R[k])
        blocks.append(C_w)
        bs.append(b_w.at[unilateral].multiply(fz_min_scale[k]))
    rows = sum(b.shape[0] for b in blocks)
    C = jnp.zeros((rows, cset.dim), dtype)
    r = 0
    for blk, sl in zip(blocks, cset.slices(), strict=True):
        C = C.at[r : r + blk.shape[0], sl].set(blk)
        r += blk.shape[0]
    return C, jnp.concatenate(bs)


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
    C, b = constraints(cset, W_R, activation)
    excess = jnp.maximum(C @ f - b, 0.0)
    owner = constraint_contact(cset)
    fn = normal_forces(cset, f, W_R)
    fz_min = jnp.asarray([c.params.fz_min for c in cset.contacts], f.dtype)
    per_contact = jnp.stack([jnp.max(excess[owner == k]) for k in range(len(cset.contacts))])
    return per_contact / jnp.maximum(fn, fz_min)


def violation(cset: ContactSet, f: Array, W_R: Array, activation: Array) -> Array:
    """Max of :func:`contact_violation` over the active contacts (activation (K,) > 0)."""
    return jnp.max(jnp.where(activation > 0, contact_violation(cset, f, W_R, activation), 0.0))


def row_weights(cset: ContactSet) -> np.ndarray | None:
    """(M,) weights of the constraint rows in the QP solver's scaled problem
    (:func:`wbc_jax.qp.solve_qp`'s ``row_weight``): ``max_j fz_min_j / fz_min_k`` for the rows of
    contact k, so each contact's constraints are met to the same tolerance relative to its own
    smallest normal force (a hand's 1 N next to the feet's 10 N). None when every contact has the
    same fz_min (the two feet: the solver's unit rows, unchanged)."""
    fz_min = np.array([c.params.fz_min for c in cset.contacts])
    if np.all(fz_min == fz_min[0]):
        return None
    return (fz_min.max() / fz_min)[constraint_contact(cset)]


def measured_wrenches(cset: ContactSet, contact_pos: Array, contact_force: Array, contact_geom: Array,
                      ngeom: int, W_p: Array) -> Array:  # fmt: skip
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


def range_basis(N: Array, dim: int) -> Array:
    """(k, dim) basis Z of range(N) for a symmetric projector N (k, k), differentiable through N.

    ``Q`` = the eigenvectors of the ``dim`` largest eigenvalues of ``stop_gradient(N)``, then
    ``Z = N Q``. For a projector ``N Q = Q``, so Z is orthonormal at the evaluation point, while its
    derivative ``dN Q`` carries the rotation of the range. Differentiating an eigenbasis directly
    would divide by the gaps between the repeated eigenvalues 1 of the projector (NaN); the QP's
    solution ``Z y`` does not depend on the basis of the same range. Where ``rank(N) < dim`` the
    surplus columns are zero (up to rounding). A symmetric eigensolver, not an SVD: the
    eigenvalues 0 and 1 are a gap of 1 apart, and batched on a GPU it is the cheaper of the two.
    """
    _, V = jnp.linalg.eigh(lax.stop_gradient(N))  # ascending eigenvalues
    return N @ V[:, ::-1][:, :dim]


@dataclasses.dataclass(frozen=True)
class ForceSettings:
    """What the formulations need from the controller's configuration (hashable)."""

    mode: str = "qp"
    hessian_reg: float = 1e-7
    qp_iterations: int = qp.DEFAULT_ITERATIONS
    torque_weight_soft: float = 1e-4  # |tau|^2 against |A f - w|^2 (N^2 vs (N m)^2), soft QP
    angular_weight_soft: float = 1.0  # the angular rows of |A f - w|^2 against the linear ones, soft QP
    normal_force_weight: float = 1e3  # desired normal forces, per N^2 against (N m)^2
    violation_tol: float | None = None  # accepted contact_violation of a QP's wrenches (None: by dtype)

    def tolerance(self, dtype) -> float:
        """The largest :func:`contact_violation` a formulation's wrenches may have (else the next
        formulation is used): ``violation_tol`` or :data:`VIOLATION_TOL` of the precision."""
        return VIOLATION_TOL[jnp.dtype(dtype).itemsize] if self.violation_tol is None else self.violation_tol


def _restricted(cset: ContactSet, A: Array, mask: Array, wrench_des: Array):
    """f1, Z of the momentum equality restricted to the contacts with ``mask`` (K,) = 1: the other
    contacts' wrenches are zero. Z (D, D - 6) spans null(A) over the kept coordinates; its surplus
    columns (fewer kept coordinates) are zero and flagged in ``spare`` (D - 6,)."""
    D = cset.dim
    dtype = A.dtype
    keep = _row_mask(cset, mask)
    A_m = A * keep[None, :]
    A_pinv = jnp.linalg.solve(A_m @ A_m.T, A_m).T  # A_m has full row rank 6 (a sole is kept)
    f1 = A_pinv @ wrench_des
    N = keep[:, None] * (jnp.eye(D, dtype=dtype) - A_pinv @ A_m) * keep[None, :]
    Z = range_basis(N, D - 6)
    spare = lax.stop_gradient(jnp.sum(Z * Z, axis=0)) < 0.5
    # Surplus columns are rounding noise: zero them, or the QP solver's unit-row scaling would
    # blow the noise up into a direction the wrenches could move along.
    return f1, jnp.where(spare[None, :], 0.0, Z), spare, keep


def _row_mask(cset: ContactSet, mask: Array) -> Array:
    return jnp.concatenate([jnp.full(c.dim, mask[k]) for k, c in enumerate(cset.contacts)])


def _normal_force_scaling(NZ: Array, weight: float) -> Array:
    """T (m, m): the change of variables y = T u that scales the k directions of y that move the
    desired normal forces (the row space of NZ = S_n Z, (k, m)) so that ``weight |NZ T u|^2`` is
    ``|u|^2`` there, and leaves the others alone. Without it the Hessian sums the torque terms
    (eigenvalues 1e-2 to 1) with ``weight`` (1e3) x a rank-k term: in float32 the rounding of
    the large term (1e-7 x 1e3) swamps the weakly determined directions (the weights' split
    between the feet), whose solution then jumped by several N from tick to tick in closed loop.
    A change of basis of null(A): the minimiser f is the same (held constant in derivatives)."""
    _, s, Vt = jnp.linalg.svd(lax.stop_gradient(NZ), full_matrices=False)
    scale = jnp.where(s > 1e-3, 1.0 / (math.sqrt(weight) * jnp.maximum(s, 1e-3)), 1.0)
    return jnp.eye(NZ.shape[1], dtype=NZ.dtype) + (Vt.T * (scale - 1.0)) @ Vt


def momentum_equality_qp(cset: ContactSet, mask: Array, A: Array, wrench_des: Array, tt, W_R: Array,
                         settings: ForceSettings) -> tuple[Array, qp.QPInfo]:  # fmt: skip
    """The WBC QP (module docstring) over the contacts with ``mask`` = 1, the others' wrenches 0::

        min |tau_model + Sigma f|^2 + w_n |S_n f - F_n|^2   s.t.  A f = wrench_des,  C f <= b

    solved in y with f = f1 + Z y (f1 = A^+ wrench_des, Z a basis of null(A) over the kept
    contacts), as WBC's f0 formulation but well conditioned. With desired normal forces, the
    directions of y that change them are rescaled (:func:`_normal_force_scaling`).

    Args:
      mask: (K,) 1 for the contacts that may carry a wrench. A: (6, D) wrench map.
      wrench_des: (6,) L_dot* - f_grav. tt: anything with ``Sigma`` (n, D) and ``tau_model`` (n,)
        (:class:`wbc_jax.torques.TorqueTerms`). W_R: (K, 3, 3) contact frames.

    Returns:
      ``(f (D,), info)``; where infeasible, f = f1 + Z y with y the unconstrained minimiser (the
      solver's fallback) and ``info.infeasible`` set.
    """
    dtype = A.dtype
    f1, Z, spare, keep = _restricted(cset, A, mask, wrench_des)
    C, b = constraints(cset, W_R, jnp.ones(len(cset.contacts), dtype))
    row_kept = mask[jnp.asarray(constraint_contact(cset))] > 0
    S_n, F_n = normal_force_rows(cset, W_R)
    if Z.shape[1] == 0:  # a single surface contact: the equality fixes the wrench
        rows = jnp.linalg.norm(C, axis=1)
        excess = jnp.where(row_kept, (C @ f1 - b) / rows, 0.0)
        violation = jnp.max(excess)
        infeasible = violation > qp.default_tolerances(dtype)[1] * (1.0 + jnp.max(jnp.abs(f1)))
        zero = jnp.zeros((), dtype)
        return f1, qp.QPInfo(converged=~infeasible, infeasible=infeasible, max_violation=jnp.maximum(violation, 0.0),
                             kkt_residual=zero, iterations=jnp.zeros((), jnp.int32))  # fmt: skip
    S_n = S_n * keep[None, :]
    w_n = settings.normal_force_weight
    if S_n.shape[0]:
        Z = Z @ _normal_force_scaling(S_n @ Z, w_n)
    SZ, NZ = tt.Sigma @ Z, S_n @ Z
    H = SZ.T @ SZ + w_n * NZ.T @ NZ + jnp.diag(settings.hessian_reg + spare.astype(dtype))
    g = SZ.T @ (tt.tau_model + tt.Sigma @ f1) + w_n * NZ.T @ (S_n @ f1 - F_n)
    # Rows of dropped contacts: 0 <= 1, trivially met (their wrench is zero).
    y, info = qp.solve_qp(H, g, C @ Z, jnp.where(row_kept, b - C @ f1, 1.0), iterations=settings.qp_iterations,
                          row_weight=row_weights(cset))  # fmt: skip
    return f1 + Z @ y, info


def soft_momentum_qp(cset: ContactSet, mask: Array, A: Array, wrench_des: Array, tt, W_R: Array,
                     settings: ForceSettings) -> tuple[Array, qp.QPInfo]:  # fmt: skip
    """The soft momentum QP over the contacts with ``mask`` = 1 (always feasible)::

        min |A f - wrench_des|_W^2 + c (|tau_model + Sigma f|^2 + w_n |S_n f - F_n|^2) + eps |f|^2
        s.t. C f <= b,   the other contacts' wrenches 0

    (c = ``settings.torque_weight_soft``; W = diag(1, 1, 1, a, a, a) with a =
    ``settings.angular_weight_soft``: a < 1 keeps the force that moves the CoM and gives up the
    angular-momentum rate first, docs/tuning/README.md). Arguments as :func:`momentum_equality_qp`."""
    dtype = A.dtype
    keep = _row_mask(cset, mask)
    C, b = constraints(cset, W_R, jnp.ones(len(cset.contacts), dtype))
    row_kept = mask[jnp.asarray(constraint_contact(cset))] > 0
    S_n, F_n = normal_force_rows(cset, W_R)
    c, w_n = settings.torque_weight_soft, settings.normal_force_weight
    Ak, Sk, Nk = A * keep[None, :], tt.Sigma * keep[None, :], S_n * keep[None, :]
    rows = jnp.asarray([1.0, 1.0, 1.0] + [settings.angular_weight_soft] * 3, dtype)
    H = Ak.T @ (rows[:, None] * Ak) + c * (Sk.T @ Sk + w_n * Nk.T @ Nk) + jnp.diag(settings.hessian_reg + 1.0 - keep)
    g = -Ak.T @ (rows * wrench_des) + c * (Sk.T @ tt.tau_model - w_n * Nk.T @ F_n)
    x, info = qp.solve_qp(H, g, C * keep[None, :], jnp.where(row_kept, b, 1.0), iterations=settings.qp_iterations,
                          row_weight=row_weights(cset))  # fmt: skip
    return keep * x, info


def wbc_qp(cset: ContactSet, mask: Array, A: Array, wrench_des: Array, tt, W_R: Array,
           settings: ForceSettings) -> tuple[Array, Array]:  # fmt: skip
    """:func:`momentum_equality_qp`, or :func:`soft_momentum_qp` where the equality is infeasible
    (a push asks for a momentum rate that no feasible wrench realises).

    The equality QP's wrenches are used only if every kept contact's own constraints hold within
    ``settings.tolerance`` relative to its normal force (:func:`contact_violation`): a solver that
    stops short of an infeasible problem can return a point whose violation is small next to the
    feet's forces but not next to a hand's (the 0.34 of a hand's normal force under pushes).

    Returns ``(f (D,), infeasible ())``: infeasible when the soft QP failed too (flagged, or its
    wrenches violate a contact's constraints beyond the tolerance)."""
    tol = settings.tolerance(A.dtype)

    def exceeds(f):
        return jnp.max(jnp.where(mask > 0, contact_violation(cset, f, W_R, mask), 0.0)) > tol

    f, info = momentum_equality_qp(cset, mask, A, wrench_des, tt, W_R, settings)

    def soft():
        f_soft, info_soft = soft_momentum_qp(cset, mask, A, wrench_des, tt, W_R, settings)
        return f_soft, info_soft.infeasible | exceeds(f_soft)

    use_soft = info.infeasible | exceeds(f)
    # The soft QP only in ticks where some environment of a batch needs it (batch_any), used
    # only where this one does.
    f_soft, soft_failed = lax.cond(batch_any(use_soft), soft, lambda: (f, jnp.zeros((), bool)))
    return jnp.where(use_soft, f_soft, f), use_soft & soft_failed


def analytic(cset: ContactSet, mask: Array, A: Array, wrench_des: Array, tt, settings: ForceSettings) -> Array:
    """The seed paper's C++ distribution over the contacts with ``mask`` = 1: least torque norm
    among the wrenches that realise the momentum rate, no inequality constraints (one foot:
    ``f = A_k^-1 wrench_des``). Returns f (D,)."""
    dtype = A.dtype
    f1, Z, spare, _ = _restricted(cset, A, mask, wrench_des)
    if Z.shape[1] == 0:
        return f1
    SZ = tt.Sigma @ Z
    y = -jnp.linalg.solve(
        SZ.T @ SZ + jnp.diag(settings.hessian_reg + spare.astype(dtype)),
        SZ.T @ (tt.tau_model + tt.Sigma @ f1),
    )
    return f1 + Z @ y


def distribute(cset: ContactSet, activation: Array, A: Array, wrench_des: Array, tt, W_R: Array,
               settings: ForceSettings) -> tuple[Array, Array]:  # fmt: skip
    """Contact wrenches f (D,) for the momentum rate ``wrench_des`` (6,) = L_dot* - f_grav, with the
    blend of the module docstring over the activations (K,).

    Returns ``(f (D,), infeasible ())``: infeasible when a formulation in use had no feasible
    solution (its soft QP failed too); always False for ``analytic``.
    """
    act = jnp.clip(activation, 0.0, 1.0)
    # Sets that cannot be empty (their wrench map must have rank 6): with no contact engaged the
    # wrenches are zero below; with none fully active, the most active ones stand in.
    any_engaged = jnp.any(act > 0)
    engaged = jnp.where(any_engaged, act > 0, True).astype(A.dtype)
    active = jnp.where(jnp.any(act >= 1), act >= 1, act >= jnp.max(act)).astype(A.dtype)
    w = jnp.min(jnp.where(act > 0, act, 1.0))

    def formulation(mask):
        if settings.mode == "analytic":
            return analytic(cset, mask, A, wrench_des, tt, settings), jnp.zeros((), bool)
        return wbc_qp(cset, mask, A, wrench_des, tt, W_R, settings)

    f_engaged, infeasible_engaged = formulation(engaged)
    # The fully active contacts' formulation only in ticks where a contact of some environment
    # of the batch ramps (w < 1), used only where one does.
    ramping = w < 1
    f_active, infeasible_active = lax.cond(
        batch_any(ramping), lambda: formulation(active), lambda: (jnp.zeros_like(f_engaged), jnp.zeros((), bool))
    )
    f_active = jnp.where(ramping, f_active, 0.0)
    f = jnp.where(any_engaged, w * f_engaged + (1.0 - w) * f_active, 0.0)
    return f, any_engaged & ((w > 0) & infeasible_engaged | (w < 1) & infeasible_active)
