"""The committed iCub model: what it contains, that it is regenerable, and bad input."""

import pathlib
import sys

import mujoco
import numpy as np
import pytest

from wbc_jax.robot import model
from wbc_jax.robot.icub import DESCRIPTION as ICUB

ROOT = pathlib.Path(__file__).resolve().parent.parent


def test_summary_matches_the_urdf(robot):
    s = model.summary(robot)
    assert (s["nq"], s["nv"], s["nu"]) == (30, 29, 23)
    # Sum of the iCubGazeboV2_5 URDF link masses (controller-spec 4): 33.06 kg.
    assert s["mass"] == pytest.approx(33.0617, abs=1e-3)
    assert s["joints"] == list(ICUB.joints)
    assert s["timestep"] == 0.001


def test_urdf_mass_is_preserved(robot):
    import xml.etree.ElementTree as ET

    import icub_models

    urdf = ET.parse(str(icub_models.get_model_file("iCubGazeboV2_5")))
    total = sum(float(e.get("value")) for e in urdf.iter("mass"))
    assert robot.index.mass == pytest.approx(total, rel=1e-6)


def test_home_keyframe_has_soles_on_the_floor(robot):
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.home_qpos()
    mujoco.mj_forward(m, d)
    sole_z = d.site_xpos[robot.index.foot_sites, 2]
    np.testing.assert_allclose(sole_z, 0.0, atol=2e-5)
    # Sole frames aligned with the world (x forward): robot faces +x.
    for s in robot.index.foot_sites:
        np.testing.assert_allclose(d.site_xmat[s].reshape(3, 3), np.eye(3), atol=0.2)
    # Feet 0.14 m apart, left foot at +y.
    y = d.site_xpos[robot.index.foot_sites, 1]
    assert y[0] - y[1] == pytest.approx(0.14, abs=0.01)
    # Posture as in the WBC simulator (degrees).
    elbow = d.qpos[robot.index.qpos_joints[ICUB.joints.index("l_elbow")]]
    assert np.rad2deg(elbow) == pytest.approx(50.0)


def test_contact_geometry_spans_the_real_sole(robot):
    m = robot.mj_model
    d = mujoco.MjData(m)
    d.qpos[:] = robot.home_qpos()
    mujoco.mj_forward(m, d)
    for foot, (ylo, yhi) in zip(range(2), [(-0.044, 0.052), (-0.052, 0.044)]):
        s = robot.index.foot_sites[foot]
        R, p = d.site_xmat[s].reshape(3, 3), d.site_xpos[s]
        local = (d.geom_xpos[robot.index.foot_geoms[foot]] - p) @ R
        # Sole extent (controller-spec 4): x in [-0.066, 0.129], y mirrored per foot.
        assert local[:, 0].min() == pytest.approx(-0.066, abs=0.004)
        assert local[:, 0].max() == pytest.approx(0.129, abs=0.004)
        assert local[:, 1].min() == pytest.approx(ylo, abs=0.004)
        assert local[:, 1].max() == pytest.approx(yhi, abs=0.004)
        np.testing.assert_allclose(local[:, 2], 0.005, atol=1e-6)  # bottoms on the sole plane


def test_only_the_feet_collide_with_the_floor(robot):
    m = robot.mj_model
    assert np.all(m.geom_contype == 0) and np.all(m.geom_conaffinity == 0)
    assert m.npair == 8


def test_visual_model_loads_meshes_from_icub_models():
    m = model.load_mj_model("icub", visual=True)
    assert m.nmesh == 39 and m.nv == 29


def test_committed_model_is_what_the_script_builds():
    sys.path.insert(0, str(ROOT / "assets"))
    try:
        import build_icub_mjcf
    finally:
        sys.path.pop(0)
    assert build_icub_mjcf.build() == (ROOT / "assets" / "icub" / "icub_23dof.xml").read_text()


def test_unknown_robot_lists_valid_names():
    with pytest.raises(ValueError, match=r"unknown robot 'atlas'.*icub"):
        model.load_robot("atlas")


def test_unknown_joint_lists_valid_names(robot):
    with pytest.raises(ValueError, match=r"unknown joint 'l_wrist_yaw'.*l_elbow"):
        model.build_index(robot.mj_model, joints=("l_elbow", "l_wrist_yaw"))


def test_duplicate_joint_names_rejected(robot):
    with pytest.raises(ValueError, match="duplicate"):
        model.build_index(robot.mj_model, joints=("l_elbow", "l_elbow"))


def test_unknown_site_and_body(robot):
    with pytest.raises(ValueError, match=r"unknown site 'head'.*chest"):
        robot.index.site_id("head")
    with pytest.raises(ValueError, match=r"unknown body 'foo'.*root_link"):
        robot.index.body_id("foo")


def test_model_without_free_joint_is_rejected():
    m = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint type='hinge'/><geom size='.1'/></body></worldbody></mujoco>"
    )
    with pytest.raises(ValueError, match="free joint"):
        model.build_index(m)
