"""The robot: what each robot is (``description``: one :class:`RobotDescription` per robot in
``icub``, ``talos``, registered by name in ``robots``), the MuJoCo model and its names resolved
once (``model``), the free-floating dynamics terms in the mixed representation (``dynamics``), the
contact set (``contacts``), the scene its contacts touch (``scene``), whether a contact set is
physical at the initial posture (``placement``), the theoretical bounds on push recovery
(``bounds``) and the same robot in Pinocchio (``pinocchio``: the model reduced to the controller's
joints and the state map, JAX-free). Imports only :mod:`wbc_jax.core`; nothing outside this layer
names a robot."""
