"""Tests of wbc_jax.control.qp and wbc_jax.control.forces: the QP solver, contact constraints, the WBC QPs.

The reference solver is quadprog (Goldfarb-Idnani dual active set, float64):
an exact active-set solution independent of the interior-point code.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import quadprog

from wbc_jax.control import constraints, forces, qp
from wbc_jax.robot import contacts

jax.config.update("jax_enable_x64", True)

# Compile at XLA's lowest backend optimisation level: halves the compile time
# that dominates this module (each vmapped solver takes seconds to compile on
# a 2-core CPU) at a ~1.5x cost in the (tiny) run time.
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})

MASS = 33.0  # iCub-like total mass [kg]
GRAVITY = 9.81
N_JOINTS = 23


# --------------------------------------------------------------------------------------
# Reference solver and problem generators (numpy, float64)
# --------------------------------------------------------------------------------------


def ref_qp(H, g, C, b):
    """quadprog solution of min 1/2 x'Hx + g'x s.t. Cx <= b: (x, multipliers)."""
    H = 0.5 * (H + H.T)
    x, _, _, _, lam, _ = quadprog.solve_qp(H, -g, -C.T, -b, 0)
    return x, lam


def objective(H, g, x):
    return 0.5 * x @ H @ x + g @ x


def random_qp(rng, n, m):
    """Random feasible QP whose unconstrained minimiser is outside the feasible set.

    Scales of H vary over 3 decades; x0 is strictly feasible, the unconstrained
    minimiser x0 + 5 N(0, 1) so that several constraints are active.
    """
    A = rng.normal(size=(n + 3, n)) * 10 ** rng.uniform(-1, 2)
    H = A.T @ A + 1e-3 * np.eye(n)
    C = rng.normal(size=(m, n))
    x0 = rng.normal(size=n)
    b = C @ x0 + rng.uniform(0.0, 1.0, size=m) * rng.uniform(0.05, 3.0)
    g = -H @ (x0 + 5.0 * rng.normal(size=n))
    return H, g, C, b


def skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rot(axis, angle):
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = skew(k)
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def random_sole_rotation(rng, tilt=0.1, yaw=0.5):
    return (
        rot([0, 0, 1], rng.uniform(-yaw, yaw))
        @ rot([1, 0, 0], rng.uniform(-tilt, tilt))
        @ rot([0, 1, 0], rng.uniform(-tilt, tilt))
    )


def centroidal_map(p_sole, p_com):
    """A_k (6, 6): wrench at the sole origin (world axes) -> wrench at the CoM."""
    A = np.eye(6)
    A[3:, :3] = skew(p_sole - p_com)
    return A


def random_two_feet(rng, horizontal=0.2, torque_scale=30.0):
    """A two-feet balancing problem (WBC conventions) as a dict of numpy arrays."""
    p_L = np.array([0.0, 0.07, 0.0]) + rng.uniform(-0.02, 0.02, 3) * [1, 1, 0]
    p_R = np.array([0.0, -0.07, 0.0]) + rng.uniform(-0.02, 0.02, 3) * [1, 1, 0]
    p_c = np.array([0.0, 0.0, 0.53]) + rng.uniform(-1, 1, 3) * [0.03, 0.04, 0.02]
    A = np.concatenate([centroidal_map(p_L, p_c), centroidal_map(p_R, p_c)], axis=1)
    w_des = np.concatenate(
        [
            MASS * GRAVITY * np.array([*rng.uniform(-horizontal, horizontal, 2), 1.0]),
            rng.uniform(-3.0, 3.0, 3),
        ]
    )
    pinvA = np.linalg.pinv(A)
    return dict(
        Sigma=rng.normal(size=(N_JOINTS, 12)) * rng.uniform(0.05, 0.5, size=12),
        tau_model=rng.normal(size=N_JOINTS) * torque_scale,
        f1=pinvA @ w_des,
        N_A=np.eye(12) - pinvA @ A,
        W_R_left=random_sole_rotation(rng),
        W_R_right=random_sole_rotation(rng),
        A=A,
        w_des=w_des,
    )


def feasibility_margin(C, b):
    """max t s.t. C x + t |C_i| <= b (LP): > 0 iff strictly feasible."""
    from scipy.optimize import linprog

    n = C.shape[1]
    res = linprog(
        np.r_[np.zeros(n), -1.0],
        A_ub=np.c_[C, np.linalg.norm(C, axis=1)],
        b_ub=b,
        bounds=[(None, None)] * n + [(None, 1.0)],
    )
    assert res.status == 0
    return -res.fun


def two_feet_f0_problem(p, params, hessian_reg=1e-7):
    """WBC's original f0 formulation (n = 12, m = 38) of the two-feet QP."""
    C_foot, b_foot = constraints.contact_constraints(params)
    C_L = C_foot @ np.kron(np.eye(2), p["W_R_left"].T)
    C_R = C_foot @ np.kron(np.eye(2), p["W_R_right"].T)
    C2 = np.block([[C_L, np.zeros_like(C_R)], [np.zeros_like(C_L), C_R]])
    b2 = np.concatenate([b_foot, b_foot])
    SN = p["Sigma"] @ p["N_A"]
    H = SN.T @ SN + hessian_reg * np.eye(12)
    g = SN.T @ (p["tau_model"] + p["Sigma"] @ p["f1"])
    return H, g, C2 @ p["N_A"], b2 - C2 @ p["f1"], C2, b2


def random_one_foot(rng, horizontal=0.6, torque=15.0, com=0.05):
    p_sole = np.array([0.0, 0.07, 0.0])
    p_c = np.array([0.0, 0.07, 0.53]) + rng.uniform(-1, 1, 3) * [com, com, 0.02]
    w_des = np.concatenate(
        [
            MASS * GRAVITY * np.array([*rng.uniform(-horizontal, horizontal, 2), 1.0]),
            rng.uniform(-torque, torque, 3),
        ]
    )
    return centroidal_map(p_sole, p_c), w_des, random_sole_rotation(rng)


TWO_FEET_KEYS = ("Sigma", "tau_model", "A", "w_des", "W_R_left", "W_R_right")


def stack_dicts(dicts, keys):
    return {k: np.stack([d[k] for d in dicts]) for k in keys}


# --------------------------------------------------------------------------------------
# Shared jitted functions (compiled once per shape/dtype for the whole module)
# --------------------------------------------------------------------------------------

PARAMS = contacts.ContactParams()
SETTINGS = forces.ForceSettings()


def contact_set(count: int) -> contacts.ContactSet:
    """``count`` sole-like surface contacts (the default parameters; kinematics unused here)."""
    return contacts.ContactSet(
        tuple(
            contacts.ResolvedContact(
                name=f"c{k}",
                type="surface",
                body=0,
                point=(0.0, 0.0, 0.0),
                R_body_contact=tuple(np.eye(3).ravel()),
                params=PARAMS,
                normal_force=math.nan,
                activation=contacts.ContactActivation(),
                foot=k,
                geoms=(),
            )
            for k in range(count)
        )
    )


FEET, ONE_FOOT = contact_set(2), contact_set(1)


