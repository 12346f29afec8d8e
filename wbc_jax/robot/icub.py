"""The iCub (iCubGazeboV2_5 of icub-models, 23 controlled joints as in robotology's
whole-body-controllers): the model, its names and the controller's defaults for it.

Sources: the WBC iCubGazeboV2_5 configuration (robotology whole-body-controllers, configRobot.m,
gainsAndReferences.m) and assets/build_icub_mjcf.py for the model.
"""

from __future__ import annotations

import types

from wbc_jax.robot.description import DefaultGains, RobotDescription


def _mesh_dir():
    """Folder of the iCub STL meshes inside the installed ``icub-models`` package."""
    import pathlib

    try:
        import icub_models
    except ImportError as err:  # pragma: no cover - icub-models is a hard dependency
        raise ImportError("visual meshes need the 'icub-models' package") from err
    urdf = pathlib.Path(str(icub_models.get_model_file("iCubGazeboV2_5")))
    return urdf.parents[2] / "meshes" / "simmechanics"


def _urdf_text() -> str:
    """The URDF of iCubGazeboV2_5 in the installed ``icub-models`` package (the MJCF's source)."""
    import pathlib

    import icub_models

    return pathlib.Path(str(icub_models.get_model_file("iCubGazeboV2_5"))).read_text()


DESCRIPTION = RobotDescription(
    name="icub",
    model_file="icub/icub_23dof.xml",
    source="icub-models iCubGazeboV2_5 URDF (assets/icub/icub_23dof.xml)",
    builder="assets/build_icub_mjcf.py",
    # The 23 joints of the WBC balancing controllers (configRobot.m, ROBOT_DOF = 23), in order.
    joints=(
        "torso_pitch",
        "torso_roll",
        "torso_yaw",
        "l_shoulder_pitch",
        "l_shoulder_roll",
        "l_shoulder_yaw",
        "l_elbow",
        "r_shoulder_pitch",
        "r_shoulder_roll",
        "r_shoulder_yaw",
        "r_elbow",
        "l_hip_pitch",
        "l_hip_roll",
        "l_hip_yaw",
        "l_knee",
        "l_ankle_pitch",
        "l_ankle_roll",
        "r_hip_pitch",
        "r_hip_roll",
        "r_hip_yaw",
        "r_knee",
        "r_ankle_pitch",
        "r_ankle_roll",
    ),
    feet=("l_sole", "r_sole"),
    foot_contact_prefixes=("l_foot_contact", "r_foot_contact"),
    # WBC's CoP rectangle of the iCub sole (x: toe +, y: left +), in the sole frame.
    sole_cop=((-0.07, 0.12), (-0.045, 0.045)),
    # WBC iCubGazeboV2_5, state 1 "two feet balancing" (gainsAndReferences.m): K_P,w = 2 sqrt(K_I,w).
    gains=DefaultGains(
        kp_com=(50.0, 50.0, 10.0),
        kp_ang=1.0,
        ki_ang=0.25,
        kp_postural=(10, 30, 20) + (10, 10, 10, 8) * 2 + (30, 30, 20, 20, 100, 100) + (30, 50, 30, 60, 100, 100),
    ),
    hand_set_gains="gains/com_critical_100.json",
    default_envelope="tuning/default_envelope.json",
    # The hand frames sit on bodies merged into the forearms (l_elbow_1 carries the left hand).
    bodies=types.MappingProxyType(
        {"trunk": "chest", "pelvis": "root_link", "left_hand": "l_elbow_1", "right_thigh": "r_upper_leg"}
    ),
    # The URDF's hand frames sit on bodies merged into the forearms (the wrist joints are not
    # controlled). Offsets: sum of the fixed origins of r/l_wrist_prosup, _wrist_pitch and
    # _wrist_yaw in icub-models iCubGazeboV2_5 model.urdf (joints at 0).
    named_points=types.MappingProxyType(
        {
            "r_hand": ("r_elbow_1", (-0.141328, 0.003007, 0.022344)),
            "l_hand": ("l_elbow_1", (0.141258, 0.014507, 0.022631)),
        }
    ),
    hip_pitch=("l_hip_pitch", "r_hip_pitch"),
    hip_roll=("l_hip_roll", "r_hip_roll"),
    # Lift the right foot 5 cm, sole parallel to the floor (from the iCub kinematics at home).
    foot_lift_deg=types.MappingProxyType({"r_hip_pitch": 20.0, "r_knee": -40.0, "r_ankle_pitch": -20.0}),
    mesh_dir=_mesh_dir,
    urdf_text=_urdf_text,
)
