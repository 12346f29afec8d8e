"""The crocoddyl cross-check of ``wbc-jax limit`` (issue 43): contact-aware DDP on Pinocchio, on the CPU.

An optimiser independent of the MJX trajectory optimiser (:mod:`wbc_jax.jobs.trajopt`): for one
push (body, azimuth, impulse, duration, onset: the pushes of :mod:`wbc_jax.jobs.limit`),

1. the post-push state: the balancing controller alone in C MuJoCo (float64) from the standing
   start through the push, read at the first tick after it (k1), as the limit's replays see it;
2. crocoddyl's box-constrained FDDP (``SolverBoxFDDP``) on the Pinocchio model of the robot
   (:func:`wbc_jax.robot.pinocchio.pinocchio_model`: the controller model of the TSID peer, equal to
   the MJCF's to 1e-12) from that state over ``ddp_horizon`` s at the control tick: both soles
   held by rigid 6-D contacts (``ContactModel6D``) at their post-push placements, a wrench-cone
   cost per sole (friction pyramid at the controller's mu and the CoP inside the controller's CoP
   rectangle, :class:`wbc_jax.robot.contacts.ContactParams`) as a quadratic barrier, state
   regularisation toward the standing state at the onset, the CoM toward its standing position,
   and the torque bounds of the model (:func:`wbc_jax.robot.bounds.joint_torque_limits`: the
   actuators' ctrlrange and the joints' actuatorfrcrange) as control bounds;
3. the replay: the controller with feedforward torques u_k = tau_DDP,k + D s_dot_DDP,k -
   tau_WBC(x_DDP,k) over the DDP's ticks (:class:`wbc_jax.sim.state.Feedforward`), where
   tau_WBC(x_DDP,k) is the controller evaluated along the DDP's planned states and D the plant's
   joint damping (absent from Pinocchio's dynamics): on the planned trajectory the plant gets the
   DDP's torques, off it the controller's feedback acts on the deviation; the controller alone
   after it. Judged by the limit's strict criterion in C MuJoCo
   (:meth:`wbc_jax.jobs.limit_rounds.Search.judge`).

A bisection over the impulse per direction (:func:`bisect`) gives the largest impulse whose DDP
trajectory, so tracked, passes: a lower bound of the physical limit from a second optimiser.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import pathlib
import time

import jax
import numpy as np

from wbc_jax.core import constants
from wbc_jax.core.options import check_options, option
from wbc_jax.jobs import grids, limit, limit_rounds
from wbc_jax.robot import bounds, contacts, model, pinocchio
from wbc_jax.robot.robots import robot_option
from wbc_jax.sim import host_loop, physics

STEP = 1.25  # the bisection's factor while a direction's bracket is open
RESUME_FREE = ("directions", "tests")  # config fields a resumed cross-check may change


def crocoddyl_problem() -> str | None:
    """Why the cross-check cannot run here (one sentence), or None."""
    if importlib.util.find_spec("crocoddyl") is None:
        return "crocoddyl is not installed (pip install -e '.[dev]' installs crocoddyl==3.2.1)"
    return None


@dataclasses.dataclass(frozen=True)
class DdpConfig:
    """The crocoddyl cross-check: the pushes (as ``wbc-jax limit``'s), the DDP problem, the bisection."""

    directions: tuple[float, ...] = grids.directions_option((0.0, 90.0, 180.0, 270.0))
    robot: str = robot_option()
    body: str = option(
        "trunk",
        "pushed body: a body of the robot or a role (trunk, pelvis, left_hand, right_thigh)",
        names=model.pushable_bodies,
    )
    push_duration: float = grids.push_duration_option()
    push_onset: float = grids.push_onset_option()
    gains: str | None = option(None, "gains JSON file of the tracking controller", metavar="FILE", input_file=True)
    horizon: float = option(
        3.0, "seconds per replay (the strict criterion is judged at its end)", gt=0.0, le=limit.MAX_HORIZON_S, unit="s"
    )
    ddp_horizon: float = option(
        1.0, "seconds of the DDP problem from the post-push state", gt=0.0, le=limit.MAX_WINDOW_S, unit="s"
    )
    max_iterations: int = option(100, "DDP iterations per solve", ge=1, le=10_000)
    w_state: float = option(1.0, "weight of the state regularisation toward standing", gt=0.0, le=1e6)
    w_com: float = option(100.0, "weight of the CoM toward its standing position", ge=0.0, le=1e6)
    w_wrench_cone: float = option(100.0, "weight of the wrench-cone barrier (friction, CoP)", gt=0.0, le=1e9)
    cop_scale: float = option(
        1.0,
        "the barrier's CoP rectangle as a fraction of the controller's, about its centre "
        "(below 1: a margin for the tracking)",
        gt=0.0,
        le=1.0,
    )
    w_control: float = option(1e-3, "weight of the torque regularisation", ge=0.0, le=1e6)
    w_terminal: float = option(100.0, "terminal weight multiplier of state and CoM", ge=1.0, le=1e6)
    tests: int = option(5, "impulses tested per direction (the bisection's steps)", ge=1, le=50)

    def check(self) -> None:
        """Every check before anything compiles or solves."""
        check_options(self)
        problem = crocoddyl_problem()
        if problem is not None:
            raise ValueError(problem)
        peers = pinocchio.ROBOTS  # the robots whose crocoddyl check was run
        if self.robot not in peers:
            raise ValueError(
                f"--robot {self.robot}: the crocoddyl cross-check has the Pinocchio models of {list(peers)}"
            )
        self.limit_config().check()

    def limit_config(self) -> limit.LimitConfig:
        """The limit search's config whose pushes, setups and judge the cross-check shares: the
        feedforward window from the onset through the push and the DDP's horizon, every tick free."""
        return limit.LimitConfig(
            robot=self.robot,
            directions=self.directions,
            body=self.body,
            push_duration=self.push_duration,
            push_onset=self.push_onset,
            gains=self.gains,
            horizon=self.horizon,
            window=self.push_duration + self.ddp_horizon,
            tail=0.0,
            knot_interval=constants.CONTROL_DT,
            candidates=1,
            rounds=1,
            out="/nonexistent/limit_ddp",
        )


class CrossCheck:
    """The robot's Pinocchio model and crocoddyl state, the limit search's setups and judge."""

    def __init__(self, cfg: DdpConfig):
        import crocoddyl
        import pinocchio as pin

        self.cfg, self.croc, self.pin = cfg, crocoddyl, pin
        self.search = limit_rounds.Search(cfg.limit_config())
        robot = self.search.replay_setup.robot
        m = robot.mj_model
        self.pin_model = pinocchio.pinocchio_model(robot.index.joints, robot=cfg.robot)
        self.map = pinocchio.StateMap(m, self.pin_model, robot.index.joints)
        self.loop = self.search.replay_setup.loop
        self.dt = self.loop.cfg.control_dt
        self.k0 = self.search.k0
        self.k1 = self.k0 + int(round(cfg.push_duration / self.dt))
        self.T = int(round(cfg.ddp_horizon / self.dt))
        self.params = contacts.ContactParams(foot_size=robot.description.sole_cop)
        (x_lo, x_hi), (y_lo, y_hi) = self.params.foot_size
        self.box = cfg.cop_scale * np.array([x_hi - x_lo, y_hi - y_lo])
        centre = pin.SE3(np.eye(3), np.array([(x_lo + x_hi) / 2, (y_lo + y_hi) / 2, 0.0]))
        self.feet = robot.description.feet
        self.contact_frames = []
        for foot in self.feet:  # the CoP rectangle's centre, where the wrench cone is centred
            sole = self.pin_model.getFrameId(foot)
            parent = self.pin_model.frames[sole]
            frame = pin.Frame(
                f"{foot}_cop_centre", parent.parentJoint, sole, parent.placement * centre, pin.FrameType.OP_FRAME
            )
            self.contact_frames.append(self.pin_model.addFrame(frame))
        self.pin_data = self.pin_model.createData()
        limits = bounds.joint_torque_limits(m, self.map.joints)
        self.torque_limit = self.map.joints_to_pin(limits)  # Pinocchio's actuated order
        self.damping = m.dof_damping[self.map.mj_dof]  # joints order
        self.state = crocoddyl.StateMultibody(self.pin_model)
        self.actuation = crocoddyl.ActuationModelFloatingBase(self.state)

    # -- the post-push state and the controller along a plan, in C MuJoCo -----------------------

    def post_push(self, scen):
        """C MuJoCo, the controller alone, from the start through the push. Returns (qpos, qvel
        at the onset tick k0 (B, nq), (B, nv); the same at k1, the first tick after the push;
        the loop state at k1; the host programs)."""
        loop, st = self.loop, self.search.replay_setup
        scen = jax.tree_util.tree_map(np.asarray, scen)
        B = int(scen.friction.shape[0])
        qpos0 = np.asarray(st.qpos0, float)[None].repeat(B, 0)
        cast = lambda x: np.asarray(x, st.dtype if np.asarray(x).dtype.kind == "f" else None)  # noqa: E731
        gains, push = jax.tree_util.tree_map(cast, scen.gains), jax.tree_util.tree_map(cast, scen.push)
        fns, _ = host_loop.host_programs(loop, gains, cast(qpos0), push)
        state = fns["init"](cast(qpos0))
        host = physics.HostBatch(host_loop.host_models(loop, scen), qpos0, 1)
        try:
            for k in range(self.k1):
                if k == self.k0:
                    onset = host.state()
                q, v = host.state()
                state, ctrl, _, forces, bodies = fns["control"](
                    gains, state, cast(q), cast(v), np.int32(k), ~host.diverged, push, None
                )
                host.step(np.asarray(ctrl, float), host_loop.host_xfrc(loop, forces, bodies))
            after = host.state()
            if host.diverged.any():
                raise RuntimeError("C MuJoCo diverged during the push")
        finally:
            host.close()
        return onset, after, state, (fns, gains, push, cast)

    def controller_along(self, plan_qpos, plan_qvel, state, programs) -> np.ndarray:
        """(B, T, n) tau_WBC at the planned states (B, T, nq), (B, T, nv) of ticks k1..k1+T-1, the
        controller's state threaded from the loop state at k1."""
        fns, gains, push, cast = programs
        out = []
        ok = np.ones(plan_qpos.shape[0], bool)
        for i in range(plan_qpos.shape[1]):
            state, ctrl, *_ = fns["control"](
                gains, state, cast(plan_qpos[:, i]), cast(plan_qvel[:, i]), np.int32(self.k1 + i), ok, push, None
            )
            out.append(np.asarray(ctrl, float)[:, self.loop.idx.actuators])
        return np.stack(out, 1)

    # -- the DDP --------------------------------------------------------------------------------

    def problem(self, x0: np.ndarray, x_stand: np.ndarray, T: int):
        """The crocoddyl shooting problem from x0 (nq + nv,) (Pinocchio) over T ticks toward the
        standing state x_stand; the contacts at the soles' placements in x0."""
        croc, pin, cfg = self.croc, self.pin, self.cfg
        nu, nv = self.actuation.nu, self.state.nv
        q0 = x0[: self.state.nq]
        pin.forwardKinematics(self.pin_model, self.pin_data, q0)
        pin.updateFramePlacements(self.pin_model, self.pin_data)
        com_stand = pin.centerOfMass(self.pin_model, self.pin_data, x_stand[: self.state.nq])
        state_w = np.concatenate([[10.0] * 3, [50.0] * 3, [1.0] * (nv - 6), [1.0] * nv])

        def node(terminal: bool):
            weight = cfg.w_terminal if terminal else 1.0
            contact = croc.ContactModelMultiple(self.state, nu)
            costs = croc.CostModelSum(self.state, nu)
            for foot, frame in zip(self.feet, self.contact_frames, strict=True):
                # Baumgarte damping 0.5 / dt: Euler halves a contact-velocity error per tick (at
                # 2 / dt it flips sign every tick and the contact forces ring).
                placement = self.pin_data.oMf[frame]
                contact.addContact(
                    f"{foot}_contact",
                    croc.ContactModel6D(self.state, frame, placement, pin.LOCAL, nu, np.array([0.0, 0.5 / self.dt])),
                )
                if terminal:  # no torques at the terminal node: its contact forces are no decision
                    continue
                cone = croc.WrenchCone(np.eye(3), self.params.mu, self.box, 4, True, self.params.fz_min)
                residual = croc.ResidualModelContactWrenchCone(self.state, frame, cone, nu)
                barrier = croc.ActivationModelQuadraticBarrier(croc.ActivationBounds(cone.lb, cone.ub))
                costs.addCost(
                    f"{foot}_wrench_cone", croc.CostModelResidual(self.state, barrier, residual), cfg.w_wrench_cone
                )
            reg = croc.ResidualModelState(self.state, x_stand, nu)
            costs.addCost(
                "state",
                croc.CostModelResidual(self.state, croc.ActivationModelWeightedQuad(state_w**2), reg),
                cfg.w_state * weight,
            )
            costs.addCost(
                "com",
                croc.CostModelResidual(self.state, croc.ResidualModelCoMPosition(self.state, com_stand, nu)),
                cfg.w_com * weight,
            )
            if not terminal:
                costs.addCost(
                    "torque",
                    croc.CostModelResidual(self.state, croc.ResidualModelControl(self.state, nu)),
                    cfg.w_control,
                )
            dam = croc.DifferentialActionModelContactFwdDynamics(self.state, self.actuation, contact, costs, 0.0, True)
            dam.u_lb, dam.u_ub = -self.torque_limit, self.torque_limit
            return croc.IntegratedActionModelEuler(dam, 0.0 if terminal else self.dt)

        running = node(False)
        return croc.ShootingProblem(x0, [running] * T, node(True))

    def solve(self, x0: np.ndarray, x_stand: np.ndarray, T: int | None = None) -> dict:
        """BoxFDDP from x0 (warm start: x0 held, quasi-static torques). Returns {"xs" (T + 1, nx),
        "us" (T, nu), "iterations", "cost", "converged", "solve_s", "solve_cpu_s" (this process's CPU
        time, every thread: the machine is shared), "solver"}."""
        problem = self.problem(x0, x_stand, self.T if T is None else T)
        solver = self.croc.SolverBoxFDDP(problem)
        xs = [x0] * (problem.T + 1)
        us = problem.quasiStatic([x0] * problem.T)
        t0, cpu0 = time.perf_counter(), time.process_time()
        converged = solver.solve(xs, us, self.cfg.max_iterations, False)
        return {
            "xs": np.array(solver.xs),
            "us": np.array(solver.us),
            "iterations": int(solver.iter),
            "cost": float(solver.cost),
            "converged": bool(converged),
            "solve_s": time.perf_counter() - t0,
            "solve_cpu_s": time.process_time() - cpu0,
            "solver": solver,
        }

    def contact_forces(self, solver) -> np.ndarray:
        """(T, 2, 6) the DDP's contact wrenches [force, torque] per sole in its contact frame."""
        out = []
        for data in solver.problem.runningDatas:
            cs = data.differential.multibody.contacts.contacts
            out.append([np.concatenate([cs[f"{f}_contact"].f.linear, cs[f"{f}_contact"].f.angular]) for f in self.feet])
        return np.array(out)

    # -- mapping between the engines -------------------------------------------------------------

    def to_pin(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        q, v = self.map.q_v(qpos, qvel)
        return np.concatenate([q, v])

    def to_mujoco(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pinocchio x (nq + nv,) -> MuJoCo (qpos (nq,), qvel (nv,)) (the inverse of StateMap.q_v)."""
        sm, nq = self.map, self.state.nq
        q, v = x[:nq], x[nq:]
        R = self.pin.Quaternion(q[6], q[3], q[4], q[5]).toRotationMatrix()
        qpos, qvel = np.empty(nq), np.empty(self.state.nv)
        qpos[:3], qpos[3] = q[:3], q[6]
        qpos[4:7] = q[3:6]
        qpos[sm.mj_qpos] = q[sm.pin_q]
        qvel[:3], qvel[3:6] = R @ v[:3], v[3:6]
        qvel[sm.mj_dof] = v[sm.pin_v]
        return qpos, qvel

    # -- one batch of pushes ----------------------------------------------------------------------

    def run(self, d: np.ndarray, impulse: np.ndarray) -> list[dict]:
        """Solve and replay the pushes of directions ``d`` (B,) (indices) with ``impulse`` (B,) N s.
        Returns per push {"verified", "iterations", "cost", "converged", "solve_s", "solve_cpu_s", "failed",
        "feedforward" (ticks, n) the torques replayed from the onset (the witness; not JSON),
        "replay_<column>"}."""
        scen = self.search.scenarios(np.asarray(d), np.asarray(impulse, float))
        (q_on, _), (q1, v1), state, programs = self.post_push(scen)
        B, n = len(d), self.map.joints.__len__()
        solves, plan_q, plan_v = [], [], []
        for b in range(B):
            x_stand = self.to_pin(q_on[b], np.zeros(self.state.nv))
            sol = self.solve(self.to_pin(q1[b], v1[b]), x_stand)
            solves.append(sol)
            mj = [self.to_mujoco(x) for x in sol["xs"][: self.T]]
            plan_q.append([a for a, _ in mj])
            plan_v.append([b_ for _, b_ in mj])
        plan_q, plan_v = np.array(plan_q), np.array(plan_v)
        tau_wbc = self.controller_along(plan_q, plan_v, state, programs)
        u = np.zeros((B, self.k1 - self.k0 + self.T, n))
        for b, sol in enumerate(solves):
            tau_ddp = self.map.joints_from_pin(sol["us"].T).T  # (T, n) joints order
            u[b, self.k1 - self.k0 :] = tau_ddp + self.damping * plan_v[b][:, self.map.mj_dof] - tau_wbc[b]
        cols = self.search.judge(scen, u, "mujoco")
        out = []
        for b, sol in enumerate(solves):
            rec = {k: sol[k] for k in ("iterations", "cost", "converged", "solve_s", "solve_cpu_s")}
            rec.update(
                verified=bool(cols["survived"][b]),
                failed=cols["failed"][b],
                impulse_ns=float(impulse[b]),
                feedforward=u[b],
                **{f"replay_{k}": float(cols[k][b]) for k in limit_rounds.REPLAY_COLUMNS},
            )
            out.append(rec)
        return out

    def replay_alone(self, d: int, impulse: float, feedforward: np.ndarray) -> dict:
        """The C MuJoCo replay of one recorded witness (feedforward (ticks, n) from :meth:`run`) in a
        batch of its own: whether it passes whatever else was replayed beside it. Returns the
        judge's columns of that push."""
        scen = self.search.scenarios(np.array([d]), np.array([float(impulse)]))
        cols = self.search.judge(scen, np.asarray(feedforward)[None], "mujoco")
        return {
            "verified": bool(cols["survived"][0]),
            "failed": cols["failed"][0],
            **{f"replay_{k}": float(cols[k][0]) for k in limit_rounds.REPLAY_COLUMNS},
        }


def next_impulse(tests: list[dict], start: float, cap: float) -> float:
    """The next impulse of a direction's bisection from its ``tests`` so far: ``start`` first; x1.25
    above the largest verified impulse while nothing above it failed (at most ``cap``); /1.25 below
    the smallest failed one while nothing passed; else the bracket's middle."""
    lo, hi = limit.bracket([(r["impulse_ns"], r["verified"]) for r in tests])
    if not tests:
        return float(start)
    if np.isinf(hi):
        return float(min(cap, STEP * lo))
    if lo == 0.0:
        return float(hi / STEP)
    return float(0.5 * (lo + hi))


def bisect(
    check: CrossCheck, start: np.ndarray, cap: np.ndarray, tested: list[list[dict]] | None = None, on_test=None
) -> list[list[dict]]:
    """Per direction ``cfg.tests`` impulses (:func:`next_impulse`) from ``start`` (D,) N s, capped at
    ``cap`` (D,); ``tested``: each direction's tests already made (a resumed run), which are kept and
    continued. The directions still short of ``cfg.tests`` run in one batch a step; ``on_test``
    (tested) after each. Returns per direction its tests (records)."""
    D = len(start)
    tested = [list(t) for t in tested] if tested is not None else [[] for _ in range(D)]
    while todo := [d for d in range(D) if len(tested[d]) < check.cfg.tests]:
        impulses = [next_impulse(tested[d], start[d], cap[d]) for d in todo]
        for d, rec in zip(todo, check.run(np.array(todo), np.array(impulses)), strict=True):
            tested[d].append(rec)
        if on_test is not None:
            on_test(tested)
    return tested


def witness_path(path) -> pathlib.Path:
    """Where a cross-check file keeps its verified tests' replayed torques: ``<file>_witness.npz``."""
    path = pathlib.Path(path)
    return path.with_name(path.stem + "_witness.npz")


def stored_config(config: dict) -> dict:
    """A cross-check file's ``config`` with every field it predates at its default (the run had
    that setting then): the form two files' configs are compared in."""
    return {**{name: f.default for name, f in DdpConfig.__dataclass_fields__.items()}, **config}


def resumed_tests(previous: dict | None, cfg: DdpConfig, path) -> dict[float, list[dict]]:
    """{azimuth: tests} of a cross-check file written before (None: a fresh run) whose problem is
    ``cfg``'s: every config field but the directions and the tests per direction must agree, else a
    one-line error naming the file and the first field that differs."""
    if previous is None:
        return {}
    stored = stored_config(previous["config"])
    for name in cfg.__dataclass_fields__:
        if name in RESUME_FREE:
            continue
        was, now = stored[name], getattr(cfg, name)
        if was != now:
            raise ValueError(
                f"{path} was written with {name}={was!r}, this run has {now!r}: pass the same settings "
                "to resume it, or another --out"
            )
    return {float(a): row["tests"] for a, row in previous["directions"].items()}
