"""Gradient-free baselines of gain tuning: CMA-ES (evosax) and random search, given the gradient's
budget of simulated physics steps and of wall time, or (``--budget-s``) a wall-time budget of their own.

Both search the unconstrained parameters of the gradient (:mod:`wbc_jax.tuning.algorithms.params`, or the gain
schedule of :mod:`wbc_jax.tuning.algorithms.schedule`: same groups, bounds and stability conditions) on the same
loss (:mod:`wbc_jax.tuning.algorithms.loss`), on their fastest engine (``--search-backend``: MJX-Warp on a GPU,
MJX-JAX elsewhere). A generation draws b fresh pushes of the training distribution and evaluates P
candidates plus the current solution on them (common random numbers), in one forward program of
(P + 1) b rollouts (:func:`wbc_jax.tuning.algorithms.objectives.make_population_objective`):

* ``cmaes``: evosax's CMA-ES (population P, initial step ``es_sigma``); the current solution is
  its mean, told nothing (only the P asked candidates are told);
* ``random``: a (1 + P) random search: P Gaussian perturbations (std ``es_sigma``) of the
  incumbent; the best of them replaces it when it beats the incumbent on the same pushes.

A generation costs (P + 1) b rollouts of the horizon's physics steps. The run goes on until both
budgets of the gradient run (simulated steps, and, with ``wall_budget``, wall time including
compilation) are spent, or until ``budget_s`` seconds; the current solution after each generation is
kept, so that the gain sets at equal simulated steps, at equal wall time and at each snapshot time
are all read from one run. Resumable (checkpoint.npz, history.csv).
"""

from __future__ import annotations

import math
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from wbc_jax.sim import runner
from wbc_jax.tuning import config, store
from wbc_jax.tuning.algorithms import objectives
from wbc_jax.tuning.algorithms import problem as tp
from wbc_jax.tuning.algorithms.gradient import at_time, forward_backend

KINDS = ("cmaes", "random")
STREAMS = {"cmaes": 1, "random": 2}  # tuning_problem.batch_rng streams
HISTORY_COLUMNS = (
    "generation",
    "loss",
    "best_candidate_loss",
    "median_candidate_loss",
    "survival_rate",
    "upright_rate",
    "step_size",
    "gen_s",
    "sim_steps",
    "wall_s",
)
PENALTY = 1e6  # fitness of a candidate whose loss is not finite


def _finite_fitness(obj: jax.Array) -> jax.Array:
    return jnp.where(jnp.isfinite(obj), obj, PENALTY)


class _CMAES:
    """evosax CMA-ES over a flat vector (D,); state: evosax's."""

    def __init__(self, p0: jax.Array, population: int, sigma: float):
        from evosax.algorithms import CMA_ES

        self.es = CMA_ES(population_size=population, solution=p0)
        self.params = self.es.default_params.replace(std_init=jnp.asarray(sigma, p0.dtype))
        self.p0 = p0

    def init(self, key):
        return self.es.init(key, self.p0, self.params)

    def ask(self, key, state):
        return self.es.ask(key, state, self.params)

    def tell(self, key, pop, fitness, state):
        return self.es.tell(key, pop, fitness, state, self.params)[0]

    @staticmethod
    def current(state):
        return state.mean

    @staticmethod
    def step_size(state) -> float:
        return float(state.std)


class _RandomSearch:
    """(1 + P) random search: state = (incumbent (D,), generation ())."""

    def __init__(self, p0: jax.Array, population: int, sigma: float):
        self.p0, self.population, self.sigma = p0, population, sigma

    def init(self, key):
        return {"incumbent": self.p0, "generation": jnp.zeros((), jnp.int32)}

    def ask(self, key, state):
        z = jax.random.normal(key, (self.population, self.p0.size), self.p0.dtype)
        return state["incumbent"] + self.sigma * z, state

    def tell(self, key, pop, fitness, state, incumbent_fitness=None):
        best = jnp.argmin(fitness)
        better = fitness[best] < incumbent_fitness
        return {"incumbent": jnp.where(better, pop[best], state["incumbent"]), "generation": state["generation"] + 1}

    @staticmethod
    def current(state):
        return state["incumbent"]

    def step_size(self, state) -> float:
        return float(self.sigma)


