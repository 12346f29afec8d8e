"""Issue 41's reliability classes 1, 2, 5 and 6, with examples of our own: set-ups that cannot be
physical (refused with the measured distance or angle), pushes whose simulated impulse must be
the one the tables report, the metrics of a robot thrown away, and files built to exhaust the
parser. Everything here runs before (or without) compiling a closed loop.

The closed-loop version of class 5 (a robot thrown metres away, every boolean of its summary) is
tests/test_rollout.py::test_a_robot_thrown_away_is_neither_upright_nor_survived (it reuses that module's compiled
loop); the command-line cases are in experiments/checks/bad_input.py (tests/test_cli.py runs them).
"""

import math
import pathlib
import re
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from wbc_jax.control import gains as gains_lib
from wbc_jax.control import task_files
from wbc_jax.core import constants, io, loader
from wbc_jax.jobs import sweep, sweep_config
from wbc_jax.robot import placement
from wbc_jax.sim import metrics as metrics_lib
from wbc_jax.sim import scenario
from wbc_jax.sim.state import Push, push_forces
from wbc_jax.tuning.algorithms import problem, schedule

ROOT = pathlib.Path(__file__).resolve().parent.parent
FEET = "contacts:\n  - {name: l, frame: l_sole, normal: %s%s}\n  - {name: r, frame: r_sole, normal: [0, 0, 1]}\n"
LIFTED = {"l_hip_pitch": 36, "l_knee": -46, "l_ankle_pitch": -10}  # the left sole flat, 4.1 cm up


def _feet(normal="[0, 0, 1]", extra="", posture=None, scene=""):
    text = FEET % (normal, extra)
    if posture:
        text += "initial_posture_deg: {" + ", ".join(f"{k}: {v}" for k, v in posture.items()) + "}\n"
    return text + scene


def _refusal(tmp_path, name: str, text: str) -> str:
    """The one-line refusal of a task file, checked to name the file and to come within seconds."""
    path = tmp_path / name
    path.write_text(text)
    t0 = time.perf_counter()
    with pytest.raises(ValueError) as err:
        scenario.load_scene("icub", path)
    message = str(err.value)
    assert time.perf_counter() - t0 < 10.0 and "\n" not in message and str(path) in message, message
    return message


# ---- Class 1: set-ups that cannot be physical -------------------------------------------------

UNPHYSICAL = [
    ("lifted.yaml", _feet(posture=LIFTED), r"contact 'l': sole l_sole is 4\.1 cm above the floor .*at most 5 mm"),
    (
        "tilted.yaml",
        _feet(posture={"l_ankle_roll": 8}),
        r"sole l_sole is tilted 8\.0 deg against the floor .*at most 3",
    ),
    ("pitched.yaml", _feet(posture={"r_ankle_pitch": -20}), r"contact 'r': sole r_sole is tilted 10\.0 deg"),
    (
        "normal.yaml",
        _feet(normal="[0, 0.1, 1]"),
        r"contact 'l': normal \[0.0, 0.1, 0.995\] is 5\.7 deg from the "
        r"normal \[0.0, 0.0, 1.0\] of the surface of 'floor'",
    ),
    ("down.yaml", _feet(normal="[0, 0, -1]"), r"contact 'l': normal \[0.0, 0.0, -1.0\] points into 'floor'"),
    (
        "cop.yaml",
        _feet(extra=", cop: [[-0.3, 0.3], [-0.1, 0.1]]"),
        r"contact 'l': CoP rectangle \[\[-0.3, 0.3\], "
        r"\[-0.1, 0.1\]\] m is larger than the foot: its contact spheres span x \[-0.073, 0.136\]",
    ),
    ("cop_toe.yaml", _feet(extra=", cop: [[-0.07, 0.2], [-0.045, 0.045]]"), r"is larger than the foot"),
    (
        "crate.yaml",
        _feet(scene="scene:\n  - {name: crate, size: [0.1, 0.1, 0.1], pos: [0, 0, 0.5]}\n"),
        r"scene object 'crate' intersects the robot at the initial posture: body '\w+' is \d+\.\d cm inside it",
    ),
    (
        "shin.yaml",
        _feet(scene="scene:\n  - {name: step, size: [0.05, 0.3, 0.1], pos: [0.0, 0.0, 0.1]}\n"),
        r"scene object 'step' intersects the robot",
    ),
    (
        "palm.yaml",
        _feet(
            scene="  - {name: h, frame: l_hand, type: surface, normal: [0, 0, 1], touches: table, "
            "cop: [[-0.2, 0.2], [-0.2, 0.2]]}\nscene:\n  - {name: table, size: [0.1, 0.1, 0.02], "
            "under: h}\n"
        ),
        r"contact 'h': CoP corner \(-0.2, -0.2\) m is 14\.1 cm off the surface of 'table'",
    ),
    (
        "default_feet.yaml",
        "tasks: [{name: posture, kind: postural}]\ninitial_posture_deg: {r_ankle_pitch: 15}\n",
        r"contact 'r_sole': sole r_sole is tilted 25\.0 deg",
    ),
]


