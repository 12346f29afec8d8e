"""The TSID peer's closed loop on C MuJoCo (:class:`TsidPeer`, :func:`simulate`)."""

from __future__ import annotations

import time
from typing import Any

import mujoco
import numpy as np

from wbc_jax.robot.pinocchio import StateMap, pinocchio_model
from wbc_jax.robot.robots import DEFAULT_ROBOT, describe

from .controller import TsidConfig, TsidController
from .model import (
    TaskSchedule,
    bc,
    body_id,
    constants,
    load_mj_model,
    make_schedule,
    non_foot_bodies,
)


class TsidPeer:
    """The robot loaded once for many closed loops: the MuJoCo model (no auto-reset), the reduced
    Pinocchio model, their :class:`StateMap`, the nominal state and its references.

    Args: robot: the robot's name (``wbc_jax.robot.robots``). mj_model: None: :func:`load_mj_model`
    of the robot. pin_model: None: :func:`wbc_jax.robot.pinocchio.pinocchio_model` of its joints.
    """

    def __init__(self, mj_model: mujoco.MjModel | None = None, pin_model=None, robot: str = DEFAULT_ROBOT):
        self.robot, self.description = robot, describe(robot)
        joints = self.description.joints
        self.mj_model = bc.solver_model(load_mj_model(robot=robot) if mj_model is None else mj_model)
        self.pin_model = pinocchio_model(joints, robot=robot) if pin_model is None else pin_model
        self.map = StateMap(self.mj_model, self.pin_model, joints)
        m = self.mj_model
        self.qpos0 = m.key(self.description.nominal_keyframe).qpos.copy()
        self.foot_sites = np.array([m.site(s).id for s in self.description.feet])
        self.non_foot_bodies = non_foot_bodies(m, self.description.feet)
        self.control_dt = constants.CONTROL_DT
        self.physics_dt = float(m.opt.timestep)
        self.n_sub = int(round(self.control_dt / self.physics_dt))
        if abs(self.n_sub * self.physics_dt - self.control_dt) > 1e-9:
            raise ValueError(
                f"control period {self.control_dt} s is not a multiple of the timestep {self.physics_dt} s"
            )
        d = mujoco.MjData(m)
        d.qpos[:] = self.qpos0
        mujoco.mj_forward(m, d)
        self.com0 = d.subtree_com[self.map.base_body].copy()
        self.s0 = self.qpos0[self.map.mj_qpos].copy()
        self.mass = float(m.body_subtreemass[self.map.base_body])

    def schedule(self, task: str = "stand", duration: float | None = None) -> TaskSchedule:
        """The task's references from the home state (:func:`make_schedule`)."""
        return make_schedule(task, self.com0, self.s0, duration)

    def simulate(
        self,
        task: str = "stand",
        *,
        duration: float | None = None,
        push=None,
        push_body: str = "trunk",
        config: TsidConfig | None = None,
        record: bool = True,
        timing: bool = False,
    ) -> dict:
        """One closed loop from the home state (as :func:`baseline_cpu.simulate` with one environment).

        Args:
          task: ``stand`` or ``sinusoid``; duration: seconds (None: the task's default).
          push: force (P, 3) N or (3,), onset, duration (P,) s (a dict; ``baseline_cpu.push_to_numpy``)
            on ``push_body``'s CoM (a body or a role such as ``trunk``), world axes; None: no push.
          config: :class:`TsidConfig` (None: the defaults). record: keep the CoM and torques per tick.
          timing: time the controller (state map; TSID problem data + solve + torques) and the physics
            (mj_step1 + mj_step2 + the tick's other mj_step): wall clock (perf_counter) and this
            thread's CPU time (thread_time: what a shared machine's other load does not add).

        Returns:
          dict: ``t`` (T,), ``com_ref`` (T, 3), ``metrics`` (``baseline_cpu.LoopMetrics.metrics``,
          (1,) arrays), ``summary`` (``baseline_cpu.summarize``: the ``constants.METRIC_NAMES``
          values; time to recover counted from the push's end), ``n_ticks``; with ``record``: ``com``
          (T, 3), ``tau`` (T, n), ``status`` (T,); with ``timing``: ``timing`` (seconds and
          microseconds per tick of each part).
        """
        m, smap = self.mj_model, self.map
        pb = body_id(m, self.description.body(push_body))
        sched = self.schedule(task, duration)
        T = int(round(sched.duration / self.control_dt))
        ref = bc.schedule_table(sched, np.arange(T) * self.control_dt)
        pu = bc.push_to_numpy(push, 1)
        ctrl = TsidController(self.pin_model, smap, m, self.qpos0, sched.s0, config, self.robot)
        d = mujoco.MjData(m)
        d.qpos[:] = self.qpos0
        d.qvel[:] = 0.0
        mujoco.mj_forward(m, d)
        sites, base, nfb = self.foot_sites, smap.base_body, self.non_foot_bodies
        # The metrics' support rectangle is the project's (the robot's CoP rectangle), whatever the contact points.
        W_R_feet0 = d.site_xmat[sites].reshape(1, 2, 3, 3).copy()
        tracker = bc.LoopMetrics(
            self.description.sole_cop, d.site_xpos[sites][None].copy(), W_R_feet0, d.subtree_com[base, 2:3].copy()
        )
        rec = {"com": np.zeros((T, 3)), "tau": np.zeros((T, len(smap.joints))), "status": np.zeros(T, int)}
        wall, cpu = time.perf_counter, time.thread_time
        t_map, t_tsid, t_phys = [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]  # (wall, this thread's CPU) seconds
        sub_times = np.arange(self.n_sub) * self.physics_dt
        F_cur = np.zeros(3)
        limit = m.actuator_ctrlrange[smap.actuators]
        n_sub, dt = self.n_sub, self.physics_dt
        for k in range(T):
            t_now = k * self.control_dt
            saved = (d.qpos.copy(), d.qvel.copy(), d.qacc_warmstart.copy(), d.time)
            F_all = bc.push_force(pu, (t_now + sub_times)[:, None, None], dt)[:, 0]  # (n_sub, 3)
            c0 = (wall(), cpu())
            mujoco.mj_step1(m, d)
            c1 = (wall(), cpu())
            q, v = smap.q_v(d.qpos, d.qvel, d.xmat[base].reshape(3, 3))
            c2 = (wall(), cpu())
            tau_pin, sol = ctrl.solve(t_now, q, v, ref["com_pos"][k], ref["com_vel"][k], ref["com_acc"][k])
            infeasible = tau_pin is None
            tau = np.clip(ctrl.torques(tau_pin, d.qvel[smap.mj_dof]), limit[:, 0], limit[:, 1])
            c4 = (wall(), cpu())
            # The tick's state for the metrics (after mj_step1: kinematics and CoM at it).
            mujoco.mj_subtreeVel(m, d)
            com, com_vel = d.subtree_com[base].copy(), d.subtree_linvel[base].copy()
            W_p_feet, W_R_feet = d.site_xpos[sites].copy(), d.site_xmat[sites].reshape(2, 3, 3).copy()
            body_low = bool(d.xpos[nfb, 2].min() < constants.BODY_FLOOR_HEIGHT)
            body_low |= not d.xmat[base, 8] >= np.cos(np.radians(constants.FALL_TRUNK_TILT_DEG))  # the trunk tipped
            violation = ctrl.violation(sol)
            c5 = (wall(), cpu())
            for j in range(n_sub):
                if np.any(F_all[j] != F_cur):
                    d.xfrc_applied[pb, :3] = F_cur = F_all[j]
                if j == 0:
                    d.ctrl[smap.actuators] = tau
                    mujoco.mj_step2(m, d)
                else:
                    mujoco.mj_step(m, d)
            c6 = (wall(), cpu())
            for j in (0, 1):
                t_phys[j] += (c1[j] - c0[j]) + (c6[j] - c5[j])
                t_map[j] += c2[j] - c1[j]
                t_tsid[j] += c4[j] - c2[j]
            qpos_, qvel_, warm, time_ = saved
            finite = (
                abs(d.time - (time_ + n_sub * dt)) < 0.5 * dt
                and np.isfinite(d.qpos).all()
                and np.isfinite(d.qvel).all()
            )
            if not finite:  # freeze at the tick's start, as baseline_cpu.simulate
                d.qpos[:], d.qvel[:], d.qacc_warmstart[:], d.time = qpos_, qvel_, warm, time_
            tracker.update(
                t_now,
                ref["com_pos"][k],
                ref["activation"][k],
                com[None],
                com_vel[None],
                W_p_feet[None],
                W_R_feet[None],
                tau[None],
                np.array([violation]),
                np.array([infeasible]),
                np.array([finite]),
                np.array([body_low]),
            )
            if record:
                rec["com"][k], rec["tau"][k], rec["status"][k] = com, tau, sol.status
        push_end = float(np.max(pu["onset"] + pu["duration"])) if push is not None else 0.0
        out = {
            "t": np.arange(T) * self.control_dt,
            "com_ref": ref["com_pos"],
            "metrics": tracker.metrics,
            "summary": bc.summarize(tracker.metrics, push_end)[0],
            "n_ticks": T,
        }
        if record:
            out.update(rec)
        if timing:
            out["timing"] = {"ticks": T}
            for j, kind in enumerate(("", "cpu_")):  # wall clock; CPU time of this thread
                out["timing"].update(
                    {
                        f"state_map_{kind}s": t_map[j],
                        f"tsid_{kind}s": t_tsid[j],
                        f"physics_{kind}s": t_phys[j],
                        f"state_map_{kind}us_per_tick": 1e6 * t_map[j] / T,
                        f"tsid_{kind}us_per_tick": 1e6 * t_tsid[j] / T,
                        f"controller_{kind}us_per_tick": 1e6 * (t_map[j] + t_tsid[j]) / T,
                        f"physics_{kind}us_per_tick": 1e6 * t_phys[j] / T,
                        f"physics_{kind}us_per_mj_step": 1e6 * t_phys[j] / (T * n_sub),
                    }
                )
        return out


def simulate(task: str = "stand", robot: str = DEFAULT_ROBOT, **kwargs: Any) -> dict:
    """:meth:`TsidPeer.simulate` on a freshly loaded robot (for one run; load a :class:`TsidPeer`
    once for many)."""
    return TsidPeer(robot=robot).simulate(task, **kwargs)
