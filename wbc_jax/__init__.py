"""wbc_jax: whole-body force (momentum-based) balancing control of the iCub in MuJoCo MJX.

Pipeline (one module per stage, imports point backwards):
model -> dynamics -> contacts -> momentum -> qp/forces -> torques -> hierarchy/tasks -> controller
-> physics/rollout -> scenario -> experiments (balance, sweep, tune) -> visualisation.
"""

import os as _os

# XLA:CPU computes the controller's small matrices; Eigen's thread pool there only competes with
# C MuJoCo's threads stepping the physics beside it (rollout.ClosedLoop.run_host), so it is off by
# default. Read when JAX creates its CPU client: importing wbc_jax before running anything in JAX
# applies it; a flag the user set in XLA_FLAGS wins.
if "xla_cpu_multi_thread_eigen" not in _os.environ.get("XLA_FLAGS", ""):
    _os.environ["XLA_FLAGS"] = (_os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false").strip()

__version__ = "0.2.0"
