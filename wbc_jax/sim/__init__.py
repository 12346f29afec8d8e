"""The closed loop: physics engines (``physics``), the loop's data (``state``), one control tick
(``loop``), the horizon on MJX (``mjx_loop``) or on C MuJoCo (``host_loop``: a Python loop of ticks,
or ``host_scan``: one compiled program calling C MuJoCo through ``native``), the metrics
(``metrics``), scenes and set-ups (``scenario``), batched runs on any engine and device mesh
(``runner``, one program per device: ``per_device``, under a ``watchdog``; MJX-Warp's CUDA graph
cache: ``warp_graphs``; MuJoCo Warp's step in two phases: ``warp_split``) and compiled programs kept on disk
(``executables``)."""