def two_feet_wrenches(Sigma, tau_model, A, w_des, W_R_left, W_R_right):
    """The two-feet WBC QP (equality form) of forces.momentum_equality_qp."""
    tt = types.SimpleNamespace(Sigma=Sigma, tau_model=tau_model)
    return forces.momentum_equality_qp(
        FEET, jnp.ones(2, A.dtype), A, w_des, tt, jnp.stack([W_R_left, W_R_right]), SETTINGS
    )


@pytest.fixture(scope="module")
def solve_batch():
    return jit(jax.vmap(lambda H, g, C, b: qp.solve_qp(H, g, C, b)))


@pytest.fixture(scope="module")
def solve_one():
    return jit(lambda H, g, C, b: qp.solve_qp(H, g, C, b))


@pytest.fixture(scope="module")
def two_feet_batch():
    return jit(jax.vmap(two_feet_wrenches))


@pytest.fixture(scope="module")
def random_qps():
    """72 random feasible QPs of the contact sizes, with quadprog solutions."""
    rng = np.random.default_rng(1234)
    sets = {}
    for n, m, count in ((6, 19, 24), (12, 38, 24), (6, 38, 24)):
        probs = [random_qp(rng, n, m) for _ in range(count)]
        refs = [ref_qp(*p) for p in probs]
        H, g, C, b = (np.stack(a) for a in zip(*probs))
        sets[(n, m)] = dict(
            H=H,
            g=g,
            C=C,
            b=b,
            x=np.stack([r[0] for r in refs]),
            lam=np.stack([r[1] for r in refs]),
        )
    return sets


@pytest.fixture(scope="module")
def two_feet_problems():
    rng = np.random.default_rng(7)
    probs = []
    while len(probs) < 24:
        p = random_two_feet(rng)
        H, g, Cy, by, _, _ = two_feet_f0_problem(p, PARAMS)
        # Keep strictly feasible problems only (margin 1e-3 N): quadprog may
        # return a "solution" with multipliers ~1e23 for an infeasible one.
        if feasibility_margin(Cy, by) < 1e-3:
            continue
        f0, _ = ref_qp(H, g, Cy, by)
        p["f_ref"] = p["f1"] + p["N_A"] @ f0
        probs.append(p)
    return probs


# --------------------------------------------------------------------------------------
# ContactParams and constraints
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(mu=-0.1), "mu"),
        (dict(mu=float("nan")), "mu"),
        (dict(mu=0.0), "mu"),
        (dict(mu_t=float("inf")), "mu_t"),
        (dict(fz_min=0.0), "fz_min"),
        (dict(n_points=1), "n_points"),
        (dict(n_points=2.5), "n_points"),
        (dict(foot_size=((0.12, -0.07), (-0.045, 0.045))), "foot_size"),
        (dict(foot_size=((-0.07, 0.12), (0.045, 0.045))), "foot_size"),
        (dict(foot_size=((-0.07, 0.12),)), "foot_size"),
        (dict(foot_size=((-0.07, float("nan")), (-0.045, 0.045))), "foot_size"),
    ],
)
def test_params_validation(kwargs, field):
    with pytest.raises(ValueError, match=field):
        contacts.ContactParams(**kwargs)


def test_params_defaults_and_static_pytree():
    p = contacts.ContactParams()
    assert (p.mu, p.n_points, p.mu_t, p.fz_min) == (1 / 3, 4, 1 / 75, 10.0)
    assert p.foot_size == ((-0.07, 0.12), (-0.045, 0.045))
    assert jax.tree_util.tree_leaves(p) == []
    # Static: usable as an ordinary jit argument, its values are the treedef.
    out = jit(lambda q, x: x * q.fz_min)(p, 2.0)
    assert float(out) == 20.0
    assert hash(p) == hash(contacts.ContactParams())


def wbc_cone_rows(mu, n_points):
    """The friction-cone rows exactly as WBC's MATLAB loop builds them."""
    step = math.pi / 2 / (n_points - 1)
    angles = np.arange(4 * (n_points - 1)) * step
    pts = np.stack([np.cos(angles), np.sin(angles)])
    rows = []
    for i in range(pts.shape[1]):
        j = (i + 1) % pts.shape[1]
        k = (pts[1, j] - pts[1, i]) / (pts[0, j] - pts[0, i])
        q = pts[1, i] - k * pts[0, i]
        sign = -1.0 if (angles[i] > math.pi or angles[j] > math.pi) else 1.0
        rows.append(sign * np.array([-k, 1.0, -q * mu, 0, 0, 0]))
    return np.array(rows)


def test_foot_constraints_friction_cone_polygon():
    params = contacts.ContactParams()
    C, b = constraints.contact_constraints(params)
    assert C.shape == (19, 6) and b.shape == (19,)
    cone = C[:12]
    fz = 200.0
    radius = params.mu * fz
    # Same half-planes as WBC's slope/offset rows (positive multiples).
    wbc = wbc_cone_rows(params.mu, params.n_points)
    for ours, theirs in zip(cone, wbc):
        ratio = theirs[[0, 1, 2]] / ours[[0, 1, 2]]
        # Two formulas of the same rows: measured 2.2e-15 relative (XLA held to AVX2).
        np.testing.assert_allclose(ratio, ratio[0], rtol=1e-12)
        assert ratio[0] > 0
    # Vertices on the friction circle: each lies on exactly two edges.
    for t in np.arange(12) * np.pi / 6:
        f = np.array([radius * np.cos(t), radius * np.sin(t), fz, 0, 0, 0])
        val = cone @ f
        assert np.max(val) == pytest.approx(0.0, abs=1e-12)
        assert np.sum(np.abs(val) < 1e-9) == 2
        assert not np.all(cone @ (f * [1.001, 1.001, 1, 1, 1, 1]) <= 0)
    # Apothem mu fz cos 15 deg in the direction of each edge midpoint.
    apothem = radius * np.cos(np.pi / 12)
    for t in (np.arange(12) + 0.5) * np.pi / 6:
        direction = np.array([np.cos(t), np.sin(t), 0, 0, 0, 0])
        inside = apothem * 0.999 * direction + [0, 0, fz, 0, 0, 0]
        outside = apothem * 1.001 * direction + [0, 0, fz, 0, 0, 0]
        assert np.all(C @ inside <= b)
        assert not np.all(C @ outside <= b)
        on = apothem * direction + [0, 0, fz, 0, 0, 0]
        assert np.max(cone @ on) == pytest.approx(0.0, abs=1e-12)


def test_foot_constraints_edge_count_other_n_points():
    for n_points, edges in ((2, 4), (3, 8), (5, 16)):
        C, b = constraints.contact_constraints(contacts.ContactParams(n_points=n_points))
        assert C.shape == (edges + 7, 6) and b.shape == (edges + 7,)


def wrench_with_cop(fz, cop_x, cop_y, tau_z=0.0):
    # CoP x = -tau_y / fz, y = tau_x / fz.
    return np.array([0.0, 0.0, fz, cop_y * fz, -cop_x * fz, tau_z])


