"""Compiled programs kept on disk, so a second run of a job starts without tracing or compiling.

    compiled(name, key_parts, args, lower) -> jax.stages.Compiled

JAX's persistent compilation cache (:func:`wbc_jax.sim.runner.enable_compilation_cache`) skips
XLA's compilation on a second run but not the tracing and lowering before it, which cost seconds
for the closed loop. Here the compiled executable itself is serialised
(:mod:`jax.experimental.serialize_executable`) into ``wbc_executables/`` inside JAX's cache folder
and loaded back by a key computed without tracing: the caller's key parts (a loop's
``structure_key``), the arguments' tree, shapes and dtypes, the source of this package, the
versions of jax, jaxlib and MuJoCo, the device, ``XLA_FLAGS``, the CPU and the float settings.
Where JAX's persistent cache is off, nothing is written. A file that cannot be loaded (another
jaxlib, a truncated write) is compiled again and replaced.

Two faults of jax 0.9.2's XLA:CPU are worked around here. An executable that JAX loaded from its
persistent cache serialises into a program that fails to run ("Function ... not found"), so the
programs saved here are compiled with JAX's persistent cache bypassed. And jaxlib fills its LAPACK
kernels' function pointers when a program using them is lowered; a program
loaded without lowering anything would call a null pointer (a segmentation fault in the
controller's LU solves, jax 0.9.2), so :func:`compiled` fills them first.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import pathlib
import pickle
import platform
import warnings
from collections.abc import Callable
from importlib import metadata

import jax
import numpy as np
from jax.experimental import serialize_executable

PACKAGE = pathlib.Path(__file__).resolve().parent.parent
FOLDER = "wbc_executables"


# The package's layers whose code is traced into programs (jobs, tuning and the CLI only call them).
TRACED = ("core", "robot", "control", "sim")


@functools.cache
def source_digest(layers: tuple[str, ...] = TRACED) -> str:
    """sha256 of the Python and C++ sources of ``layers`` (default: those traced into every program; a
    program compiled from other code never loads). Programs that trace more code (the tuning objectives)
    add the digest of their own layers to their key."""
    h = hashlib.sha256()
    paths = [p for layer in layers for p in (PACKAGE / layer).rglob("*") if p.suffix in (".py", ".cc")]
    for path in sorted(paths):
        h.update(str(path.relative_to(PACKAGE)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


@functools.cache
def _machine() -> str:
    """The versions, device and CPU a compiled program is bound to."""
    versions = [f"{name}={metadata.version(name)}" for name in ("jax", "jaxlib", "mujoco")]
    device = jax.devices()[0]
    cpu = platform.machine()
    try:  # an executable compiled for other CPU features may not run here (XLA:CPU)
        flags = [line for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("flags")]
        cpu += hashlib.sha256(flags[0].encode()).hexdigest()[:16] if flags else ""
    except OSError:
        pass
    return "|".join([*versions, device.platform, device.device_kind, str(len(jax.devices())), cpu])


def program_key(name: str, key_parts, args) -> str:
    """The file name of a program: everything that shapes it, without tracing it."""
    leaves, tree = jax.tree_util.tree_flatten(args)
    shapes = [(tuple(np.shape(x)), str(x.dtype if hasattr(x, "dtype") else np.asarray(x).dtype)) for x in leaves]
    parts = [
        name,
        repr(key_parts),
        str(tree),
        repr(shapes),
        source_digest(),
        _machine(),
        os.environ.get("XLA_FLAGS", ""),
        str(jax.config.jax_enable_x64),
        str(jax.config.jax_default_matmul_precision),
    ]
    return f"{name}-{hashlib.sha256(chr(0).join(parts).encode()).hexdigest()}"


@functools.cache
def _init_lapack() -> None:
    """Fill jaxlib's LAPACK function pointers (what lowering a linear solve does)."""
    from jax._src.lib import lapack

    lapack.prepare_lapack_call("getrf_ffi", np.dtype(np.float32))


@contextlib.contextmanager
def _persistent_cache_bypassed():
    """Compile without reading (or writing) JAX's persistent cache."""
    from jax._src import compilation_cache

    before = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    compilation_cache.reset_cache()
    try:
        yield
    finally:
        jax.config.update("jax_enable_compilation_cache", before)
        compilation_cache.reset_cache()


def default_folder() -> pathlib.Path | None:
    """Where serialised programs live: ``wbc_executables/`` in JAX's persistent cache folder
    (None: the persistent cache is off)."""
    cache = jax.config.jax_compilation_cache_dir
    return pathlib.Path(cache) / FOLDER if cache else None


def _devices_of(program: jax.stages.Compiled) -> list:
    """The devices a compiled program runs on, by id: where its loaded copy must run too (left to
    itself, a deserialised program runs on every device of the backend and expects a shard of each
    argument per device)."""
    shardings = jax.tree_util.tree_leaves(program.input_shardings)
    return sorted({d for sharding in shardings for d in sharding.device_set}, key=lambda d: d.id)


def compiled(
    name: str, key_parts, args, lower: Callable[[], jax.stages.Lowered], folder: pathlib.Path | None = None
) -> jax.stages.Compiled:
    """The compiled program ``lower().compile()``, loaded from disk when an earlier process
    compiled it under the same key (:func:`program_key`), else compiled and saved.

    Args:
      name: the program's name (file prefix).
      key_parts: what shapes the program besides its arguments (e.g. a loop's structure_key);
        anything with a stable ``repr``.
      args: the arguments (arrays or ShapeDtypeStructs), for their tree, shapes and dtypes.
      lower: returns the lowered program (called only when it must be compiled).
      folder: where the programs are kept (None: :func:`default_folder`).
    """
    where = default_folder() if folder is None else pathlib.Path(folder)
    path = None if where is None else where / program_key(name, key_parts, args)
    if path is not None and path.exists():
        try:
            payload, in_tree, out_tree, platform_name, device_ids = pickle.loads(path.read_bytes())
            by_id = {d.id: d for d in jax.devices(platform_name)}
            _init_lapack()
            return serialize_executable.deserialize_and_load(
                payload, in_tree, out_tree, backend=platform_name, execution_devices=[by_id[i] for i in device_ids]
            )
        except Exception as err:
            warnings.warn(f"recompiling {name}: the saved program {path} did not load ({err})", stacklevel=2)
    if path is None:
        return lower().compile()
    lowered = lower()
    with _persistent_cache_bypassed():
        program = lowered.compile()
    try:
        devices = _devices_of(program) or jax.devices()[:1]  # a program without arguments: the default device
        payload = pickle.dumps((*serialize_executable.serialize(program), devices[0].platform, [d.id for d in devices]))
    except (NotImplementedError, ValueError, pickle.PicklingError) as err:  # e.g. hoisted constants
        warnings.warn(f"{name} is not kept on disk: {err}", stacklevel=2)
        return program
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_bytes(payload)
    os.replace(tmp, path)  # atomic: a reader never sees half a file
    return program
