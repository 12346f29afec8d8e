"""The package's layers (docs/architecture.md): every import points to the same layer or an
earlier one, and no two modules import each other, directly or through others."""

import ast
import pathlib
import re

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "wbc_jax"
# The flow of data: robot -> control -> closed loop -> figures -> jobs -> tuning -> commands -> command line.
LAYERS = ("core", "robot", "control", "sim", "report", "jobs", "tuning", "commands", "cli")


def _module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: pathlib.Path) -> set[str]:
    """The wbc_jax modules a file imports (at any depth: function-level imports count too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("wbc_jax"):
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                found.add(sub if (PACKAGE.parent / (sub.replace(".", "/") + ".py")).exists() else node.module)
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("wbc_jax")}
    return found


def _layer(module: str) -> int:
    parts = module.split(".")
    if len(parts) == 1:
        return -1  # the package's __init__ (its lazy public surface points anywhere)
    return LAYERS.index(parts[1] if parts[1] in LAYERS else "cli")


MODULES = {_module_name(p): _imports(p) for p in sorted(PACKAGE.rglob("*.py"))}


def test_every_module_belongs_to_a_layer():
    stray = [m for m in MODULES if m.count(".") == 1 and m.split(".")[1] not in (*LAYERS, "cli")]
    assert not stray, f"modules outside the layers {LAYERS}: {stray}"


@pytest.mark.parametrize("module", sorted(m for m in MODULES if m != "wbc_jax"))
def test_imports_point_backwards(module):
    upward = sorted(t for t in MODULES[module] if _layer(t) > _layer(module))
    assert not upward, f"{module} ({LAYERS[_layer(module)]}) imports later layers: {upward}"


def test_no_import_cycle():
    graph = {m: {t for t in deps if t in MODULES and t != m} for m, deps in MODULES.items() if m != "wbc_jax"}
    state: dict[str, int] = {}

    def visit(m, path):
        state[m] = 1
        for t in sorted(graph.get(m, ())):
            if state.get(t) == 1:
                raise AssertionError("import cycle: " + " -> ".join([*path[path.index(t) :], t]))
            if t not in state:
                visit(t, [*path, t])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


def _closed_loop_subclasses(path: pathlib.Path) -> list[str]:
    """Classes of a file built on ClosedLoop (a base named ClosedLoop, or any class made by a
    three-argument ``type()``, which is how a subclass of a loop's own class was made)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ClassDef) and any("ClosedLoop" in ast.unparse(base) for base in node.bases):
            found.append(f"class {node.name}")
        elif isinstance(node, ast.Call) and ast.unparse(node.func) == "type" and len(node.args) == 3:
            found.append(f"type({ast.unparse(node.args[0])}, ...)")
    return found


def test_no_subclass_of_the_closed_loop():
    """Issue 44: what a use of the closed loop varies (gains function, recorder, feedforward) is
    given as values (``wbc_jax.sim.loop.compose``); no module overrides the loop's methods."""
    found = {_module_name(p): _closed_loop_subclasses(p) for p in sorted(PACKAGE.rglob("*.py"))}
    assert not {m: c for m, c in found.items() if c}, found
    from wbc_jax.sim.loop import ClosedLoop
    from wbc_jax.tuning.algorithms import gradient, schedule, windows  # noqa: F401  (the former subclasses' modules)
    from wbc_jax.tuning.orchestration import heldout  # noqa: F401

    assert ClosedLoop.__subclasses__() == []


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _private_uses(where: str, me: str, source: str) -> list[str]:
    """``where:line name`` for each private name of another wbc_jax module that the module ``me``
    (its text ``source``) imports (``from wbc_jax.x import _name``) or reads as an attribute of a
    module it imported (``x._name``)."""
    tree = ast.parse(source)
    modules = {}  # local name -> the wbc_jax module it is bound to
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("wbc_jax"):
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                if sub in MODULES:
                    modules[alias.asname or alias.name] = sub
                elif _private(alias.name) and node.module != me:
                    found.append(f"{where}:{node.lineno} imports {node.module}.{alias.name}")
        elif isinstance(node, ast.Import):
            modules |= {a.asname: a.name for a in node.names if a.asname and a.name.startswith("wbc_jax")}
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and _private(node.attr)):
            continue
        owner = ast.unparse(node.value)
        target = modules.get(owner, owner if owner in MODULES else None)
        if target is not None and target != me:
            found.append(f"{where}:{node.lineno} reads {target}.{node.attr}")
    return found


def test_no_private_name_used_across_modules():
    """Issue 44: what a module shares is public in the layer it belongs to; no module imports or
    reads another wbc_jax module's private (``_name``) names."""
    found = [
        use
        for p in sorted(PACKAGE.rglob("*.py"))
        for use in _private_uses(str(p.relative_to(PACKAGE.parent)), _module_name(p), p.read_text())
    ]
    assert not found, "private names used across modules:\n" + "\n".join(found)