@pytest.mark.parametrize("cop", [(0.12, 0.0), (-0.07, 0.0), (0.0, 0.045), (0.0, -0.045)])
def test_foot_constraints_cop_rectangle(cop):
    C, b = constraints.contact_constraints(contacts.ContactParams())
    fz, d = 150.0, 1e-4
    inside = np.array(cop) - d * np.sign(cop)
    outside = np.array(cop) + d * np.sign(cop)
    assert np.all(C @ wrench_with_cop(fz, *inside) <= b)
    violated = C @ wrench_with_cop(fz, *outside) - b
    assert np.sum(violated > 0) == 1
    assert np.argmax(violated) in range(15, 19)


def test_foot_constraints_torsion_and_unilateral():
    params = contacts.ContactParams()
    C, b = constraints.contact_constraints(params)
    fz = 100.0
    limit = params.mu_t * fz
    for sign, row in ((1.0, 12), (-1.0, 13)):
        ok = wrench_with_cop(fz, 0, 0, sign * limit * 0.999)
        bad = wrench_with_cop(fz, 0, 0, sign * limit * 1.001)
        assert np.all(C @ ok <= b)
        assert np.flatnonzero(C @ bad > b).tolist() == [row]
    assert np.all(C @ wrench_with_cop(params.fz_min + 1e-3, 0, 0) <= b)
    assert np.flatnonzero(C @ wrench_with_cop(params.fz_min - 1e-3, 0, 0) > b).tolist() == [14]


def test_constraint_products_rotate_the_wrench():
    """C f of the world-axes wrenches (constraint_products, and constraints' C) equals each contact's
    contact-frame rows on its wrench rotated into its frame, for a set of surface and point contacts."""
    rng = np.random.default_rng(3)
    cset = contacts.ContactSet(
        tuple(dataclasses.replace(c, type=t) for c, t in zip(contact_set(3).contacts, ("surface", "point", "surface")))
    )
    R = np.stack([random_sole_rotation(rng, tilt=0.5, yaw=3.0) for _ in range(3)])
    rows = [constraints.contact_constraints(c.params, c.type) for c in cset.contacts]
    scale = np.array([1.0, 0.5, 0.25])
    C, b = constraints.constraints(cset, jnp.asarray(R), jnp.asarray(scale))
    assert C.shape == (19 + 13 + 19, 15) and C.dtype == jnp.float64
    f_local = [rng.normal(size=(c.dim, 4)) * 30 for c in cset.contacts]
    f_world = np.concatenate(
        [np.concatenate([R[k] @ f[i : i + 3] for i in range(0, len(f), 3)]) for k, f in enumerate(f_local)]
    )
    expected = np.concatenate([C_k @ f for (C_k, _), f in zip(rows, f_local)])
    np.testing.assert_allclose(
        constraints.constraint_products(cset, jnp.asarray(R), jnp.asarray(f_world)), expected, atol=1e-10
    )
    np.testing.assert_allclose(np.asarray(C) @ f_world, expected, atol=1e-10)
    np.testing.assert_allclose(
        constraints.constraint_products(cset, jnp.asarray(R), jnp.asarray(f_world[:, 0])), expected[:, 0], atol=1e-10
    )
    # b: each contact's -fz_min on its unilateral row, times its scale; zero elsewhere.
    np.testing.assert_array_equal(np.asarray(b), np.concatenate([b_k * s for (_, b_k), s in zip(rows, scale)]))
    C32 = constraints.constraint_products(cset, jnp.asarray(R, jnp.float32), jnp.asarray(f_world, jnp.float32))
    assert C32.dtype == jnp.float32


def test_contact_violation_per_contact_relative_to_its_normal_force():
    """Each contact's largest constraint excess over its normal force (or its scaled fz_min), from
    its contact-frame rows, for surface and point contacts and wrenches inside and outside."""
    rng = np.random.default_rng(5)
    cset = contacts.ContactSet(
        tuple(dataclasses.replace(c, type=t) for c, t in zip(contact_set(3).contacts, ("surface", "point", "surface")))
    )
    R = np.stack([random_sole_rotation(rng, tilt=0.5, yaw=3.0) for _ in range(3)])
    activation = np.array([1.0, 0.5, 0.0])
    seen = set()
    for _ in range(30):
        f_local = [
            rng.normal(size=c.dim) * [20, 20, 60, 3, 3, 1][: c.dim] + [0, 0, 40, 0, 0, 0][: c.dim]
            for c in cset.contacts
        ]
        f_world = np.concatenate(
            [np.concatenate([R[k] @ f[i : i + 3] for i in range(0, len(f), 3)]) for k, f in enumerate(f_local)]
        )
        expected = []
        for c, f, a in zip(cset.contacts, f_local, activation):
            C_k, b_k = constraints.contact_constraints(c.params, c.type)
            expected.append(max(np.max(C_k @ f - a * b_k), 0.0) / max(f[2], c.params.fz_min))
        got = constraints.contact_violation(cset, jnp.asarray(f_world), jnp.asarray(R), jnp.asarray(activation))
        np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-12, atol=1e-14)
        seen.update(np.flatnonzero(np.asarray(expected) > 0))
    assert seen == {0, 1, 2}  # every contact was violated somewhere


@pytest.mark.parametrize(
    "types_, mask",
    [
        (("surface", "surface"), (1, 1)),
        (("surface", "surface"), (0, 1)),
        (("surface", "point", "surface"), (0, 1, 1)),
        (("point", "surface", "point", "point"), (1, 1, 1, 1)),
        (("point", "surface", "point", "point"), (1, 0, 1, 1)),  # no surface kept: the eigenbasis
    ],
)
def test_null_space_basis_of_the_kept_contacts(types_, mask):
    """Z is an orthonormal basis of null(A) over the kept contacts' coordinates (the same space as
    scipy's null_space of their columns), its surplus columns zero and flagged; A f1 = w."""
    from scipy.linalg import null_space as scipy_null_space

    rng = np.random.default_rng(11)
    cset = contacts.ContactSet(
        tuple(dataclasses.replace(c, type=t) for c, t in zip(contact_set(len(types_)).contacts, types_))
    )
    p_c = np.array([0.0, 0.0, 0.5])
    A = np.concatenate([centroidal_map(rng.uniform(-0.3, 0.3, 3), p_c)[:, : c.dim] for c in cset.contacts], axis=1)
    w = rng.normal(size=6) * 50
    f1, Z, spare, keep = forces.null_space(cset, jnp.asarray(A), jnp.asarray(mask, float), jnp.asarray(w))
    Z, spare, keep = np.asarray(Z), np.asarray(spare), np.asarray(keep) > 0
    reference = np.zeros((cset.dim, cset.dim))
    basis = scipy_null_space(A[:, keep])
    reference[np.ix_(keep, keep)] = basis @ basis.T
    assert np.sum(~spare) == basis.shape[1] == keep.sum() - 6
    np.testing.assert_allclose(Z @ Z.T, reference, atol=1e-12)
    np.testing.assert_allclose(Z.T @ Z, np.diag(~spare).astype(float), atol=1e-12)
    assert np.all(Z[:, spare] == 0.0) and np.all(Z[~keep] == 0.0)
    np.testing.assert_allclose(A @ np.asarray(f1), w, atol=1e-10)


