"""Gain tuning: the tuned parameters (``params``), the smooth loss (``loss``), the problem and its
configuration (``config``, ``problem``), gradient training and the pipeline of ``wbc-jax tune``
(``tune``), gradient-free baselines (``baselines``) and the held-out evaluation (``heldout``)."""
