"""Host-side output: figures (matplotlib) and rerun recordings, numpy in and files out. Nothing
here is traced by JAX; jobs call it after a run."""