# --------------------------------------------------------------------------------------
# solve_qp
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("size", [(6, 19), (12, 38), (6, 38)])
def test_solve_qp_matches_quadprog_float64(random_qps, solve_batch, size):
    s = random_qps[size]
    x, info = solve_batch(*(jnp.asarray(s[k]) for k in "HgCb"))
    x = np.asarray(x)
    n_active = np.sum(s["C"] @ s["x"][..., None] >= s["b"][..., None] - 1e-9, axis=(1, 2))
    assert np.mean(n_active >= 2) > 0.8  # the generator gives active constraints
    assert np.all(info.converged) and not np.any(info.infeasible)
    scale = 1.0 + np.max(np.abs(s["x"]), axis=1)
    err = np.max(np.abs(x - s["x"]), axis=1) / scale
    assert np.max(err) < 1e-8
    obj = np.array([objective(H, g, xi) for H, g, xi in zip(s["H"], s["g"], x)])
    obj_ref = np.array([objective(H, g, xi) for H, g, xi in zip(s["H"], s["g"], s["x"])])
    assert np.max(np.abs(obj - obj_ref) / (1.0 + np.abs(obj_ref))) < 1e-8
    assert np.max(info.max_violation) < 1e-9
    assert np.max(info.iterations) < qp.DEFAULT_ITERATIONS


@pytest.mark.parametrize("size", [(6, 19), (6, 38)])
def test_solve_qp_matches_quadprog_float32(random_qps, solve_batch, size):
    s = random_qps[size]
    x, info = solve_batch(*(jnp.asarray(s[k], jnp.float32) for k in "HgCb"))
    assert x.dtype == jnp.float32 and info.max_violation.dtype == jnp.float32
    scale = 1.0 + np.max(np.abs(s["x"]), axis=1)
    err = np.max(np.abs(np.asarray(x, np.float64) - s["x"]), axis=1) / scale
    assert np.max(err) < 1e-4
    assert np.median(err) < 1e-5
    assert np.mean(info.converged) > 0.9 and not np.any(info.infeasible)


def test_solve_qp_unconstrained_minimiser(solve_one):
    rng = np.random.default_rng(5)
    H, g, C, _ = random_qp(rng, 6, 19)
    x_unc = -np.linalg.solve(H, g)
    b = C @ x_unc + 1.0  # all constraints inactive, slack 1
    x, info = solve_one(H, g, C, b)
    # Interior point vs NumPy's solve (two paths): measured 5.8e-11 abs, 1.8e-11 rel, here and with XLA held to AVX2
    # (the solver's stopping tolerance); bars ~100x that.
    np.testing.assert_allclose(np.asarray(x), x_unc, rtol=5e-9, atol=5e-9)
    assert bool(info.converged) and not bool(info.infeasible)
    assert float(info.max_violation) == 0.0


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_solve_qp_infeasible_falls_back(solve_one, dtype):
    rng = np.random.default_rng(6)
    H, g, C, b = random_qp(rng, 6, 19)
    # x_0 <= -1 and x_0 >= 1 cannot both hold.
    C[0] = np.eye(6)[0]
    C[1] = -np.eye(6)[0]
    b[0] = b[1] = -1.0
    x, info = solve_one(*(jnp.asarray(a, dtype) for a in (H, g, C, b)))
    assert bool(info.infeasible) and not bool(info.converged)
    assert np.all(np.isfinite(np.asarray(x)))
    # The fallback vs NumPy's float64 solve: measured 5.6e-14 rel in float64 and 2.9e-5 in float32, here and with XLA
    # held to AVX2; the float32 bar is ~100x that (1e-4 left 3x), float64's far above its noise.
    rtol = 1e-9 if dtype == jnp.float64 else 3e-3
    np.testing.assert_allclose(np.asarray(x), -np.linalg.solve(H, g), rtol=rtol, atol=rtol)
    assert float(info.max_violation) >= 1.0 - 1e-6


def test_solve_qp_nan_input_is_flagged(solve_one):
    rng = np.random.default_rng(8)
    H, g, C, b = random_qp(rng, 6, 19)
    b[3] = np.nan
    x, info = solve_one(H, g, C, b)
    assert np.all(np.isnan(np.asarray(x)))
    assert not bool(info.converged) and bool(info.infeasible)


def test_solve_qp_vmap_equals_loop_and_jit_cache(solve_batch, solve_one):
    rng = np.random.default_rng(9)
    probs = [random_qp(rng, 6, 19) for _ in range(256)]
    H, g, C, b = (np.stack(a) for a in zip(*probs))
    traces = []

    def traced(H, g, C, b):
        traces.append(1)
        return qp.solve_qp(H, g, C, b)

    batched = jit(jax.vmap(traced))
    x, info = batched(H, g, C, b)
    x2, _ = batched(H * 2.0, g, C, b)  # new values, same shapes: no retrace
    assert len(traces) == 1
    assert x.shape == (256, 6) and info.converged.shape == (256,)
    assert info.iterations.dtype == jnp.int32 and info.converged.dtype == jnp.bool_
    loop = np.stack([np.asarray(solve_one(*p)[0]) for p in probs])
    # vmap vs one at a time (two programs): measured 4e-15 abs, 9.6e-14 relative (XLA held to AVX2).
    np.testing.assert_allclose(np.asarray(x), loop, rtol=1e-9, atol=1e-9)
    assert not np.allclose(np.asarray(x2), np.asarray(x))


def test_solve_qp_validates_shapes():
    with pytest.raises(ValueError, match="shapes"):
        qp.solve_qp(jnp.eye(3), jnp.zeros(3), jnp.zeros((4, 2)), jnp.zeros(4))
    with pytest.raises(ValueError, match="m >= 1"):
        qp.solve_qp(jnp.eye(3), jnp.zeros(3), jnp.zeros((0, 3)), jnp.zeros(0))
    with pytest.raises(ValueError, match=r"start must have shape \(2, 4\)"):
        qp.solve_qp(jnp.eye(3), jnp.zeros(3), jnp.zeros((4, 3)), jnp.zeros(4), start=jnp.zeros((2, 3)))


