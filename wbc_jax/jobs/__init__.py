"""The jobs of the command line: run folders (``runs``), the one chunk runner of batched jobs
(``chunks``), the robot model's summary (``info``), a balancing run (``balance``), batched
push-recovery sweeps (``sweep``, ``sweep_config``, ``grids``, ``sweep_table``), the recovery envelope
(``envelope``), the physical limit of push recovery by trajectory optimisation (``limit``,
``trajopt``, ``limit_rounds``, ``limit_table``, and the crocoddyl cross-check ``limit_ddp``) and
recordings of any run (``view``)."""
