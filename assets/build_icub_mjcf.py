"""Regenerate ``assets/icub/icub_23dof.xml`` from the iCubGazeboV2_5 URDF of ``icub-models``.

Run ``python assets/build_icub_mjcf.py`` (deterministic; ``tests/test_model.py`` checks that
the committed file is what this script writes). What it does, and why:

* free-floating base: a ``floating`` URDF joint from a ``world`` link to ``root_link``
  (MuJoCo's URDF importer otherwise welds the root to the world);
* the 23 joints of the balancing controllers stay hinges; neck and wrists become ``fixed``
  at zero (as in whole-body-controllers, ``ROBOT_DOF = 23``); static links are fused, so the
  total mass (33.06 kg) and the inertia of every moving body are those of the URDF;
* the URDF's visual mesh geoms are kept as *visual* geoms (group 2, no collision); the meshes are
  referenced by file name and read from the installed icub-models package at load time;
* contact: four 5 mm spheres per foot at the corners of the real sole (extent taken from the
  sole mesh, bottoms on the sole plane), colliding only with the floor through explicit
  ``<pair>`` s. Spheres, not boxes: reverse-mode gradients through MJX box-plane contact
  were NaN in float32 while corner spheres gave finite gradients (shared/reference/measured.md);
* sites ``l_sole``/``r_sole`` at the URDF sole frames and ``chest`` for pushes;
* one torque motor per driven joint, ctrlrange +-60 N m (Sat.torque of the WBC controllers);
* timestep 1 ms, Newton solver, pyramidal cones; keyframe ``home`` = the WBC simulator posture
  with both soles on the floor and the robot facing world +x (root_link x points backward).
"""

from __future__ import annotations

import pathlib
import re

import mujoco
import numpy as np

from wbc_jax.robot.icub import DESCRIPTION

ROBOT_NAME = "iCubGazeboV2_5"
OUT = pathlib.Path(__file__).resolve().parent / "icub" / "icub_23dof.xml"

DRIVEN_JOINTS = DESCRIPTION.joints  # the controller's 23 joints, in order (one declaration: wbc_jax/robot/icub.py)
FIXED_JOINTS = ("neck_pitch", "neck_roll", "neck_yaw") + tuple(
    f"{side}_wrist_{j}" for side in "lr" for j in ("prosup", "pitch", "yaw")
)
# WBC Matlab simulator initial posture (configRobotSim.m), degrees, DRIVEN_JOINTS order.
HOME_POSTURE_DEG = [0.0, 0.0, 0.0] + [-35.97, 29.97, 0.06, 50.0] * 2 + [10.0, 0.0, 0.0, -20.0, -10.0, 0.0] * 2
MESHDIR_PLACEHOLDER = "ICUB_MODELS_MESHES"
TORQUE_LIMIT = 60.0  # N m
SPHERE_RADIUS = 0.005  # m
FLOOR_FRICTION = 1.0
CONTACT_SOLREF = (0.004, 1.0)  # stiff contact (>= 2 timesteps): ~0.2 mm sink at rest


def icub_paths() -> tuple[pathlib.Path, pathlib.Path]:
    """(URDF file, mesh folder) of the installed icub-models package."""
    import icub_models

    urdf = pathlib.Path(str(icub_models.get_model_file(ROBOT_NAME)))
    meshes = urdf.parents[2] / "meshes" / "simmechanics"
    return urdf, meshes


def _urdf_text(fusestatic: bool) -> str:
    urdf, _ = icub_paths()
    text = urdf.read_text()
    for joint in FIXED_JOINTS:
        text, n = re.subn(rf'<joint name="{joint}" type="revolute"', f'<joint name="{joint}" type="fixed"', text)
        if n != 1:
            raise RuntimeError(f"joint {joint!r} not found once in {urdf}")
    head = (
        f'<mujoco><compiler fusestatic="{str(fusestatic).lower()}" discardvisual="false" '
        'strippath="true" balanceinertia="false"/></mujoco>'
        '<link name="world"/><joint name="floating_base" type="floating">'
        '<parent link="world"/><child link="root_link"/></joint>'
    )
    return re.sub(r"(<robot[^>]*>)", lambda mt: mt.group(1) + head, text, count=1)


def _spec(fusestatic: bool) -> mujoco.MjSpec:
    spec = mujoco.MjSpec.from_string(_urdf_text(fusestatic))
    spec.meshdir = str(icub_paths()[1])
    return spec


def _pose_in(m, d, body: int, pos: np.ndarray, mat: np.ndarray):
    """Express a world pose in the frame of `body`."""
    R = d.xmat[body].reshape(3, 3)
    return R.T @ (pos - d.xpos[body]), R.T @ mat


def _moving_ancestor(m, body: int) -> int:
    while m.body_jntnum[body] == 0 and body != 0:
        body = m.body_parentid[body]
    return body


