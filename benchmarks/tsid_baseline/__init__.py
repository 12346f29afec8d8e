"""[TSID peer] A robot balanced by TSID (Pinocchio + eiquadprog, C++) on C MuJoCo physics: the iCub
by default, any robot of ``wbc_jax.robot.robots`` whose description has a URDF (``robot=``; Talos:
example-robot-data's URDF, its sole frames ``urdf_feet``). Everything robot-specific (MJCF, joints,
feet, CoP rectangle, default gains, the trunk role of ``push_body``) comes from the robot's
description; what follows describes the iCub, and holds for Talos with its own numbers.

    model.py          the packages, the plant's C model and contacts, wbc_jax's numbers, the task references
    controller.py     the TSID controller and its settings
    peer.py           the closed loop on C MuJoCo
    push_envelope.py  pushes: the LIP bound, the strict envelope by bisection, the full grid, the sensitivity

A real peer of wbc_jax on the CPU: the controller a user of this robot would otherwise write with
TSID (stack-of-tasks/tsid), on the same plant, tasks, pushes and metrics as the rest of the project,
so that the figures compare like for like. JAX-free: it imports numpy, mujoco, pinocchio, tsid,
:mod:`wbc_jax.robot.pinocchio` (the Pinocchio model and the state map; JAX-free too),
``benchmarks/baseline_cpu/`` (the closed-loop metrics, the reference table, pushes) and
``wbc_jax/core/constants.py`` / ``assets/build_icub_mjcf.py`` by file path.

Plant (as :func:`wbc_jax.robot.model.load_mj_model`): ``assets/icub/icub_23dof.xml`` without its visual
meshes, C MuJoCo at 1 kHz (the model's Newton solver, pyramidal cones, four 5 mm corner spheres per
sole), 23 torque motors saturated at their ctrlrange (+-60 N m; MuJoCo clamps ``ctrl`` to it, the
torques are clipped here first so that the metrics see the applied torque), pushes as a world-axes
force on the CoM of a body (default ``chest``) through ``xfrc_applied``, from an onset for a duration.
No auto-reset: a diverged state is restored to the tick's start and flagged (a NaN run), as in
:func:`baseline_cpu.simulate`.

Controller model: the icub-models ``iCubGazeboV2_5`` URDF in Pinocchio with a free flyer, reduced to
the 23 joints of ``DRIVEN_JOINTS`` (neck and wrists locked at 0, as in the MJCF). Its CoM, joint-space
mass matrix and sole frames equal C MuJoCo's to ~1e-12 at any state (``tests/test_tsid_baseline.py``):
the MJCF carries the URDF's masses and inertias at 12 digits, no armature, and the static links
fused into their moving parents as Pinocchio's reduction fuses them.

State map (:class:`wbc_jax.robot.pinocchio.StateMap`): MuJoCo's free joint is qpos = [p (world), quaternion (w, x, y, z)],
qvel = [dp/dt (world axes), omega (base axes)]; Pinocchio's free flyer is q = [p, quaternion (x, y, z,
w)], v = [R' dp/dt, omega] (both in base axes, R = the base orientation). The joints are reordered by
name (Pinocchio orders them depth-first through the URDF tree: legs, torso, arms). So v = T qvel with
T = blkdiag(R', I3, P) (P the joint permutation), and M_mujoco = T' M_pinocchio T.

Formulation (TSID ``InverseDynamicsFormulationAccForce``, variables the accelerations dv (29,) and the
3-D forces at the four corners of each sole's CoP rectangle (24,); ``SolverHQuadProgFast``, TSID's
eiquadprog HQP solver, once per 10 ms control tick, torques held for 10 physics steps):

* level 0 (constraints): the floating-base rows of the dynamics; per sole a ``Contact6d``: its motion
  constraint J dv + dJ v = -Kp e - Kd de with Kp = Kd = 0 (= the WBC's rigid contact, J nu_dot +
  dJ nu = 0), and its force constraints: a friction pyramid |f_t| <= mu f_n per corner and axis with
  mu the model's floor friction (the contact pairs' sliding friction, 1.0), the sum of the corners'
  normal forces >= ``FZ_MIN`` (the WBC's minimum normal force per foot) and <= ``FZ_MAX``;
  the corners are those of ``FOOT_SIZE`` (the WBC CoP rectangle, ``ContactParams.foot_size``, the
  rectangle of the metrics' support margin), so the CoP stays inside it;
* level 1 (one weighted least-squares cost): CoM (``TaskComEquality``), centroidal angular momentum
  (``TaskAMEquality``), joint posture (``TaskJointPosture``) and the contacts' force regularisation,
  weighted as :class:`TsidConfig`.

eiquadprog's HQP solves two levels (constraints, then one weighted cost), so the WBC's strict
hierarchy (the momentum task first, the postural task in its null space) becomes weights: the CoM
task at 1, the angular momentum at ``w_am`` = 1e-3 (about 1 / m^2: an angular-momentum-rate error of
1 N m weighs as a CoM-acceleration error of 1 / m m/s^2, i.e. as 1 N of linear-momentum rate, the
equal weighting of the WBC's momentum rows), the posture at 1e-3 (small: it yields to the momentum;
TSID's own biped examples use 1e-4 to 1e-1), the forces' regularisation at 1e-5 (TSID's examples).
The weights have no WBC counterpart and move the push envelope (``tsid_peer.py --sensitivity``).
The torque limits are not in the QP: with TSID's ``TaskActuationBounds`` as hard constraints (level
0), eiquadprog looped without returning on a 158.6 N, 0.1 s forward push.

Gains: the iCub's WBC defaults (``wbc_jax/robot/icub.py``) where the formulations correspond:

* K_P,CoM = (50, 50, 10), K_D,CoM = 2 sqrt(K_P,CoM) / 20 -> ``TaskComEquality`` Kp, Kd: the same
  law (the WBC asks the momentum rate m (c_ddot_ref - K_P e - K_D e_dot), TSID the CoM acceleration
  c_ddot_ref - K_P e - K_D e_dot). K_I,CoM = 0 by default, and TSID's CoM task has no integral.
* K_P,w = 1 -> ``TaskAMEquality`` Kp: TSID asks L_dot = -Kp (L - L_ref) + L_dot_ref with L_ref = 0,
  the WBC's -K_P,w L.
* K_I,w = 0.25: no counterpart. The WBC adds -K_I,w J_G,ang (s - s_des), the integral of the angular
  momentum; TSID's angular-momentum task has none (its Kd is unused). The posture task holds the
  posture instead.
* the postural k_p (per joint) and k_d = 2 sqrt(k_p) / 20: cannot correspond. The WBC postural task
  is a torque, -k_p (s - s_des) - k_d s_dot projected into the null space of the momentum task; TSID's
  is a joint-acceleration PD, s_ddot = -Kp (s - s_des) - Kd s_dot. The same numbers are taken as
  acceleration gains (1/s^2) with TSID's critical damping Kd = 2 sqrt(Kp): with the WBC's damping
  ratio 0.05 on accelerations the posture rings (the stand task's CoM error grows ~100x).

The model's joint damping (1 N m s/rad per joint, from the URDF) is compensated, tau += D s_dot, as
the WBC controller's ``compensate_passive`` does by default. A tick whose QP fails (eiquadprog status
!= 0) keeps the previous torques and counts in ``qp_infeasible_ticks``.

Metrics: ``baseline_cpu.LoopMetrics`` (one implementation with the NumPy baseline, the quantities of
``wbc_jax.sim.loop.ClosedLoop``: CoM from MuJoCo's ``subtree_com``, the sole sites, the anchors at the start),
named by ``baseline_cpu.summary_columns`` as ``constants.METRIC_NAMES``; ``survived`` is the strict
criterion of ``constants.SURVIVAL_CRITERION``. ``max_constraint_violation``: the largest violation of
TSID's own contact-force inequalities by the commanded corner forces, divided by the foot's normal
force (at least ``FZ_MIN``), as ``wbc_jax.control.constraints.violation`` normalises.

References (:func:`make_schedule`): the ``stand`` and ``sinusoid`` tasks of
:func:`wbc_jax.control.references.make_schedule` (CoM at its initial value; plus 2 cm along world y at
0.2 Hz from t = 0; posture at the home keyframe; both feet active), evaluated with
``baseline_cpu.schedule_table``.
"""

