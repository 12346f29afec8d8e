"""MJX, imported on first use with stdout kept clean, and put on this process's own device.

``mjx`` below stands for ``mujoco.mjx``: the module is imported when one of its names is first
used (tracing a program that uses MJX), not when the package is imported. A run whose compiled
programs load from disk (:mod:`wbc_jax.sim.executables`) never imports it, which saves a second
of start-up (MJX imports trimesh and networkx).

mujoco-mjx prints "Failed to import warp" to stdout when the optional Warp backend is absent,
which would corrupt the JSON our commands print. MJX's ``put_model``/``make_data`` place their
arrays on ``jax.devices()[0]``, which after ``jax.distributed.initialize`` belongs to process 0
only: every other process would then close its programs over arrays it cannot address. The
package calls :func:`put_model` and :func:`make_data` below, which place them on this process's
first local device instead (the same device in a one-process run).
"""

import contextlib
import functools
import importlib
import io


@functools.cache
def module():
    """``mujoco.mjx``, imported once with stdout captured."""
    with contextlib.redirect_stdout(io.StringIO()):
        return importlib.import_module("mujoco.mjx")


class _Module:
    """``mujoco.mjx`` imported on first attribute access."""

    def __getattr__(self, name):
        return getattr(module(), name)


mjx = _Module()


def local_device():
    """This process's first device (``jax.devices()[0]`` in a one-process run)."""
    import jax

    return jax.local_devices()[0]


def put_model(m, **kwargs):
    """``mjx.put_model`` on :func:`local_device` (unless ``device`` is given)."""
    kwargs.setdefault("device", local_device())
    return mjx.put_model(m, **kwargs)


def make_data(m, **kwargs):
    """``mjx.make_data`` on :func:`local_device` (unless ``device`` is given)."""
    kwargs.setdefault("device", local_device())
    return mjx.make_data(m, **kwargs)
