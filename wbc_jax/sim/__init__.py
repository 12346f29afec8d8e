"""The closed loop: physics engines (``physics``), the loop's data (``state``), one control tick
(``loop``), the horizon on MJX (``mjx_loop``) or on C MuJoCo (``host_loop``), the metrics
(``metrics``), scenes and set-ups (``scenario``) and batched runs on any engine and device mesh
(``runner``)."""
