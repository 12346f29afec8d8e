"""The closed loop on C MuJoCo (:func:`simulate`): pushes, the support polygon, the running metrics of
:class:`wbc_jax.sim.loop.ClosedLoop` (:class:`LoopMetrics`) and their summary."""

from __future__ import annotations

import time

import mujoco
import numpy as np

from .controller import NumpyController
from .spec import GAIN_FIELDS, METRIC_NAMES, RECOVERY_THRESHOLD, BaselineSpec, constants
from .tasks import gains_to_numpy, push_to_numpy


def push_force(push: dict, t, step: float | None = None) -> np.ndarray:
    """Total push force (..., B, 3) at the time(s) t (as wbc_jax.sim.state.push_forces); t: scalar or
    (..., 1, 1) to broadcast against onset (B, P). With ``step``: the mean force over [t, t + step),
    so the physics steps carry exactly force x duration (as the package's engines)."""
    if step is None:
        share = (t >= push["onset"]) & (t < push["onset"] + push["duration"])
    else:
        t = np.asarray(t, float)
        covered = np.minimum(t + step, push["onset"] + push["duration"]) - np.maximum(t, push["onset"])
        share = np.clip(covered, 0.0, step) / step
        share = np.where(share >= 1 - 1e-6, 1.0, np.where(share <= 1e-6, 0.0, share))  # as the package's
    return np.sum(push["force"] * share[..., None], axis=-2)


# --------------------------------------------------------------------------------------
def _batch_size(gains, push) -> int:
    """Leading axis of batched (2-D) gains or (3-D) push forces; 1 if none is batched."""
    get = lambda x, k: x[k] if isinstance(x, dict) else getattr(x, k)  # noqa: E731
    sizes = [] if gains is None else [np.shape(get(gains, k))[0] for k in GAIN_FIELDS if np.ndim(get(gains, k)) == 2]
    if push is not None and np.ndim(get(push, "force")) == 3:
        sizes.append(np.shape(get(push, "force"))[0])
    if len(set(sizes)) > 1:
        raise ValueError(f"inconsistent batch sizes of gains/push: {sorted(set(sizes))}")
    return sizes[0] if sizes else 1


def support_corners(spec: BaselineSpec, W_p_feet: np.ndarray, W_R_feet: np.ndarray) -> np.ndarray:
    """(B, 8, 3) corners of the soles' CoP rectangles, world axes (wbc_jax.sim.metrics.support_corners)."""
    return rectangle_corners(spec.foot_size, W_p_feet, W_R_feet)


def rectangle_corners(foot_size, W_p_feet: np.ndarray, W_R_feet: np.ndarray) -> np.ndarray:
    """(B, 8, 3) corners of the CoP rectangles ``foot_size`` ((x_min, x_max), (y_min, y_max)) m of
    the soles at W_p_feet (B, 2, 3), W_R_feet (B, 2, 3, 3), world axes."""
    (x0, x1), (y0, y1) = foot_size
    local = np.array([[x, y, 0.0] for x in (x0, x1) for y in (y0, y1)])  # (4, 3)
    corners = W_p_feet[:, :, None, :] + np.einsum("cj,bkij->bkci", local, W_R_feet)
    return corners.reshape(W_p_feet.shape[0], -1, 3)