def test_solve_qp_warm_start_same_solution_fewer_steps(random_qps, solve_batch):
    """A warm start from a nearby problem's solution (the last control tick's) reaches the cold
    start's solution in fewer Newton steps; a NaN start is the cold start, bit for bit."""
    s = random_qps[(6, 38)]
    rng = np.random.default_rng(11)
    solve = jit(jax.vmap(lambda H, g, C, b, start: qp.solve_qp(H, g, C, b, start=start)))
    data = [jnp.asarray(s[k]) for k in "HgCb"]
    _, first = solve(*data, jnp.full((len(s["b"]), 2, 38), jnp.nan))
    # The next tick's problem: the linear term and the bounds moved by ~1 %.
    H, g, C, b = data
    g = g * (1.0 + 0.01 * rng.standard_normal(g.shape))
    b = b + 0.01 * np.abs(np.asarray(b)).mean() * rng.standard_normal(b.shape)
    x_cold, cold = solve(H, g, C, b, jnp.full((len(s["b"]), 2, 38), jnp.nan))
    x_warm, warm = solve(H, g, C, b, first.start)
    assert np.all(cold.converged) and np.all(warm.converged)
    x_plain, _ = solve_batch(H, g, C, b)
    np.testing.assert_array_equal(np.asarray(x_cold), np.asarray(x_plain))
    scale = 1.0 + np.max(np.abs(np.asarray(x_cold)), axis=1)
    err = np.max(np.abs(np.asarray(x_warm) - np.asarray(x_cold)), axis=1) / scale
    assert np.max(err) < 1e-9  # both within the float64 tolerance 1e-11 of the KKT point
    # Measured: 8.2 steps warm against 11.4 cold on average (float64, tol 1e-11); max err 1.7e-11.
    assert np.mean(warm.iterations) < np.mean(cold.iterations) - 1.0, (warm.iterations, cold.iterations)


# --------------------------------------------------------------------------------------
# Derivatives of solve_qp
# --------------------------------------------------------------------------------------

FD_EPS = 1e-6


def loss(x, w):
    return jnp.dot(w, x) + 0.5 * jnp.dot(x, x)


def _probe_one(H, g, C, b, w, T):
    """Derivatives of loss(x(H, g, C, b)) along K tangents T = (dH, dg, dC, db).

    Returns central differences, forward-mode jvps and reverse-mode gradient
    contractions (each (K,)), the gradients and x; all in one compiled call.
    """
    args = (H, g, C, b)

    def x_of(*a):
        return qp.solve_qp(*a)[0]

    def f(*a):
        return loss(x_of(*a), w)

    # f at args +- eps T in one vmap (one solver copy to compile, not two).
    T2 = tuple(jnp.concatenate([d, -d]) for d in T)
    shifted = jax.vmap(lambda *t: f(*(a + FD_EPS * d for a, d in zip(args, t))))(*T2)
    k = T[0].shape[0]
    fd = (shifted[:k] - shifted[k:]) / (2 * FD_EPS)
    fwd = jax.vmap(lambda *t: jax.jvp(f, args, t)[1])(*T)
    x, pullback = jax.vjp(x_of, *args)
    grads = pullback(w + x)  # d loss / dx = w + x
    rev = sum(jnp.tensordot(d, gr, axes=gr.ndim) for d, gr in zip(T, grads))
    return fd, fwd, rev, grads, x


probe = jit(jax.vmap(_probe_one))


def tangents_for(rng, H, g, C, b, n_random=3):
    """Coordinate directions of g and b, then random (dH sym, dg, dC, db)."""
    n, m = g.size, b.size
    k = n + m + n_random
    dH = np.zeros((k, n, n))
    dg = np.zeros((k, n))
    dC = np.zeros((k, m, n))
    db = np.zeros((k, m))
    dg[:n] = np.eye(n)
    db[n : n + m] = np.eye(m)
    for j in range(n + m, k):
        A = rng.normal(size=(n, n))
        dH[j] = 0.05 * np.abs(H).max() * (A + A.T)
        dg[j] = rng.normal(size=n)
        dC[j] = rng.normal(size=(m, n))
        db[j] = rng.normal(size=m)
    return dH, dg, dC, db


def strictly_complementary(s, margin=1e-3):
    """Problems whose active set is stable under small perturbations."""
    keep = []
    for i, (C, b, x, lam) in enumerate(zip(s["C"], s["b"], s["x"], s["lam"])):
        slack = b - C @ x
        active = lam > margin * (1.0 + np.max(lam))
        if np.any(active) and np.all(slack[~active] > margin) and np.all(slack[active] < 1e-9):
            keep.append(i)
    return keep


def special_problems():
    """Two hand-made (6, 19) problems: a weakly active row and an infeasible one.

    H = diag(2, 1, 1, 1, 1, 1), g = e_1; rows 1..12 are the box |x_i| <= 10,
    rows 13..18 loose couplings. Row 0 is

    * x_0 <= 0: the minimiser x* = -H^-1 g = (0, -1, 0, ...) lies exactly on
      it with multiplier 0 (no strict complementarity);
    * and, with the box row -x_0 <= 10 replaced by -x_0 <= -1, x_0 <= -1:
      infeasible (robustly: also for perturbed C, thanks to the box).
    """
    H = np.diag([2.0, 1, 1, 1, 1, 1])
    g = np.eye(6)[1]
    box = np.concatenate([np.eye(6), -np.eye(6)])
    couplings = np.ones((6, 6)) - 2 * np.eye(6)
    C = np.concatenate([np.eye(6)[:1], box, couplings])
    b = np.concatenate([[0.0], np.full(12, 10.0), np.full(6, 50.0)])
    C_inf, b_inf = C.copy(), b.copy()
    b_inf[0] = -1.0
    b_inf[7] = -1.0  # row 7 is -x_0 <= 10 -> -x_0 <= -1
    return [(H, g, C, b), (H, g, C_inf, b_inf)]


@pytest.fixture(scope="module")
def probed_6x19(random_qps):
    """All derivative probes of the (6, 19) random QPs plus the two special
    problems (the last two) in one compiled call."""
    s = random_qps[(6, 19)]
    probs = [tuple(s[k][i] for k in "HgCb") for i in range(len(s["g"]))]
    probs += special_problems()
    rng = np.random.default_rng(11)
    T = tuple(np.stack(t) for t in zip(*(tangents_for(rng, *p) for p in probs)))
    w = rng.normal(size=(len(probs), 6))
    H, g, C, b = (np.stack(a) for a in zip(*probs))
    out = probe(H, g, C, b, w, T)
    return s, w, [np.asarray(a) if not isinstance(a, tuple) else a for a in out]


def test_solve_qp_gradients_match_finite_differences(probed_6x19):
    s, _, (fd, fwd, rev, grads, _) = probed_6x19
    idx = strictly_complementary(s)
    assert len(idx) >= 5
    fd, fwd, rev = fd[idx], fwd[idx], rev[idx]
    scale = 1.0 + np.abs(fd).max(axis=1, keepdims=True)
    # Forward mode == central differences (coordinates of g and b, random
    # directions in H, g, C, b jointly) ...
    assert np.all(np.abs(fwd - fd) <= 2e-6 * scale)
    # ... and reverse mode == forward mode to rounding.
    assert np.all(np.abs(rev - fwd) <= 1e-9 * scale)
    # The loss depends on b through active rows only.
    assert np.any(np.abs(fwd[:, 6:25]) > 1e-3)


def test_solve_qp_gradients_finite_everywhere(probed_6x19):
    _, _, (fd, fwd, rev, grads, _) = probed_6x19
    for a in (fwd, rev, *grads):
        assert np.all(np.isfinite(np.asarray(a)))


