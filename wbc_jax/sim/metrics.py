"""The metrics of a rollout: running per-tick updates, one summary with one set of names.

Everything here is evaluation (no gradient flows through it; gain tuning uses a smooth loss). The
names of :func:`summarize` are :data:`wbc_jax.core.constants.METRIC_NAMES`, for a balance run (plain
numbers) and a sweep (one column each) alike.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.core import constants
from wbc_jax.core.math import safe_norm
from wbc_jax.core.types import Array, pytree_dataclass


@pytree_dataclass
class Metrics:
    """Per-environment running metrics (scalars; a batch axis under vmap)."""

    com_sq_err_sum: Array
    com_max_err: Array
    max_abs_torque: Array
    max_violation: Array
    max_slip: Array
    max_tilt: Array  # rad, of a fully active contact's normal from where it was set down
    max_trunk_tilt: Array  # rad, of the trunk's (root body's) z axis from world z
    qp_infeasible_ticks: Array
    fell: Array
    nan: Array
    last_time_off: Array  # last time the CoM error exceeded RECOVERY_THRESHOLD
    min_com_height: Array
    end_com_speed: Array  # at the last tick
    end_support_margin: Array  # CoM xy inside the feet's support polygon (m, < 0: outside)
    ticks: Array


def initial(com_height: Array, dtype) -> Metrics:
    """Metrics before the first tick (CoM height (), the initial one)."""
    zero = jnp.zeros((), dtype)
    return Metrics(
        com_sq_err_sum=zero,
        com_max_err=zero,
        max_abs_torque=zero,
        max_violation=zero,
        max_slip=zero,
        max_tilt=zero,
        max_trunk_tilt=zero,
        qp_infeasible_ticks=jnp.zeros((), jnp.int32),
        fell=jnp.zeros((), bool),
        nan=jnp.zeros((), bool),
        last_time_off=zero,
        min_com_height=com_height,
        end_com_speed=zero,
        end_support_margin=zero,
        ticks=jnp.zeros((), jnp.int32),
    )


def update(
    met: Metrics,
    *,
    com,
    com_ref,
    com_vel,
    tau,
    violation,
    infeasible,
    contact_pos,
    normals,
    anchors,
    anchor_normals,
    fully_active,
    body_heights,
    trunk_z,
    support,
    com0_height,
    t_now,
    physics_ok,
) -> Metrics:
    """The metrics after one tick at this state (K contacts).

    Args: com, com_ref, com_vel (3,); tau (n,); violation (), infeasible () of the force QP;
    contact_pos, normals (K, 3) now; anchors, anchor_normals (K, 3) where and with what normal each
    fully active contact was set down; fully_active (K,); body_heights (b,) of the bodies that must
    stay off the floor; trunk_z (3,) the root body's z axis (world); support (F, 2) the soles'
    corners; com0_height (); t_now (); physics_ok ().
    """
    com_err = jnp.linalg.norm(com - com_ref)
    # Slip: displacement of each fully active contact, tangential to its surface; tilt: the
    # rotation of its normal since it was set down.
    dp = contact_pos - anchors
    dp = dp - jnp.sum(dp * normals, -1)[:, None] * normals
    slip = jnp.max(jnp.where(fully_active, safe_norm(dp), 0.0))
    tilt_k = jnp.arctan2(safe_norm(jnp.cross(normals, anchor_normals)), jnp.sum(normals * anchor_normals, -1))
    tilt = jnp.max(jnp.where(fully_active, tilt_k, 0.0))
    body_low = jnp.min(body_heights) < constants.BODY_FLOOR_HEIGHT
    trunk_tilt = trunk_tilt_angle(trunk_z)
    # A trunk tilted past the threshold is a fall wherever the CoM is: a robot thrown through the air
    # upside down keeps its CoM high and every body off the floor.
    tipped = ~(trunk_tilt <= np.radians(constants.FALL_TRUNK_TILT_DEG))  # NaN: tipped
    fell = met.fell | (com[2] < constants.FALL_COM_HEIGHT * com0_height) | body_low | tipped
    finite = jnp.all(jnp.isfinite(tau)) & physics_ok
    return Metrics(
        com_sq_err_sum=met.com_sq_err_sum + com_err**2,
        com_max_err=jnp.maximum(met.com_max_err, com_err),
        max_abs_torque=jnp.maximum(met.max_abs_torque, jnp.max(jnp.abs(tau))),
        max_violation=jnp.maximum(met.max_violation, violation),
        max_slip=jnp.maximum(met.max_slip, slip),
        max_tilt=jnp.maximum(met.max_tilt, tilt),
        max_trunk_tilt=jnp.maximum(met.max_trunk_tilt, trunk_tilt),
        qp_infeasible_ticks=met.qp_infeasible_ticks + infeasible.astype(jnp.int32),
        fell=fell,
        nan=met.nan | ~finite,
        last_time_off=jnp.where(com_err > constants.RECOVERY_THRESHOLD, t_now, met.last_time_off),
        min_com_height=jnp.minimum(met.min_com_height, com[2]),
        end_com_speed=jnp.linalg.norm(com_vel),
        end_support_margin=polygon_margin(support, com[:2]),
        ticks=met.ticks + 1,
    )


def trunk_tilt_angle(trunk_z: Array) -> Array:
    """The angle () rad between the trunk's z axis (..., 3) (world axes) and world z, in [0, pi]."""
    return jnp.arctan2(safe_norm(trunk_z[..., :2]), trunk_z[..., 2])


