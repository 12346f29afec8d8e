"""The controller of one tick, stage by stage: gains and references (``gains``, ``references``), the
momentum task (``momentum``), the contact forces (``qp``, ``qp_ipm``, the Warp engines ``qp_warp`` with their kernels
``qp_warp_kernel`` and ``qp_active_set_kernel``, the CPU engine ``qp_eiquadprog``, ``constraints``, ``forces``), the
torques with the postural task in the null space (``torques``; its mass-matrix solve optionally one Warp tile kernel,
``cholesky_warp``, its projector's Ritz decomposition optionally one Warp kernel, ``ritz_warp``; what the Warp
engines share, ``warp_launch``), motion tasks in recursive null spaces
(``hierarchy``, ``tasks``, ``task_rows``, ``task_files``), and ``controller``, which composes them;
its flags, declared once for every job (``flags``). Imports :mod:`wbc_jax.core` and :mod:`wbc_jax.robot` only."""
