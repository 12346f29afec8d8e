"""Regenerate ``assets/talos/talos_22dof.xml`` (and the Talos gains files) from the Talos URDF of
``example-robot-data`` (PAL Robotics' talos_data, LGPL-3.0: assets/talos/LICENSE, SOURCE.md).

Run ``python assets/build_talos_mjcf.py`` (deterministic; ``tests/test_talos.py`` checks that the
committed file is what this script writes). What it does, and why (the iCub's builder's choices,
assets/build_icub_mjcf.py, applied to Talos):

* free-floating base: a ``floating`` URDF joint from a ``world`` link to ``base_link``;
* 22 controlled joints: torso (2), each arm's shoulder and elbow (arm_*_1..4), each leg (6). The
  head, the wrists (arm_*_5..7) and the grippers become ``fixed`` at zero, as the iCub's neck and
  wrists (a balancing controller does not move them); static links are fused, so the total mass
  and the inertia of every moving body are those of the URDF (``talos_reduced.urdf``);
* no mesh geoms: the URDF's meshes are neither needed for balancing nor collide with the floor;
* contact: four 5 mm spheres per foot at the corners of the foot's collision box
  (``talos_reduced_box.urdf``: 0.21 m x 0.13 m under the ankle), bottoms on the sole plane
  (the URDF's ``*_sole_link``), colliding only with the floor through explicit ``<pair>`` s;
* sites ``l_sole``/``r_sole`` at the URDF sole frames (the names every model of assets/ uses);
* one torque motor per controlled joint, ctrlrange +- the URDF's effort limit (its real motors);
* timestep 1 ms, Newton solver, pyramidal cones (the iCub's); keyframe ``home`` = the SRDF's
  ``half_sitting`` posture (TSID's and crocoddyl's standing posture of Talos), soles at z = 0,
  feet centred on the world origin, facing world +x.

The default gains (assets/talos/gains/): WBC's momentum-task gains (K_P,CoM = [50, 50, 10],
K_P,w = 1, K_I,w = 0.25: accelerations, the same on any robot since the task is mass-normalised)
and WBC's iCub postural gains by joint function (torso pitch 10 / yaw 20, shoulder 10, elbow 8, hip
pitch and roll 30, hip yaw 20, knee 20, ankle 100: the "stable" postural task is mass-weighted, so a
gain is a natural frequency squared, not a stiffness), the left leg's values on both legs; the
hand-set row ``com_critical_100.json``: K_P,CoM = 100 on every axis, K_D,CoM = 2 sqrt(100) (critical
damping), as the iCub's.
"""

from __future__ import annotations

import json
import pathlib
import re
import xml.etree.ElementTree as ET

import mujoco
import numpy as np

from wbc_jax.robot.talos import DESCRIPTION, talos_paths, urdf_text

OUT = pathlib.Path(__file__).resolve().parent / "talos" / "talos_22dof.xml"
GAINS_DIR = OUT.parent / "gains"

# The controller's joints, in its order: the robot description is their one declaration.
DRIVEN_JOINTS = DESCRIPTION.joints
# WBC postural k_p by joint function (the iCub's gainsAndReferences.m values; module docstring).
POSTURAL_GAINS = [20, 10] + [10, 10, 10, 8] * 2 + [20, 30, 30, 20, 100, 100] * 2
FOOT_BOX_HALF = (0.105, 0.065)  # m: half the foot collision box of talos_reduced_box.urdf (x, y)
SPHERE_RADIUS = 0.005  # m
FLOOR_FRICTION = 1.0
CONTACT_SOLREF = (0.004, 1.0)  # stiff contact (>= 2 timesteps), as the iCub's


def _spec(fusestatic: bool) -> mujoco.MjSpec:
    head = (
        f'<mujoco><compiler fusestatic="{str(fusestatic).lower()}" discardvisual="true" '
        'balanceinertia="false"/></mujoco>'
        '<link name="world"/><joint name="floating_base" type="floating">'
        '<parent link="world"/><child link="base_link"/></joint>'
    )
    text = re.sub(r"(<robot[^>]*>)", lambda mt: mt.group(1) + head, urdf_text(), count=1)
    return mujoco.MjSpec.from_string(text)


def half_sitting() -> dict[str, float]:
    """The SRDF's ``half_sitting`` joint angles (rad) by joint name."""
    _, srdf = talos_paths()
    root = ET.parse(srdf).getroot()
    (state,) = [s for s in root.iter("group_state") if s.get("name") == "half_sitting"]
    return {j.get("name"): float(j.get("value")) for j in state.iter("joint") if " " not in j.get("value").strip()}


def effort_limits() -> dict[str, float]:
    """The URDF's effort limit (N m) by joint name."""
    root = ET.fromstring(talos_paths()[0].read_text())
    return {
        j.get("name"): float(j.find("limit").get("effort")) for j in root.iter("joint") if j.find("limit") is not None
    }


