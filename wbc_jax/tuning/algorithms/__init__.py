"""Gain tuning's problem and the methods that solve it (:mod:`wbc_jax.tuning`): the tuned parameters
(``params``, and the gain schedule on the push state: ``schedule``), the smooth loss (``loss``), the push
distribution and the closed loop with its loss trace (``problem``), the data-parallel programs
(``objectives``), short-horizon windows (``windows``), the gradient's estimators (``estimators``) and
training (``gradient``), the gradient-free searches (``baselines``) and the gradient refining CMA-ES's set
(``hybrid``). They import the shared config and store, never the orchestration folder."""
