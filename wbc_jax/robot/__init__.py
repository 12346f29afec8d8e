"""The robot: the MuJoCo model and its names resolved once (``model``), the free-floating dynamics
terms in the mixed representation (``dynamics``), the contact set (``contacts``) and the scene its
contacts touch (``scene``). Imports only :mod:`wbc_jax.core`."""