def test_solve_qp_gradients_degenerate_and_fallback(probed_6x19):
    """Weakly active row (lam = slack = 0) and the infeasible fallback."""
    _, w, (fd, fwd, rev, grads, x) = probed_6x19
    (H, g, _, _), _ = special_problems()
    # Finiteness of the degenerate one is checked with all the others above.
    np.testing.assert_allclose(x[-2], -np.linalg.solve(H, g), atol=1e-7)
    # Fallback: d loss / d g = (w + x)' d(-H^-1 g)/dg = -(w + x)' H^-1.
    x_inf = -np.linalg.solve(H, g)
    # Below: measured 2.7e-15 (x), 3.2e-14 relative (forward mode), 4.9e-16 (reverse vs forward), XLA held to AVX2.
    np.testing.assert_allclose(x[-1], x_inf, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(fwd[-1, :6], -(w[-1] + x_inf) @ np.linalg.inv(H), rtol=1e-9)
    np.testing.assert_allclose(fwd[-1], fd[-1], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(rev[-1], fwd[-1], rtol=1e-9, atol=1e-12)


def test_solve_qp_jacobians_forward_equals_reverse(random_qps):
    s = random_qps[(6, 19)]
    i = strictly_complementary(s)[0]
    H, g, C, b = (jnp.asarray(s[k][i]) for k in "HgCb")

    def x_of(g, b):
        return qp.solve_qp(H, g, C, b)[0]

    jf, jr = jit(
        lambda g, b: (
            jax.jacfwd(x_of, argnums=(0, 1))(g, b),
            jax.jacrev(x_of, argnums=(0, 1))(g, b),
        )
    )(g, b)
    for a, r in zip(jf, jr):
        # jacfwd vs jacrev: measured 5.6e-16 abs with XLA held to AVX2.
        np.testing.assert_allclose(np.asarray(a), np.asarray(r), rtol=1e-9, atol=1e-12)
    # With k active rows (independent normals) x moves with g only in the
    # n - k free directions: dx/dg has rank n - k.
    lam = s["lam"][i]
    k = int(np.sum(lam > 1e-6 * (1 + lam.max())))
    sv = np.linalg.svd(np.asarray(jf[0]), compute_uv=False)
    assert np.sum(sv > 1e-6 * np.linalg.norm(np.linalg.inv(s["H"][i]), 2)) == 6 - k


def test_solve_qp_inside_scan_and_grad():
    """A rollout-like scan with a QP per step, differentiated in both modes."""
    rng = np.random.default_rng(12)
    H, g, C, b = random_qp(rng, 6, 19)

    def rollout(theta):
        def step(x, _):
            x_new, _ = qp.solve_qp(H, g + theta * x, C, b)
            return 0.5 * x_new, None

        x, _ = jax.lax.scan(step, jnp.zeros(6), None, length=4)
        return jnp.sum(x)

    @jit
    def all_modes(theta):
        fd = (rollout(theta + 1e-6) - rollout(theta - 1e-6)) / 2e-6
        return jax.grad(rollout)(theta), jax.jvp(rollout, (theta,), (1.0,))[1], fd

    rev, fwd, fd = (float(a) for a in all_modes(0.3))
    assert rev == pytest.approx(fwd, rel=1e-9)
    assert fwd == pytest.approx(fd, rel=1e-5, abs=1e-8)
    assert abs(fwd) > 1e-6


# --------------------------------------------------------------------------------------
# The WBC contact-force QPs
# --------------------------------------------------------------------------------------


def world_constraint_matrix(R):
    C_foot, b_foot = constraints.contact_constraints(PARAMS)
    return C_foot @ np.kron(np.eye(2), R.T), b_foot


def torque_norm(p, f):
    return np.linalg.norm(p["tau_model"] + p["Sigma"] @ f)


def test_two_feet_wrenches_float64(two_feet_problems, two_feet_batch):
    probs = two_feet_problems
    batch = stack_dicts(probs, TWO_FEET_KEYS)
    f, info = two_feet_batch(*(jnp.asarray(batch[k]) for k in TWO_FEET_KEYS))
    f = np.asarray(f)
    assert np.all(info.converged) and not np.any(info.infeasible)
    assert np.max(info.max_violation) < 1e-6
    n_active = 0
    n_f1_feasible = 0
    for p, fi in zip(probs, f):
        C_L, b_L = world_constraint_matrix(p["W_R_left"])
        C_R, b_R = world_constraint_matrix(p["W_R_right"])
        viol = max(np.max(C_L @ fi[:6] - b_L), np.max(C_R @ fi[6:] - b_R))
        assert viol < 1e-6
        # Momentum: f - f1 lies in range(N_A) (the total wrench is unchanged).
        d = fi - p["f1"]
        # Measured: 5.7e-14 (momentum rows), 4.8e-9 N against quadprog (its tolerance), XLA held to AVX2: bars >= 1e3x.
        np.testing.assert_allclose(p["N_A"] @ d, d, atol=1e-8 * (1 + np.abs(d).max()))
        np.testing.assert_allclose(p["A"] @ fi, p["w_des"], rtol=1e-9, atol=1e-8)
        # Same optimum as quadprog on WBC's f0 formulation.
        np.testing.assert_allclose(fi, p["f_ref"], rtol=0, atol=1e-6 * np.abs(fi).max())
        assert torque_norm(p, fi) == pytest.approx(torque_norm(p, p["f_ref"]), rel=1e-9)
        f1_ok = max(np.max(C_L @ p["f1"][:6] - b_L), np.max(C_R @ p["f1"][6:] - b_R)) <= 0
        if f1_ok:
            n_f1_feasible += 1
            assert torque_norm(p, fi) <= torque_norm(p, p["f1"]) + 1e-9
        n_active += int(viol > -1e-7)
    assert n_active >= len(probs) // 2  # constraints matter in these problems
    assert n_f1_feasible >= 3


def test_two_feet_wrenches_float32(two_feet_problems, two_feet_batch):
    batch = stack_dicts(two_feet_problems, TWO_FEET_KEYS)
    f, info = two_feet_batch(*(jnp.asarray(batch[k], jnp.float32) for k in TWO_FEET_KEYS))
    assert f.dtype == jnp.float32 and not np.any(info.infeasible)
    f_ref = np.stack([p["f_ref"] for p in two_feet_problems])
    err = np.max(np.abs(np.asarray(f, np.float64) - f_ref), axis=1)
    assert np.max(err / np.max(np.abs(f_ref), axis=1)) < 1e-4
    # Violation relative to the force scale (mg): float32 rounding only.
    assert np.max(info.max_violation) < 1e-4 * MASS * GRAVITY


def test_two_feet_z_basis_equals_f0_formulation(two_feet_problems, solve_batch):
    """Our solver on WBC's f0 formulation (n = 12, m = 38) gives the same f."""
    probs = two_feet_problems
    parts = [two_feet_f0_problem(p, PARAMS) for p in probs]
    H, g, Cy, by = (np.stack([q[i] for q in parts]) for i in range(4))
    f0, info = solve_batch(H, g, Cy, by)
    assert np.all(info.converged)
    for p, f0_i in zip(probs, np.asarray(f0)):
        f = p["f1"] + p["N_A"] @ f0_i
        np.testing.assert_allclose(f, p["f_ref"], atol=1e-6 * np.abs(f).max())


def test_two_feet_infeasible_total_wrench_falls_back(two_feet_problems, two_feet_batch):
    probs = [dict(p) for p in two_feet_problems]
    p = probs[0]
    # Ask the feet to pull the robot down: impossible with f_z >= fz_min.
    w_pull = np.array([0.0, 0.0, -100.0, 0.0, 0.0, 0.0])
    p["w_des"] = w_pull
    p["f1"] = np.linalg.pinv(p["A"]) @ w_pull
    batch = stack_dicts(probs, TWO_FEET_KEYS)
    f, info = two_feet_batch(*(jnp.asarray(batch[k]) for k in TWO_FEET_KEYS))
    assert bool(info.infeasible[0]) and not bool(info.converged[0])
    assert not np.any(info.infeasible[1:])
    f = np.asarray(f[0])
    assert np.all(np.isfinite(f))
    # Fallback: unconstrained torque minimiser on f1 + range(N_A).
    SN = p["Sigma"] @ p["N_A"]
    f0 = np.linalg.lstsq(SN, -(p["tau_model"] + p["Sigma"] @ p["f1"]), rcond=None)[0]
    np.testing.assert_allclose(f, p["f1"] + p["N_A"] @ f0, rtol=1e-6, atol=1e-6)


def test_distribute_batch_runs_fallbacks_only_where_needed(two_feet_problems):
    """Under vmap the soft-QP fallback and the ramp's second formulation run as branches on a
    batch-level ``any`` (math.batch_any): each environment's wrenches equal those it gets alone,
    whether or not others in its batch needed a fallback; with none needing one, the program
    keeps both branches as conds (a batched predicate would have turned them into selects)."""

    def one(Sigma, tau_model, A, w_des, W_R_left, W_R_right, activation):
        tt = types.SimpleNamespace(Sigma=Sigma, tau_model=tau_model)
        return forces.distribute(FEET, activation, A, w_des, tt, jnp.stack([W_R_left, W_R_right]), SETTINGS)[:2]

    probs = [dict(p) for p in two_feet_problems[:4]]
    pull = np.array([0.0, 0.0, -100.0, 0.0, 0.0, 0.0])  # infeasible: the feet cannot pull
    probs[1]["w_des"] = pull
    acts = np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 0.4], [1.0, 1.0]])
    batch = {k: jnp.asarray(v) for k, v in stack_dicts(probs, TWO_FEET_KEYS).items()}
    args = [batch[k] for k in TWO_FEET_KEYS] + [jnp.asarray(acts)]
    f_batch, infeasible_batch = jit(jax.vmap(one))(*args)
    single = jit(one)
    alone = [single(*(a[i] for a in args)) for i in range(4)]
    for i, (f_i, inf_i) in enumerate(alone):
        # Batched vs alone (two programs): measured 9.1e-14 abs, 1.8e-14 relative (XLA held to AVX2).
        np.testing.assert_allclose(f_batch[i], f_i, rtol=1e-9, atol=1e-9 * np.abs(f_i).max(), err_msg=str(i))
        assert bool(infeasible_batch[i]) == bool(inf_i)
    # The fallbacks were taken where needed and only there: the pull got the soft QP's wrenches
    # (not the equality QP's unconstrained fallback), the ramping feet a blend of two formulations.
    W_R1 = jnp.stack([args[4][1], args[5][1]])

    @jit  # compiled: op by op these two QPs cost more CPU time than their programs' compile
    def both_formulations(Sigma, tau_model, A, w_des, W_R):
        tt = types.SimpleNamespace(Sigma=Sigma, tau_model=tau_model)
        soft = forces.soft_momentum_qp(FEET, jnp.ones(2), A, w_des, tt, W_R, SETTINGS)
        return soft, forces.momentum_equality_qp(FEET, jnp.ones(2), A, w_des, tt, W_R, SETTINGS)

    (f_soft, _), (f_eq, info_eq) = both_formulations(*(a[1] for a in args[:4]), W_R1)
    assert bool(info_eq.infeasible)
    np.testing.assert_allclose(f_batch[1], f_soft, rtol=1e-9, atol=1e-9 * np.abs(f_soft).max())
    assert np.abs(np.asarray(f_batch[1] - f_eq)).max() > 1.0
    f_full, _ = single(*(a[2] for a in args[:-1]), jnp.ones(2))
    assert np.abs(np.asarray(f_batch[2] - f_full)).max() > 1.0
    for i in (0, 3):  # neither needs a fallback: the equality QP's wrenches
        np.testing.assert_allclose(f_batch[i], alone[i][0], rtol=1e-9, atol=1e-9)
    calm = [a[jnp.array([0, 3])] for a in args]
    jaxpr = str(jax.make_jaxpr(jax.vmap(one))(*calm))
    # Three branches (the soft QP after each of the two formulations, the ramp) and one in each of
    # the four QPs (its unconstrained fallback minimiser); the linear algebra's own conds are
    # dispatch on the platform (platform_index).
    branches = len(re.findall(r"= cond\[", jaxpr)) - len(re.findall(r"= platform_index\[", jaxpr))
    assert branches == 3 + 4


