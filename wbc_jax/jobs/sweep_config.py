"""The configuration of a push-recovery sweep (``wbc-jax push-sweep``; ``wbc-jax envelope`` uses
the same fields): the grid of pushes, the gain sets, the plant's variations, the engine and the
output folder. Its fields are the command's flags; :meth:`SweepConfig.check` validates them
before anything loads or compiles."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from wbc_jax.control.controller import ControllerConfig
from wbc_jax.control.flags import ControllerFlags
from wbc_jax.core import constants as limits
from wbc_jax.core.options import check_options, flat_dict, nested, option
from wbc_jax.jobs import grids, runs
from wbc_jax.robot import model
from wbc_jax.robot.robots import robot_option
from wbc_jax.sim import physics, scenario, warp_graphs, watchdog
from wbc_jax.sim.state import HOST_LOOPS

SWEEP_TASKS = ("stand", "one-foot")
# The one-foot task (references.make_schedule) balances on the left foot from 7 to 9 s.
ONE_FOOT_WINDOW = (7.0, 9.0)
SUPPORTS = ("two-feet", "left-foot")
MAX_ENVS = 10_000_000  # a grid larger than this is a typo (its scenarios alone take ~3 GB of memory)
MAX_QUEUE = 1024


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """What a sweep covers; the defaults are the README's main job (a laptop CPU in a minute).
    The CLI flags of ``wbc-jax push-sweep`` are generated from these fields, and their declared
    ranges are checked by :meth:`check`."""

    robot: str = robot_option()
    magnitudes: tuple[float, ...] = grids.magnitudes_option((20.0, 60.0, 100.0), "push force grid [N]: LO HI N")
    directions: tuple[float, ...] = grids.directions_option((0.0, 90.0, 180.0, 270.0))
    elevation: float = option(0.0, "push elevation [deg] (+90: straight up)", ge=-90.0, le=90.0, unit="deg")
    push_duration: float = grids.push_duration_option()
    push_onset: float = grids.push_onset_option()
    body: str = option(
        "trunk",
        "pushed body: a body of the robot or a role (trunk, pelvis, left_hand, right_thigh)",
        names=model.pushable_bodies,
    )
    gains: str | None = option(None, "gains JSON file (the first gain set)", metavar="FILE", input_file=True)
    gain_sets: int = option(1, "gain sets: the first, then seeded log-uniform scalings of it", ge=1, le=MAX_ENVS)
    gain_scale_range: tuple[float, float] = option(
        (0.5, 2.0),
        "range of those scalings",
        nargs=2,
        ge=limits.GAIN_SCALE_RANGE[0],
        le=limits.GAIN_SCALE_RANGE[1],
        ordered=True,
    )
    joint_noise: float = option(0.0, "initial joint noise std [rad]", ge=0.0, le=limits.MAX_JOINT_NOISE_RAD, unit="rad")
    friction: tuple[float, float] = option(
        (1.0, 1.0),
        "floor friction range",
        nargs=2,
        metavar=("LO", "HI"),
        ge=limits.FRICTION_RANGE[0],
        le=limits.FRICTION_RANGE[1],
        ordered=True,
    )
    mass_scale: tuple[float, float] = option(
        (1.0, 1.0),
        "plant mass scale range",
        nargs=2,
        metavar=("LO", "HI"),
        ge=limits.MASS_SCALE_RANGE[0],
        le=limits.MASS_SCALE_RANGE[1],
        ordered=True,
    )
    horizon: float = option(1.5, "seconds per rollout", gt=0.0, le=limits.MAX_HORIZON_S, unit="s")
    task: str = option(
        "stand",
        "two feet (stand) or pushed in the single-support phase of the one-foot task "
        "(7-9 s: e.g. --push-onset 7.5 --horizon 9)",
        choices=SWEEP_TASKS,
    )
    controller: ControllerFlags = nested(ControllerFlags())
    solver_iterations: int | None = option(
        None, "contact solver Newton iterations (default: the model's, 4)", ge=1, le=limits.MAX_SOLVER_ITERATIONS
    )
    seed: int = option(0, "seed of the random perturbations", ge=0, le=limits.MAX_SEED)
    chunk_size: int = option(
        12,
        "environments per compiled batch (at most the sweep's; its memory is estimated "
        "and checked before it is allocated)",
        ge=1,
        le=MAX_ENVS,
    )
    queue: int = option(
        1,
        "scenarios per batch slot (MJX backends): a fallen or diverged robot is retired and its slot "
        "starts the next scenario; same outcomes, fewer physics steps (1: off)",
        ge=1,
        le=MAX_QUEUE,
    )
    backend: str = option(
        "auto", "physics engine (auto: C MuJoCo on a CPU, MJX-Warp/JAX on a GPU)", choices=physics.BACKENDS
    )
    host_loop: str = option(
        "auto",
        "C MuJoCo engine: each chunk as one compiled program, or a Python loop of ticks with threaded physics "
        "(auto: compiled where the native step builds)",
        choices=HOST_LOOPS,
    )
    out: str | None = option("runs/push_sweep", "output folder (a sweep resumes there)")
    stall_timeout_s: float | None = option(
        None,
        "seconds a chunk may run on a device before the run stops with an error naming the device and the "
        f"chunk (default: max({watchdog.MIN_STALL_S:g} s, {watchdog.STALL_FACTOR:g}x the slowest finished chunk), "
        f"{watchdog.FIRST_CHUNK_STALL_S:g} s for the first; compiling gets at least {watchdog.COMPILE_STALL_S:g} s)",
        gt=0.0,
        le=watchdog.MAX_STALL_S,
        unit="s",
    )
    warp_graph_mode: str = option(
        "warp",
        "who captures MJX-Warp's CUDA graphs: Warp (per GPU and buffer addresses; MJX's default), JAX "
        "(XLA's command buffers) or none; a diagnostic of issue 45",
        choices=warp_graphs.GRAPH_MODES,
    )
    warp_graph_cache: int | None = option(
        None,
        "CUDA graphs each MJX-Warp foreign call keeps, for all GPUs of the process together (0: no bound; "
        "default: Warp's 32 on one GPU, 32 per GPU on several); it changes no result, only the speed",
        ge=0,
        le=warp_graphs.MAX_GRAPH_CACHE,
    )
    simulate_stall: tuple[int, int] | None = option(
        None,
        "test of the watchdog: device DEVICE (its index in the run's devices) blocks in chunk CHUNK until "
        "--stall-timeout-s ends the run",
        nargs=2,
        metavar=("CHUNK", "DEVICE"),
        ge=0,
        le=MAX_ENVS,
    )

    KIND: ClassVar[str] = "sweep"  # the run kind of its output folder (jobs/runs.py)
    # Fields that bound or test how a run proceeds, not what it computes: no part of the fingerprint.
    # The Warp graph settings launch the same kernels otherwise (issue 45's diagnostics): an older run resumes.
    PROCEDURE: ClassVar[tuple[str, ...]] = ("stall_timeout_s", "simulate_stall", "warp_graph_mode", "warp_graph_cache")

    def check(self) -> None:
        """Every check that compiles nothing (run first, before any file is written): the declared
        ranges, then what ties the flags together."""
        check_options(self)
        push_end = self.push_onset + self.push_duration
        if self.horizon <= push_end:
            raise ValueError(
                f"--horizon {self.horizon:g} s must end after the push (--push-onset {self.push_onset:g} "
                f"+ --push-duration {self.push_duration:g} s)"
            )
        if abs(self.elevation) == 90.0 and len(self.directions) > 1:
            raise ValueError(
                f"--elevation {self.elevation:g} is a vertical push, the same at every azimuth: use "
                f"--directions 1 (got {len(self.directions)})"
            )
        if self.size > MAX_ENVS:
            gb = self.size * 300 / 1e9  # bytes of scenario data per environment, roughly
            raise ValueError(
                f"the grid has {self.size:,} environments (about {gb:,.0f} GB of scenarios), more than "
                f"{MAX_ENVS:,}; use a coarser grid"
            )
        if self.task == "one-foot":
            lo, hi = ONE_FOOT_WINDOW
            if not (lo <= self.push_onset and push_end <= hi):
                raise ValueError(
                    f"one-foot sweeps push during the single-support phase {lo}-{hi} s of the "
                    f"one-foot task: push onset {self.push_onset} s + duration "
                    f"{self.push_duration} s is outside it (e.g. --push-onset 7.5 --horizon 9)"
                )
        backend = physics.resolve_backend(self.backend)
        for flag, value, default in (
            ("--warp-graph-cache", self.warp_graph_cache, None),
            ("--warp-graph-mode", self.warp_graph_mode, "warp"),
        ):
            if value != default and backend != "warp":
                raise ValueError(
                    f"{flag} sets MJX-Warp's CUDA graphs: it needs --backend warp (--backend {self.backend} "
                    f"runs {backend} here)"
                )
        if self.host_loop != "auto" and backend != "mujoco":
            raise ValueError(
                f"--host-loop {self.host_loop} sets how the C MuJoCo engine runs the ticks: it needs --backend "
                f"mujoco (--backend {self.backend} runs {backend} here)"
            )
        if self.queue > 1 and backend == "mujoco":
            raise ValueError(
                f"--queue {self.queue} (scenarios per batch slot) needs an MJX backend: --backend jax or "
                f"warp (--backend {self.backend} runs C MuJoCo here)"
            )
        self.controller_config()
        runs.check_output_dir(self.out, self.KIND, self.fingerprint())

    def fingerprint(self) -> dict:
        """What determines the results (:func:`wbc_jax.jobs.runs.fingerprint`): the engine as it resolves
        here (``auto`` on a CPU is ``mujoco``)."""
        fields = {k: v for k, v in flat_dict(self).items() if k not in self.PROCEDURE}
        return runs.fingerprint(
            {**fields, "backend": physics.resolve_backend(self.backend), "dtype": str(scenario.float_dtype())},
            [self.gains, self.controller.tasks],
            self.robot,
        )

    def watchdog(self, chunk: int, finished_run_s: list[float]) -> watchdog.Watchdog:
        """The watchdog of chunk ``chunk``, given the run seconds of the chunks finished before it in
        this process (:func:`wbc_jax.sim.watchdog.stall_bound`)."""
        bound = watchdog.stall_bound(self.stall_timeout_s, finished_run_s)
        return watchdog.Watchdog(chunk, bound, warm=bool(finished_run_s), simulate_stall=self.simulate_stall)

    def controller_config(self, base: ControllerConfig | None = None) -> ControllerConfig:
        """``base`` (default: the defaults) with this sweep's controller settings."""
        return self.controller.config(base)

    @property
    def size(self) -> int:
        return len(self.magnitudes) * len(self.directions) * self.gain_sets

    @property
    def batch_size(self) -> int:
        """Environments per compiled batch: the chunk size, never more than the sweep holds."""
        return min(self.chunk_size, self.size)

    @property
    def perturbs_plant(self) -> bool:
        return self.friction != (1.0, 1.0) or self.mass_scale != (1.0, 1.0)


def default_config() -> SweepConfig:
    return SweepConfig()
