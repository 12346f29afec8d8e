"""General contact sets (feet, a hand on a table): scene geometry against C MuJoCo, contact
kinematics against the feet terms, the force distribution against its constraints and against the
two-feet QP, a short closed loop with the measured hand force, and clear errors for bad input."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from wbc_jax.control import constraints, forces, task_files, torques
from wbc_jax.control import controller as C
from wbc_jax.control.gains import default_gains
from wbc_jax.control.references import Reference
from wbc_jax.jobs import balance
from wbc_jax.robot import contacts, dynamics
from wbc_jax.robot import scene as contact_scene
from wbc_jax.sim import physics, scenario

HAND_FILE = "experiments/tasks/hand_on_table.yaml"
FEET = [
    {"name": "left_foot", "frame": "l_sole", "normal": [0, 0, 1]},
    {"name": "right_foot", "frame": "r_sole", "normal": [0, 0, 1]},
]
HAND = {
    "name": "left_hand",
    "frame": "l_hand",
    "type": "point",
    "normal": [0, 0, 1],
    "touches": "table",
    "mu": 0.5,
    "fz_min": 1.0,
    "normal_force": 5.0,
}
TABLE = {"name": "table", "size": [0.15, 0.3, 0.02], "under": "left_hand", "shift": [0.05, -0.1, 0.0]}


@pytest.fixture(scope="module")
def hand_scene():
    scene = scenario.load_scene("icub", HAND_FILE)
    return scene.robot, scene.tasks, scene.contact_set, scene.qpos


def _data(robot, qpos, qvel=None):
    d = mjx.make_data(robot.mj_model).replace(qpos=jnp.asarray(qpos, jnp.float64))
    return d if qvel is None else d.replace(qvel=jnp.asarray(qvel, jnp.float64))


def _forward(robot, qpos):
    d = mujoco.MjData(robot.mj_model)
    d.qpos[:] = qpos
    mujoco.mj_forward(robot.mj_model, d)
    return d


def test_scene_geometry(hand_scene):
    """The table's top is at the hand's point; the hand sphere and the soles touch at distance 0."""
    robot, _, cset, qpos = hand_scene
    m = robot.mj_model
    assert m.geom(physics.FLOOR_GEOM).name == "floor"
    d = _forward(robot, qpos)
    dist = {}
    for k in range(m.npair):
        fromto = np.zeros(6)
        g1, g2 = m.pair_geom1[k], m.pair_geom2[k]
        dist[m.geom(g2).name] = mujoco.mj_geomDistance(m, d, g1, g2, 0.1, fromto)
    assert abs(dist["left_hand_contact_0"]) < 1e-9
    assert max(abs(v) for k, v in dist.items() if "foot" in k) < 2e-5  # soles on the floor (home keyframe)
    hand = cset.contacts[2]
    assert hand.type == "point" and hand.dim == 3 and hand.geoms == (m.geom("left_hand_contact_0").id,)
    # The feet reuse their four corner spheres; their contact frames are the sole sites.
    assert len(cset.contacts[0].geoms) == 4 and cset.contacts[0].foot == 0 and cset.contacts[1].foot == 1
    table = m.geom("table")
    top = d.geom_xpos[table.id][2] + table.size[2]
    R = d.xmat[hand.body].reshape(3, 3)
    assert abs(top - (d.xpos[hand.body] + R @ np.array(hand.point))[2]) < 1e-12


@pytest.mark.slow  # 40 CPU s; the feet's terms and the force distribution stay in the default set
def test_contact_terms_stack_the_feet_terms(hand_scene):
    """Feet rows of the general set = the sole terms of dynamics.terms; the hand rows = its linear
    Jacobian (C MuJoCo mj_jac, mixed velocity); contact frames have z along the given normals."""
    robot, _, cset, qpos = hand_scene
    rng = np.random.default_rng(3)
    qvel = rng.normal(scale=0.3, size=robot.mj_model.nv)
    dx = _data(robot, qpos, qvel)
    t = dynamics.terms(robot.mjx_model, dx, robot.index)  # the default frames: the two soles
    ct = contacts.contact_terms(cset, dynamics.terms(robot.mjx_model, dx, robot.index, cset.frames), 1.0, jnp.ones(2))
    assert ct.J.shape == (15, robot.index.nv) and ct.Jdot_nu.shape == (15,)
    # Two implementations of the same kinematics: measured <= 1.2e-15 abs, here and with XLA held to AVX2.
    np.testing.assert_allclose(ct.J[:12], t.J_frames.reshape(12, -1), atol=1e-12)
    np.testing.assert_allclose(ct.Jdot_nu[:12], t.Jdot_nu_frames.reshape(12), atol=1e-10)
    sole_R = np.einsum("kij,kjl->kil", t.W_R_frames, robot.index.foot_rotations)
    np.testing.assert_allclose(ct.W_R[:2], sole_R, atol=1e-12)
    d0 = _forward(robot, qpos)
    np.testing.assert_allclose(sole_R, d0.site_xmat[robot.index.foot_sites].reshape(2, 3, 3), atol=1e-12)
    np.testing.assert_allclose(ct.W_R[2][:, 2], [0, 0, 1], atol=1e-12)
    d = _forward(robot, qpos)
    hand = cset.contacts[2]
    jacp = np.zeros((3, robot.mj_model.nv))
    point = d.xpos[hand.body] + d.xmat[hand.body].reshape(3, 3) @ np.array(hand.point)
    mujoco.mj_jac(robot.mj_model, d, jacp, None, point, hand.body)
    J = jacp[:, robot.index.dof_perm]
    J[:, 3:6] = J[:, 3:6] @ d.xmat[robot.index.base_body].reshape(3, 3).T  # mixed: world angular velocity
    np.testing.assert_allclose(ct.J[12:], J, atol=1e-12)
    np.testing.assert_allclose(ct.activation, [1, 1, 1])


@pytest.fixture(scope="module")
def distribution(hand_scene):
    """Terms and the force distribution at the home state (float64), for a wrench the contacts can
    produce and for its opposite (pulling the robot down through the floor). One compiled program:
    run op by op, the same code cost 2.3x the CPU time (51 against 22 CPU s on the 2-core machine)."""
    robot, _, cset, qpos = hand_scene
    g = default_gains(robot.description, jnp.float64)
    cfg = C.ControllerConfig()
    # A desired wrench that needs the contacts: the weight and a forward/sideways force.
    wrench = jnp.array([8.0, -3.0, 9.81 * robot.index.mass, 0.5, -1.0, 0.2])

    @jax.jit
    def compute(qpos, wrench):
        t = dynamics.terms(robot.mjx_model, _data(robot, qpos), robot.index, cset.frames)
        ct = contacts.contact_terms(cset, t, 2.0, jnp.ones(2))
        rows = contacts.row_activation(cset, ct.activation)
        tt = torques.torque_terms(
            t,
            ct.J * rows[:, None],
            ct.Jdot_nu * rows,
            postural="stable",
            kp_postural=g.kp_postural,
            kd_postural=g.kd_postural,
            s_des=t.s,
        )
        A = constraints.wrench_map(cset, ct.W_p, t.W_p_CoM)
        f, infeasible, _ = forces.wbc_qp(cset, jnp.ones(3), A, wrench, tt, ct.W_R, cfg.force_settings)
        f_bad, infeasible_bad, _ = forces.wbc_qp(cset, jnp.ones(3), A, -wrench, tt, ct.W_R, cfg.force_settings)
        return {
            "t": t,
            "ct": ct,
            "A": A,
            "f": f,
            "infeasible": infeasible,
            "f_bad": f_bad,
            "infeasible_bad": infeasible_bad,
        }

    return {**compute(jnp.asarray(qpos, jnp.float64), wrench), "robot": robot, "cset": cset, "wrench": wrench, "g": g}


def test_force_distribution_meets_its_constraints(distribution):
    """A f = the desired wrench, the hand presses with its desired 5 N, every contact's cone / CoP."""
    s = distribution
    f, cset, ct = s["f"], s["cset"], s["ct"]
    assert not bool(s["infeasible"])
    # The QP's equality rows: measured 3.8e-13 abs (AVX2 3.2e-13); the bar is ~1e4x that.
    np.testing.assert_allclose(s["A"] @ f, s["wrench"], rtol=1e-8, atol=1e-8)
    assert abs(float(f[12:15] @ ct.W_R[2][:, 2]) - 5.0) < 0.05
    Cm, b = constraints.constraints(cset, ct.W_R, ct.activation)
    assert Cm.shape == (19 + 19 + 13, 15)
    assert float(jnp.max(Cm @ f - b)) < 1e-7
    assert float(constraints.violation(cset, f, ct.W_R, ct.activation)) < 1e-8
    # A wrench the contacts cannot produce (pulling the robot down through the floor) is infeasible
    # for the equality; the soft QP still returns a constrained answer.
    f_bad = s["f_bad"]
    assert not bool(s["infeasible_bad"]) and np.all(np.isfinite(f_bad))
    assert float(jnp.max(Cm @ f_bad - b)) < 1e-6


