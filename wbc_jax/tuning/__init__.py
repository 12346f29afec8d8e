"""Gain tuning, in two folders over two shared modules:

* ``config`` (the commands' flags: :class:`~wbc_jax.tuning.config.TuneConfig`, ``HeldoutConfig``) and
  ``store`` (checkpoints, history tables, gain files written once): used by both folders;
* ``algorithms/``: the problem and the methods that solve it: the tuned parameters (``params``,
  ``schedule``), the smooth loss (``loss``), the push distribution and objectives (``problem``,
  ``objectives``, ``windows``), the gradient's estimators (``estimators``) and training (``gradient``),
  the gradient-free searches (``baselines``) and the gradient refining CMA-ES (``hybrid``);
* ``orchestration/``: what runs and judges them: the phases of ``wbc-jax tune`` (``campaign``), the held-out
  evaluation (``heldout``, also ``wbc-jax heldout``), the race's report (``race``), the gradient's
  quality and profile (``quality``, ``profile``).

Algorithms never import orchestration (tests/test_layers.py)."""
