"""C MuJoCo inside XLA programs: the physics of a tick as an XLA FFI call (``mujoco_ffi.cc``).

    available()                          -> None, or why the native step cannot be used here
    step(handles, ctrl, xfrc, ok)        -> (qpos (B, nq), qvel (B, nv), ok (B,))   one tick's physics
    contacts(handles, after, C, dtype)   -> contact slots (B, C, ...) after it
    step_terms(handles, ctrl, xfrc, ok, slots, ...) -> (qpos, qvel, ok, slots, EngineTerms)
                                            the tick's physics split at mj_step1, with the
                                            controller's dynamics terms from C MuJoCo
    handles(models, datas)               -> (B, 4) uint32: each environment's model and data
    physics_cpu(reset=False)             -> (CPU seconds inside the physics, ticks) so far
    terms_cpu()                          -> CPU seconds extracting the dynamics terms so far

``mujoco_ffi.cc`` is compiled at first use (:mod:`wbc_jax.core.native_build`) against the MuJoCo
library the ``mujoco`` package ships; later processes load it from beside JAX's compilation cache.
The handlers are registered with :func:`jax.ffi.register_ffi_target` by name, so programs that
call them are ordinary XLA programs: JAX's persistent cache and serialised executables work
(programs with Python callbacks get neither). Without a compiler, :func:`available` says so and
the C MuJoCo engine runs its ticks in Python (:mod:`wbc_jax.sim.host_loop`).
"""

from __future__ import annotations

import ctypes
import functools
import pathlib
import subprocess

import jax
import mujoco
import numpy as np

from wbc_jax.core import native_build
from wbc_jax.core.constants import DIVERGED_SPEED
from wbc_jax.robot.dynamics import EngineTerms

SOURCE = pathlib.Path(__file__).with_name("mujoco_ffi.cc")
TARGETS = {
    "wbc_mujoco_step": "WbcMujocoStep",
    "wbc_mujoco_contacts": "WbcMujocoContacts",
    "wbc_mujoco_step_terms": "WbcMujocoStepTerms",
}


def mujoco_library() -> pathlib.Path:
    """The MuJoCo shared library of the ``mujoco`` package (the one its Python bindings load)."""
    folder = pathlib.Path(mujoco.__file__).parent
    found = sorted(
        p for p in folder.iterdir() if p.name.startswith("libmujoco") and (".so" in p.name or p.suffix == ".dylib")
    )
    if not found:
        raise FileNotFoundError(f"no libmujoco shared library in {folder}")
    return found[0]


def _build(cxx: str) -> pathlib.Path:
    """Compile the handlers (once per source, compiler and versions); the library's path."""
    lib = mujoco_library()
    return native_build.build_library(
        cxx,
        SOURCE,
        "wbc_mujoco_ffi",
        include_dirs=[str(pathlib.Path(mujoco.__file__).parent / "include")],
        libraries=[lib],
        key=[mujoco.__version__, str(lib)],
    )


_LIBRARY: list = []  # the loaded library, once registered


@functools.cache
def _register() -> str | None:
    """Build, load and register the handlers once per process: None, or why not."""
    if jax.default_backend() != "cpu":
        return f"the native step runs in CPU programs (JAX's default device here: {jax.default_backend()})"
    cxx = native_build.compiler()
    if cxx is None:
        return "no C++ compiler found (set $CXX or install g++/clang++)"
    try:
        library = ctypes.CDLL(str(_build(cxx)))
    except (OSError, RuntimeError, FileNotFoundError, subprocess.TimeoutExpired) as err:
        return f"building the native C MuJoCo step failed: {err}"
    for name, symbol in TARGETS.items():
        jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(getattr(library, symbol)), platform="cpu")
    for counter in (library.WbcMujocoPhysicsNs, library.WbcMujocoPhysicsTicks, library.WbcMujocoTermsNs):
        counter.restype = ctypes.c_int64
    _LIBRARY.append(library)
    return None


def available() -> str | None:
    """None when the native step is registered in this process; otherwise the reason it is not."""
    return _register()


def physics_cpu(reset: bool = False) -> tuple[float, int]:
    """(CPU seconds the programs' threads spent in the physics of :func:`step`, ticks stepped)
    since the last reset (``reset``: then start again from zero); for timing the closed loop."""
    problem = available()
    if problem is not None:
        raise RuntimeError(problem)
    lib = _LIBRARY[0]
    out = (lib.WbcMujocoPhysicsNs() * 1e-9, int(lib.WbcMujocoPhysicsTicks()))
    if reset:
        lib.WbcMujocoResetCounters()
    return out


