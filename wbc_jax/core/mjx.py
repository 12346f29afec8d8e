"""MJX, imported once with stdout kept clean: mujoco-mjx prints "Failed to import warp" to stdout
when the optional Warp backend is absent, which would corrupt the JSON our commands print."""

import contextlib
import io

with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx  # noqa: F401
