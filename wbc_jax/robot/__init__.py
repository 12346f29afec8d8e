"""The robot: the MuJoCo model and its names resolved once (``model``), the free-floating dynamics
terms in the mixed representation (``dynamics``), the contact set (``contacts``) and the scene its
contacts touch (``scene``), and the same robot in Pinocchio (``pinocchio``: the model reduced to the
controller's joints and the state map, JAX-free). Imports only :mod:`wbc_jax.core`."""
