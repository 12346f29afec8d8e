"""Gain tuning's problem and methods: parameters, loss, objectives, the gradient and the searches
(:mod:`wbc_jax.tuning`); they import ``config`` and ``store``, never ``orchestration``."""
