"""Talos (PAL Robotics; the Talos URDF of example-robot-data, TSID's and crocoddyl's demo robot), 22
controlled joints: the model, its names and the controller's defaults for it.

Sources: assets/build_talos_mjcf.py (the model, the posture, the gains and how they were derived from
WBC's) and assets/talos/SOURCE.md (where the URDF comes from, its licence).
"""

from __future__ import annotations

import pathlib
import re
import types

from wbc_jax.robot.description import DefaultGains, RobotDescription

# Joints of the URDF held at zero (fixed), as the iCub's neck and wrists: a balancing controller does not move them.
FIXED_JOINTS = ("head_1_joint", "head_2_joint", "gripper_left_joint", "gripper_right_joint") + tuple(
    f"arm_{side}_{k}_joint" for side in ("left", "right") for k in (5, 6, 7)
)


def talos_paths() -> tuple[pathlib.Path, pathlib.Path]:
    """(URDF, SRDF) of the installed example-robot-data."""
    import example_robot_data

    robots = pathlib.Path(example_robot_data.getModelPath("talos_data/robots/talos_reduced.urdf"))
    data = robots / "talos_data"
    return data / "robots" / "talos_reduced.urdf", data / "srdf" / "talos.srdf"


def urdf_text() -> str:
    """The URDF without geometry, the :data:`FIXED_JOINTS` made fixed: what the MJCF is built from
    (assets/build_talos_mjcf.py) and what Pinocchio reads (the same joints and inertias)."""
    urdf, _ = talos_paths()
    text = urdf.read_text()
    text = re.sub(r"<visual>.*?</visual>|<collision>.*?</collision>", "", text, flags=re.S)
    text = re.sub(r"<transmission.*?</transmission>|<gazebo.*?</gazebo>", "", text, flags=re.S)
    for joint in FIXED_JOINTS:
        text, n = re.subn(rf'<joint name="{joint}" type="revolute"', f'<joint name="{joint}" type="fixed"', text)
        if n != 1:
            raise RuntimeError(f"joint {joint!r} not found once in {urdf}")
    return text


DESCRIPTION = RobotDescription(
    name="talos",
    model_file="talos/talos_22dof.xml",
    source="example-robot-data talos_reduced.urdf (assets/talos/talos_22dof.xml)",
    builder="assets/build_talos_mjcf.py",
    # Torso, left arm, right arm, left leg, right leg (the iCub's order); wrists, head, grippers fixed.
    joints=(
        "torso_1_joint",
        "torso_2_joint",
        "arm_left_1_joint",
        "arm_left_2_joint",
        "arm_left_3_joint",
        "arm_left_4_joint",
        "arm_right_1_joint",
        "arm_right_2_joint",
        "arm_right_3_joint",
        "arm_right_4_joint",
        "leg_left_1_joint",
        "leg_left_2_joint",
        "leg_left_3_joint",
        "leg_left_4_joint",
        "leg_left_5_joint",
        "leg_left_6_joint",
        "leg_right_1_joint",
        "leg_right_2_joint",
        "leg_right_3_joint",
        "leg_right_4_joint",
        "leg_right_5_joint",
        "leg_right_6_joint",
    ),
    feet=("l_sole", "r_sole"),
    urdf_feet=("left_sole_link", "right_sole_link"),  # the URDF frames the sole sites are placed at
    foot_contact_prefixes=("l_foot_contact", "r_foot_contact"),
    # The foot's collision box is +-0.105 m x +-0.065 m about the sole origin: the CoP rectangle keeps
    # 5 mm from its edges (the corner spheres' contact points sit on them).
    sole_cop=((-0.1, 0.1), (-0.06, 0.06)),
    # WBC's gains carried over by joint function (assets/build_talos_mjcf.py says how).
    gains=DefaultGains(
        kp_com=(50.0, 50.0, 10.0),
        kp_ang=1.0,
        ki_ang=0.25,
        kp_postural=(20, 10) + (10, 10, 10, 8) * 2 + (20, 30, 30, 20, 100, 100) * 2,
    ),
    hand_set_gains="talos/gains/com_critical_100.json",
    bodies=types.MappingProxyType(
        {
            "trunk": "torso_2_link",
            "pelvis": "base_link",
            "left_hand": "arm_left_4_link",
            "right_thigh": "leg_right_3_link",
        }
    ),
    hip_pitch=("leg_left_3_joint", "leg_right_3_joint"),
    hip_roll=("leg_left_2_joint", "leg_right_2_joint"),
    # Lift the right foot 5 cm, sole parallel to the floor (from the Talos kinematics at half_sitting).
    foot_lift_deg=types.MappingProxyType(
        {"leg_right_3_joint": -7.4, "leg_right_4_joint": 16.4, "leg_right_5_joint": -9.0}
    ),
    urdf_text=urdf_text,
)