def _assert_same_contacts(cset: contacts.ContactSet, default: contacts.ContactSet) -> None:
    """Every field of every contact: equal, but the frame's point and axes (computed) to rounding."""
    for a, b in zip(cset.contacts, default.contacts, strict=True):
        for field in dataclasses.fields(contacts.ResolvedContact):
            x, y = getattr(a, field.name), getattr(b, field.name)
            if field.name in ("point", "R_body_contact"):
                np.testing.assert_allclose(x, y, atol=1e-12 if field.name == "point" else 1e-9, err_msg=field.name)
            elif field.name == "name":  # the file names its contacts; the default set names the soles
                continue
            elif field.name == "normal_force":
                assert x == y or (math.isnan(x) and math.isnan(y)), (x, y)  # nan: free
            else:
                assert x == y, (field.name, x, y)


def test_feet_from_a_spec_file_are_the_default_contact_set(robot):
    """The two feet listed in a contact file resolve to the default contact set: every field the
    controller is built from (frames, sole axes, geoms, parameters, activation) is the default's.
    The controller's tick with either (a compiled program each): test_feet_from_a_spec_file_give_the_default_wrenches."""
    _assert_same_contacts(contact_scene.build_scene("icub", FEET, [])[1], contacts.feet_contact_set(robot))