def _sole_frames():
    """Sole and chest frames relative to their moving parent body, and the sole extents."""
    spec = _spec(fusestatic=False)
    m = spec.compile()
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    frames = {}
    for side in "lr":
        sole = m.body(f"{side}_sole").id
        anc = _moving_ancestor(m, sole)
        R_sole = d.xmat[sole].reshape(3, 3)
        p_sole = d.xpos[sole]
        # Bottom face of the real sole mesh, in the sole frame.
        mesh_geom = [
            g
            for g in range(m.ngeom)
            if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
            and "sole" in m.mesh(m.geom_dataid[g]).name
            and m.mesh(m.geom_dataid[g]).name.split("_")[-3] == side
        ]
        assert len(mesh_geom) == 1, mesh_geom
        g = mesh_geom[0]
        mid = m.geom_dataid[g]
        verts = m.mesh_vert[m.mesh_vertadr[mid] : m.mesh_vertadr[mid] + m.mesh_vertnum[mid]]
        world = d.geom_xpos[g] + verts @ d.geom_xmat[g].reshape(3, 3).T
        in_sole = (world - p_sole) @ R_sole
        lo, hi = in_sole.min(0), in_sole.max(0)
        pos, mat = _pose_in(m, d, anc, p_sole, R_sole)
        frames[side] = dict(parent=m.body(anc).name, pos=pos, mat=mat, lo=lo, hi=hi)
    chest = m.body("chest").id
    frames["chest"] = dict(parent=m.body(_moving_ancestor(m, chest)).name)
    return frames


def _quat(mat: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, mat.reshape(-1))
    return q


def _full_xml_precision() -> None:
    """MuJoCo writes 6 significant digits by default: masses and inertias of the fused bodies
    would move by ~1e-6 relative, enough to fail the 1e-6 checks against Pinocchio. The setter
    is exported by libmujoco but not bound in Python, hence ctypes."""
    import ctypes
    import glob
    import os

    (lib,) = glob.glob(os.path.join(os.path.dirname(mujoco.__file__), "libmujoco.so*"))
    ctypes.CDLL(lib)._mjPRIVATE__set_xml_precision(ctypes.c_int(12))


def build() -> str:
    """Return the MJCF text of the 23-joint iCub."""
    _full_xml_precision()
    frames = _sole_frames()
    spec = _spec(fusestatic=True)
    spec.modelname = "icub_23dof"
    spec.option.timestep = 0.001
    spec.option.solver = mujoco.mjtSolver.mjSOL_NEWTON
    spec.option.iterations = 4
    spec.option.ls_iterations = 8
    spec.option.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
    spec.option.jacobian = mujoco.mjtJacobian.mjJAC_DENSE
    spec.compiler.autolimits = True

    seen_meshes = set()
    for geom in list(spec.geoms):
        # The URDF lists most meshes twice (visual + collision): keep one visual copy.
        # Its 1 mm foot boxes are replaced by the corner spheres below.
        if geom.type != mujoco.mjtGeom.mjGEOM_MESH or geom.meshname in seen_meshes:
            spec.delete(geom)
            continue
        seen_meshes.add(geom.meshname)
        geom.contype, geom.conaffinity, geom.group = 0, 0, 2

    floor = spec.worldbody.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[0, 0, 0.05],
        contype=0,
        conaffinity=0,
        rgba=[0.55, 0.6, 0.65, 1],
    )
    spec.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1])

    for side in "lr":
        fr = frames[side]
        body = spec.body(fr["parent"])
        body.add_site(name=f"{side}_sole", pos=fr["pos"], quat=_quat(fr["mat"]), size=[0.01])
        lo, hi = fr["lo"], fr["hi"]
        corners = [(x, y) for x in (lo[0], hi[0]) for y in (lo[1], hi[1])]
        for k, (x, y) in enumerate(corners):
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
    spec.body(frames["chest"]["parent"]).add_site(name="chest", pos=[0, 0, 0], size=[0.02])
    del floor

    for joint in DRIVEN_JOINTS:
        spec.add_actuator(
            name=joint,
            target=joint,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            ctrlrange=[-TORQUE_LIMIT, TORQUE_LIMIT],
            ctrllimited=True,
        )

    # Home keyframe: posture, base yawed 180 deg (root_link x points backward), soles at z=0.
    m = spec.compile()
    d = mujoco.MjData(m)
    qpos = m.qpos0.copy()
    qpos[3:7] = [0.0, 0.0, 0.0, 1.0]
    for joint, deg in zip(DRIVEN_JOINTS, HOME_POSTURE_DEG):
        qpos[m.joint(joint).qposadr[0]] = np.deg2rad(deg)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    sole_z = [d.site_xpos[m.site(f"{s}_sole").id][2] for s in "lr"]
    assert abs(sole_z[0] - sole_z[1]) < 1e-4, sole_z  # the URDF is symmetric to ~20 um
    qpos[2] -= float(np.mean(sole_z))
    mid = 0.5 * (d.site_xpos[m.site("l_sole").id][:2] + d.site_xpos[m.site("r_sole").id][:2])
    qpos[:2] -= mid  # centre the feet on the world origin
    spec.add_key(name="home", qpos=qpos, ctrl=np.zeros(m.nu))
    spec.compile()
    # Machine-independent mesh folder: wbc_jax.robot.model points it at the installed package.
    xml = spec.to_xml()
    return xml.replace(f'meshdir="{icub_paths()[1]}', f'meshdir="{MESHDIR_PLACEHOLDER}')


def main() -> None:
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(build())
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