from .controller import TsidConfig, TsidController
from .model import (
    DRIVEN_JOINTS,
    FEET,
    FOOT_SIZE,
    FZ_MAX,
    FZ_MIN,
    MODEL_XML,
    SINE_AMPLITUDE,
    SINE_AXIS,
    SINE_FREQUENCY,
    TASK_DURATION,
    TASKS,
    TSID_PINOCCHIO,
    TaskSchedule,
    bc,
    body_id,
    constants,
    floor_friction,
    load_mj_model,
    make_schedule,
    non_foot_bodies,
    sole_contact_rectangle,
    tsid_problem,
)
from .peer import TsidPeer, simulate

__all__ = [
    "DRIVEN_JOINTS",
    "FEET",
    "FOOT_SIZE",
    "FZ_MAX",
    "FZ_MIN",
    "MODEL_XML",
    "SINE_AMPLITUDE",
    "SINE_AXIS",
    "SINE_FREQUENCY",
    "TASK_DURATION",
    "TASKS",
    "TSID_PINOCCHIO",
    "TaskSchedule",
    "TsidConfig",
    "TsidController",
    "TsidPeer",
    "bc",
    "body_id",
    "constants",
    "floor_friction",
    "load_mj_model",
    "make_schedule",
    "non_foot_bodies",
    "simulate",
    "sole_contact_rectangle",
    "tsid_problem",
]
