"""The tuned parameters of the controller: every gain, bounded, positive, stable.

Gain tuning (:mod:`wbc_jax.tuning.algorithms.gradient`, :mod:`wbc_jax.tuning.algorithms.baselines`) searches an unconstrained vector
``params`` ({group: (k,)}) mapped to the controller's gains and regularisation by

    value = exp(log lo + sigmoid(p) (log hi - log lo))          (each entry in (lo, hi), log-scaled)

over these groups (P = 3 + 3 + 3 + 3 + 23 + 23 + 2 = 60 entries):

* ``kp_com`` (3), ``zeta_com`` (3): K_P,CoM and the damping ratio of the CoM error dynamics
  x~'' + K_D x~' + K_P x~ = 0, K_D,CoM = 2 zeta sqrt(K_P,CoM);
* ``ki_ang`` (3), ``zeta_ang`` (3): K_I,w on the angular-momentum integral I and the damping
  ratio of I'' + K_P,w I' + K_I,w I = 0, K_P,w = 2 zeta sqrt(K_I,w) (WBC: zeta = 1);
* ``kp_postural`` (n), ``zeta_postural`` (n): postural k_p and k_d = 2 zeta sqrt(k_p);
* ``regularisation`` (2, optional: ``--tune-regularisation``): Reg.pinvDamp (the damped
  pseudo-inverse of the torque law) and Reg.KP_postural (the 0.1 I added to the stable postural
  K_P), differentiable controller-state entries (:class:`wbc_jax.control.controller.ControllerState`).
  They are regularisers rather than gains: a gains file cannot hold them, and the sweep and
  balance jobs take them from the controller settings, so by default they stay at the WBC's.

K_I,CoM stays 0 (the WBC law has no CoM integral). The QP's weights (``hessian_reg``,
``torque_weight_soft``, ``normal_force_weight``) are static controller settings, not gains.

Stability (Nava et al., IROS 2016): with the stable postural task, the closed-loop momentum
dynamics are asymptotically stable for symmetric positive-definite K_P,CoM, K_D,CoM, K_P,w,
K_I,w and postural K_P, K_D (the Lyapunov function of the paper needs each of them > 0), and the
regularised postural K_P = diag(k_p) pinv(N M) + Reg.KP_postural I stays positive definite for
Reg.KP_postural > 0. The map enforces these by construction: every entry is strictly inside
(lo, hi) with lo > 0, so all diagonal gains are positive and each second-order error dynamics is
Hurwitz, with its damping ratio inside [zeta_min, zeta_max] (bounded away from undamped and from
sluggish overdamping) and its natural frequency inside the K_P bounds. :func:`nava_conditions`
checks a gain set against them.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.control.controller import ControllerConfig
from wbc_jax.control.gains import Gains
from wbc_jax.core.types import pytree_dataclass

PARAM_GROUPS = ("kp_com", "zeta_com", "ki_ang", "zeta_ang", "kp_postural", "zeta_postural", "regularisation")
REGULARISATION = ("pinv_damping", "kp_postural_reg")  # the entries of the ``regularisation`` group


@pytree_dataclass
class Bounds:
    """Per-entry bounds of the tuned groups: lo, hi {group: (k,)} with 0 < lo < hi."""

    lo: dict
    hi: dict


def default_regularisation(config: ControllerConfig | None = None) -> np.ndarray:
    """(2,) Reg.pinvDamp, Reg.KP_postural of a controller config (the WBC's 1 and 0.1)."""
    config = ControllerConfig() if config is None else config
    return np.array([config.pinv_damping, config.kp_postural_reg], float)


def damping_ratio(kd, kp):
    """zeta = kd / (2 sqrt(kp)) (numpy or JAX arrays)."""
    return kd / (2.0 * kp**0.5)


def controls_of(gains: Gains, reg) -> dict:
    """The tuned groups {group: (k,) numpy} of a gain set and regularisation (2,)."""
    g = {
        k: np.asarray(getattr(gains, k), float)
        for k in ("kp_com", "kd_com", "kp_ang", "ki_ang", "kp_postural", "kd_postural")
    }
    return {
        "kp_com": g["kp_com"],
        "zeta_com": damping_ratio(g["kd_com"], g["kp_com"]),
        "ki_ang": g["ki_ang"],
        "zeta_ang": damping_ratio(g["kp_ang"], g["ki_ang"]),
        "kp_postural": g["kp_postural"],
        "zeta_postural": damping_ratio(g["kd_postural"], g["kp_postural"]),
        "regularisation": np.asarray(reg, float).reshape(2),
    }


def default_bounds(base: Gains, factor: float = 10.0, zeta_range=(0.02, 2.0), reg=None) -> Bounds:
    """Bounds around the base gains: K_P-like entries and the regularisation within [base / f,
    base * f], damping ratios within ``zeta_range`` (which must hold the base's)."""
    if not (math.isfinite(factor) and factor > 1.0):
        raise ValueError(f"bound factor must be > 1, got {factor}")
    zlo, zhi = (float(z) for z in zeta_range)
    if not (math.isfinite(zlo) and math.isfinite(zhi) and 0 < zlo < zhi):
        raise ValueError(f"damping-ratio range must be 0 < lo < hi, got {zeta_range}")
    c = controls_of(base, default_regularisation() if reg is None else reg)
    lo, hi = {}, {}
    for k, v in c.items():
        if not np.all(v > 0):
            raise ValueError(f"base {k} must be positive to be tuned, got {v.tolist()}")
        if k.startswith("zeta"):
            if np.any(v < zlo) or np.any(v > zhi):
                raise ValueError(f"base {k} {v.tolist()} lies outside the damping-ratio range {zeta_range}")
            lo[k], hi[k] = np.full_like(v, zlo), np.full_like(v, zhi)
        else:
            lo[k], hi[k] = v / factor, v * factor
    return Bounds(lo={k: jnp.asarray(v) for k, v in lo.items()}, hi={k: jnp.asarray(v) for k, v in hi.items()})


def tracking_bounds(bounds: Bounds, base: Gains, kp_com_floor: float, yaw_fraction: float) -> Bounds:
    """``bounds`` raised so that tuned gains keep tracking the CoM: the lower bound of K_P,CoM in x
    and y to ``kp_com_floor``, and of K_I,w z and the angular damping ratio z to ``yaw_fraction``
    x ``base``'s (horizontal pushes hardly excite yaw, so a push loss leaves these free to drop).
    Raises ValueError if a raised lower bound reaches its upper bound."""
    lo = {k: np.array(v) for k, v in bounds.lo.items()}
    c = controls_of(base, default_regularisation())
    lo["kp_com"][:2] = np.maximum(lo["kp_com"][:2], kp_com_floor)
    lo["ki_ang"][2] = max(lo["ki_ang"][2], yaw_fraction * float(c["ki_ang"][2]))
    lo["zeta_ang"][2] = max(lo["zeta_ang"][2], yaw_fraction * float(c["zeta_ang"][2]))
    for k, v in lo.items():
        if np.any(v >= np.asarray(bounds.hi[k])):
            raise ValueError(
                f"tracking bounds: {k} lower bound {v.tolist()} reaches its upper bound "
                f"{np.asarray(bounds.hi[k]).tolist()}"
            )
    return Bounds(lo={k: jnp.asarray(v) for k, v in lo.items()}, hi=bounds.hi)


def _to_unit(value, lo, hi):
    return (jnp.log(value) - jnp.log(lo)) / (jnp.log(hi) - jnp.log(lo))


def params_to_controls(params: dict, bounds: Bounds, base: Gains) -> tuple[Gains, dict | None]:
    """Unconstrained params {group: (k,)} -> (Gains, {"pinv_damping": (), "kp_postural_reg": ()}, or
    None when ``params`` has no ``regularisation`` group: the controller's own).

    Differentiable; every value strictly inside its bounds. ``base`` supplies ki_com (not tuned)."""
    v = {}
    for k in PARAM_GROUPS:
        if k not in params:
            continue
        llo, lhi = jnp.log(bounds.lo[k]), jnp.log(bounds.hi[k])
        v[k] = jnp.exp(llo + jax.nn.sigmoid(params[k]) * (lhi - llo))
    dtype = v["kp_com"].dtype
    gains = Gains(
        kp_com=v["kp_com"],
        kd_com=2.0 * v["zeta_com"] * jnp.sqrt(v["kp_com"]),
        ki_com=jnp.asarray(base.ki_com, dtype),
        kp_ang=2.0 * v["zeta_ang"] * jnp.sqrt(v["ki_ang"]),
        ki_ang=v["ki_ang"],
        kp_postural=v["kp_postural"],
        kd_postural=2.0 * v["zeta_postural"] * jnp.sqrt(v["kp_postural"]),
    )
    reg = None
    if "regularisation" in v:
        reg = {name: v["regularisation"][..., i] for i, name in enumerate(REGULARISATION)}
    return gains, reg


def params_to_gains(params: dict, bounds: Bounds, base: Gains) -> Gains:
    """The Gains of :func:`params_to_controls`."""
    return params_to_controls(params, bounds, base)[0]


def controls_to_params(gains: Gains, reg, bounds: Bounds, *, regularisation: bool = True) -> dict:
    """Inverse of :func:`params_to_controls` (values clipped strictly inside the bounds); without
    the ``regularisation`` group unless ``regularisation``."""
    c = controls_of(gains, reg)
    out = {}
    for k in PARAM_GROUPS:
        if k == "regularisation" and not regularisation:
            continue
        u = _to_unit(jnp.asarray(c[k]), bounds.lo[k], bounds.hi[k])
        u = jnp.clip(u, 1e-6, 1 - 1e-6)
        out[k] = jnp.log(u) - jnp.log1p(-u)
    return out


def check_in_bounds(gains: Gains, reg, bounds: Bounds, source: str = "gains", rtol: float = 1e-4) -> None:
    """Raise ValueError naming the entries of a gain set (and regularisation) that are non-finite,
    non-positive or outside the tuning bounds (before anything compiles)."""
    c = controls_of(gains, reg)
    problems = []
    for k in PARAM_GROUPS:
        v, lo, hi = c[k], np.asarray(bounds.lo[k]), np.asarray(bounds.hi[k])
        if not np.all(np.isfinite(v)):
            problems.append(f"{k} has non-finite entries {v.tolist()}")
        elif np.any(v <= 0):
            problems.append(f"{k} has non-positive entries at {np.flatnonzero(v <= 0).tolist()}")
        else:
            out = np.flatnonzero((v < lo * (1 - rtol)) | (v > hi * (1 + rtol)))
            if out.size:
                i = int(out[0])
                problems.append(
                    f"{k} is outside its bounds at entries {out.tolist()} (e.g. [{i}] = {v[i]:.4g} "
                    f"not in [{lo[i]:.4g}, {hi[i]:.4g}])"
                )
    if problems:
        raise ValueError(f"{source}: " + "; ".join(problems))


def nava_conditions(gains: Gains, reg) -> dict:
    """The stability conditions of Nava et al. (2016) for a gain set: every momentum and postural
    gain positive (positive-definite diagonal matrices), Reg.KP_postural > 0, and the damping
    ratios of the CoM, angular-momentum-integral and postural error dynamics. Returns
    {"holds": bool, "min_gain": float, "zeta_com": [...], "zeta_ang": [...],
    "zeta_postural_min": float, "zeta_postural_max": float}."""
    c = controls_of(gains, reg)
    positive = [
        np.asarray(getattr(gains, k), float)
        for k in ("kp_com", "kd_com", "kp_ang", "ki_ang", "kp_postural", "kd_postural")
    ] + [c["regularisation"]]
    min_gain = float(min(np.min(v) for v in positive))
    finite = all(np.all(np.isfinite(v)) for v in positive)
    return {
        "holds": bool(finite and min_gain > 0),
        "min_gain": min_gain,
        "zeta_com": c["zeta_com"].tolist(),
        "zeta_ang": c["zeta_ang"].tolist(),
        "zeta_postural_min": float(c["zeta_postural"].min()),
        "zeta_postural_max": float(c["zeta_postural"].max()),
    }
