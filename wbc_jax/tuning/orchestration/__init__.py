"""What runs gain tuning and judges its sets (:mod:`wbc_jax.tuning`): the phases of ``wbc-jax tune``
(``campaign``), the held-out evaluation, also ``wbc-jax heldout`` (``heldout``) and its summary
(``heldout_report``), whether the loss predicts survival (``prediction``), the race's report (``race``),
the gradient's quality against zeroth-order estimates (``quality``), where a step's time goes
(``profile``) and each phase's seconds, kept across re-runs (``timings``)."""