def _sole_frames() -> dict:
    """Each sole frame (the URDF's *_sole_link) relative to its moving parent body."""
    m = _spec(fusestatic=False).compile()
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    frames = {}
    for side, name in (("l", "left_sole_link"), ("r", "right_sole_link")):
        sole = m.body(name).id
        parent = sole
        while m.body_jntnum[parent] == 0:
            parent = m.body_parentid[parent]
        R = d.xmat[parent].reshape(3, 3)
        pos = R.T @ (d.xpos[sole] - d.xpos[parent])
        mat = R.T @ d.xmat[sole].reshape(3, 3)
        frames[side] = dict(parent=m.body(parent).name, pos=pos, mat=mat)
    return frames


def _quat(mat: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, mat.reshape(-1))
    return q


def _full_xml_precision() -> None:
    """Write 12 significant digits (MuJoCo's default 6 would move the fused inertias by ~1e-6
    relative; the setter is exported by libmujoco but not bound in Python, hence ctypes)."""
    import ctypes
    import glob
    import os

    (lib,) = glob.glob(os.path.join(os.path.dirname(mujoco.__file__), "libmujoco.so*"))
    ctypes.CDLL(lib)._mjPRIVATE__set_xml_precision(ctypes.c_int(12))


def build() -> str:
    """Return the MJCF text of the 22-joint Talos."""
    _full_xml_precision()
    frames = _sole_frames()
    spec = _spec(fusestatic=True)
    spec.modelname = "talos_22dof"
    spec.option.timestep = 0.001
    spec.option.solver = mujoco.mjtSolver.mjSOL_NEWTON
    spec.option.iterations = 4
    spec.option.ls_iterations = 8
    spec.option.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
    spec.option.jacobian = mujoco.mjtJacobian.mjJAC_DENSE
    spec.compiler.autolimits = True
    for geom in list(spec.geoms):
        spec.delete(geom)

    spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[0, 0, 0.05],
        contype=0,
        conaffinity=0,
        rgba=[0.55, 0.6, 0.65, 1],
    )
    spec.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1])
    hx, hy = FOOT_BOX_HALF
    for side in "lr":
        fr = frames[side]
        body = spec.body(fr["parent"])
        body.add_site(name=f"{side}_sole", pos=fr["pos"], quat=_quat(fr["mat"]), size=[0.01])
        for k, (x, y) in enumerate([(x, y) for x in (-hx, hx) for y in (-hy, hy)]):
            p = fr["pos"] + fr["mat"] @ np.array([x, y, SPHERE_RADIUS])
            name = f"{side}_foot_contact_{k}"
            body.add_geom(
                name=name,
                type=mujoco.mjtGeom.mjGEOM_SPHERE,
                size=[SPHERE_RADIUS, 0, 0],
                pos=p,
                contype=0,
                conaffinity=0,
                group=3,
                mass=0.0,
                rgba=[0.9, 0.3, 0.2, 1],
            )
            spec.add_pair(
                name=f"{name}_floor",
                geomname1="floor",
                geomname2=name,
                condim=3,
                friction=[FLOOR_FRICTION, FLOOR_FRICTION, 0.005, 1e-4, 1e-4],
                solref=list(CONTACT_SOLREF),
            )

    effort = effort_limits()
    for joint in DRIVEN_JOINTS:
        spec.add_actuator(
            name=joint,
            target=joint,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            ctrlrange=[-effort[joint], effort[joint]],
            ctrllimited=True,
        )

    # Home keyframe: half_sitting, soles at z = 0, feet centred on the world origin.
    m = spec.compile()
    d = mujoco.MjData(m)
    qpos = m.qpos0.copy()
    posture = half_sitting()
    for joint in DRIVEN_JOINTS:
        qpos[m.joint(joint).qposadr[0]] = posture[joint]
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    sole_z = [d.site_xpos[m.site(f"{s}_sole").id][2] for s in "lr"]
    assert abs(sole_z[0] - sole_z[1]) < 1e-4, sole_z
    qpos[2] -= float(np.mean(sole_z))
    qpos[:2] -= 0.5 * (d.site_xpos[m.site("l_sole").id][:2] + d.site_xpos[m.site("r_sole").id][:2])
    spec.add_key(name="home", qpos=qpos, ctrl=np.zeros(m.nu))
    spec.compile()
    return spec.to_xml()


def gains_files() -> dict[str, dict]:
    """The hand-set gains file (``com_critical_100.json``) by name (module docstring)."""
    kp = np.array(POSTURAL_GAINS, float)
    critical = {
        "kp_com": [100.0] * 3,
        "kd_com": [20.0] * 3,
        "ki_com": [0.0] * 3,
        "kp_ang": [1.0] * 3,
        "ki_ang": [0.25] * 3,
        "kp_postural": kp.tolist(),
        "kd_postural": (2 * np.sqrt(kp) / 20).tolist(),
    }
    return {"com_critical_100.json": critical}


def main() -> None:
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(build())
    GAINS_DIR.mkdir(exist_ok=True)
    for name, values in gains_files().items():
        (GAINS_DIR / name).write_text(json.dumps(values, indent=1) + "\n")
    print(f"wrote {OUT} and {GAINS_DIR}")


if __name__ == "__main__":
    main()