def test_two_feet_gradients(two_feet_problems):
    """jvp/grad w.r.t. every input vs central differences (N_A through A)."""
    p = two_feet_problems[1]
    rng = np.random.default_rng(13)
    w = rng.normal(size=12)
    E = rng.normal(size=(6, 12)) * 0.01

    def pipeline(Sigma, tau_model, w_des, theta, W_R_left):
        # N_A and f1 from a perturbed momentum map A + theta E (a projector
        # family), so the derivative w.r.t. N_A is exercised consistently.
        A = jnp.asarray(p["A"]) + theta * E
        f, _ = two_feet_wrenches(Sigma, tau_model, A, w_des, W_R_left, jnp.asarray(p["W_R_right"]))
        return jnp.dot(w, f)

    args = (p["Sigma"], p["tau_model"], p["w_des"], 0.0, p["W_R_left"])
    # One tangent per argument, all others zero: T[j][k] is the tangent of
    # argument j in probe k.
    directions = (
        rng.normal(size=p["Sigma"].shape) * 0.01,
        rng.normal(size=N_JOINTS),
        rng.normal(size=6),
        1.0,
        skew(rng.normal(size=3)) @ p["W_R_left"] * 0.01,
    )
    T = tuple(
        np.stack([d if j == k else np.zeros_like(d) for k in range(5)])
        for j, d in enumerate(np.asarray(d, float) for d in directions)
    )
    # Central differences of an interior-point solution carry its stopping tolerance (relative 1e-11
    # of ~300 N wrenches) divided by the step: at 1e-6 that noise reached 1.2e-3 of the derivative on
    # one CPU (theta: -1.58821 vs -1.58631 by steps 1e-5, 1e-7, 1e-8 and the jvp); 1e-5 keeps it and
    # the truncation error (~1e-7 relative here) well below rtol.
    eps = 1e-5

    @jit
    def all_modes(args, T):
        T2 = tuple(jnp.concatenate([d, -d]) for d in T)
        shifted = jax.vmap(lambda *t: pipeline(*(a + eps * d for a, d in zip(args, t))))(*T2)
        fd = (shifted[:5] - shifted[5:]) / (2 * eps)
        fwd = jax.vmap(lambda *t: jax.jvp(pipeline, args, t)[1])(*T)
        grads = jax.grad(pipeline, argnums=(0, 1, 2, 3, 4))(*args)
        return fd, fwd, grads

    fd, fwd, grads = all_modes(args, T)
    rev = np.array([float(jnp.vdot(gr, d)) for gr, d in zip(grads, directions)])
    fd, fwd = np.asarray(fd), np.asarray(fwd)
    assert np.all(np.abs(fwd) > 1e-6)
    np.testing.assert_allclose(fwd, fd, rtol=1e-5, atol=1e-6)
    # Reverse vs forward mode: measured 5.6e-14 abs, 3.5e-14 relative (XLA held to AVX2).
    np.testing.assert_allclose(rev, fwd, rtol=1e-8, atol=1e-10)
    for gr in grads:
        assert np.all(np.isfinite(np.asarray(gr)))


