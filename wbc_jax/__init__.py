"""wbc_jax: whole-body force (momentum-based) balancing control of the iCub in MuJoCo MJX.

Pipeline (one module per stage, imports point backwards):
model -> dynamics -> contacts -> momentum -> qp/forces -> torques -> hierarchy/tasks -> controller
-> physics/rollout -> scenario -> experiments (balance, sweep, tune) -> visualisation.
"""

__version__ = "0.1.0"

import contextlib as _contextlib
import io as _io

# mujoco-mjx 3.17 prints "Failed to import warp" to stdout when the optional Warp backend is
# absent (we use the JAX backend); keep stdout clean for the JSON our commands print.
with _contextlib.redirect_stdout(_io.StringIO()):
    from mujoco import mjx as _mjx  # noqa: F401
