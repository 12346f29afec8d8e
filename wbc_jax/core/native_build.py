"""C++ sources compiled at first use into XLA FFI libraries (the C MuJoCo step, wbc_jax/sim/native.py; eiquadprog's
QP, wbc_jax/control/qp_eiquadprog.py).

Each library is compiled with the system's C++ compiler (``$CXX``, ``c++``, ``g++`` or ``clang++``) against the FFI
headers jaxlib ships, into a folder beside JAX's compilation cache (a temporary folder without one), keyed by the
source, the compiler, jaxlib's version and what the caller adds (its libraries' versions and paths); later
processes load it from there. Installed atomically, so processes that build at once each install a whole library.
"""

from __future__ import annotations

import hashlib
import os
import pathlib
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from importlib import metadata

import jax

BUILD_TIMEOUT_S = 300


def compiler() -> str | None:
    """The C++ compiler: ``$CXX``, else the first of c++, g++, clang++ on the PATH."""
    if os.environ.get("CXX"):
        return shutil.which(os.environ["CXX"]) or os.environ["CXX"]
    return next((path for name in ("c++", "g++", "clang++") if (path := shutil.which(name))), None)


def build_dir() -> pathlib.Path:
    """Where built libraries go: beside JAX's compilation cache, or a temporary folder."""
    cache = jax.config.jax_compilation_cache_dir
    if cache:
        return pathlib.Path(cache) / "wbc_native"
    return pathlib.Path(tempfile.gettempdir()) / f"wbc_jax_native_{os.getuid() if hasattr(os, 'getuid') else 0}"


def build_library(
    cxx: str,
    source: pathlib.Path,
    stem: str,
    *,
    include_dirs: Sequence[str],
    libraries: Sequence[pathlib.Path],
    key: Sequence[str],
) -> pathlib.Path:
    """Compile ``source`` into ``lib<stem>_<hash>.so`` (once per source, compiler, jaxlib and ``key``); its path.

    include_dirs: beside jaxlib's FFI headers; libraries: shared libraries to link, found at run time by their
    folders (rpath). RuntimeError with the compiler's message if it fails."""
    code = source.read_bytes()
    parts = [code, cxx.encode(), metadata.version("jaxlib").encode(), *(str(k).encode() for k in key)]
    digest = hashlib.sha256(b"\0".join(parts)).hexdigest()[:16]
    out = build_dir() / f"lib{stem}_{digest}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(f".{os.getpid()}.tmp")
    cmd = [
        cxx,
        "-O2",
        "-std=c++17",
        "-shared",
        "-fPIC",
        *(f"-I{d}" for d in (jax.ffi.include_dir(), *include_dirs)),
        str(source),
        "-o",
        str(tmp),
        *(str(lib) for lib in libraries),
        *(f"-Wl,-rpath,{lib.parent}" for lib in libraries),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    if proc.returncode != 0:
        tmp.unlink(missing_ok=True)
        raise RuntimeError(f"{' '.join(cmd)} failed: {proc.stderr.strip()[-2000:]}")
    os.replace(tmp, out)  # atomic: processes building at once each install a whole library
    return out
