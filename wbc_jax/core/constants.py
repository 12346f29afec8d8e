"""Numbers and names shared by the package and the NumPy CPU baseline (``benchmarks/``).

This module imports neither JAX nor MuJoCo: the baseline's worker processes load it alone.
Sources of the numbers: the whole-body-controllers conventions (robotology) and the measurements in
results/ of this repository; robot-specific numbers live in the robot descriptions (wbc_jax/robot/).
"""

from __future__ import annotations

GRAVITY = 9.81  # m/s^2, as in the papers and MuJoCo's default

# ---------------------------------------------------------------------------------------------
# Controller gains (their default values belong to each robot: wbc_jax/robot/<name>.py)

GAIN_FIELDS = ("kp_com", "kd_com", "ki_com", "kp_ang", "ki_ang", "kp_postural", "kd_postural")
# ki_com may be 0 in a gains file (the WBC law has no CoM integral); the others must be > 0.
NON_NEGATIVE_GAINS = ("ki_com",)
# Gains files are checked against these ranges (a gain outside is a typo, not a setting).
GAIN_RANGES = {
    "kp_com": (0.0, 1e4),
    "kd_com": (0.0, 1e3),
    "ki_com": (0.0, 1e4),
    "kp_ang": (0.0, 1e3),
    "ki_ang": (0.0, 1e3),
    "kp_postural": (0.0, 1e4),
    "kd_postural": (0.0, 1e3),
}


# ---------------------------------------------------------------------------------------------
# Physical ranges of the jobs' flags (wbc_jax.core.options declarations; one place for all jobs)

MAX_HORIZON_S = 600.0  # simulated seconds of one rollout: ten minutes of balancing
MAX_PUSH_N = 5000.0  # 5 g on a 100 kg humanoid for the push's length: beyond it a typo
MAX_PUSH_DURATION_S = 60.0
# One physics step of the model (1 kHz): a shorter push would be spread over the step (its impulse
# kept, its force not); longer ones need not be whole steps (wbc_jax.sim.state.push_forces).
MIN_PUSH_DURATION_S = 0.001
MAX_JOINT_NOISE_RAD = 0.5  # 29 deg std: beyond it the initial postures leave the joint ranges
FRICTION_RANGE = (0.01, 10.0)  # floor friction of the plant
MASS_SCALE_RANGE = (0.1, 10.0)  # plant mass scale
GAIN_SCALE_RANGE = (0.01, 100.0)  # scalings of a gain set
ANGULAR_WEIGHT_RANGE = (0.0, 1e4)  # the soft QP's angular weight: (open, closed]
MAX_SOLVER_ITERATIONS = 1000
MAX_SEED = 2**32 - 1

# ---------------------------------------------------------------------------------------------
# Closed loop and metrics

CONTROL_DT = 0.01  # s: the controller at 100 Hz (physics at the model's 1 kHz)
RECOVERY_THRESHOLD = 0.01  # m: "recovered" = CoM back within 1 cm of its reference
FALL_COM_HEIGHT = 0.7  # a fall: CoM below this fraction of its initial height
BODY_FLOOR_HEIGHT = 0.05  # m: a fall: a body other than the feet/ankles this close to the floor
# deg: a fall: the trunk's (root body's) z axis this far from vertical at any tick. Balancing and
# the one-foot task tilt it by a few degrees; 60 deg is a robot on its way to the floor.
FALL_TRUNK_TILT_DEG = 60.0
# A state with a speed above this (m/s or rad/s) has diverged even if finite: blown-up physics is
# flagged and frozen like NaN instead of feeding overflowing numbers into the metrics.
DIVERGED_SPEED = 1e4

# Survival that means balance (issue 20, step 0): the feet stay in place, the robot stays up
# and ends balanced. ``survived`` in every summary uses these thresholds; ``upright`` keeps
# the lax count (no fall, no NaN) for comparison.
SURVIVAL_MAX_SLIP_M = 0.02
SURVIVAL_MAX_TILT_DEG = 5.0
SURVIVAL_END_COM_SPEED = 0.05  # m/s: CoM speed at the end
# Tuned gains must keep the seed's task: CoM RMSE on the 20 s sinusoid (issue 20's bound).
SINUSOID_MAX_COM_RMSE_M = 1.5e-3
# Tuning bounds that keep that bound (docs/tuning/README.md, results/tuning/stiff_com/ and keep_tracking/; measured
# on the tuned sets of 2026-11-25): K_P,CoM in x and y at least this, and the yaw (z) entries of the
# angular-momentum task, K_I,w and its damping ratio, at least this fraction of the WBC defaults.
TRACKING_KP_COM_FLOOR = 30.0
TRACKING_YAW_FRACTION = 0.9
SURVIVAL_CRITERION = {
    "max_foot_slip_m": SURVIVAL_MAX_SLIP_M,
    "max_foot_tilt_deg": SURVIVAL_MAX_TILT_DEG,
    "end_com_speed_mps": SURVIVAL_END_COM_SPEED,
    "end_com_over_support": True,
    "no_fall": f"CoM above {FALL_COM_HEIGHT} x its initial height, no body but the feet below {BODY_FLOOR_HEIGHT} m, "
    f"the trunk within {FALL_TRUNK_TILT_DEG:g} deg of vertical",
}

# One set of metric names, for a balance run (scalars) and a sweep (one column per name).
METRIC_NAMES = (
    "survived",
    "upright",
    "fell",
    "nan",
    "com_rmse_m",
    "com_max_err_m",
    "max_constraint_violation",
    "max_foot_slip_m",
    "max_foot_tilt_deg",
    "max_abs_torque_nm",
    "qp_infeasible_ticks",
    "time_to_recover_s",
    "min_com_height_m",
    "end_com_speed_mps",
    "end_com_support_margin_m",
)


def min_jerk(u):
    """Minimum-jerk ramp mj(u) = 10u^3 - 15u^4 + 6u^5 and its first two derivatives, for u
    clipped to [0, 1] (numpy or JAX arrays alike: arithmetic only). mj' and mj'' vanish at both
    ends, so clipping alone gives the constant continuations."""
    u = u.clip(0.0, 1.0) if hasattr(u, "clip") else min(max(u, 0.0), 1.0)
    p = u**3 * (10 - 15 * u + 6 * u**2)
    v = 30 * u**2 * (1 - u) ** 2
    a = 60 * u * (1 - u) * (1 - 2 * u)
    return p, v, a
