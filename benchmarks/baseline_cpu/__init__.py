"""[CPU baseline] C MuJoCo stepping + the balancing controller in NumPy, one process per core.

    spec.py        what a worker needs (constants, the task's spec, references, the C model)
    tasks.py       specs from the package's set-ups; gains and pushes as arrays
    controller.py  the controller tick in NumPy, its QPs on quadprog
    loop.py        the closed loop on C MuJoCo and its metrics
    workers.py     one process per core; the benchmark's scenario (worker.py: a worker's script)

This is the baseline a user would write without JAX/MJX, used only by the benchmark
(``benchmarks/benchmark.py``): the controller of :mod:`wbc_jax.control.controller` on the default contact
set (the two soles) reproduced equation for equation in NumPy (batched over the environments of a
worker with stacked ``np.linalg`` calls), the dynamics terms read from C MuJoCo, the contact-wrench
QPs solved with ``quadprog`` (Goldfarb-Idnani, C), physics with ``mujoco.mj_step`` at 1 kHz, the
controller at 100 Hz with zero-order hold, pushes through ``xfrc_applied`` on the CoM of the push
body, and the metrics of :class:`wbc_jax.sim.loop.ClosedLoop`.

Dynamics terms from C MuJoCo (mixed representation, controller joint order, as
:func:`wbc_jax.robot.dynamics.terms` with the two sole frames; ``T = blkdiag(I3, W_R_B, I_n)``):

* ``M = T^-T M_mj T^-1`` with ``M_mj`` from ``mj_fullM``; ``h = T^-T qfrc_bias``,
  ``tau_passive = T^-T qfrc_passive``;
* sole Jacobians ``J = J_mj T^-1`` from ``mj_jacSite`` (``J_frames``); ``Jdot nu = Jdot_mj qvel``
  from ``mj_jacDot`` (exact: d/dt(T^-1) nu = 0, see :mod:`wbc_jax.robot.dynamics`); the sole frames
  ``site_xmat`` (= ``W_R_frames[k] @ foot_rotations[k]``, the contact frames of the feet);
* CoM, CoM velocity and the centroidal angular momentum from ``subtree_com``,
  ``mj_subtreeVel`` -> ``subtree_linvel``/``subtree_angmom`` of the base body;
* J_G,ang (Nava 2016) at the postural reference: from C MuJoCo Jacobians
  (:func:`centroidal_jacobian_ref`), or taken from the JAX controller state
  (``controller.init``, :func:`spec_from_setup`).

The loop uses the split step of C MuJoCo: ``mj_step1`` (position- and velocity-dependent
computations at the current state, which the controller reads) -> controller -> ``ctrl`` ->
``mj_step2``; with the Euler integrator this is exactly ``mj_step``, so the controller costs no
extra ``mj_forward``. The other 9 physics steps of a tick are plain ``mj_step``.

Force distribution (:func:`wbc_jax.control.forces.distribute` for the two feet): with activations a_k,
the engaged feet (a_k > 0) and the fully active ones (a_k = 1) each get the formulation, restricted
to them, and ``f = w f_engaged + (1 - w) f_active`` with ``w = min a_k`` over the engaged feet.
The formulation (:func:`wbc_jax.control.forces.wbc_qp`): the momentum-equality QP ``min |tau_model +
Sigma f|^2 s.t. A f = L_dot* - f_grav, C f <= b`` in ``f = f1 + Z y``; where it is infeasible, the
soft momentum QP ``min |A f - w|^2 + c |tau_model + Sigma f|^2 + eps |f|^2 s.t. C f <= b``. For
two feet the orthonormal basis Z of null(A) comes from a QR factorisation instead of an SVD
(changes y by a rotation, not f); for one foot null(A) is empty: ``f1 = A_k^-1 w`` is the equality
QP's only point, kept if it meets the foot's constraints (to the JAX solver's relative tolerance),
else the soft QP. quadprog solves ``min 1/2 x'Gx - a'x, C'x >= b``, so it is called with
``(H, -g, -C', -b)``; when it reports infeasibility the result is ``-(H + ridge I)^-1 g`` and the
tick is flagged, as in the JAX code. Formulations the JAX code skips by ``lax.cond`` (the active
feet's one while no foot ramps, the soft QP while the equality is feasible) are skipped here too.
The postural projector pinv(X, tol) X = V diag(sigma > tol) V' is built from ``eigh(X'X)``
instead of the SVD of X (same V and sigma^2, cheaper).

Workers: ``run_parallel`` starts ``n_workers`` processes with the ``spawn`` context; each runs
``worker.py`` through ``runpy.run_path`` (not ``import wbc_jax...``, whose package ``__init__``
imports JAX/MJX, ~3 s and ~200 MB per worker), so a worker imports only numpy, mujoco, quadprog
and ``wbc_jax/core/constants.py`` (loaded by file path, ``spec.py``). (As always with ``spawn``, the parent's
``__main__`` script is re-imported in the children: keep heavy imports of a driver script under
``if __name__ == "__main__"`` or inside functions.) The parent builds a picklable, JAX-free job
(model, indices, references at the ticks, constants) with :func:`spec_from_setup` (from a
:class:`wbc_jax.sim.scenario.Setup`) or :func:`make_spec` (the same, from a task name).
"""

from .controller import NumpyController, Terms, solve_qp
from .loop import LoopMetrics, polygon_margin, push_force, rectangle_corners, simulate, summarize, summary_columns
from .spec import (
    FORCE_MODES,
    GAIN_FIELDS,
    GRAVITY,
    METRIC_NAMES,
    POSTURAL_VARIANTS,
    QP_FALLBACK_TOL,
    RECOVERY_THRESHOLD,
    BaselineSpec,
    constants,
    schedule_table,
    solver_model,
)
from .tasks import centroidal_jacobian_ref, gains_to_numpy, make_spec, push_to_numpy, spec_from_setup
from .workers import benchmark, cpu_name, run_parallel

__all__ = [
    "FORCE_MODES",
    "GAIN_FIELDS",
    "GRAVITY",
    "METRIC_NAMES",
    "POSTURAL_VARIANTS",
    "QP_FALLBACK_TOL",
    "RECOVERY_THRESHOLD",
    "BaselineSpec",
    "LoopMetrics",
    "NumpyController",
    "Terms",
    "benchmark",
    "centroidal_jacobian_ref",
    "constants",
    "cpu_name",
    "gains_to_numpy",
    "make_spec",
    "polygon_margin",
    "push_force",
    "push_to_numpy",
    "rectangle_corners",
    "run_parallel",
    "schedule_table",
    "simulate",
    "solve_qp",
    "solver_model",
    "spec_from_setup",
    "summarize",
    "summary_columns",
]
