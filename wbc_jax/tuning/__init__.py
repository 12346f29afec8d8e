"""Gain tuning, in two folders over two shared modules:

* ``config`` and ``heldout_config`` (the commands' flags: :class:`~wbc_jax.tuning.config.TuneConfig`,
  :class:`~wbc_jax.tuning.heldout_config.HeldoutConfig`) and ``store`` (checkpoints, history tables, gain
  files written once): used by both folders;
* ``algorithms``: the problem and the methods that solve it (its docstring lists its modules);
* ``orchestration``: what runs and judges them (its docstring lists its modules).

Algorithms never import orchestration (tests/test_layers.py)."""
