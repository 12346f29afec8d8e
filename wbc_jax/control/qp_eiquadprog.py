"""The force QP's CPU engine ``"eiquadprog"``: eiquadprog (the dual active-set method of Goldfarb and Idnani, the QP
solver of TSID's controller; pip ``eiquadprog``, with Eigen's headers from ``cmeel-eigen``) called from inside the
XLA program through XLA's FFI (``qp_eiquadprog.cc``, built at first use by :mod:`wbc_jax.core.native_build`), one
problem after another of a batch.

Why: on the CPU the interior point in XLA runs some 6 Newton steps of about 70 small kernels each (BENCHMARKS.md), while
the whole problem is 6 unknowns and 38 rows of which at most 6 are active: an active-set solve in C++ is a few small
dense updates. The method is the Warp kernel's (:mod:`wbc_jax.control.qp_active_set_kernel`, the GPU's engine
``"warp_active_set"``), and the outputs are the same :class:`wbc_jax.control.qp_ipm.IPMResult`.

    available() -> None, or why the engine cannot run here (no eiquadprog, no Eigen headers, no C++ compiler)
    active_set_eiquadprog(H, g, C, b, tol, weight) -> IPMResult
"""

from __future__ import annotations

import ctypes
import functools
import pathlib
import subprocess
from importlib import metadata

import jax
import jax.numpy as jnp

from wbc_jax.control.qp_ipm import IPMResult, result_of_outputs
from wbc_jax.core import native_build

SOURCE = pathlib.Path(__file__).with_name("qp_eiquadprog.cc")
TARGET = "wbc_eiquadprog_solve"
INSTALL = "pip install eiquadprog cmeel-eigen (the 'eiquadprog' extra)"

_LIBRARY: list = []  # the loaded library, once registered


def _prefix(distribution: str) -> pathlib.Path:
    return pathlib.Path(str(metadata.distribution(distribution).locate_file("cmeel.prefix")))


@functools.cache
def available() -> str | None:
    """None when the engine is built and registered in this process; otherwise why it is not (one line)."""
    if jax.default_backend() != "cpu":
        return (
            f"the force QP's eiquadprog engine runs in CPU programs (JAX's default device here: "
            f"{jax.default_backend()}; on a GPU: qp_engine 'warp_active_set')"
        )
    cxx = native_build.compiler()
    if cxx is None:
        return "the force QP's eiquadprog engine needs a C++ compiler (set $CXX or install g++/clang++)"
    try:
        quadprog_prefix, eigen_prefix = _prefix("eiquadprog"), _prefix("cmeel-eigen")
    except metadata.PackageNotFoundError as err:
        return f"the force QP's eiquadprog engine needs {err.name}: {INSTALL}"
    library = quadprog_prefix / "lib" / "libeiquadprog.so"
    headers = [quadprog_prefix / "include", eigen_prefix / "include" / "eigen3"]
    missing = [str(p) for p in (library, headers[0] / "eiquadprog", headers[1] / "Eigen") if not p.exists()]
    if missing:
        return f"the force QP's eiquadprog engine: {missing} not found ({INSTALL})"
    try:
        built = native_build.build_library(
            cxx,
            SOURCE,
            "wbc_eiquadprog",
            include_dirs=[str(h) for h in headers],
            libraries=[library],
            key=[metadata.version("eiquadprog"), metadata.version("cmeel-eigen"), str(library)],
        )
        lib = ctypes.CDLL(str(built))
    except (OSError, RuntimeError, subprocess.TimeoutExpired) as err:
        return f"building the force QP's eiquadprog engine failed: {err}"
    jax.ffi.register_ffi_target(TARGET, jax.ffi.pycapsule(lib.WbcEiquadprogSolve), platform="cpu")
    _LIBRARY.append(lib)
    return None


def active_set_eiquadprog(
    H: jax.Array, g: jax.Array, C: jax.Array, b: jax.Array, tol: float, weight: jax.Array | None = None
) -> IPMResult:
    """The QP ``min 1/2 x'Hx + g'x s.t. Cx <= b`` by eiquadprog: H (n, n) positive definite, g (n,), C (m, n), b (m,),
    weight (m,) or None (the scaled rows' norms, as :func:`wbc_jax.control.qp_ipm.interior_point`'s); under ``vmap``
    one call over the batch. ``tol``: the largest violation of a row, in the scaled problem, that counts as none.
    Returns :class:`wbc_jax.control.qp_ipm.IPMResult` (``iterations``: eiquadprog's iterations that added a row). float32 or
    float64 data, solved in float64; CPU programs only. Not differentiated (callers pass ``stop_gradient`` data)."""
    problem = available()
    if problem is not None:
        raise RuntimeError(problem)
    dtype = H.dtype
    lead = g.shape[:-1]
    n, m = g.shape[-1], b.shape[-1]
    weighted = weight is not None
    w = jnp.broadcast_to(weight, lead + (m,)).astype(dtype) if weighted else jnp.ones((1, 1), dtype)
    shapes = [
        jax.ShapeDtypeStruct(lead + (n,), dtype),
        jax.ShapeDtypeStruct(lead + (m,), dtype),
        jax.ShapeDtypeStruct(lead + (m,), dtype),
        jax.ShapeDtypeStruct(lead + (3,), jnp.int32),
        jax.ShapeDtypeStruct(lead + (5,), dtype),
    ]
    call = jax.ffi.ffi_call(TARGET, shapes, vmap_method="broadcast_all")
    x, lam, s, flags, stats = call(H, g, C, b, w, tol=float(tol), weighted=weighted)
    return result_of_outputs(x, lam, s, flags, stats)
