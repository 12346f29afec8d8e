"""wbc_jax: whole-body force (momentum-based) balancing control of torque-controlled humanoids in MuJoCo MJX
(one description per robot in ``wbc_jax/robot/``; jobs choose it with ``--robot``).

The subpackages follow the flow of data; each imports only those before it
(tests/test_layers.py):

    core -> robot -> control -> sim -> report -> jobs -> tuning -> commands -> cli

``core`` numbers, types, helpers, results on disk; ``robot`` the model, dynamics terms and
contacts; ``control`` one controller tick (momentum task, contact forces, torques, motion tasks);
``sim`` the closed loop on three physics engines and batched runs; ``report`` figures and rerun
recordings; ``jobs`` balance, push sweep, envelope, the physical limit of push recovery, view;
``tuning`` gain tuning and its held-out evaluation; ``commands`` one module per command of the
``wbc-jax`` command line (``cli``), each with the same shape, in one registry.

The names below are the public surface, imported on first use (``import wbc_jax`` stays light):

    robot = wbc_jax.load_robot("talos")
    st = wbc_jax.setup("sinusoid", duration=5.0)
    result = wbc_jax.run(st, wbc_jax.single(st))
"""

import importlib

__version__ = "0.3.0"

_PUBLIC = {
    "load_robot": "wbc_jax.robot.model",
    "Robot": "wbc_jax.robot.model",
    "ContactSet": "wbc_jax.robot.contacts",
    "Gains": "wbc_jax.control.gains",
    "default_gains": "wbc_jax.control.gains",
    "load_gains": "wbc_jax.control.gains",
    "ControllerConfig": "wbc_jax.control.controller",
    "make_controller": "wbc_jax.control.controller",
    "SimConfig": "wbc_jax.sim.state",
    "Push": "wbc_jax.sim.state",
    "Scenario": "wbc_jax.sim.state",
    "PhysicsConfig": "wbc_jax.sim.physics",
    "load_scene": "wbc_jax.sim.scenario",
    "setup": "wbc_jax.sim.scenario",
    "single": "wbc_jax.sim.scenario",
    "make_push": "wbc_jax.sim.scenario",
    "run": "wbc_jax.sim.runner",
    "summarize": "wbc_jax.sim.metrics",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'wbc_jax' has no attribute {name!r}; public names: {__all__}")


def __dir__():
    return sorted([*globals(), *__all__])
