"""The jobs of the command line: run folders (``runs``), a balancing run (``balance``), batched
push-recovery sweeps (``sweep``, ``push_grid``, ``sweep_table``), the recovery envelope
(``envelope``), the physical limit of push recovery by trajectory optimisation (``limit``,
``trajopt``, ``limit_rounds``, ``limit_table``) and recordings of any run (``view``)."""
