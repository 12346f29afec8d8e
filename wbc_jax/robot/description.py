"""A robot as a value: everything robot-specific that the controller, the simulator and the jobs read.

One :class:`RobotDescription` per robot (``wbc_jax/robot/<name>.py``), registered by name in
:mod:`wbc_jax.robot.robots`; jobs take the name as ``--robot`` and everything below the job reads the
description instead of naming a robot. This module imports neither JAX nor
MuJoCo (the NumPy CPU baseline reads the default gains from it).
"""

from __future__ import annotations

import dataclasses
import types

import numpy as np

from wbc_jax.core.assets import asset

# Roles of bodies that jobs name by role (flags, held-out variations): each description maps them
# to its own bodies, so a default such as ``--body trunk`` means the same on every robot.
BODY_ROLES = ("trunk", "pelvis", "left_hand", "right_thigh")


@dataclasses.dataclass(frozen=True)
class DefaultGains:
    """The default gains of the two-level momentum law (WBC's ``gainsAndReferences.m`` shape):
    K_P,CoM (3,), K_P,w and K_I,w (scalars, per axis alike) and the postural k_p per joint (n,).
    The dampings follow WBC's rule: K_D,CoM = 2 sqrt(K_P,CoM) / 20, k_d = 2 sqrt(k_p) / 20, K_I,CoM = 0."""

    kp_com: tuple[float, float, float]
    kp_ang: float
    ki_ang: float
    kp_postural: tuple[float, ...]

    def values(self) -> dict[str, np.ndarray]:
        """The gains as float64 arrays by gains-file field name."""
        kp_com = np.array(self.kp_com, dtype=float)
        kp_post = np.array(self.kp_postural, dtype=float)
        return {
            "kp_com": kp_com,
            "kd_com": 2 * np.sqrt(kp_com) / 20,
            "ki_com": np.zeros(3),
            "kp_ang": np.full(3, float(self.kp_ang)),
            "ki_ang": np.full(3, float(self.ki_ang)),
            "kp_postural": kp_post,
            "kd_postural": 2 * np.sqrt(kp_post) / 20,
        }


@dataclasses.dataclass(frozen=True, eq=False)
class RobotDescription:
    """Everything robot-specific, in one value.

    Attributes:
      name: the registry name (``--robot``).
      model_file: the MJCF, relative to the package data (``wbc_jax.core.assets``).
      source: where the model comes from, in words (``wbc-jax info``).
      builder: the script that regenerates ``model_file`` from its source (in a checkout).
      joints: the controlled joints, in controller order (n,).
      feet: the left and right sole sites (their z axis the sole normal).
      foot_contact_prefixes: name prefixes of each foot's contact geoms (left, right).
      sole_cop: ((x_min, x_max), (y_min, y_max)) m: the CoP rectangle of each sole in its site frame.
      nominal_keyframe: the keyframe of the initial posture (soles flat on the floor).
      gains: the default gains (:class:`DefaultGains`).
      hand_set_gains: the hand-set comparison row of tuning (a gains file in the package data), or None.
      default_envelope: the default gains' envelope per direction (package data), or None.
      bodies: body of each role of :data:`BODY_ROLES`.
      named_points: points that are not bodies or sites: name -> (body, offset in the body frame).
      hip_pitch, hip_roll: the (left, right) hip joints of the flywheel bound (``wbc_jax.robot.bounds``).
      foot_lift_deg: joint -> degrees added to the posture to lift the right foot, sole parallel to
        the floor (the one-foot task).
      mesh_dir: the visual meshes' folder (a callable: it may import an installed package), or None.
      urdf_text: the URDF the model file is built from, as text, for Pinocchio (the TSID peer, the
        crocoddyl check): a callable (it may import an installed package), or None.
      urdf_feet: the URDF frames at the sole sites ``feet`` (left, right); None: the same names.
    """

    name: str
    model_file: str
    source: str
    builder: str
    joints: tuple[str, ...]
    feet: tuple[str, str]
    foot_contact_prefixes: tuple[str, str]
    sole_cop: tuple[tuple[float, float], tuple[float, float]]
    gains: DefaultGains
    bodies: types.MappingProxyType
    hip_pitch: tuple[str, str]
    hip_roll: tuple[str, str]
    foot_lift_deg: types.MappingProxyType
    named_points: types.MappingProxyType = dataclasses.field(default_factory=lambda: types.MappingProxyType({}))
    nominal_keyframe: str = "home"
    hand_set_gains: str | None = None
    default_envelope: str | None = None
    mesh_dir: object = None
    urdf_text: object = None
    urdf_feet: tuple[str, str] | None = None

    def __post_init__(self):
        if len(self.gains.kp_postural) != len(self.joints):
            raise ValueError(
                f"robot {self.name}: {len(self.gains.kp_postural)} postural gains for {len(self.joints)} joints"
            )
        missing = sorted(set(BODY_ROLES) - set(self.bodies))
        if missing:
            raise ValueError(f"robot {self.name}: no body for the roles {missing}")

    @property
    def model_path(self):
        """The MJCF's path in the package data."""
        return asset(self.model_file)

    def asset_path(self, relative: str | None):
        """A package data file of this robot (None stays None)."""
        return None if relative is None else asset(relative)

    @property
    def pinocchio_feet(self) -> tuple[str, str]:
        """The URDF (Pinocchio) frames of the left and right sole sites."""
        return self.feet if self.urdf_feet is None else self.urdf_feet

    def body(self, name: str) -> str:
        """A body name, or the body of a role (``trunk`` -> the iCub's ``chest``)."""
        return self.bodies.get(name, name)

    def default_gain_values(self, n: int | None = None) -> dict[str, np.ndarray]:
        """The default gains as float64 arrays (``n``: the joint count the caller expects, checked)."""
        if n is not None and n != len(self.joints):
            raise ValueError(f"the default gains of {self.name} are for {len(self.joints)} joints, got n={n}")
        return self.gains.values()