def terms_cpu() -> float:
    """CPU seconds the programs' threads spent extracting the dynamics terms in :func:`step_terms`
    (the controller's share of that call; its mj_step1 and mj_step2 count in :func:`physics_cpu`)
    since the counters' last reset."""
    problem = available()
    if problem is not None:
        raise RuntimeError(problem)
    return _LIBRARY[0].WbcMujocoTermsNs() * 1e-9


def handles(models, datas) -> np.ndarray:
    """(B, 4) uint32: the 32-bit halves of each environment's ``mjModel*`` and ``mjData*``."""
    out = np.zeros((len(datas), 4), np.uint32)
    for i, (m, d) in enumerate(zip(models, datas, strict=True)):
        for j, address in enumerate((m._address, d._address)):
            out[i, 2 * j], out[i, 2 * j + 1] = address & 0xFFFFFFFF, address >> 32
    return out


def step(handles, ctrl, xfrc, ok, nq: int, nv: int):
    """One tick's physics of B environments (``HostBatch.step``): ``ctrl`` (B, nu) held over the
    ``xfrc`` (B, n_sub, nbody, 6) body wrenches of each step, environments with ``ok`` (B,) False
    left frozen. Returns (qpos (B, nq), qvel (B, nv)) in ctrl's dtype and ok (B,) (False where the
    tick diverged: the state is restored to the tick's start)."""
    B, dtype = ctrl.shape[0], ctrl.dtype
    out = (
        jax.ShapeDtypeStruct((B, nq), dtype),
        jax.ShapeDtypeStruct((B, nv), dtype),
        jax.ShapeDtypeStruct((B,), np.bool_),
    )
    call = jax.ffi.ffi_call("wbc_mujoco_step", out, has_side_effect=True)
    return call(handles, ctrl, xfrc.astype(dtype), ok, max_speed=np.float64(DIVERGED_SPEED))


def contacts(handles, after, max_contacts: int, dtype):
    """The contact slots of B environments (``HostBatch.contacts``) once ``after`` (an output of
    :func:`step`) exists: points (B, C, 3), world-axes forces on geom 2 (B, C, 3), geom ids
    (B, C, 2) int32."""
    B = handles.shape[0]
    out = (
        jax.ShapeDtypeStruct((B, max_contacts, 3), dtype),
        jax.ShapeDtypeStruct((B, max_contacts, 3), dtype),
        jax.ShapeDtypeStruct((B, max_contacts, 2), np.int32),
    )
    return jax.ffi.ffi_call("wbc_mujoco_contacts", out, has_side_effect=True)(handles, after)


def step_terms(handles, ctrl, xfrc, ok, slots, *, nq: int, nv: int, nbody: int, base_body: int, frames, start=False):
    """One tick's physics of B environments (:func:`step`'s) with C MuJoCo's ``mj_step`` split at
    ``mj_step1``, and the dynamics terms at the new state. The data hold ``mj_step1`` of their state
    between calls: ``start`` (the loop's first call) steps nothing and runs it at the initial state.

    Args:
      handles: (B, 4) uint32. ctrl: (B, nu). xfrc: (B, n_sub, nbody, 6). ok: (B,) bool.
      slots: the last call's contact slots (points (B, C, 3), forces (B, C, 3), geoms (B, C, 2)
        int32), passed on by environments that do not step (C may be 0).
      frames: :class:`wbc_jax.robot.dynamics.Frames` whose Jacobians the controller needs.

    Returns:
      (qpos (B, nq), qvel (B, nv), ok (B,), the contact slots after the tick (those of
      :func:`contacts`), :class:`EngineTerms`), in ctrl's dtype.
    """
    B, dtype, C, k = ctrl.shape[0], ctrl.dtype, slots[0].shape[1], len(frames)
    shapes = [(B, nq), (B, nv), (B,), (B, C, 3), (B, C, 3), (B, C, 2)]
    shapes += [(B, nv, nv), (B, nv), (B, nv), (B, nbody, 3), (B, nbody, 3, 3), (B, 3), (B, k, 6, nv)]
    shapes += [(B, k, 6), (B, 6, nv), (B, 3)]
    types = {2: np.bool_, 5: np.int32}
    out = tuple(jax.ShapeDtypeStruct(shape, types.get(i, dtype)) for i, shape in enumerate(shapes))
    call = jax.ffi.ffi_call("wbc_mujoco_step_terms", out, has_side_effect=True)
    res = call(
        handles,
        ctrl,
        xfrc.astype(dtype),
        ok,
        slots[0].astype(dtype),
        slots[1].astype(dtype),
        slots[2],
        max_speed=np.float64(DIVERGED_SPEED),
        start=bool(start),
        base_body=np.int64(base_body),
        frame_bodies=np.asarray(frames.bodies, np.int64),
        frame_points=np.asarray(frames.points, np.float64).reshape(-1),
    )
    return res[0], res[1], res[2], tuple(res[3:6]), EngineTerms(*res[6:])