@pytest.mark.slow  # two compiled controller ticks: 16 s alone, 52 s in the loaded 2-core suite; the fields: default
def test_feet_from_a_spec_file_give_the_default_wrenches(robot):
    """The controller gives the same wrenches and torques with the contact file's feet and the default set."""
    cset = contact_scene.build_scene("icub", FEET, [])[1]
    default = contacts.feet_contact_set(robot)
    _assert_same_contacts(cset, default)
    qvel = np.random.default_rng(5).normal(scale=0.2, size=robot.mj_model.nv)
    g = default_gains(robot.description, jnp.float64)

    def tick(contact_set):  # compiled: op by op it cost twice the CPU time
        ctrl = C.make_controller(robot, contact_set=contact_set)

        def first_output(qpos, qvel):
            t = dynamics.terms(robot.mjx_model, _data(robot, qpos, qvel), robot.index)
            ref = Reference(
                com_pos=t.W_p_CoM + jnp.array([0.01, -0.005, 0.0]),
                com_vel=jnp.zeros(3),
                com_acc=jnp.zeros(3),
                s_des=t.s,
                activation=jnp.ones(2),
            )
            return ctrl.step(g, ctrl.init(t), t, ref, 0.0)[0]

        return jax.jit(first_output)(jnp.asarray(robot.home_qpos()), jnp.asarray(qvel))

    outs = [tick(cs) for cs in (cset, default)]
    np.testing.assert_allclose(outs[0].f, outs[1].f, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(outs[0].tau, outs[1].tau, rtol=1e-6, atol=1e-6)
    assert float(outs[0].qp_violation) < 1e-8


# Compiles the closed loop of the hand-on-table scene (its own model): nightly (`slow`). The default suite keeps the
# hand contact through the controller (test_contact_detection_gates_the_hand, test_force_distribution_...).
@pytest.mark.slow
def test_hand_on_table_closed_loop():
    """1.5 s on the CPU (float64, as the test session): no fall, the measured (MuJoCo) hand force within 1 N of
    the desired 5 N, the QP constraints hold, nothing slips."""
    r = balance.run(task="stand", duration=1.5, tasks=HAND_FILE, progress=False, out=None)
    hand = r["contacts"]["left_hand"]
    assert not r["fell"] and not r["nan"] and r["qp_infeasible_ticks"] == 0
    assert hand["normal_force_err_max_n"] < 1.0
    assert abs(hand["normal_force_meas_median_n"] - 5.0) < 0.2
    assert r["max_constraint_violation"] < 1e-2
    assert r["max_foot_slip_m"] < 2e-3
    assert r["com_rmse_m"] < 1e-3


def test_plant_friction_keeps_the_table(hand_scene):
    robot = hand_scene[0]
    mx = physics.plant_model(robot.mjx_model, jnp.asarray(0.4), jnp.asarray(1.0))
    m = robot.mj_model
    m_c = physics.plant_mj_model(m, 0.4, 1.0)
    for k in range(m.npair):
        expected = 0.4 if m.pair_geom1[k] == physics.FLOOR_GEOM else 0.8  # the table's friction
        assert math.isclose(float(mx.pair_friction[k, 0]), expected, rel_tol=1e-6)
        assert math.isclose(float(m_c.pair_friction[k, 0]), expected, rel_tol=1e-6)


def test_activation_ramps():
    c = contacts.ResolvedContact(
        name="h",
        type="point",
        body=1,
        point=(0, 0, 0),
        R_body_contact=tuple(np.eye(3).ravel()),
        params=contacts.ContactParams(),
        normal_force=math.nan,
        activation=contacts.ContactActivation(start=1.0, stop=3.0, ramp=0.5),
        foot=-1,
        geoms=(),
    )
    a = [float(contacts.activation_at(c, t, jnp.ones(2), jnp.float64)) for t in (0.9, 1.25, 1.5, 2.9, 3.25, 3.6)]
    np.testing.assert_allclose(a, [0, 0.5, 1, 1, 0.5, 0], atol=1e-12)
    # On from before the first tick and never off: 1, and not a function of a batched time (a
    # queued sweep's slots each keep their own tick; vmap with out_axes=None refuses a batched output).
    ts = jnp.linspace(0.0, 5.0, 7)
    for act in (contacts.ContactActivation(), contacts.ContactActivation(start=-1.0, ramp=0.5)):
        on = dataclasses.replace(c, activation=act)
        a = jax.vmap(lambda t, on=on: contacts.activation_at(on, t, jnp.ones(2), jnp.float64), out_axes=None)(ts)
        assert float(a) == 1.0
    with pytest.raises(ValueError, match="out_axes"):  # a ramping contact depends on the time
        jax.vmap(lambda t: contacts.activation_at(c, t, jnp.ones(2), jnp.float64), out_axes=None)(ts)


@pytest.mark.parametrize(
    "contact_list, objects, message",
    [
        ([{**FEET[0], "normal": None}, FEET[1]], [], "no normal direction"),
        ([{"name": "left_foot", "frame": "l_sole"}], [], "no normal direction"),
        ([{**FEET[0], "normal": [0, 0, 0]}], [], "non-zero"),
        ([{**FEET[0], "frame": "l_palm"}, FEET[1]], [], "unknown frame 'l_palm'; valid frames"),
        ([FEET[0], FEET[0]], [], "duplicate contact names"),
        ([FEET[0], {**HAND, "touches": "wall"}], [TABLE], "touches unknown object 'wall'; valid"),
        ([FEET[0], {**HAND, "cop": [[-0.01, 0.01], [-0.01, 0.01]]}], [TABLE], "point contact has no CoP"),
        ([*FEET, {**HAND, "touches": None}], [], "has no collision geoms"),
        ([FEET[0], {**FEET[1], "offset": [0.01, 0.0, 0.0]}], [], "both soles"),
        ([FEET[0], {**HAND, "type": "line"}], [TABLE], r"type must be one of \['surface', 'point'\], got 'line'"),
        ([FEET[0], {**HAND, "normal_force": 0.5}], [TABLE], "normal_force must be"),
        ([FEET[0], {**HAND, "mu": -1}], [TABLE], r"mu must be a number in \(0, 10\], got -1"),
        ([FEET[0], {**HAND, "activation": {True: 0.0}}], [TABLE], "activation must map"),
        ([*FEET, {**HAND, "normal": [1, 1, 0]}], [TABLE], "'under' needs a contact with normal \\+z or horizontal"),
        ([FEET[0], HAND], [{**TABLE, "under": "right_hand"}], "under unknown contact"),
        ([FEET[0], HAND], [{**TABLE, "pos": [0, 0, 0]}], "exactly one of 'pos' or 'under'"),
        ([FEET[0], HAND], [{**TABLE, "size": [0.1, 0.1]}], r"size must be a list of 3 numbers, got \(0.1, 0.1\)"),
        ([], [], "the contact set is empty"),
    ],
)
def test_bad_contact_sets_are_named(contact_list, objects, message):
    with pytest.raises(ValueError, match=message):
        contact_scene.build_scene("icub", contact_list, objects)


def test_bad_spec_files(tmp_path, robot):
    bad = tmp_path / "bad.yaml"
    bad.write_text("contacts: [{name: lf, frame: l_sole, normal: [0, 0, 1]}]\nscenery: []\n")
    with pytest.raises(ValueError, match="unknown keys \\['scenery'\\]"):
        task_files.load_spec_file(bad)
    bad.write_text("scene: [{name: t, pos: [0, 0, 0]}]\ntasks: [{name: posture, kind: postural}]\n")
    with pytest.raises(ValueError, match="scene objects need a 'contacts' list"):
        scenario.load_scene("icub", bad)
    with pytest.raises(ValueError, match="unknown joint 'l_wrist'"):
        task_files.initial_qpos(robot, {"l_wrist": 10.0})


def test_touching_contacts_must_touch(hand_scene):
    """A contact's point must be on the surface it touches, its normal leaving that surface."""
    table_pos = hand_scene[0].mj_model.geom("table").pos.copy()
    placed = {k: v for k, v in TABLE.items() if k not in ("under", "shift")}
    with pytest.raises(ValueError, match="cm away from the surface of 'table'"):
        contact_scene.build_scene("icub", [*FEET, HAND], [{**placed, "pos": (table_pos - [0, 0, 0.05]).tolist()}])
    with pytest.raises(ValueError, match="points into 'table'"):
        contact_scene.build_scene(
            "icub", [*FEET, {**HAND, "normal": [0, 0, -1]}], [{**placed, "pos": table_pos.tolist()}]
        )


def test_wall_is_placed_at_the_hand():
    """'under' with a horizontal normal: the wall's face the normal leaves goes through the hand's point."""
    scene = scenario.load_scene("icub", "experiments/tasks/hand_on_wall.yaml")
    m = scene.robot.mj_model
    d = _forward(scene.robot, scene.qpos)
    hand = next(c for c in scene.contact_set.contacts if c.name == "left_hand")
    p_hand = d.xpos[hand.body] + d.xmat[hand.body].reshape(3, 3) @ np.asarray(hand.point)
    wall = m.geom("wall")
    assert abs((wall.pos[0] - wall.size[0]) - p_hand[0]) < 1e-9  # the face x = hand x; the wall in front
    assert abs(wall.pos[2] - p_hand[2]) < 1e-9 and abs(wall.pos[1] - 0.05 - p_hand[1]) < 1e-9
    assert hand.detect


def test_contact_detection_gates_the_hand(hand_scene, distribution):
    """Contact detection (Contact.detect): while MuJoCo measures no hand force the hand's activation
    ramps out within detection_ramp_out (its wrench goes to 0, the feet take the whole wrench); once
    the force is seen again it ramps back in over detection_ramp_in."""
    robot, _, cset, _ = hand_scene
    ctrl = C.make_controller(robot, contact_set=cset)
    assert ctrl.config.contact_detection
    t = distribution["t"]  # the terms at the scene's home state
    g = default_gains(robot.description, jnp.float64)
    ref = Reference(com_pos=t.W_p_CoM, com_vel=jnp.zeros(3), com_acc=jnp.zeros(3), s_des=t.s, activation=jnp.ones(2))
    step = jax.jit(ctrl.step)
    seen, unseen = jnp.array([300.0, 300.0, 5.0]), jnp.array([300.0, 300.0, 0.0])
    state = ctrl.init(t)
    out, state = step(g, state, t, ref, 1.0, seen)
    hand_force = lambda o: float(o.f[14])  # noqa: E731  (the table's normal is +z)
    assert abs(hand_force(out) - 5.0) < 0.5
    ticks_out = math.ceil(ctrl.config.detection_ramp_out / 0.01 - 1e-9)
    for _ in range(ticks_out):
        out, state = step(g, state, t, ref, 1.0, unseen)
    assert float(state.contact_gate[2]) == 0.0 and hand_force(out) < 1e-6
    assert np.all(np.asarray(state.contact_gate[:2]) == 1.0)  # the soles are never gated
    ticks_in = round(ctrl.config.detection_ramp_in / 0.01)
    forces_in = []
    for _ in range(ticks_in):
        out, state = step(g, state, t, ref, 1.0, seen)
        forces_in.append(hand_force(out))
    assert 0.0 < forces_in[ticks_in // 2 - 1] < 5.0  # part way up the ramp
    assert abs(forces_in[-1] - 5.0) < 0.5 and float(state.contact_gate[2]) == pytest.approx(1.0)