def budget_generations(problem: tp.Problem, sim_steps: int) -> int:
    """Generations whose simulated steps reach ``sim_steps``."""
    tc = problem.tc
    per_gen = (tc.population + 1) * tc.candidate_batch * problem.steps_per_rollout
    return max(1, math.ceil(sim_steps / per_gen))


NOT_SEARCH = (
    "out",
    "phases",
    "steps",
    "wall_budget",
    "eval_pushes",
    "eval_horizon",
    "snapshots_s",
    "lr",
    "clip_norm",
    "estimator",
    "smoothing_sigma",
    "bias_factor",
    "window_s",
    "windows",
    "terminal_weight",
    "checkpoint",
    "env_clip",
    "quality_pushes",
    "quality_directions",
)


def search(
    problem: tp.Problem,
    kind: str,
    out,
    *,
    budget: dict,
    progress: bool = True,
    max_generations: int | None = None,
    evaluate_fn=None,
    mesh=None,
    times=(),
) -> dict:
    """Run (or resume) a gradient-free search into ``out`` until ``budget`` {"sim_steps",
    "wall_s"} is spent, or with ``tc.budget_s`` until that wall time (or ``max_generations``).
    ``evaluate_fn``: an objective with :func:`~wbc_jax.tuning.algorithms.objectives.make_population_objective`'s
    signature (tests); default: that one on ``--search-backend``, compiled here.

    Returns {"history": rows, "equal_steps": {...}, "equal_wall": {...}, "compile_s"}; each
    "equal_*" entry holds the generation, its sim_steps and wall_s, and "controls": (Gains,
    regularisation (2,)) of the current solution after it."""
    from tqdm.auto import tqdm

    if kind not in KINDS:
        raise ValueError(f"unknown baseline {kind!r}; valid: {list(KINDS)}")
    tc = problem.tc
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    p0_tree = problem.init_params()
    p0, unravel = ravel_pytree(p0_tree)
    strategy = (_CMAES if kind == "cmaes" else _RandomSearch)(p0, tc.population, tc.es_sigma)
    key0 = jax.random.key(tc.seed * 1000 + STREAMS[kind])
    state = strategy.init(key0)
    key = f"{problem.key}-{kind}-{config.config_key(tc, exclude=NOT_SEARCH)}"
    ckpt, hist_path = out / "checkpoint.npz", out / "history.csv"
    start, rows, snapshots, compile_s = 0, [], np.zeros((0, p0.size)), None
    if ckpt.exists():
        state, start, extra = store.load_checkpoint(ckpt, state, key)
        rows = store.read_csv(hist_path)[:start]
        snapshots = extra["snapshots"][:start]
        compile_s = float(extra["compile_s"])
    b = tc.candidate_batch
    per_gen = (tc.population + 1) * b * problem.steps_per_rollout
    if evaluate_fn is None:
        fwd = tp.with_backend(problem, forward_backend(tc))
        evaluate = jax.jit(objectives.make_population_objective(fwd, tc.population + 1, b, mesh))
    else:
        evaluate = evaluate_fn

    def batch(g):
        scen, _ = tp.sample_pushes(
            tc, problem.robot, problem.table, tp.batch_rng(tc.seed, STREAMS[kind], g), b, problem.setup.dtype
        )
        return objectives.cast_batch(scen, problem.setup.dtype)

    def done(g):
        if tc.budget_s > 0:
            spent = bool(rows) and float(rows[-1]["wall_s"]) >= tc.budget_s
        else:
            wall_spent = not tc.wall_budget or not rows or float(rows[-1]["wall_s"]) >= budget["wall_s"]
            spent = g * per_gen >= budget["sim_steps"] and wall_spent
        return spent or (max_generations is not None and g >= max_generations)

    if not done(start) and hasattr(evaluate, "lower"):  # ahead of time: the compile timed apart
        pop_like = jax.vmap(unravel)(jnp.zeros((tc.population + 1, p0.size), p0.dtype))
        t0 = time.perf_counter()
        evaluate = runner.compile_ahead(evaluate, pop_like, batch(start))  # keyed by the program alone
        compile_s = time.perf_counter() - t0 if compile_s is None else compile_s  # the first one counts
    compile_s = compile_s or 0.0
    wall = float(rows[-1]["wall_s"]) if rows else compile_s
    g = start
    total = max_generations or (None if tc.budget_s > 0 else budget_generations(problem, budget["sim_steps"]))
    with tqdm(total=total, initial=start, unit="gen", disable=not progress, desc=kind) as bar:
        while not done(g):
            t0 = time.perf_counter()
            k_ask, k_tell = jax.random.split(jax.random.fold_in(key0, g))
            pop, state = strategy.ask(k_ask, state)
            current = strategy.current(state)
            flat = jnp.concatenate([current[None], pop])
            obj, terms, metrics = evaluate(jax.vmap(unravel)(flat), batch(g))
            fitness = _finite_fitness(obj[1:])
            if kind == "random":
                state = strategy.tell(k_tell, pop, fitness, state, incumbent_fitness=_finite_fitness(obj[0]))
            else:
                state = strategy.tell(k_tell, pop, fitness, state)
            jax.block_until_ready(jax.tree_util.tree_leaves(state))
            dt = time.perf_counter() - t0
            wall += dt
            cand = np.asarray(obj[1:])
            stats = tp.survival_stats(jax.tree_util.tree_map(lambda x: x[0], metrics))
            rows.append(
                {
                    "generation": g,
                    "loss": float(obj[0]),
                    "best_candidate_loss": float(np.nanmin(cand)),
                    "median_candidate_loss": float(np.nanmedian(cand)),
                    "survival_rate": stats["survival_rate"],
                    "upright_rate": stats["upright_rate"],
                    "step_size": strategy.step_size(state),
                    "gen_s": round(dt, 3),
                    "sim_steps": (g + 1) * per_gen,
                    "wall_s": round(wall, 3),
                }
            )
            snapshots = np.concatenate([snapshots, np.asarray(strategy.current(state))[None]])
            g += 1
            store.save_checkpoint(ckpt, state, g, key, snapshots=snapshots, compile_s=compile_s)
            store.write_csv(hist_path, rows, HISTORY_COLUMNS)
            bar.set_postfix(loss=f"{float(obj[0]):.4g}")
            bar.update(1)

    return result(problem, kind, out, budget, times)


