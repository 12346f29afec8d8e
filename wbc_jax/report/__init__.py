"""Host-side output: figures (matplotlib: ``plots``, ``sweep_plots``, ``tuning_plots``, ``limit_plots``)
and rerun recordings (``recording``), numpy in and files out. Nothing here is traced by JAX; jobs
call it after a run."""
