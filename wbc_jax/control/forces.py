"""The momentum rate distributed over the contact set: constraints, wrench map, QPs.

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

Every function takes a :class:`wbc_jax.robot.contacts.ContactSet` (static) and arrays of one state;
the constraint rows of a contact are named by :func:`constraint_rows`.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from wbc_jax.control import qp
from wbc_jax.control.constraints import (
    VIOLATION_TOL,
    constraint_bounds,
    constraint_contact,
    constraint_products,
    constraints,
    contact_violation,
    normal_force_rows,
    row_weights,
)
from wbc_jax.core.math import batch_any, cho_solve_spd
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.robot.contacts import ContactSet

FORCE_MODES = ("qp", "analytic")


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
    warm_start: bool = False  # the equality QP from the last tick's multipliers and slacks
    qp_tol: float | None = None  # the QPs' relative KKT tolerance (None: qp.default_tolerances)
    qp_unrolled_steps: int = 0  # Newton steps written out before the interior point's while loop
    qp_engine: str = "jax"  # the interior point's engine, qp.QP_ENGINES ("warp": one Warp kernel)

    def tolerance(self, dtype) -> float:
        """The largest :func:`contact_violation` a formulation's wrenches may have (else the next
        formulation is used): ``violation_tol`` or :data:`VIOLATION_TOL` of the precision."""
        return VIOLATION_TOL[jnp.dtype(dtype).itemsize] if self.violation_tol is None else self.violation_tol


def null_space(cset: ContactSet, A: Array, mask: Array, wrench_des: Array) -> tuple[Array, Array, Array, Array]:
    """``(f1 (D,), Z (D, D - 6), spare (D - 6,), keep (D,))`` of the momentum equality restricted to
    the contacts with ``mask`` (K,) = 1 (the other contacts' wrenches are zero): f1 = A^+ wrench_des,
    Z an orthonormal basis of null(A) over the kept coordinates ``keep``; its surplus columns (fewer
    kept coordinates) are zero and flagged in ``spare``.

    The basis: with N the orthogonal projector onto that null space, a kept surface contact p (the
    first) has an invertible 6 x 6 block of A, so the columns of N outside p's coordinates (N E)
    span the null space; ``Z = N E L^-T`` with ``L L' = (N E)'(N E)`` (Cholesky: with a 12 x 12
    eigensolver instead the null space cost twice as much on a CPU, benchmarks/force_build.py). L is held constant in derivatives (dZ = dN E
    L^-T, as :func:`range_basis`): the QP's solution ``Z y`` does not depend on the basis of the
    same space. A set that can keep three point contacts and no surface one uses
    :func:`range_basis` where it does."""
    D = cset.dim
    dtype = A.dtype
    keep = _row_mask(cset, mask)
    A_m = A * keep[None, :]
    A_pinv = cho_solve_spd(A_m @ A_m.T, A_m).T  # A_m has full row rank 6 (a sole is kept)
    f1 = A_pinv @ wrench_des
    N = keep[:, None] * (jnp.eye(D, dtype=dtype) - A_pinv @ A_m) * keep[None, :]
    selections, surface = _pivot_selections(cset)
    kept_surface = mask[surface] > 0
    pivot = kept_surface & (jnp.cumsum(kept_surface) == 1)  # the first kept surface contact
    E = jnp.tensordot(pivot.astype(dtype), jnp.asarray(selections, dtype), 1)  # (D, D - 6)
    spare = lax.stop_gradient(keep @ E) < 0.5  # free coordinates of dropped contacts (or no pivot)
    NE = N @ E
    L = jnp.linalg.cholesky(lax.stop_gradient(NE.T @ NE + jnp.diag(spare.astype(dtype))))
    Z = jax.scipy.linalg.solve_triangular(L, NE.T, lower=True).T
    if sum(c.type == "point" for c in cset.contacts) < 3:  # rank 6 needs a surface contact
        return f1, Z, spare, keep

    def eigen_basis():
        Z = range_basis(N, D - 6)
        spare = lax.stop_gradient(jnp.sum(Z * Z, axis=0)) < 0.5
        # Surplus columns are rounding noise: zero them, or the QP solver's unit-row scaling would
        # blow the noise up into a direction the wrenches could move along.
        return jnp.where(spare[None, :], 0.0, Z), spare

    Z, spare = lax.cond(batch_any(~jnp.any(kept_surface)), eigen_basis, lambda: (Z, spare))
    return f1, Z, spare, keep


def _pivot_selections(cset: ContactSet) -> tuple[np.ndarray, np.ndarray]:
    """``(E (S, D, D - 6), surface (S,))``: for each surface contact, the selection of the D - 6
    coordinates outside it, and the surface contacts' indices in the set."""
    surface = [k for k, c in enumerate(cset.contacts) if c.type == "surface"]
    E = np.zeros((len(surface), cset.dim, cset.dim - 6))
    for j, k in enumerate(surface):
        free = np.delete(np.arange(cset.dim), np.arange(cset.dim)[cset.slices()[k]])
        E[j, free, np.arange(cset.dim - 6)] = 1.0
    return E, np.asarray(surface, int)


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


def qp_start_rows(cset: ContactSet) -> int:
    """M, the constraint rows of the contact set: a QP warm start (``qp.QPInfo.start``) is (2, M)."""
    return len(constraint_contact(cset))


def cold_start(cset: ContactSet, dtype) -> Array:
    """(2, M) the warm start that means none: the next force QP starts cold."""
    return jnp.full((2, qp_start_rows(cset)), jnp.nan, dtype)


def momentum_equality_qp(
    cset: ContactSet,
    mask: Array,
    A: Array,
    wrench_des: Array,
    tt,
    W_R: Array,
    settings: ForceSettings,
    start: Array | None = None,
) -> tuple[Array, qp.QPInfo]:
    """The WBC QP (module docstring) over the contacts with ``mask`` = 1, the others' wrenches 0::

        min |tau_model + Sigma f|^2 + w_n |S_n f - F_n|^2   s.t.  A f = wrench_des,  C f <= b

    solved in y with f = f1 + Z y (f1 = A^+ wrench_des, Z a basis of null(A) over the kept
    contacts), as WBC's f0 formulation but well conditioned. With desired normal forces, the
    directions of y that change them are rescaled (:func:`_normal_force_scaling`).

    Args:
      mask: (K,) 1 for the contacts that may carry a wrench. A: (6, D) wrench map.
      wrench_des: (6,) L_dot* - f_grav. tt: anything with ``Sigma`` (n, D) and ``tau_model`` (n,)
        (:class:`wbc_jax.control.torques.TorqueTerms`). W_R: (K, 3, 3) contact frames.
      start: (2, M) ``info.start`` of the last tick's solve (:func:`wbc_jax.control.qp.solve_qp`), or None.

    Returns:
      ``(f (D,), info)``; where infeasible, f = f1 + Z y with y the unconstrained minimiser (the
      solver's fallback) and ``info.infeasible`` set.
    """
    dtype = A.dtype
    data = equality_qp_data(cset, mask, A, wrench_des, tt, W_R, settings)
    f1, Z = data.f1, data.Z
    if Z.shape[1] == 0:  # a single surface contact: the equality fixes the wrench
        C, b = constraints(cset, W_R, jnp.ones(len(cset.contacts), dtype))
        rows = jnp.linalg.norm(C, axis=1)
        row_kept = mask[jnp.asarray(constraint_contact(cset))] > 0
        excess = jnp.where(row_kept, (C @ f1 - b) / rows, 0.0)
        violation = jnp.max(excess)
        infeasible = violation > qp.default_tolerances(dtype)[1] * (1.0 + jnp.max(jnp.abs(f1)))
        zero = jnp.zeros((), dtype)
        return f1, qp.QPInfo(
            converged=~infeasible,
            infeasible=infeasible,
            max_violation=jnp.maximum(violation, 0.0),
            kkt_residual=zero,
            iterations=jnp.zeros((), jnp.int32),
            start=cold_start(cset, dtype),
        )
    y, info = qp.solve_qp(
        data.H,
        data.g,
        data.C,
        data.b,
        iterations=settings.qp_iterations,
        tol=settings.qp_tol,
        row_weight=row_weights(cset),
        start=start if settings.warm_start else None,
        unrolled=settings.qp_unrolled_steps,
        engine=settings.qp_engine,
    )
    return f1 + Z @ y, info


@pytree_dataclass
class EqualityQP:
    """The equality QP of :func:`momentum_equality_qp` in y (f = f1 + Z y): min 1/2 y'Hy + g'y s.t. C y <= b."""

    f1: Array  # (D,) A^+ wrench_des over the kept contacts
    Z: Array  # (D, n) the basis of null(A) over them (n = D - 6), rescaled for desired normal forces
    H: Array  # (n, n)
    g: Array  # (n,)
    C: Array  # (M, n)
    b: Array  # (M,)


def equality_qp_data(
    cset: ContactSet, mask: Array, A: Array, wrench_des: Array, tt, W_R: Array, settings: ForceSettings
) -> EqualityQP:
    """The QP that :func:`momentum_equality_qp` solves (arguments as there); with a single surface
    contact (n = 0) only f1 and Z are meaningful."""
    dtype = A.dtype
    f1, Z, spare, keep = null_space(cset, A, mask, wrench_des)
    if Z.shape[1] == 0:
        empty = jnp.zeros((0, 0), dtype)
        return EqualityQP(f1=f1, Z=Z, H=empty, g=jnp.zeros(0, dtype), C=empty, b=jnp.zeros(0, dtype))
    b = constraint_bounds(cset, jnp.ones(len(cset.contacts), dtype))
    row_kept = mask[jnp.asarray(constraint_contact(cset))] > 0
    S_n, F_n = normal_force_rows(cset, W_R)
    S_n = S_n * keep[None, :]
    w_n = settings.normal_force_weight
    if S_n.shape[0]:
        Z = Z @ _normal_force_scaling(S_n @ Z, w_n)
    # f1 and Z side by side, so that each product is one (on a CPU a tiny product's cost is its call):
    # R = [r, R_Z], the residuals of the cost |tau_model + Sigma f|^2 + w_n |S_n f - F_n|^2 at f1 and
    # their derivative along Z; then R_Z' R = [g, H] and C [f1, Z] = [C f1, C Z].
    F = jnp.concatenate([f1[:, None], Z], axis=1)
    R = (tt.Sigma @ F).at[:, 0].add(tt.tau_model)
    if S_n.shape[0]:
        R = jnp.concatenate([R, math.sqrt(w_n) * (S_n @ F).at[:, 0].add(-F_n)])
    gH = R[:, 1:].T @ R
    CF = constraint_products(cset, W_R, F)
    return EqualityQP(
        f1=f1,
        Z=Z,
        H=gH[:, 1:] + jnp.diag(settings.hessian_reg + spare.astype(dtype)),
        g=gH[:, 0],
        C=CF[:, 1:],
        b=jnp.where(row_kept, b - CF[:, 0], 1.0),  # rows of dropped contacts: 0 <= 1 (their wrench is 0)
    )


def soft_momentum_qp(
    cset: ContactSet, mask: Array, A: Array, wrench_des: Array, tt, W_R: Array, settings: ForceSettings
) -> tuple[Array, qp.QPInfo]:
    """The soft momentum QP over the contacts with ``mask`` = 1 (always feasible)::

        min |A f - wrench_des|_W^2 + c (|tau_model + Sigma f|^2 + w_n |S_n f - F_n|^2) + eps |f|^2
        s.t. C f <= b,   the other contacts' wrenches 0

    (c = ``settings.torque_weight_soft``; W = diag(1, 1, 1, a, a, a) with a =
    ``settings.angular_weight_soft``: a < 1 keeps the force that moves the CoM and gives up the
    angular-momentum rate first, results/tuning/angular_weight/). Arguments as :func:`momentum_equality_qp`."""
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
    x, info = qp.solve_qp(
        H,
        g,
        C * keep[None, :],
        jnp.where(row_kept, b, 1.0),
        iterations=settings.qp_iterations,
        tol=settings.qp_tol,
        row_weight=row_weights(cset),
        unrolled=settings.qp_unrolled_steps,
        engine=settings.qp_engine,
    )
    return keep * x, info


def wbc_qp(
    cset: ContactSet,
    mask: Array,
    A: Array,
    wrench_des: Array,
    tt,
    W_R: Array,
    settings: ForceSettings,
    start: Array | None = None,
) -> tuple[Array, Array, Array]:
    """:func:`momentum_equality_qp`, or :func:`soft_momentum_qp` where the equality is infeasible
    (a push asks for a momentum rate that no feasible wrench realises).

    The equality QP's wrenches are used only if every kept contact's own constraints hold within
    ``settings.tolerance`` relative to its normal force (:func:`contact_violation`): a solver that
    stops short of an infeasible problem can return a point whose violation is small next to the
    feet's forces but not next to a hand's (the 0.34 of a hand's normal force under pushes).

    Returns ``(f (D,), infeasible (), next_start (2, M))``: infeasible when the soft QP failed too
    (flagged, or its wrenches violate a contact's constraints beyond the tolerance); next_start
    the equality QP's ``info.start`` (``start``: the last tick's, or None)."""
    tol = settings.tolerance(A.dtype)

    def exceeds(f):
        return jnp.max(jnp.where(mask > 0, contact_violation(cset, f, W_R, mask), 0.0)) > tol

    f, info = momentum_equality_qp(cset, mask, A, wrench_des, tt, W_R, settings, start)

    def soft():
        f_soft, info_soft = soft_momentum_qp(cset, mask, A, wrench_des, tt, W_R, settings)
        return f_soft, info_soft.infeasible | exceeds(f_soft)

    use_soft = info.infeasible | exceeds(f)
    # The soft QP only in ticks where some environment of a batch needs it (batch_any), used
    # only where this one does.
    f_soft, soft_failed = lax.cond(batch_any(use_soft), soft, lambda: (f, jnp.zeros((), bool)))
    return jnp.where(use_soft, f_soft, f), use_soft & soft_failed, info.start


def analytic(cset: ContactSet, mask: Array, A: Array, wrench_des: Array, tt, settings: ForceSettings) -> Array:
    """The seed paper's C++ distribution over the contacts with ``mask`` = 1: least torque norm
    among the wrenches that realise the momentum rate, no inequality constraints (one foot:
    ``f = A_k^-1 wrench_des``). Returns f (D,)."""
    dtype = A.dtype
    f1, Z, spare, _ = null_space(cset, A, mask, wrench_des)
    if Z.shape[1] == 0:
        return f1
    SZ = tt.Sigma @ Z
    y = -jnp.linalg.solve(
        SZ.T @ SZ + jnp.diag(settings.hessian_reg + spare.astype(dtype)),
        SZ.T @ (tt.tau_model + tt.Sigma @ f1),
    )
    return f1 + Z @ y


def distribute(
    cset: ContactSet,
    activation: Array,
    A: Array,
    wrench_des: Array,
    tt,
    W_R: Array,
    settings: ForceSettings,
    start: Array | None = None,
) -> tuple[Array, Array, Array]:
    """Contact wrenches f (D,) for the momentum rate ``wrench_des`` (6,) = L_dot* - f_grav, with the
    blend of the module docstring over the activations (K,).

    ``start`` (2, M): the last tick's ``next_start`` (None or :func:`cold_start`: none), from
    which the engaged contacts' equality QP, solved every tick, is warm-started
    (``settings.warm_start``).

    Returns ``(f (D,), infeasible (), next_start (2, M))``: infeasible when a formulation in use had
    no feasible solution (its soft QP failed too); always False for ``analytic``; next_start the
    equality QP's multipliers and slacks for the next tick (NaN: none).
    """
    act = jnp.clip(activation, 0.0, 1.0)
    # Sets that cannot be empty (their wrench map must have rank 6): with no contact engaged the
    # wrenches are zero below; with none fully active, the most active ones stand in.
    any_engaged = jnp.any(act > 0)
    engaged = jnp.where(any_engaged, act > 0, True).astype(A.dtype)
    active = jnp.where(jnp.any(act >= 1), act >= 1, act >= jnp.max(act)).astype(A.dtype)
    w = jnp.min(jnp.where(act > 0, act, 1.0))

    def formulation(mask, start=None):
        if settings.mode == "analytic":
            return analytic(cset, mask, A, wrench_des, tt, settings), jnp.zeros((), bool), cold_start(cset, A.dtype)
        return wbc_qp(cset, mask, A, wrench_des, tt, W_R, settings, start)

    f_engaged, infeasible_engaged, next_start = formulation(engaged, start)
    # The fully active contacts' formulation only in ticks where a contact of some environment
    # of the batch ramps (w < 1), used only where one does.
    ramping = w < 1
    f_active, infeasible_active = lax.cond(
        batch_any(ramping),
        lambda: formulation(active)[:2],
        lambda: (jnp.zeros_like(f_engaged), jnp.zeros((), bool)),
    )
    f_active = jnp.where(ramping, f_active, 0.0)
    f = jnp.where(any_engaged, w * f_engaged + (1.0 - w) * f_active, 0.0)
    next_start = next_start if settings.warm_start else cold_start(cset, A.dtype)
    return f, any_engaged & ((w > 0) & infeasible_engaged | (w < 1) & infeasible_active), next_start