def result(problem: tp.Problem, kind: str, out, budget: dict, times=()) -> dict:
    """The outcome of a (finished or stopped) search in ``out``, read back without compiling:
    {"history", "equal_steps", "equal_wall", "at": {seconds: ...}, "final", "compile_s",
    "sim_steps_per_generation"}; each entry holds the generation (-1: none yet, the start), its sim_steps
    and wall_s, and "controls": (controls, regularisation (2,)) of the current solution after it."""
    out = pathlib.Path(out)
    p0, unravel = ravel_pytree(problem.init_params())
    with np.load(out / "checkpoint.npz") as z:
        snapshots, compile_s = z["extra_snapshots"], float(z["extra_compile_s"])
    rows = store.read_csv(out / "history.csv")[: len(snapshots)]
    if not rows:
        raise ValueError(f"{out}: the {kind} search has no finished generation yet")

    def entry(i: int, reached: bool = True) -> dict:
        params = unravel(jnp.asarray(snapshots[i], p0.dtype)) if i >= 0 else problem.init_params()
        controls, reg = problem.controls(params)
        r = rows[i] if i >= 0 else {"sim_steps": 0, "wall_s": 0.0}  # -1: the start, before any generation
        return {
            "generation": i,
            "sim_steps": int(r["sim_steps"]),
            "wall_s": float(r["wall_s"]),
            "reached": reached,
            "controls": (controls, problem.regularisation(reg)),
        }

    def pick(column: str, target: float) -> dict:
        values = [float(r[column]) for r in rows]
        i = next((j for j, v in enumerate(values) if v >= target), len(rows) - 1)
        return entry(i, bool(values[i] >= target))

    tc = problem.tc
    return {
        "history": rows,
        "equal_steps": pick("sim_steps", budget["sim_steps"]),
        "equal_wall": pick("wall_s", budget["wall_s"]),
        "final": entry(len(rows) - 1),
        "at": {float(t): entry(at_time(rows, t), float(rows[-1]["wall_s"]) >= t) for t in times},
        "compile_s": round(compile_s, 2),
        "sim_steps_per_generation": (tc.population + 1) * tc.candidate_batch * problem.steps_per_rollout,
    }