def final(met: Metrics, physics_ok) -> Metrics:
    """The metrics at the end of a run: diverged if the last physics steps were."""
    return met.replace(nan=met.nan | ~physics_ok)


def support_corners(cset, contact_pos: Array, contact_R: Array) -> Array:
    """(4 x feet, 3) corners of the soles' CoP rectangles (contact set ``cset``), world axes."""
    corners = []
    for k in cset.feet:
        (x0, x1), (y0, y1) = cset.contacts[k].params.foot_size
        local = jnp.asarray([[x, y, 0.0] for x in (x0, x1) for y in (y0, y1)], contact_pos.dtype)
        # Elementwise rotation (no matrix product: see polygon_margin on TensorFloat-32).
        corners.append(contact_pos[k] + jnp.sum(local[:, None, :] * contact_R[k][None], -1))
    return jnp.concatenate(corners)


def polygon_margin(points: Array, p: Array, tol: float = 1e-6) -> Array:
    """Signed distance () of p (2,) inside the convex hull of points (N, 2): the smallest distance
    to a hull edge, negative outside. Hull edges: the ordered pairs with every point on their left
    (to ``tol`` m: rounding puts the two other corners of a sole's edge a hair to either side in
    float32). A degenerate hull (no edge found) gives minus the distance to the nearest point.

    Products are elementwise, never matrix products: on a GPU, float32 matrix products may run in
    TensorFloat-32 (10-bit mantissa, 1e-4 m on these coordinates), far coarser than ``tol``, and
    the edge test would then miss the edges of collinear sole corners."""
    a = points[:, None, :]
    b = points[None, :, :]
    e = b - a  # (N, N, 2)
    length = jnp.sqrt(jnp.sum(e * e, -1) + 1e-30)
    normal = jnp.stack([-e[..., 1], e[..., 0]], -1) / length[..., None]  # left normal, (N, N, 2)
    offset = jnp.sum(normal * a, -1)  # (N, N)
    side = jnp.sum(normal[:, :, None, :] * points[None, None], -1) - offset[..., None]  # (N, N, N)
    is_edge = (length > 1e-6) & jnp.all(side >= -tol, axis=-1)
    dist = jnp.sum(normal * p, -1) - offset
    margin = jnp.min(jnp.where(is_edge, dist, jnp.inf))
    nearest = jnp.min(jnp.linalg.norm(points - p, axis=-1))
    return jnp.where(jnp.any(is_edge), margin, -nearest)


def failed_tests(cols: dict) -> dict:
    """Which environments fail each test of the strict criterion, from :func:`summarize`'s
    columns: {"slip", "tilt", "end_speed", "end_support_margin", "not_upright": (B,) bool}. A NaN
    quantity fails its test. ``survived`` is passing them all."""
    return {
        "slip": ~(np.asarray(cols["max_foot_slip_m"]) <= constants.SURVIVAL_MAX_SLIP_M),
        "tilt": ~(np.asarray(cols["max_foot_tilt_deg"]) <= constants.SURVIVAL_MAX_TILT_DEG),
        "end_speed": ~(np.asarray(cols["end_com_speed_mps"]) <= constants.SURVIVAL_END_COM_SPEED),
        "end_support_margin": ~(np.asarray(cols["end_com_support_margin_m"]) >= 0),
        "not_upright": ~np.asarray(cols["upright"]).astype(bool),
    }


def summarize(metrics: Metrics, push_end: float = 0.0) -> dict:
    """Host-side summary of metrics under :data:`wbc_jax.core.constants.METRIC_NAMES`: plain numbers
    for one environment, numpy columns for a batch. ``survived`` is the strict criterion of
    :data:`wbc_jax.core.constants.SURVIVAL_CRITERION`; ``upright`` the lax one: no fall (the CoM
    high, no body but the feet on the floor, the trunk within ``FALL_TRUNK_TILT_DEG`` of vertical at
    every tick), no NaN."""
    m = jax.tree_util.tree_map(np.asarray, metrics)
    ticks = np.maximum(m.ticks, 1)
    upright = ~m.fell & ~m.nan
    tilt_deg = np.rad2deg(m.max_tilt)
    cols = {
        "survived": None,  # filled below from the other columns
        "upright": upright,
        "fell": m.fell,
        "nan": m.nan,
        "com_rmse_m": np.sqrt(m.com_sq_err_sum / ticks),
        "com_max_err_m": m.com_max_err,
        "max_constraint_violation": m.max_violation,
        "max_foot_slip_m": m.max_slip,
        "max_foot_tilt_deg": tilt_deg,
        "max_abs_torque_nm": m.max_abs_torque,
        "qp_infeasible_ticks": m.qp_infeasible_ticks,
        "time_to_recover_s": np.where(upright, np.maximum(m.last_time_off - push_end, 0.0), np.nan),
        "min_com_height_m": m.min_com_height,
        "end_com_speed_mps": m.end_com_speed,
        "end_com_support_margin_m": m.end_support_margin,
    }
    cols["survived"] = ~np.logical_or.reduce(list(failed_tests(cols).values()))
    assert tuple(cols) == constants.METRIC_NAMES
    if np.ndim(m.ticks) == 0:
        return {k: (v.item() if isinstance(v, np.ndarray) else v) for k, v in cols.items()}
    return cols
