"""What the torque law's postural projector costs, part by part (issue 46; wbc_jax/control/torques.py).

The ``stable`` postural task's projector cuts the eigenvectors of A (n x n) above a threshold, taken first from A's
Ritz vectors on the span of A S (S: n x D, :func:`wbc_jax.control.torques.ritz_projector`): an orthonormal basis of
A S, a D x D ``eigh``, and the certification's products; the whole n x n ``eigh`` runs only where that is not
certified. On the H100 the basis (a Householder QR) cost 0.048 µs per environment and the small ``eigh`` 0.020
(BENCHMARKS.md). This times each part vmapped over ``--batch`` environments at the standing posture with random
joint offsets and velocities (benchmarks/warp_terms_cost.py's states), µs per environment (best of ``--repeats``,
compiled first): the Ritz decomposition by Householder QR and ``eigh`` (``ritz_engine`` jax), with a Gram-Schmidt basis
(:func:`gram_schmidt`, classical Gram-Schmidt twice) and as one Warp kernel (``ritz_engine`` warp,
wbc_jax/control/ritz_warp.py; skipped without warp-lang), the certified projector of each, how far each projector lies
from the Householder one's and the share of environments each certifies:

    python benchmarks/projector_cost.py --batch 65536 --out results/gpu_h100/projector_cost.json
"""

import argparse

import jax
import jax.numpy as jnp

# from this script's folder (Python puts it first on sys.path): profile_tick's timing and warp_terms_cost's flags/states
from profile_tick import timed
from warp_terms_cost import batch_parser, checked, measured, states

from wbc_jax.control import torques
from wbc_jax.core import provenance
from wbc_jax.robot import contacts
from wbc_jax.sim import physics, scenario


def parse_args(argv=None) -> argparse.Namespace:
    return checked(batch_parser(__doc__), argv)


def main(argv=None) -> dict:
    return measured(_measure, parse_args(argv), __file__, argv)


def _problems(a: argparse.Namespace):
    """(A (B, n, n), threshold, S (B, n, D)) at the batch's states, as the torque law builds them."""
    st = scenario.setup("stand", duration=0.1, robot_name=a.robot)
    loop, cfg = st.loop, st.loop.controller.config
    qpos, qvel = (jnp.asarray(x, st.dtype) for x in states(st.robot, a.batch, a.seed))

    def one(q, v):
        t = loop.terms(q, v)
        ct = contacts.contact_terms(loop.contact_set, t, 0.0, jnp.ones(2, st.dtype))
        tt = torques.torque_terms(
            t, ct.J, ct.Jdot_nu, postural="stable", kp_postural=st.gains.kp_postural, kd_postural=st.gains.kd_postural,
            s_des=t.s, pinv_damping=cfg.pinv_damping, pinv_tol=cfg.pinv_tol,
        )  # fmt: skip
        return torques.projector_problem(tt.Lambda, tt.Mbar, cfg.pinv_damping, cfg.pinv_tol, None)

    A, threshold, S = jax.jit(jax.vmap(one))(qpos, qvel)
    return A, threshold[0], S


def _measure(a: argparse.Namespace) -> dict:
    A, threshold, S = _problems(a)
    decompositions = {"householder_qr": torques.ritz_decomposition, "gram_schmidt": _gram_schmidt_decomposition}
    skipped = {}
    if physics.has_warp():
        decompositions["warp"] = torques.ritz_decomposer("warp")
    else:
        skipped["warp"] = "warp-lang is not installed"
    parts = {"basis_householder_qr": _of_product(_householder), "basis_gram_schmidt": _of_product(gram_schmidt)}
    parts["small_eigh"] = _small_eigh
    parts["whole_eigh"] = lambda A, S: jnp.linalg.eigh(A)
    parts.update({f"ritz_decomposition_{k}": _of_product_with_A(f) for k, f in decompositions.items()})
    parts.update({f"ritz_projector_{k}": _ritz_with(threshold, f) for k, f in decompositions.items()})
    result = {
        "batch": a.batch,
        "robot": a.robot,
        "shape": {"A": list(A.shape[1:]), "S": list(S.shape[1:])},
        "dtype": str(A.dtype),
        "device": provenance.device_label(),
        "us_per_env": {},
        "skipped": skipped,
    }
    outputs = {}
    for name, f in parts.items():
        fn = jax.jit(jax.vmap(f))
        outputs[name] = fn(A, S)
        result["us_per_env"][name] = round(timed(fn, A, S, repeats=a.repeats) * 1e6 / a.batch, 4)
    P_h, _ = outputs["ritz_projector_householder_qr"]
    result["against_householder_qr"] = {
        k: {
            "projector_max_abs": float(jnp.max(jnp.abs(outputs[f"ritz_projector_{k}"][0] - P_h))),
            "certified": float(jnp.mean(outputs[f"ritz_projector_{k}"][1])),
        }
        for k in decompositions
    }
    return result


def gram_schmidt(B: jax.Array) -> jax.Array:
    """Q (m, k): orthonormal columns spanning B's (m, k), k <= m, by classical Gram-Schmidt with each column
    orthogonalised twice ("twice is enough": Giraud, Langou, Rozloznik, Comput. Math. Appl. 50, 2005), which
    leaves Q orthonormal to rounding as a Householder QR does. Matrix-vector products only: no library call under
    vmap. The alternative to the Householder QR measured here (not the torque law's: see the docstring above).
    A column that lies in the span of those before it (to rounding) comes out zero, where a Householder QR
    would complete the basis with an arbitrary direction."""
    m, k = B.shape
    Q = jnp.zeros_like(B)
    scale = jnp.max(jnp.abs(B)) * m * jnp.finfo(B.dtype).eps
    for j in range(k):
        v = B[:, j]
        for _ in range(2):
            v = v - Q @ (Q.T @ v)
        norm = jnp.linalg.norm(v)
        Q = Q.at[:, j].set(jnp.where(norm > scale, v / jnp.where(norm > scale, norm, 1.0), 0.0))
    return Q


def _householder(B):
    return jnp.linalg.qr(B)[0]


def _of_product(basis):
    return lambda A, S: basis(A @ S)


def _of_product_with_A(decompose):
    return lambda A, S: decompose(A, A @ S)


def _gram_schmidt_decomposition(A, B):
    """torques.ritz_decomposition with the basis by :func:`gram_schmidt`."""
    Q = gram_schmidt(B)
    AQ = A @ Q
    theta, W = jnp.linalg.eigh(Q.T @ AQ)
    return Q, AQ, theta, W


def _small_eigh(A, S):
    Q = _householder(A @ S)
    return jnp.linalg.eigh(Q.T @ A @ Q)


def _ritz_with(threshold, decompose):
    return lambda A, S: torques.ritz_projector(A, threshold, S, decompose)


if __name__ == "__main__":
    main()
