"""What runs gain tuning and judges its sets: the phases of ``wbc-jax tune``, the held-out
evaluation, the race's report, the gradient's quality and profile (:mod:`wbc_jax.tuning`)."""
