"""Gain tuning: the tuned parameters (``params``, and the gain schedule on the push state:
``schedule``), the smooth loss (``loss``), the problem and its configuration (``problem``,
``config``), the data-parallel programs (``objectives``), gradient estimators (``estimators``),
short-horizon windows (``windows``), gradient training (``tune``), gradient-free baselines
(``baselines``), the race's hybrid (``hybrid``) and report (``race``), the held-out evaluation
(``heldout``), gradient quality (``quality``), where a step's time goes (``profile``), what a run
keeps on disk (``store``) and the pipeline of ``wbc-jax tune`` (``campaign``)."""
