"""The robot: what each robot is (``description``: one :class:`RobotDescription` per robot in
``icub.py``, ``talos.py``, registered by name in ``robots``), the MuJoCo model and its names resolved
once (``model``), the free-floating dynamics terms in the mixed representation (``dynamics``), the
contact set (``contacts``) and the scene its contacts touch (``scene``). Imports only
:mod:`wbc_jax.core`; nothing outside this layer names a robot."""
