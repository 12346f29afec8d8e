"""wbc_jax: whole-body force (momentum-based) balancing control of the iCub in MuJoCo MJX.

Pipeline (one module per stage, imports point backwards):
model -> dynamics -> contacts -> momentum -> qp/forces -> torques -> hierarchy/tasks -> controller
-> physics/rollout -> scenario -> experiments (balance, sweep, tune) -> visualisation.
"""

__version__ = "0.2.0"