def polygon_margin(points: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(B,) signed distance of p (B, 2) inside the convex hull of points (B, N, 2): the smallest
    distance to a hull edge, negative outside (wbc_jax.sim.metrics.polygon_margin: hull edges = the ordered
    pairs with every point on their left)."""
    a = points[:, :, None, :]
    e = points[:, None, :, :] - a  # (B, N, N, 2)
    length = np.sqrt(np.sum(e * e, -1) + 1e-30)
    normal = np.stack([-e[..., 1], e[..., 0]], -1) / length[..., None]  # left normal
    offset = np.sum(normal * a, -1)  # (B, N, N)
    side = np.einsum("bijk,blk->bijl", normal, points) - offset[..., None]
    is_edge = (length > 1e-9) & np.all(side >= -1e-9, axis=-1)
    dist = np.einsum("bijk,bk->bij", normal, p) - offset
    return np.min(np.where(is_edge, dist, np.inf), axis=(1, 2))


class LoopMetrics:
    """The metrics of ``wbc_jax.sim.loop.ClosedLoop._metrics``, accumulated tick by tick for B environments.

    One implementation for every C MuJoCo closed loop of ``benchmarks/`` (:func:`simulate` here,
    the TSID peer of ``benchmarks/tsid_baseline/``): build it at the initial state, call
    :meth:`update` once per control tick with the quantities at the tick's state, then read
    ``metrics`` (the dict :func:`simulate` returns as ``"metrics"``, named by
    :func:`summary_columns` / :func:`summarize` as ``constants.METRIC_NAMES``).

    Args:
      foot_size: ((x_min, x_max), (y_min, y_max)) m, the soles' CoP rectangle (support margin).
      W_p_feet (B, 2, 3), W_R_feet (B, 2, 3, 3): the sole frames at the initial state (the slip and
        tilt anchors).
      com0_height (B,): the initial CoM height (m; the fall threshold is a fraction of it).
    """

    def __init__(self, foot_size, W_p_feet: np.ndarray, W_R_feet: np.ndarray, com0_height: np.ndarray):
        self.foot_size = foot_size
        self.anchors = np.array(W_p_feet, float)
        self.anchor_normals = np.array(W_R_feet, float)[..., :, 2]  # (B, 2, 3)
        self.com0_height = np.array(com0_height, float)
        B = self.com0_height.shape[0]
        self.metrics = {
            "com_sq_err_sum": np.zeros(B),
            "com_max_err": np.zeros(B),
            "max_abs_torque": np.zeros(B),
            "max_violation": np.zeros(B),
            "max_slip": np.zeros(B),
            "max_tilt": np.zeros(B),
            "qp_infeasible_ticks": np.zeros(B, np.int64),
            "fell": np.zeros(B, bool),
            "nan": np.zeros(B, bool),
            "last_time_off": np.zeros(B),
            "min_com_height": self.com0_height.copy(),
            "end_com_speed": np.zeros(B),
            "end_support_margin": np.zeros(B),
            "ticks": np.zeros(B, np.int64),
        }

    def update(
        self,
        t_now: float,
        ref_com: np.ndarray,
        activation: np.ndarray,
        com: np.ndarray,
        com_vel: np.ndarray,
        W_p_feet: np.ndarray,
        W_R_feet: np.ndarray,
        tau: np.ndarray,
        violation: np.ndarray,
        infeasible: np.ndarray,
        finite: np.ndarray,
        body_low: np.ndarray,
    ) -> None:
        """Add one tick (wbc_jax.sim.loop.ClosedLoop._metrics).

        Args:
          t_now: the tick's time (s). ref_com (3,): the CoM reference; activation (2,): the feet's.
          com, com_vel (B, 3): CoM position and velocity at the tick's state (world).
          W_p_feet (B, 2, 3), W_R_feet (B, 2, 3, 3): the sole frames at the tick's state.
          tau (B, n): the applied (saturated) torques; violation (B,): the contact-constraint
            violation of the commanded wrenches; infeasible (B,) bool: the QP failed this tick.
          finite (B,) bool: the physics stayed finite over the tick (False: a NaN run).
          body_low (B,) bool: a body other than the feet/ankles below ``BODY_FLOOR_HEIGHT``, or the trunk
            tilted past ``FALL_TRUNK_TILT_DEG`` (a fall, as wbc_jax.sim.metrics counts it).
        """
        met = self.metrics
        com_err = np.linalg.norm(com - ref_com, axis=1)
        pos, normal = W_p_feet, W_R_feet[..., :, 2]  # (B, 2, 3)
        fully_active = np.clip(activation, 0.0, 1.0) >= 1.0  # (2,)
        self.anchors = np.where(fully_active[None, :, None], self.anchors, pos)
        self.anchor_normals = np.where(fully_active[None, :, None], self.anchor_normals, normal)
        dp = pos - self.anchors  # slip: tangential to the contact surface
        dp = dp - np.sum(dp * normal, -1, keepdims=True) * normal
        slip = np.max(np.where(fully_active[None], np.linalg.norm(dp, axis=-1), 0.0), axis=1)
        cos = np.sum(normal * self.anchor_normals, -1)
        sin = np.linalg.norm(np.cross(normal, self.anchor_normals), axis=-1)
        tilt = np.max(np.where(fully_active[None], np.arctan2(sin, cos), 0.0), axis=1)
        corners = rectangle_corners(self.foot_size, pos, W_R_feet)
        met["fell"] |= (com[:, 2] < constants.FALL_COM_HEIGHT * self.com0_height) | body_low
        met["com_sq_err_sum"] += com_err**2
        met["com_max_err"] = np.maximum(met["com_max_err"], com_err)
        met["max_abs_torque"] = np.maximum(met["max_abs_torque"], np.max(np.abs(tau), axis=1))
        met["max_violation"] = np.maximum(met["max_violation"], violation)
        met["max_slip"] = np.maximum(met["max_slip"], slip)
        met["max_tilt"] = np.maximum(met["max_tilt"], tilt)
        met["qp_infeasible_ticks"] += infeasible
        met["nan"] |= ~finite | ~np.all(np.isfinite(tau), axis=1)
        met["last_time_off"] = np.where(com_err > RECOVERY_THRESHOLD, t_now, met["last_time_off"])
        met["min_com_height"] = np.minimum(met["min_com_height"], com[:, 2])
        met["end_com_speed"] = np.linalg.norm(com_vel, axis=1)
        met["end_support_margin"] = polygon_margin(corners[:, :, :2], com[:, :2])
        met["ticks"] += 1


def simulate(
    spec: BaselineSpec,
    gains=None,
    push=None,
    *,
    n_envs: int | None = None,
    record: bool = True,
    timing: bool = False,
    n_ticks: int | None = None,
) -> dict:
    """Closed-loop simulation of a batch of environments with C MuJoCo (as wbc_jax.sim.loop.ClosedLoop).

    Args:
      spec: the task (:func:`spec_from_setup` / :func:`make_spec`).
      gains: per-environment gains, (B, dim) or (dim,) arrays (dict or wbc_jax.control.gains.Gains);
        None: the WBC defaults.
      push: pushes on ``spec.push_body``: force (B, P, 3) or (P, 3), onset/duration (B, P)
        or (P,) (dict or wbc_jax.sim.state.Push); None: no push.
      n_envs: batch size (default: from the batched gains/push, else 1).
      record: keep per-tick trajectories (CoM, torques, wrenches).
      timing: measure the time spent in physics and in the controller (perf_counter).
      n_ticks: simulate fewer ticks than the spec's horizon.

    Returns:
      dict with ``t`` (T,), ``com_ref`` (T, 3), ``metrics`` (dict of (B,) arrays, the fields of
      wbc_jax.sim.metrics.Metrics; :func:`summarize` names them as ``constants.METRIC_NAMES``), with
      ``record``: ``com`` (B, T, 3), ``tau`` (B, T, n), ``f_cmd`` (B, T, 12), ``qp_infeasible``
      (B, T); with ``timing``: ``timing`` (dict: wall and CPU seconds of the loop, seconds in
      physics (mj_step1/mj_step2/mj_step) and in the controller (terms + tick), microseconds per
      mj_step and per environment-tick; perf_counter).
    """
    sp = spec
    B = int(_batch_size(gains, push) if n_envs is None else n_envs)
    g = gains_to_numpy(gains, B, sp.n)
    pu = push_to_numpy(push, B)
    T = sp.n_ticks if n_ticks is None else int(n_ticks)
    m = sp.mj_model
    ctrl = NumpyController(sp)
    datas = [mujoco.MjData(m) for _ in range(B)]
    for d in datas:
        d.qpos[:] = sp.qpos0
        d.qvel[:] = 0.0
    state = ctrl.init_state(B)
    acts, pb = sp.actuators, sp.push_body

    # Metrics as wbc_jax.sim.loop.ClosedLoop.init / _metrics.
    for d in datas:
        mujoco.mj_forward(m, d)
    t0 = ctrl.terms(datas)
    tracker = LoopMetrics(sp.foot_size, t0.W_p_feet, t0.W_R_feet, t0.W_p_CoM[:, 2])
    rec = None
    if record:
        rec = {
            "com": np.zeros((B, T, 3)),
            "tau": np.zeros((B, T, sp.n)),
            "f_cmd": np.zeros((B, T, 12)),
            "qp_infeasible": np.zeros((B, T), bool),
        }
    t_phys = t_ctrl = 0.0
    clock = time.perf_counter
    saved = [None] * B
    loop_start, cpu_start = clock(), time.process_time()
    F_cur = np.zeros((B, 3))  # xfrc_applied[push_body, :3] of each MjData
    sub_times = np.arange(sp.n_sub) * sp.physics_dt
    nfb = sp.non_foot_bodies
    for k in range(T):
        t_now = k * sp.control_dt
        for i, d in enumerate(datas):
            saved[i] = (d.qpos.copy(), d.qvel.copy(), d.qacc_warmstart.copy(), d.time)
        F_all = push_force(pu, (t_now + sub_times)[:, None, None], sp.physics_dt)  # (n_sub, B, 3)
        c0 = clock()
        for d in datas:
            mujoco.mj_step1(m, d)
        c1 = clock()
        terms = ctrl.terms(datas)
        ref = sp.reference(k)
        out, state = ctrl.step(terms, g, ref, state)
        tau = out["tau"]
        c2 = clock()
        body_low = np.array([d.xpos[nfb, 2].min() for d in datas]) < constants.BODY_FLOOR_HEIGHT
        # A fall as wbc_jax.sim.metrics counts it: the trunk (root body, id 1) tilted past the threshold.
        body_low |= ~(np.array([d.xmat[1, 8] for d in datas]) >= np.cos(np.radians(constants.FALL_TRUNK_TILT_DEG)))
        c2b = clock()
        for j in range(sp.n_sub):
            for i in np.flatnonzero(np.any(F_all[j] != F_cur, axis=1)).tolist():
                datas[i].xfrc_applied[pb, :3] = F_cur[i] = F_all[j, i]
            if j == 0:
                for i, d in enumerate(datas):
                    d.ctrl[acts] = tau[i]
                    mujoco.mj_step2(m, d)
            else:
                for d in datas:
                    mujoco.mj_step(m, d)
        c3 = clock()
        t_phys += (c1 - c0) + (c3 - c2b)
        t_ctrl += c2 - c1

        # Divergence: freeze at the last finite state, as the closed loop (the model does not
        # reset a diverged state itself: mjDSBL_AUTORESET; a clock that did not advance by
        # n_sub steps is treated the same way, for models without that flag).
        finite = np.ones(B, bool)
        for i, d in enumerate(datas):
            qpos, qvel, warm, time_ = saved[i]
            ok = abs(d.time - (time_ + sp.n_sub * sp.physics_dt)) < 0.5 * sp.physics_dt
            if not (ok and np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
                d.qpos[:], d.qvel[:], d.qacc_warmstart[:], d.time = qpos, qvel, warm, time_
                finite[i] = False

        # Metrics (wbc_jax.sim.loop.ClosedLoop._metrics), at the tick's state.
        tracker.update(
            t_now,
            ref["com_pos"],
            ref["activation"],
            terms.W_p_CoM,
            terms.W_v_CoM,
            terms.W_p_feet,
            terms.W_R_feet,
            tau,
            out["qp_violation"],
            out["qp_infeasible"],
            finite,
            body_low,
        )
        com = terms.W_p_CoM
        if record:
            rec["com"][:, k] = com
            rec["tau"][:, k] = tau
            rec["f_cmd"][:, k] = out["f"]
            rec["qp_infeasible"][:, k] = out["qp_infeasible"]
    result = {
        "t": np.arange(T) * sp.control_dt,
        "com_ref": sp.ref_com_pos[:T].copy(),
        "metrics": tracker.metrics,
        "n_envs": B,
        "n_ticks": T,
        "physics_steps": B * T * sp.n_sub,
    }
    if record:
        result.update(rec)
    loop_wall, loop_cpu = clock() - loop_start, time.process_time() - cpu_start
    if timing:
        ticks = max(B * T, 1)
        result["timing"] = {
            "loop_s": loop_wall,
            "loop_cpu_s": loop_cpu,  # process CPU time: < loop_s when the core is shared
            "physics_s": t_phys,
            "controller_s": t_ctrl,
            "other_s": loop_wall - t_phys - t_ctrl,  # state save, divergence check, metrics
            "physics_us_per_mj_step": 1e6 * t_phys / (ticks * sp.n_sub),
            "physics_us_per_env_tick": 1e6 * t_phys / ticks,
            "controller_us_per_env_tick": 1e6 * t_ctrl / ticks,
        }
    return result


def summary_columns(metrics: dict, push_end: float = 0.0) -> dict:
    """The metrics of :func:`simulate` under ``constants.METRIC_NAMES`` (numpy columns, (B,)),
    computed as :func:`wbc_jax.sim.metrics.summarize`: ``survived`` is the strict criterion of
    ``constants.SURVIVAL_CRITERION``, ``upright`` the lax one (no fall, no NaN)."""
    m = {k: np.asarray(v) for k, v in metrics.items()}
    ticks = np.maximum(m["ticks"], 1)
    upright = ~m["fell"] & ~m["nan"]
    tilt_deg = np.rad2deg(m["max_tilt"])
    survived = (
        upright
        & (m["max_slip"] <= constants.SURVIVAL_MAX_SLIP_M)
        & (tilt_deg <= constants.SURVIVAL_MAX_TILT_DEG)
        & (m["end_com_speed"] <= constants.SURVIVAL_END_COM_SPEED)
        & (m["end_support_margin"] >= 0)
    )
    cols = {
        "survived": survived,
        "upright": upright,
        "fell": m["fell"],
        "nan": m["nan"],
        "com_rmse_m": np.sqrt(m["com_sq_err_sum"] / ticks),
        "com_max_err_m": m["com_max_err"],
        "max_constraint_violation": m["max_violation"],
        "max_foot_slip_m": m["max_slip"],
        "max_foot_tilt_deg": tilt_deg,
        "max_abs_torque_nm": m["max_abs_torque"],
        "qp_infeasible_ticks": m["qp_infeasible_ticks"],
        "time_to_recover_s": np.where(upright, np.maximum(m["last_time_off"] - push_end, 0.0), np.nan),
        "min_com_height_m": m["min_com_height"],
        "end_com_speed_mps": m["end_com_speed"],
        "end_com_support_margin_m": m["end_support_margin"],
    }
    assert tuple(cols) == METRIC_NAMES
    return cols


def summarize(metrics: dict, push_end: float = 0.0) -> list[dict]:
    """Per-environment summaries (plain numbers) under ``constants.METRIC_NAMES``, as
    :func:`wbc_jax.sim.metrics.summarize` gives for one environment."""
    cols = summary_columns(metrics, push_end)
    B = len(cols["fell"])
    return [{k: v[i].item() for k, v in cols.items()} for i in range(B)]