@pytest.mark.parametrize("name, text, pattern", UNPHYSICAL, ids=[u[0] for u in UNPHYSICAL])
def test_unphysical_set_ups_are_refused_with_what_was_measured(tmp_path, name, text, pattern):
    assert re.search(pattern, _refusal(tmp_path, name, text))


def test_the_refusals_report_the_geometry(robot, tmp_path):
    """The reported distance and angle are the model's: the lifted sole's height (site z, spheres
    of 5 mm radius 5 mm above it), the tilt an ankle roll of 8 deg gives, atan(0.1) of a normal."""
    d = mujoco.MjData(robot.mj_model)
    d.qpos[:] = task_files.initial_qpos(robot, LIFTED)
    mujoco.mj_forward(robot.mj_model, d)
    height = d.site_xpos[robot.mj_model.site("l_sole").id][2]
    message = _refusal(tmp_path, "lifted.yaml", _feet(posture=LIFTED))
    assert float(re.search(r"is (\d+\.\d) cm above", message)[1]) == pytest.approx(100 * height, abs=0.051)
    assert 0.03 < height < 0.05
    normal = _refusal(tmp_path, "n.yaml", _feet(normal="[0, 0.1, 1]"))
    assert float(re.search(r"is (\d+\.\d) deg from", normal)[1]) == pytest.approx(
        math.degrees(math.atan(0.1)), abs=0.05
    )


@pytest.mark.parametrize(
    "text",
    [
        _feet(posture={"l_ankle_roll": 2}),
        _feet(normal="[0, 0.035, 1]"),
        _feet(extra=", cop: [[-0.0635, 0.1255], [-0.0425, 0.0505]]"),
    ],
)
def test_set_ups_within_the_tolerances_are_accepted(tmp_path, text):
    """A 2 deg ankle roll (the sole's edge 3.5 mm up), a normal 2 deg off, the model's own sole
    rectangle: inside the tolerances (3 deg, the spheres' 5 mm), so they run."""
    path = tmp_path / "ok.yaml"
    path.write_text(text)
    assert len(scenario.load_scene("icub", path).contact_set.contacts) == 2


@pytest.mark.parametrize("path", sorted((ROOT / "experiments" / "tasks").glob("*.yaml")), ids=lambda p: p.name)
def test_the_example_task_files_are_physical(path):
    scenario.load_scene("icub", path)