def test_soft_qp_angular_weight_puts_the_linear_momentum_first():
    """angular_weight_soft < 1 weighs the angular rows of |A f - w|^2 down: the soft QP matches
    quadprog on the weighted objective, and where the constraints bind its linear-momentum residual
    falls below the unweighted QP's while the angular residual grows."""
    rng = np.random.default_rng(22)
    probs = [random_one_foot(rng) for _ in range(12)]
    A, w, R = (np.stack(a) for a in zip(*probs))
    Sigma = rng.normal(size=(len(probs), N_JOINTS, 6)) * 0.2
    tau = rng.normal(size=(len(probs), N_JOINTS)) * 10.0
    weighted = dataclasses.replace(SETTINGS, angular_weight_soft=0.01)

    def solve(A, w, R, Sigma, tau):
        tt = types.SimpleNamespace(Sigma=Sigma, tau_model=tau)
        one = jnp.ones(1, A.dtype)
        return tuple(forces.soft_momentum_qp(ONE_FOOT, one, A, w, tt, R[None], s)[0] for s in (SETTINGS, weighted))

    plain, light = (np.asarray(f) for f in jit(jax.vmap(solve))(A, w, R, Sigma, tau))
    c, rows = SETTINGS.torque_weight_soft, np.array([1.0, 1, 1, 0.01, 0.01, 0.01])
    lin_plain, lin_light, ang_plain, ang_light = [], [], [], []
    for k, (A_k, w_k, R_k) in enumerate(probs):
        C, b = world_constraint_matrix(R_k)
        H = A_k.T @ (rows[:, None] * A_k) + c * Sigma[k].T @ Sigma[k] + 1e-7 * np.eye(6)
        x_ref, _ = ref_qp(H, -A_k.T @ (rows * w_k) + c * Sigma[k].T @ tau[k], C, b)
        np.testing.assert_allclose(light[k], x_ref, atol=1e-7 * np.abs(x_ref).max())
        for f, lin, ang in ((plain[k], lin_plain, ang_plain), (light[k], lin_light, ang_light)):
            r = A_k @ f - w_k
            lin.append(np.linalg.norm(r[:3]))
            ang.append(np.linalg.norm(r[3:]))
    lin_plain, lin_light, ang_plain, ang_light = map(np.array, (lin_plain, lin_light, ang_plain, ang_light))
    binding = lin_plain > 1e-3  # the demanding problems: the plain QP misses the linear rate
    assert binding.sum() >= 8
    # Never worse on the linear rows (the trade-off of a convex two-objective problem is monotone);
    # much better where the CoP rows, not the friction cone alone, bound the force.
    assert np.all(lin_light[binding] <= lin_plain[binding] * (1 + 1e-4))
    assert np.median(lin_light[binding] / lin_plain[binding]) < 0.8
    assert np.sum(lin_light[binding] < 0.2 * lin_plain[binding]) >= 3
    assert np.all(ang_light[binding] >= ang_plain[binding] * (1 - 1e-4))


def test_one_foot_wrench():
    """One foot: the equality QP returns A_k^-1 w where that wrench meets the constraints; the soft
    momentum QP (the fallback) matches quadprog on its objective, with constraints active."""
    rng = np.random.default_rng(21)
    # Mostly demanding wrenches (constraints active), some easy (achievable).
    probs = [random_one_foot(rng) for _ in range(18)]
    probs += [random_one_foot(rng, 0.05, 0.5, 0.01) for _ in range(6)]
    A, w, R = (np.stack(a) for a in zip(*probs))
    Sigma = rng.normal(size=(len(probs), N_JOINTS, 6)) * 0.2
    tau = rng.normal(size=(len(probs), N_JOINTS)) * 10.0

    def solve(A, w, R, Sigma, tau):
        tt = types.SimpleNamespace(Sigma=Sigma, tau_model=tau)
        one = jnp.ones(1, A.dtype)
        exact, info_eq = forces.momentum_equality_qp(ONE_FOOT, one, A, w, tt, R[None], SETTINGS)
        soft, info = forces.soft_momentum_qp(ONE_FOOT, one, A, w, tt, R[None], SETTINGS)
        return exact, info_eq.infeasible, soft, info

    one_foot = jit(jax.vmap(solve))
    exact_f, eq_infeasible, f, info = one_foot(A, w, R, Sigma, tau)
    f = np.asarray(f)
    assert np.all(info.converged) and np.max(info.max_violation) < 1e-6
    n_active = n_exact = 0
    c = SETTINGS.torque_weight_soft
    for k, ((A_k, w_k, R_k), f_k) in enumerate(zip(probs, f)):
        C, b = world_constraint_matrix(R_k)
        H = A_k.T @ A_k + c * Sigma[k].T @ Sigma[k] + 1e-7 * np.eye(6)
        x_ref, _ = ref_qp(H, -A_k.T @ w_k + c * Sigma[k].T @ tau[k], C, b)
        assert np.max(C @ f_k - b) < 1e-6
        np.testing.assert_allclose(f_k, x_ref, atol=1e-7 * np.abs(x_ref).max())
        n_active += int(np.max(C @ f_k - b) > -1e-6)
        exact = np.linalg.solve(A_k, w_k)
        if np.all(C @ exact <= b):  # achievable: the equality QP returns it
            n_exact += 1
            assert not eq_infeasible[k]
            np.testing.assert_allclose(exact_f[k], exact, atol=1e-6 * np.abs(exact).max())
        else:
            assert eq_infeasible[k]
    assert n_active >= 12 and n_exact >= 3
    f32 = one_foot(*(jnp.asarray(a, jnp.float32) for a in (A, w, R, Sigma, tau)))[2]
    assert f32.dtype == jnp.float32
    rel = np.max(np.abs(np.asarray(f32, np.float64) - f)) / np.max(np.abs(f))
    assert rel < 1e-4
    # (Derivatives of the formulations: test_two_feet_gradients.)