def test_the_private_name_scan_finds_both_forms():
    """The scan above is not vacuous: it flags an import and an attribute read of another module's
    private name (a module's own private names, and public ones, pass)."""
    source = (
        "from wbc_jax.jobs.grids import _hidden\nfrom wbc_jax.core import io\nio._secret(1)\nio.jsonable\n"
        "import wbc_jax.robot.model as m\nm._check_name\nfrom wbc_jax.tuning.algorithms.gradient import _own\n"
    )
    found = _private_uses("probe.py", "wbc_jax.tuning.algorithms.gradient", source)
    assert sorted(found) == [
        "probe.py:1 imports wbc_jax.jobs.grids._hidden",
        "probe.py:3 reads wbc_jax.core.io._secret",
        "probe.py:6 reads wbc_jax.robot.model._check_name",
    ]


# Names of gain tuning's settings (its loss trace, its rematerialisation choice ``--checkpoint``).
TUNING_SETTINGS = ("loss_trace", "checkpoint")
LOWER_LAYERS = ("core", "robot", "control", "sim", "report", "jobs")


def _tuning_names(where: str, source: str) -> list[str]:
    """``where:line name`` for each variable, argument, keyword, field or attribute of a file named
    after a tuning setting (JAX's own ``jax.checkpoint`` excepted)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute):
            name = None if ast.unparse(node.value) == "jax" else node.attr
        else:
            name = getattr(node, "id", None) or getattr(node, "arg", None)
        if name in TUNING_SETTINGS:
            found.append(f"{where}:{node.lineno} {name}")
    return found


def test_lower_layers_hold_no_tuning_setting():
    """Issue 44: the loop takes a differentiated rollout's record and rematerialisation as values
    (``wbc_jax.sim.loop.compose(trace=, remat=)``); no settings of tuning in SimConfig or the jobs."""
    found = [
        use
        for layer in LOWER_LAYERS
        for p in sorted((PACKAGE / layer).rglob("*.py"))
        for use in _tuning_names(str(p.relative_to(PACKAGE.parent)), p.read_text())
    ]
    assert not found, "tuning settings in lower layers:\n" + "\n".join(found)


def test_the_tuning_name_scan_finds_fields_arguments_and_attributes():
    source = (
        "class C:\n    loss_trace: bool = False\n"
        "def f(checkpoint=False):\n    return g(loss_trace=True, x=cfg.checkpoint, y=jax.checkpoint(h))\n"
    )
    assert _tuning_names("probe.py", source) == [
        "probe.py:2 loss_trace",
        "probe.py:3 checkpoint",
        "probe.py:4 loss_trace",
        "probe.py:4 checkpoint",
    ]


def _icub_specific_words() -> tuple[set[str], list[str]]:
    """(names, number literals) that belong to the iCub alone: its joint, body, site and named-point
    names that the other robots lack, its mass and its sole's and gains' numbers."""
    from wbc_jax.robot import model
    from wbc_jax.robot.robots import DESCRIPTIONS

    def names(robot: str) -> set[str]:
        idx = model.load_robot(robot).index
        desc = DESCRIPTIONS[robot]
        return {*idx.joints, *idx.body_names, *idx.site_names, *desc.named_points, *desc.bodies.values()} - {""}

    others = set().union(*(names(r) for r in DESCRIPTIONS if r != "icub"))
    icub = DESCRIPTIONS["icub"]
    mass = model.load_robot("icub").index.mass
    numbers = [
        f"{mass:.2f}",
        f"{mass:.0f} kg",
        "23-joint",
        "23 joints",
        str(icub.sole_cop[0]),
        str(icub.sole_cop[1]),
        str(icub.gains.kp_postural[-6:]),
    ]
    return (names("icub") - others) | {"icub"}, numbers


def test_no_module_outside_the_robot_layer_names_the_icub():
    """Everything robot-specific comes from a robot description (issue 47): no module of the package
    outside wbc_jax/robot/ holds an iCub name (``icub`` in any case, its joints, bodies, sites) or
    number (its mass, its sole's CoP rectangle, its postural gains)."""
    words, numbers = _icub_specific_words()
    pattern = re.compile(r"(?i)icub|\b(" + "|".join(sorted(map(re.escape, words - {"icub"}))) + r")\b")
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.relative_to(PACKAGE).parts[0] == "robot":
            continue
        text = path.read_text()
        found += [f"{path.relative_to(PACKAGE.parent)}: {m.group(0)}" for m in pattern.finditer(text)]
        found += [f"{path.relative_to(PACKAGE.parent)}: {n}" for n in numbers if n in text]
    assert not found, found


def _icub_motor_limits() -> set[float]:
    """The iCub's motor limits (N m) that no other robot's motors have."""
    from wbc_jax.robot import model
    from wbc_jax.robot.robots import DESCRIPTIONS

    def limits(robot: str) -> set[float]:
        return {float(x) for x in model.load_robot(robot).index.torque_limit}

    return limits("icub") - set().union(*(limits(r) for r in DESCRIPTIONS if r != "icub"))


def _motor_limit_uses(where: str, source: str, limits: set[float]) -> list[str]:
    """``where:line text`` for each use of a motor limit in ``limits`` as a torque: in any text, the
    number beside a torque unit or a +- sign (``60 N m``, ``+-60``, ``\\pm 60``); in code, a literal
    of that value that divides, the default of a field named after a torque, or a bound of an option
    in N m."""
    numbers = "|".join(sorted({re.escape(f"{x:g}") for x in limits}))
    text = re.compile(rf"(?:\+-|\u00b1|\\pm\s*)(?:{numbers})(?:\.0)?\b|\b(?:{numbers})(?:\.0)?\s*N\s?m\b")
    found = [f"{where}:{source.count(chr(10), 0, m.start()) + 1} {m.group(0)}" for m in text.finditer(source)]

    def is_limit(node) -> bool:
        value = getattr(node, "value", None)
        return isinstance(node, ast.Constant) and not isinstance(value, bool) and value in limits

    for node in ast.walk(ast.parse(source)):
        hits = []
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            hits = [node.right] if is_limit(node.right) else []
        elif isinstance(node, (ast.AnnAssign, ast.Assign)) and re.search(r"(?i)torque|tau", ast.unparse(node)):
            hits = [node.value] if is_limit(node.value) else []
        elif isinstance(node, ast.Call) and any(
            k.arg == "unit" and getattr(k.value, "value", None) == "N m" for k in node.keywords
        ):
            hits = [k.value for k in node.keywords if is_limit(k.value)]
        found += [f"{where}:{h.lineno} {ast.unparse(node)[:60]}" for h in hits]
    return found


def test_no_module_outside_the_robot_layer_holds_the_icubs_motor_limit():
    """Issue 47: a torque scale, saturation or bound comes from the robot's motor limits (its model's
    actuators), never the iCub's 60 N m written into a generic layer."""
    limits = _icub_motor_limits()
    assert limits == {60.0}
    found = [
        use
        for path in sorted(PACKAGE.rglob("*.py"))
        if path.relative_to(PACKAGE).parts[0] != "robot"
        for use in _motor_limit_uses(str(path.relative_to(PACKAGE.parent)), path.read_text(), limits)
    ]
    assert not found, "the iCub's motor limit outside wbc_jax/robot/:\n" + "\n".join(found)


def test_the_motor_limit_scan_finds_each_form():
    source = (
        '"""within +-60 N m, sat_{\\\\pm 60}; 60 s and 600 N m are not"""\n'
        "class C:\n    torque_scale: float = 60.0\n    settle_s: float = 60.0\n"
        "effort = (u / 60.0) ** 2\nquintic = 60 * u\n"
        'step = option(1.0, "step", le=60.0, unit="N m")\nhorizon = option(1.0, "s", le=60.0, unit="s")\n'
    )
    found = _motor_limit_uses("probe.py", source, {60.0})
    assert sorted(f.split(" ")[0] for f in found) == ["probe.py:1"] * 2 + ["probe.py:3", "probe.py:5", "probe.py:7"]


def test_the_icub_word_list_catches_a_name():
    """The check above finds what it looks for: the iCub's names and numbers are in its words."""
    words, numbers = _icub_specific_words()
    assert {"icub", "chest", "root_link", "l_elbow_1", "r_knee"} <= words and "l_sole" not in words
    assert "33.06" in numbers and "(-0.07, 0.12)" in numbers


# Gain tuning's folders, each importing only those before it: the shared configs and store, the
# problem and its methods, what runs and judges them.
TUNING_PARTS = (
    ("wbc_jax.tuning.config", "wbc_jax.tuning.heldout_config", "wbc_jax.tuning.store"),
    ("wbc_jax.tuning.algorithms",),
    ("wbc_jax.tuning.orchestration",),
)


def _tuning_part(module: str) -> int | None:
    for rank, prefixes in enumerate(TUNING_PARTS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return rank
    return None


@pytest.mark.parametrize("module", sorted(m for m in MODULES if _tuning_part(m) is not None))
def test_tuning_algorithms_never_import_its_orchestration(module):
    """Issue 44: tuning/ shows which module is which; the algorithms (and the config and store they
    share with the orchestration) never import the orchestration."""
    mine = _tuning_part(module)
    later = sorted(t for t in MODULES[module] if (_tuning_part(t) is not None and _tuning_part(t) > mine))
    assert not later, f"{module} imports later parts of tuning: {later}"


def test_every_tuning_module_is_in_a_part():
    stray = [m for m in MODULES if m.startswith("wbc_jax.tuning.") and _tuning_part(m) is None]
    assert not stray, f"tuning modules outside {TUNING_PARTS}: {stray}"


MAX_LINES = 450
ROOT = PACKAGE.parent


@pytest.mark.parametrize("folder", ["wbc_jax", "benchmarks"])
def test_no_module_over_450_lines(folder):
    """Issue 44: no Python file under wbc_jax/ or benchmarks/ is longer than 450 lines."""
    files = sorted((ROOT / folder).rglob("*.py"))
    assert files, f"no Python files under {folder}/"
    long = {str(p.relative_to(ROOT)): n for p in files if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"files over {MAX_LINES} lines: {long}"


MAX_FMT_SKIP_LINES = 20  # only a literal table whose columns need aligning escapes the formatter
FORMATTED_FOLDERS = ("wbc_jax", "benchmarks", "tests", "experiments", "assets", ".ci")


def _fmt_skip_lines(text: str) -> int:
    """Lines that carry a ``# fmt: skip`` comment (ruff leaves their statement unformatted)."""
    return sum(1 for line in text.splitlines() if re.search(r"#\s*fmt:\s*skip", line))


def test_the_fmt_skip_counter_finds_markers():
    assert _fmt_skip_lines("x = (1,\n  2)  # fmt: skip\ny = 3\nz = [4]  #fmt:skip # table\n") == 2
    assert _fmt_skip_lines("x = 1  # format: kept\n") == 0


def test_fmt_skip_only_where_a_table_needs_it():
    """Issue 44: the code is as `ruff format` writes it; at most 20 lines in all carry ``# fmt: skip``."""
    files = [p for folder in FORMATTED_FOLDERS for p in sorted((ROOT / folder).rglob("*.py"))]
    assert files
    marked = {str(p.relative_to(ROOT)): n for p in files if (n := _fmt_skip_lines(p.read_text()))}
    most = sorted(marked.items(), key=lambda item: -item[1])[:5]
    assert sum(marked.values()) <= MAX_FMT_SKIP_LINES, (
        f"{sum(marked.values())} lines carry '# fmt: skip' (at most {MAX_FMT_SKIP_LINES}), most in {most}: "
        "re-apply the commands of the commit 'Format pass (issue 44)'"
    )


def _calls(path: pathlib.Path) -> set[str]:
    return {ast.unparse(n.func) for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Call)}


def test_one_chunk_runner():
    """Issue 44: the push sweep and the held-out evaluation run their batches through the one chunk
    runner (wbc_jax.jobs.chunks): no other module names a Parquet part file or runs chunks itself."""
    users = {
        m for m in ("jobs/sweep.py", "tuning/orchestration/heldout.py") if "chunks.run_chunks" in _calls(PACKAGE / m)
    }
    assert users == {"jobs/sweep.py", "tuning/orchestration/heldout.py"}
    naming = sorted(str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py") if "part-{" in p.read_text())
    assert naming == ["jobs/chunks.py"], f"part files named outside jobs/chunks.py: {naming}"


# Issue 44: the push grid's flags (--magnitudes, --directions, a push's length and start) are declared once, in
# wbc_jax/jobs/grids.py; the configs of push-sweep, envelope, limit, its cross-check, balance, tune and the held-out
# evaluation name only their defaults and help.
GRID_DECLARATION = re.compile(
    r"parse=(grids\.)?(magnitude_grid|azimuths)\b"  # a grid axis
    r"|option\(\s*[\d.]+,\s*\"[^\"]*\",\s*ge=\w+\.MIN_PUSH_DURATION_S"  # a push's length
    r"|ge=0\.0, lt=\w+\.MAX_HORIZON_S"  # a push's start
)


def test_the_push_grid_flags_are_declared_once():
    declared = {
        p.relative_to(PACKAGE).as_posix() for p in PACKAGE.rglob("*.py") if GRID_DECLARATION.search(p.read_text())
    }
    assert declared == {"jobs/grids.py"}


def test_the_grid_declaration_scan_finds_each_form():
    for text in (
        "x = option((1.0,), 'h', parse=magnitude_grid)",
        "x = option(azimuths(4), 'h', metavar='N', parse=grids.azimuths)",
        'push_duration: float = option(\n    0.1, "push length [s]", ge=limits.MIN_PUSH_DURATION_S, le=1.0\n)',
        'push_onset: float = option(0.5, "push start [s]", ge=0.0, lt=constants.MAX_HORIZON_S, unit="s")',
    ):
        assert GRID_DECLARATION.search(text), text