def test_box_distance_and_surface_normal():
    centre, half = np.zeros(3), np.array([0.1, 0.2, 0.3])
    assert placement.box_distance(np.array([0.3, 0.0, 0.0]), centre, half) == pytest.approx(0.2)
    assert placement.box_distance(np.zeros(3), centre, half) == pytest.approx(-0.1)
    np.testing.assert_allclose(placement.surface_normal(np.array([0.0, 0.0, 0.3]), centre, half), [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(
        placement.surface_normal(np.array([-0.1, 0.05, 0.0]), centre, half), [-1, 0, 0], atol=1e-9
    )


# ---- Class 2: the simulated impulse is the reported one ---------------------------------------


def _impulse(push: Push, dt: float, horizon: float, step) -> np.ndarray:
    t = dt * np.arange(int(round(horizon / dt)))
    return np.sum([push_forces(push, s, step)[0] for s in t], axis=0) * dt


@pytest.mark.parametrize("onset", [0.3, 0.3004, 0.29995])
@pytest.mark.parametrize("duration", [0.001, 0.0015, 0.0103, 0.05 + 1e-7, 0.1])
def test_each_physics_step_carries_its_share_of_the_push(onset, duration):
    """Summed over the physics steps, the push's force gives force x duration for any onset and
    duration, also off the 1 ms grid (on/off per step would add or drop whole steps: 2x for a
    1.5 ms push)."""
    push = Push(
        force=np.array([[0.0, 250.0, 0.0]]), onset=np.array([onset]), duration=np.array([duration]), body=np.array([-1])
    )
    np.testing.assert_allclose(_impulse(push, 0.001, 0.6, 0.001), [0.0, 250.0 * duration, 0.0], rtol=1e-9, atol=1e-12)
    if duration == 0.0015 and onset == 0.3:  # what a per-step on/off test simulated
        assert _impulse(push, 0.001, 0.6, None)[1] == pytest.approx(250.0 * 0.002)
    if duration == 0.1 and onset == 0.3:  # edges on the step grid: whole steps, bit for bit (t = k 0.01 + j 0.001)
        t = (0.01 * np.arange(60)[:, None] + 0.001 * np.arange(10)[None]).ravel()
        forces = np.array([push_forces(push, s, 0.001)[0, 1] for s in t])
        assert set(forces.tolist()) == {0.0, 250.0} and np.sum(forces == 250.0) == 100


@pytest.fixture(scope="module")
def stand():
    return scenario.setup("stand", duration=1.0)


@pytest.mark.parametrize("duration, onset", [(0.0123, 0.3004), (0.1, 0.3), (0.0015, 0.35)])
def test_a_free_body_gains_the_tables_impulse(stand, duration, onset):
    """The sweep's table row (impulse_ns) against what the closed loop's physics steps apply
    (ClosedLoop.step_push_forces, every engine's one source), integrated by C MuJoCo on a free 2 kg
    body without gravity: its momentum change is the table's impulse to 1e-9."""
    cfg = sweep_config.SweepConfig(push_duration=duration, push_onset=onset)
    scen, cols = sweep.scenarios_at(
        cfg, [stand.gains], [180.0], [90.0], [0], [1.0], [1.0], np.zeros((1, 23)), np.float64
    )
    push = jax.tree_util.tree_map(lambda x: jnp.asarray(x[0]), scen.push)
    loop = stand.loop
    m = mujoco.MjModel.from_xml_string(
        f'<mujoco><option timestep="{loop.physics_dt}" gravity="0 0 0"/><worldbody><body><freejoint/>'
        '<geom type="box" size=".1 .1 .1" mass="2"/></body></worldbody></mujoco>'
    )
    d = mujoco.MjData(m)
    for k in range(int(onset / loop.cfg.control_dt) - 1, int((onset + duration) / loop.cfg.control_dt) + 2):
        for force in np.asarray(loop.step_push_forces(push, k))[:, 0]:
            d.xfrc_applied[1, :3] = force
            mujoco.mj_step(m, d)
    momentum = 2.0 * d.qvel[:3]
    assert cols["impulse_ns"][0] == pytest.approx(180.0 * duration)
    np.testing.assert_allclose(momentum, [0.0, cols["impulse_ns"][0], 0.0], rtol=1e-9, atol=1e-12)


# ---- Class 5: upright is the trunk's tilt ------------------------------------------------------


def _summary(trunk_tilt_deg: float, com_z: float = 0.55, nan: bool = False) -> dict:
    """The summary after one tick of a robot whose trunk is tilted ``trunk_tilt_deg`` about x, its
    CoM at ``com_z`` (initially 0.55 m), feet in place, nothing else wrong."""
    a = math.radians(trunk_tilt_deg)
    met = metrics_lib.initial(jnp.asarray(0.55), jnp.float64)
    feet = jnp.asarray([[0.0, 0.07, 0.0], [0.0, -0.07, 0.0]])
    up = jnp.asarray([[0.0, 0.0, 1.0]] * 2)
    square = jnp.asarray([[x, y] for x in (-0.07, 0.12) for y in (-0.115, 0.115)])
    met = jax.jit(metrics_lib.update)(
        met,
        com=jnp.asarray([0.0, 0.0, com_z]),
        com_ref=jnp.asarray([0.0, 0.0, 0.55]),
        com_vel=jnp.zeros(3),
        tau=jnp.full(23, jnp.nan if nan else 1.0),
        violation=jnp.asarray(0.0),
        infeasible=jnp.asarray(False),
        contact_pos=feet,
        normals=up,
        anchors=feet,
        anchor_normals=up,
        fully_active=jnp.ones(2, bool),
        body_heights=jnp.asarray([0.3, 0.5]),
        trunk_z=jnp.asarray([0.0, -math.sin(a), math.cos(a)]),
        support=square,
        com0_height=jnp.asarray(0.55),
        t_now=jnp.asarray(0.01),
        physics_ok=jnp.asarray(True),
    )
    return metrics_lib.summarize(met)


@pytest.mark.parametrize(
    "tilt, com_z, nan, expected",
    [
        (0.0, 0.55, False, dict(survived=True, upright=True, fell=False, nan=False)),
        (constants.FALL_TRUNK_TILT_DEG - 1, 0.55, False, dict(survived=True, upright=True, fell=False, nan=False)),
        (constants.FALL_TRUNK_TILT_DEG + 1, 0.55, False, dict(survived=False, upright=False, fell=True, nan=False)),
        (170.0, 3.0, False, dict(survived=False, upright=False, fell=True, nan=False)),  # thrown, upside down
        (180.0, 0.55, False, dict(survived=False, upright=False, fell=True, nan=False)),
        (0.0, 0.2, False, dict(survived=False, upright=False, fell=True, nan=False)),  # the CoM low: fell too
        (0.0, 0.55, True, dict(survived=False, upright=False, fell=False, nan=True)),
    ],
)
def test_every_boolean_outcome_follows_the_trunk(tilt, com_z, nan, expected):
    """survived, upright, fell and nan of one summary, for a trunk tilted about the threshold
    (constants.FALL_TRUNK_TILT_DEG), upside down at 3 m (the CoM high: the old test said upright),
    and for the other two ways to fail; time to recover only for an upright robot."""
    summary = _summary(tilt, com_z, nan)
    booleans = {k: v for k, v in summary.items() if isinstance(v, (bool, np.bool_))}
    assert set(booleans) == set(expected)
    assert {k: bool(v) for k, v in booleans.items()} == expected
    assert math.isnan(summary["time_to_recover_s"]) == (not expected["upright"])


def test_trunk_tilt_angle():
    for deg in (0.0, 30.0, 90.0, 170.0, 180.0):
        a = math.radians(deg)
        z = jnp.asarray([math.sin(a) * 0.6, math.sin(a) * 0.8, math.cos(a)])
        assert math.degrees(float(jax.jit(metrics_lib.trunk_tilt_angle)(z))) == pytest.approx(deg, abs=1e-9)


# ---- Class 6: files that attack the parser -----------------------------------------------------


def _laughs(levels: int = 9) -> str:
    lines = ['a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for prev, name in zip("abcdefghijk"[: levels - 1], "bcdefghijkl"[: levels - 1]):
        lines.append(f"{name}: &{name} [{', '.join([f'*{prev}'] * 9)}]")
    return "\n".join(lines) + f"\ncontacts: *{'abcdefghijkl'[levels - 1]}\n"


HOSTILE = [
    ("bomb.yaml", _laughs(), r"expands to more than 200,000 values"),
    ("recursive.yaml", "contacts: &r [*r]\n", r"a YAML alias refers to a value that contains it"),
    ("recursive_map.yaml", "contacts: &r {a: *r}\n", r"a YAML alias refers to a value that contains it"),
    ("deep_flow.yaml", "contacts: " + "[" * 100000 + "]" * 100000 + "\n", r"nests 33 levels deep; at most 32"),
    ("deep_block.yaml", "".join(" " * k + "a:\n" for k in range(200)) + " " * 200 + "a: 1\n", r"nests 33 levels deep"),
    ("deep.json", '{"tasks": ' + "[" * 100000 + "]" * 100000 + "}", r"nests 100001 levels deep; at most 32"),
    ("strings.json", '{"tasks": ["[[[[", "]]"], "x": ' + "[" * 40 + "]" * 40 + "}", r"nests 41 levels deep"),
    ("big.json", '{"tasks": [' + "0, " * (2 * 2**20) + "0]}", r"is larger than 4 MiB, the limit of an input file"),
    ("big.yaml", "tasks: [" + "0, " * 400_000 + "0]\n", r"is larger than 1 MiB"),
    ("digits.json", '{"tasks": ' + "9" * 5000 + "}", r"is not valid JSON: .*4300"),
]


@pytest.mark.parametrize("name, text, pattern", HOSTILE, ids=[h[0] for h in HOSTILE])
def test_hostile_files_fail_in_one_short_line(tmp_path, name, text, pattern):
    path = tmp_path / name
    path.write_text(text)
    t0 = time.perf_counter()
    with pytest.raises(ValueError) as err:
        task_files.load_spec_file(path)
    message = str(err.value)
    assert time.perf_counter() - t0 < 5.0
    assert re.search(pattern, message) and str(path) in message and "\n" not in message and len(message) < 300


@pytest.mark.parametrize(
    "read",
    [
        lambda p: gains_lib.load_gains(p),
        lambda p: problem.load_envelope(p),
        lambda p: schedule.load_schedule(p),
        lambda p: loader.read_json(p, "sweep summary"),
        lambda p: loader.read_data(p, "held-out set"),
    ],
    ids=["gains", "envelope", "schedule", "summary", "read_data"],
)
def test_every_json_input_goes_through_the_one_loader(tmp_path, read):
    """Gains, envelope, schedule and summary files: deep nesting and oversized files refused by the
    loader's limits (no RecursionError, no minutes of parsing), naming the file."""
    deep, big = tmp_path / "deep.json", tmp_path / "big.json"
    deep.write_text("[" * 50000 + "]" * 50000)
    big.write_text("[" + "1, " * (2 * 2**20) + "1]")
    for path, pattern in ((deep, "nests 50000 levels deep"), (big, "larger than 4 MiB")):
        with pytest.raises(ValueError, match=pattern) as err:
            read(path)
        assert str(path) in str(err.value)


def test_a_device_is_read_only_up_to_the_limit():
    with pytest.raises(ValueError, match=r"file /dev/zero is larger than 1 MiB"):
        io.read_text("/dev/zero", "task", 2**20)


def test_aliases_within_the_limits_are_read(tmp_path):
    path = tmp_path / "anchors.yaml"
    path.write_text(
        _feet()
        .replace("normal: [0, 0, 1]}", "normal: &up [0, 0, 1], mu: &mu 0.4}", 1)
        .replace("r_sole, normal: [0, 0, 1]}", "r_sole, normal: *up, mu: *mu}")
        + "# 1e3 is a number\n"
    )
    spec = task_files.load_spec_file(path)
    assert spec["contacts"][1]["normal"] == [0, 0, 1] and spec["contacts"][1]["mu"] == 0.4
    assert loader.parse_yaml("x: 1e3\n", path, "task") == {"x": 1000.0}
    small = tmp_path / "small_bomb.yaml"
    small.write_text(_laughs(4))  # 9^4 = 6561 values: within the limit
    assert len(loader.read_data(small, "task")["contacts"]) == 9


def test_echoed_values_are_cut(tmp_path):
    message = _refusal(tmp_path, "long.yaml", _feet(extra=", mu: [" + ", ".join(["1"] * 2000) + "]"))
    assert len(message) < 200 and message.endswith("got (1, 1, 1, 1, 1, 1, 1, 1, ...)")
    assert len(loader.echo(list(range(10**6)))) <= loader.ECHO_CHARS
