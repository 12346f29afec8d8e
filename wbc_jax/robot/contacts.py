"""The contact set: feet, hands or any body, on the floor or on objects of the scene.

A contact is data (Nori et al. 2015, "rigid non-coplanar contacts"): a frame on the robot, the
normal of the surface it touches, its friction, its CoP rectangle (``surface`` contacts: a 6-D
wrench, the constraints of the feet) or none (``point`` contacts: a 3-D force in the friction
cone), a minimum normal force, an optional desired normal force, and an activation with
minimum-jerk ramps. The two soles on the floor are the default set (:func:`feet_contact_set`);
the controller knows no other path.

Contacts on bodies other than the feet need something to touch: :class:`SceneObject` boxes (a
table, a wall) are added to the MuJoCo model, together with small collision spheres on the robot
(one for a point contact, the four corners of the CoP rectangle for a surface one, like the feet)
and the contact pairs between them. :func:`wbc_jax.robot.scene.build_scene` does this before anything is compiled;
:func:`contact_terms` reads the contact kinematics out of the dynamics terms (pure,
jit/vmap/grad-safe).

Conventions: the contact frame's z axis is the surface normal (pointing out of the surface, into
the robot), fixed to the robot's body; wrenches are in world axes at the contact point, force
first. The normal is given in world axes at the initial posture.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from wbc_jax.core import constants
from wbc_jax.core.loader import echo
from wbc_jax.core.options import check_options, entry
from wbc_jax.core.types import Array, pytree_dataclass
from wbc_jax.robot import icub
from wbc_jax.robot import model as model_lib
from wbc_jax.robot.dynamics import DynamicsTerms, Frames

CONTACT_TYPES = ("surface", "point")
OBJECT_TYPES = ("box",)
DIMENSION = {"surface": 6, "point": 3}
# Ranges of a contact file's numbers: a contact point within a metre of its frame, friction
# coefficients up to 10, forces up to 10 kN, scene objects within 100 m.
MAX_OFFSET_M = 1.0
MAX_FRICTION = 10.0
MAX_NORMAL_FORCE_N = 1e4
MAX_OBJECT_M = 100.0


@dataclasses.dataclass(frozen=True)
class ContactParams:
    """Static parameters of the rigid-contact constraints of one contact.

    Registered as a pytree without leaves, so it can be passed to ``jax.jit``
    functions as a normal argument (its values are part of the treedef, i.e.
    static: a change recompiles).

    Attributes:
        mu: static friction coefficient (tangential force <= mu f_z).
        n_points: points per quadrant of the linearised friction cone; the cone
            is a polygon with 4 (n_points - 1) edges.
        mu_t: torsional friction coefficient (|tau_z| <= mu_t f_z).
        fz_min: minimal normal force [N].
        foot_size: ((x_min, x_max), (y_min, y_max)) of the centre-of-pressure
            rectangle in the contact frame [m] (a sole's: its robot description's ``sole_cop``; the
            default, the iCub's, is for robot-free uses: every contact built on a robot passes its own).
    """

    mu: float = 1.0 / 3.0
    n_points: int = 4
    mu_t: float = 1.0 / 75.0
    fz_min: float = 10.0
    foot_size: tuple[tuple[float, float], tuple[float, float]] = icub.DESCRIPTION.sole_cop

    def __post_init__(self) -> None:
        for name in ("mu", "mu_t", "fz_min"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"ContactParams.{name} must be a real number, got {echo(value)}")
            if not math.isfinite(value) or value <= 0.0:
                raise ValueError(f"ContactParams.{name} must be positive and finite, got {echo(value)}")
            object.__setattr__(self, name, float(value))
        n = self.n_points
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
            raise ValueError(f"ContactParams.n_points must be an integer >= 2, got {echo(n)}")
        object.__setattr__(self, "n_points", int(n))
        try:
            (x_min, x_max), (y_min, y_max) = ((float(a), float(b)) for a, b in self.foot_size)
        except (TypeError, ValueError) as err:
            raise ValueError(
                f"ContactParams.foot_size must be ((x_min, x_max), (y_min, y_max)), got {echo(self.foot_size)}"
            ) from err
        if not all(math.isfinite(v) for v in (x_min, x_max, y_min, y_max)):
            raise ValueError(f"ContactParams.foot_size must be finite, got {echo(self.foot_size)}")
        if not (x_min < x_max and y_min < y_max):
            raise ValueError(
                f"ContactParams.foot_size needs x_min < x_max and y_min < y_max, got {echo(self.foot_size)}"
            )
        # A CoP rectangle that excludes the sole origin is legal (the rows stay
        # meaningful), so only the ordering is checked.
        object.__setattr__(self, "foot_size", ((x_min, x_max), (y_min, y_max)))


jax.tree_util.register_dataclass(
    ContactParams,
    data_fields=[],
    meta_fields=["mu", "n_points", "mu_t", "fz_min", "foot_size"],
)


@dataclasses.dataclass(frozen=True)
class ContactActivation:
    """a(t) = mj((t - start) / ramp) - mj((t - stop) / ramp), mj the minimum-jerk ramp (0 -> 1).
    (Not "on"/"off": YAML 1.1 reads those keys as booleans.)"""

    start: float = entry(0.0, ge=0.0, le=constants.MAX_HORIZON_S, unit="s")
    stop: float = entry(math.inf, gt=0.0, finite=False, unit="s")
    ramp: float = entry(0.0, ge=0.0, le=constants.MAX_HORIZON_S, unit="s")


@dataclasses.dataclass(frozen=True)
class Contact:
    """One contact of the set (user-facing; names not yet resolved).

    Attributes:
      name: unique name.
      frame: body, site or named point (the robot description's ``named_points``) where the contact acts.
      normal: (3,) surface normal in world axes at the initial posture (required).
      type: ``"surface"`` (6-D wrench, friction cone, torsion, CoP rectangle) or ``"point"``.
      offset: (3,) added to the frame's point, in the body frame.
      mu, mu_t: friction and torsional friction coefficients (controller side).
      fz_min: minimum normal force (N) while active.
      cop: ((x_min, x_max), (y_min, y_max)) CoP rectangle in the contact frame (surface only;
        None: the iCub sole's).
      normal_force: desired normal force (N), tracked by the force distribution; None: free.
      touches: scene object this contact touches: collision spheres are added on the body and
        paired with it. None: the body's existing contact geoms (the feet on the floor).
      activation: :class:`ContactActivation` (feet: multiplied by the task's foot activation).
      detect: contact detection: the normal force the simulator measures gates the activation (a
        contact it does not see ramps out, a re-touch ramps back in; the settings are the
        ``detection_*`` fields of :class:`wbc_jax.control.controller.ControllerConfig`). Not for the soles,
        which follow the task's foot schedule.
    """

    name: str = entry()
    frame: str = entry()
    normal: tuple[float, float, float] | None = entry(None)
    type: str = entry("surface", choices=CONTACT_TYPES)
    offset: tuple[float, float, float] = entry((0.0, 0.0, 0.0), ge=-MAX_OFFSET_M, le=MAX_OFFSET_M, unit="m")
    mu: float = entry(1.0 / 3.0, gt=0.0, le=MAX_FRICTION)
    mu_t: float = entry(1.0 / 75.0, gt=0.0, le=MAX_FRICTION)
    fz_min: float = entry(10.0, gt=0.0, le=MAX_NORMAL_FORCE_N, unit="N")
    cop: tuple[tuple[float, float], tuple[float, float]] | None = entry(
        None, ge=-MAX_OFFSET_M, le=MAX_OFFSET_M, unit="m"
    )
    normal_force: float | None = entry(None, gt=0.0, le=MAX_NORMAL_FORCE_N, unit="N")
    touches: str | None = entry(None)
    activation: ContactActivation = entry(ContactActivation())
    detect: bool = entry(False)


@dataclasses.dataclass(frozen=True)
class SceneObject:
    """A fixed box in the world.

    Attributes:
      name: geom name. size: (3,) half sizes (m), world axes. pos: (3,) centre (world); or
      under: the name of a contact whose normal is along a world axis (+z: a table, horizontal: a
        wall): the box's face that the normal leaves is put at that contact's point (at the initial
        posture), centred on it, then moved by ``shift``.
      friction: sliding friction of the contacts with this object (physics).
    """

    name: str = entry()
    type: str = entry("box", choices=OBJECT_TYPES)
    size: tuple[float, float, float] = entry((0.1, 0.1, 0.1), gt=0.0, le=MAX_OBJECT_M, unit="m")
    pos: tuple[float, float, float] | None = entry(None, ge=-MAX_OBJECT_M, le=MAX_OBJECT_M, unit="m")
    under: str | None = entry(None)
    shift: tuple[float, float, float] = entry((0.0, 0.0, 0.0), ge=-MAX_OBJECT_M, le=MAX_OBJECT_M, unit="m")
    friction: float = entry(1.0, ge=constants.FRICTION_RANGE[0], le=constants.FRICTION_RANGE[1])


@dataclasses.dataclass(frozen=True)
class ResolvedContact:
    """A contact with indices (hashable: static configuration of the controller and rollout)."""

    name: str
    type: str
    body: int
    point: tuple[float, float, float]  # in the body frame
    R_body_contact: tuple[float, ...]  # (9,) contact-frame axes in the body frame, row-major
    params: ContactParams
    normal_force: float  # nan: free
    activation: ContactActivation
    foot: int  # 0 / 1 for the soles (the schedule's activation applies), else -1
    geoms: tuple[int, ...]  # collision geoms of this contact (measured wrenches)
    detect: bool = False  # contact detection gates the activation (Contact.detect)

    @property
    def dim(self) -> int:
        return DIMENSION[self.type]


@dataclasses.dataclass(frozen=True)
class ContactSet:
    """Resolved contacts, in order; ``dim`` = total wrench size D."""

    contacts: tuple[ResolvedContact, ...]

    @property
    def dim(self) -> int:
        return sum(c.dim for c in self.contacts)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.contacts)

    def slices(self) -> list[slice]:
        out, k = [], 0
        for c in self.contacts:
            out.append(slice(k, k + c.dim))
            k += c.dim
        return out

    @property
    def frames(self) -> Frames:
        """The contact points, in order (the first ``len(contacts)`` frames of the dynamics terms)."""
        return Frames(tuple(c.body for c in self.contacts), tuple(c.point for c in self.contacts))

    @property
    def feet(self) -> tuple[int, int]:
        """Indices in the set of the left and right sole contacts (for the angular-momentum
        integral, linearised about the stance foot). Every contact set holds both soles."""
        where = {c.foot: k for k, c in enumerate(self.contacts) if c.foot >= 0}
        return where[0], where[1]


def feet_contact_set(robot: model_lib.Robot, params: ContactParams | None = None) -> ContactSet:
    """The default contact set: both soles on the floor (surface contacts of the WBC controller,
    rigid-contact constraints ``params``, default :class:`ContactParams` on the description's sole
    CoP rectangle), activated by the task's foot schedule."""
    idx = robot.index
    params = ContactParams(foot_size=robot.description.sole_cop) if params is None else params
    return ContactSet(
        contacts=tuple(
            ResolvedContact(
                name=name,
                type="surface",
                body=int(idx.foot_bodies[k]),
                point=tuple(float(x) for x in idx.foot_points[k]),
                R_body_contact=tuple(float(x) for x in idx.foot_rotations[k].ravel()),
                params=params,
                normal_force=math.nan,
                activation=ContactActivation(),
                foot=k,
                geoms=tuple(int(g) for g in idx.foot_geoms[k]),
            )
            for k, name in enumerate(robot.description.feet)
        )
    )


# ---- Specification: parsing and checks (before anything is compiled) ---------------------


def contact_from_dict(values: dict) -> Contact:
    """A :class:`Contact` from a JSON/YAML mapping (``activation`` as a nested mapping)."""
    if not isinstance(values, dict):
        raise ValueError(f"a contact must be a mapping, got {echo(values)}")
    fields = {f.name for f in dataclasses.fields(Contact)}
    unknown = sorted(map(str, set(values) - fields))
    if unknown or "name" not in values or "frame" not in values:
        raise ValueError(
            f"contact {echo(values.get('name'))}: unknown keys {unknown} (valid: {sorted(fields)}); "
            "'name' and 'frame' are required"
        )
    values = dict(values)
    act = values.pop("activation", {}) or {}
    act_fields = {f.name for f in dataclasses.fields(ContactActivation)}
    if (
        not isinstance(act, dict)
        or set(act) - act_fields
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in act.values())
    ):
        raise ValueError(
            f"contact {echo(values['name'])}: activation must map {sorted(act_fields)} to numbers, got {echo(act)}"
        )
    if isinstance(values.get("cop"), list):
        values["cop"] = tuple(tuple(r) if isinstance(r, list) else r for r in values["cop"])
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
    return Contact(**values, activation=ContactActivation(**{k: float(v) for k, v in act.items()}))


def object_from_dict(values: dict) -> SceneObject:
    """A :class:`SceneObject` from a JSON/YAML mapping."""
    if not isinstance(values, dict):
        raise ValueError(f"a scene object must be a mapping, got {echo(values)}")
    fields = {f.name for f in dataclasses.fields(SceneObject)}
    unknown = sorted(map(str, set(values) - fields))
    if unknown or "name" not in values:
        raise ValueError(
            f"scene object {echo(values.get('name'))}: unknown keys {unknown} (valid: {sorted(fields)}); "
            "'name' is required"
        )
    return SceneObject(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


def _vector(owner: str, name: str, value, size: int = 3) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{owner}: {name} must be {size} numbers, got {echo(value)}") from err
    if arr.shape != (size,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{owner}: {name} must be {size} finite numbers, got {echo(value)}")
    return arr


def check_spec(contacts, objects, feet: tuple[str, str]) -> tuple[tuple[Contact, ...], tuple[SceneObject, ...]]:
    """Check a contact set and scene objects for errors that need no model (names, shapes, values);
    ``feet``: the robot's sole sites (left, right)."""
    contacts = tuple(contact_from_dict(c) if isinstance(c, dict) else c for c in contacts)
    objects = tuple(object_from_dict(o) if isinstance(o, dict) else o for o in objects)
    if not contacts:
        raise ValueError("the contact set is empty; list at least one contact (e.g. the feet)")
    for c in contacts:  # types and ranges first: the checks below assume them
        check_options(c, owner=f"contact {echo(c.name)}")
        check_options(c.activation, owner=f"contact {echo(c.name)}: activation")
    for o in objects:
        check_options(o, owner=f"scene object {echo(o.name)}")
    for kind, items in (("contact", contacts), ("scene object", objects)):
        names = [i.name for i in items]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"duplicate {kind} names {duplicates}; each needs its own name")
    object_names = [o.name for o in objects]
    for c in contacts:
        owner = f"contact {echo(c.name)}"
        if c.type not in CONTACT_TYPES:
            raise ValueError(f"{owner}: unknown type {echo(c.type)}; valid types: {list(CONTACT_TYPES)}")
        if c.normal is None:
            raise ValueError(
                f"{owner}: no normal direction; give 'normal: [nx, ny, nz]' (world axes, "
                "pointing out of the touched surface)"
            )
        n = _vector(owner, "normal", c.normal)
        if np.linalg.norm(n) < 1e-6:
            raise ValueError(f"{owner}: the normal must be a non-zero vector, got {list(c.normal)}")
        _vector(owner, "offset", c.offset)
        for name in ("mu", "mu_t", "fz_min"):
            value = getattr(c, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{owner}: {name} must be positive and finite, got {echo(value)}")
        if c.normal_force is not None and not (math.isfinite(c.normal_force) and c.normal_force >= c.fz_min):
            raise ValueError(f"{owner}: normal_force must be finite and >= fz_min ({c.fz_min}), got {c.normal_force}")
        if c.type == "point" and c.cop is not None:
            raise ValueError(f"{owner}: a point contact has no CoP rectangle (got cop {c.cop}); use type 'surface'")
        if not isinstance(c.detect, bool):
            raise ValueError(f"{owner}: detect must be true or false, got {echo(c.detect)}")
        if c.detect and c.frame in feet and not np.any(_vector(owner, "offset", c.offset)):
            raise ValueError(
                f"{owner}: the soles follow the task's foot schedule; contact detection (detect) is for "
                "the other contacts"
            )
        a = c.activation
        if not (math.isfinite(a.start) and a.ramp >= 0 and math.isfinite(a.ramp) and a.stop > a.start + a.ramp):
            raise ValueError(f"{owner}: activation needs finite start, ramp >= 0 and stop > start + ramp, got {a}")
        if c.touches is not None and c.touches not in object_names + ["floor"]:
            raise ValueError(f"{owner}: touches unknown object {echo(c.touches)}; valid: {object_names + ['floor']}")
    contact_names = [c.name for c in contacts]
    for o in objects:
        owner = f"scene object {echo(o.name)}"
        if o.type not in OBJECT_TYPES:
            raise ValueError(f"{owner}: unknown type {echo(o.type)}; valid types: {list(OBJECT_TYPES)}")
        if np.any(_vector(owner, "size", o.size) <= 0):
            raise ValueError(f"{owner}: size (half sizes) must be positive, got {list(o.size)}")
        _vector(owner, "shift", o.shift)
        if (o.pos is None) == (o.under is None):
            raise ValueError(f"{owner}: give exactly one of 'pos' or 'under' (a contact name)")
        if o.pos is not None:
            _vector(owner, "pos", o.pos)
        if o.under is not None and o.under not in contact_names:
            raise ValueError(f"{owner}: under unknown contact {echo(o.under)}; valid: {contact_names}")
        if not (math.isfinite(o.friction) and o.friction > 0):
            raise ValueError(f"{owner}: friction must be positive, got {o.friction}")
    return contacts, objects


# ---- At run time -------------------------------------------------------------------------


@pytree_dataclass
class ContactTerms:
    """Contact kinematics at one state (K contacts, D = total wrench size).

    Attributes:
      J: (D, nv) stacked contact Jacobians (surface: [linear; angular], point: linear), unscaled
      Jdot_nu: (D,) their Jdot nu
      W_p: (K, 3) contact points;  W_R: (K, 3, 3) contact frames (z = normal)
      activation: (K,) in [0, 1]
    """

    J: Array
    Jdot_nu: Array
    W_p: Array
    W_R: Array
    activation: Array


def activation_at(c: ResolvedContact, t: Array, foot_activation: Array, dtype) -> Array:
    """Activation () of one contact at time t (feet: times the schedule's ``foot_activation`` (2,))."""
    a = c.activation
    t = jnp.asarray(t, dtype)
    if a.start + a.ramp <= 0.0 and not math.isfinite(a.stop):
        # Fully on from the first tick (t >= 0) and never off: a constant, not a function of t
        # (queued sweeps batch t; nothing downstream then depends on it).
        up, down = jnp.ones((), dtype), 0.0
    elif a.ramp > 0:
        up = constants.min_jerk((t - a.start) / a.ramp)[0]
        down = constants.min_jerk((t - a.stop) / a.ramp)[0] if math.isfinite(a.stop) else 0.0
    else:
        up = (t >= a.start).astype(dtype)
        down = (t >= a.stop).astype(dtype) if math.isfinite(a.stop) else 0.0
    value = jnp.asarray(up - down, dtype)
    return value * foot_activation[c.foot] if c.foot >= 0 else value


def contact_terms(cset: ContactSet, t: DynamicsTerms, time: Array, foot_activation: Array) -> ContactTerms:
    """Contact Jacobians, Jdot nu, poses and activations at one state.

    Args:
      cset: the contact set. t: dynamics terms whose first frames are ``cset.frames``.
      time: () s, for the activation schedules. foot_activation: (2,) the task's foot schedule.
    """
    K = len(cset.contacts)
    dtype = t.M.dtype
    R_bc = jnp.asarray(np.array([c.R_body_contact for c in cset.contacts]).reshape(-1, 3, 3), dtype)
    rows = np.concatenate([np.arange(6 * k, 6 * k + c.dim) for k, c in enumerate(cset.contacts)])
    act = jnp.stack([activation_at(c, time, foot_activation, dtype) for c in cset.contacts])
    return ContactTerms(
        J=t.J_frames[:K].reshape(-1, t.J_frames.shape[-1])[rows],
        Jdot_nu=t.Jdot_nu_frames[:K].reshape(-1)[rows],
        W_p=t.W_p_frames[:K],
        W_R=jnp.einsum("kij,kjl->kil", t.W_R_frames[:K], R_bc),
        activation=act,
    )


def row_activation(cset: ContactSet, activation: Array) -> Array:
    """(D,) the activation of each wrench row (activation: (K,))."""
    return jnp.concatenate([jnp.full(c.dim, activation[k]) for k, c in enumerate(cset.contacts)])
