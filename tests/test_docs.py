"""The written docs match the code (issue 44): every ``wbc_jax.…`` name cited in the package's
docstrings and in the written markdown imports, each subpackage's docstring lists its modules,
docs/architecture.md names only modules and files that exist, links between the markdown pages
resolve, README.md stays a five-minute read that names every command and carries .ci/run's
test command verbatim, and the generated results stay apart from the written pages (results/ and docs/)."""

import ast
import importlib
import pathlib
import re

ROOT = pathlib.Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "wbc_jax"
# The written pages (the generated result files are under results/: not scanned).
TOP_PAGES = [ROOT / "README.md", ROOT / "BENCHMARKS.md"]
WRITTEN = sorted({*TOP_PAGES, *(ROOT / "experiments").rglob("*.md"), *(ROOT / "docs").rglob("*.md")})
# A dotted name of the package; not a file name such as results/peers/wbc_jax.json.
CITED = re.compile(r"(?<![\w/.-])wbc_jax(?:\.[A-Za-z_]\w*)+")
FILE_SUFFIXES = {"json", "py", "md", "yaml", "yml", "npz", "parquet", "png", "csv", "txt", "log", "cc"}


def _resolves(name: str) -> bool:
    """Whether ``name`` is a module of the package, or an attribute (chain) of one."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        module_name = ".".join(parts[:i])
        try:
            obj = importlib.import_module(module_name)
        except ModuleNotFoundError as err:
            if err.name is None or not (module_name + ".").startswith(err.name + "."):
                raise  # the module exists and one of its own imports failed
            continue  # this module (or a parent of it) does not exist
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def _cited(text: str) -> set[str]:
    return {n for n in CITED.findall(text) if n.rsplit(".", 1)[-1] not in FILE_SUFFIXES}


def test_every_cited_package_name_resolves():
    sources = [*sorted(PACKAGE.rglob("*.py")), *WRITTEN]
    missing = [
        f"{path.relative_to(ROOT)}: {name}"
        for path in sources
        for name in sorted(_cited(path.read_text()))
        if not _resolves(name)
    ]
    assert not missing, "names of the package that do not exist:\n" + "\n".join(missing)


def test_the_name_check_is_not_vacuous():
    assert _resolves("wbc_jax.sim.loop.ClosedLoop.control")
    assert not _resolves("wbc_jax.sim.rollout.LossTrace")  # a module that is gone
    assert not _resolves("wbc_jax.sim.loop.ClosedLoop.rollout")  # a method that is gone
    assert _cited("see `wbc_jax.sim.state.LossTrace` and results/peers/wbc_jax.json.") == {
        "wbc_jax.sim.state.LossTrace"
    }


def _modules(folder: pathlib.Path) -> set[str]:
    return {p.stem for p in folder.glob("*.py") if p.stem != "__init__"} | {
        p.name for p in folder.iterdir() if (p / "__init__.py").exists()
    }


def test_each_subpackage_docstring_lists_its_modules():
    """A subpackage's docstring names its modules (``name``): only modules that exist, and all of
    them (commands lists them in its ``MODULES``, the order of ``wbc-jax --help``)."""
    problems = []
    for init in sorted(PACKAGE.glob("**/__init__.py")):
        folder = init.parent
        if folder == PACKAGE:
            continue
        named = set(re.findall(r"``([a-z_][a-z0-9_]*)``", ast.get_docstring(ast.parse(init.read_text())) or ""))
        if folder.name == "commands":
            named = set(importlib.import_module("wbc_jax.commands").MODULES)
        if named - _modules(folder):
            problems.append(
                f"{folder.relative_to(PACKAGE)}: names modules that do not exist: {sorted(named - _modules(folder))}"
            )
        if _modules(folder) - named:
            problems.append(f"{folder.relative_to(PACKAGE)}: does not name {sorted(_modules(folder) - named)}")
    assert not problems, "\n".join(problems)


ARCHITECTURE = ROOT / "docs" / "architecture.md"


def test_architecture_names_only_what_exists():
    text = ARCHITECTURE.read_text()
    names = _cited(text)
    assert len(names) >= 30, "the push sweep's path names its functions"
    assert not [n for n in names if not _resolves(n)]
    # Files and folders named by path.
    paths = [s for s in re.findall(r"`([^`\s]+)`", text) if "/" in s and not s.startswith("wbc_jax.")]
    assert not [p for p in paths if not (ROOT / p.rstrip("/")).exists()], paths
    # Each folder's row lists its modules: all, and only those that exist.
    rows = re.findall(r"^\| `wbc_jax/(\w+)/` \| ([^|]*) \|", text, re.M)
    assert {folder for folder, _ in rows} >= {"core", "robot", "control", "sim", "report", "jobs", "commands"}
    for folder, cell in rows:
        listed = {re.sub(r"\.py$", "", m) for m in re.findall(r"`([\w.]+)`", cell) if not m.endswith(".cc")}
        if listed:  # tuning's row describes its folder and points to its docstring
            assert listed == _modules(PACKAGE / folder), (folder, sorted(listed ^ _modules(PACKAGE / folder)))


def _anchors(page: pathlib.Path) -> set[str]:
    """The anchors of a page's headings, as GitHub makes them (lower case, punctuation dropped, spaces to -)."""
    headings = re.findall(r"^#+ (.+)$", page.read_text(), re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings}


def test_markdown_links_resolve():
    """Every relative link of a written page reaches a file, and its #anchor a heading of that file."""
    broken = []
    for page in WRITTEN:
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if re.match(r"[a-z]+:", target):
                continue
            path, _, anchor = target.partition("#")
            linked = page.parent / path if path else page
            if not linked.exists() or (anchor and linked.suffix == ".md" and anchor not in _anchors(linked)):
                broken.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not broken, broken
    assert "physics-engines---backend" in _anchors(ROOT / "docs" / "usage.md")


def test_readme_is_a_five_minute_read_naming_every_command():
    from wbc_jax.commands import registry

    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    assert not [name for name in registry() if f"wbc-jax {name}" not in readme]
    # .ci/run runs the README's test command verbatim.
    ci_command = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    assert ci_command.startswith("python3 .ci/install_libtsid.py") and ci_command in readme
    assert "python3 -m pip install -e . && wbc-jax push-sweep" in readme


# What may name a result file: every text file of the repository but the results themselves (records keep the
# docs/ paths they were written with: wbc_jax.core.provenance.current_path), the provenance tests of that reading
# and this file's own example.
SCANNED_SUFFIXES = {".py", ".md", ".sh", ".toml", ".ipynb", ".json", ".yaml", ".yml", ".cfg", ""}
NOT_SCANNED = {ROOT / "tests" / "test_provenance.py", pathlib.Path(__file__).resolve()}
NAMED_UNDER_DOCS = re.compile(r"(?<![\w./-])docs/(\w[\w.-]*(?:/[\w.-]+)*)")


def _results_named_under_docs(text: str) -> list[str]:
    """The docs/ paths of ``text`` that are not written pages (.md) nor folders of them."""
    return [
        f"docs/{rest}"
        for rest in NAMED_UNDER_DOCS.findall(text)
        if not rest.endswith(".md") and not (ROOT / "docs" / rest).is_dir()
    ]


def test_docs_holds_only_written_pages_and_each_topic_has_its_results():
    """docs/ holds markdown only; docs/<topic>/README.md explains results/<topic>/, which exists."""
    generated = [
        p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").rglob("*") if p.is_file() and p.suffix != ".md"
    ]
    assert not generated, f"generated files belong in results/ (same sub-path): {generated}"
    topics = [p.parent.name for p in (ROOT / "docs").glob("*/README.md")]
    assert len(topics) >= 5 and all((ROOT / "results" / t).is_dir() for t in topics), topics


def test_nothing_names_a_result_under_docs():
    example = "--out docs/tuning/heldout.json; docs/tuning/README.md, docs/limit/, ``docs/...``, docs/../x.json"
    assert _results_named_under_docs(example) == ["docs/tuning/heldout.json"]
    files = [ROOT / "README.md", ROOT / "BENCHMARKS.md", ROOT / "pyproject.toml", ROOT / ".gitignore"]
    for folder in ("wbc_jax", "tests", "benchmarks", "experiments", "notebooks", "docs", ".ci", "assets"):
        files += [p for p in sorted((ROOT / folder).rglob("*")) if p.is_file() and p.suffix in SCANNED_SUFFIXES]
    stale = [
        f"{path.relative_to(ROOT)}: {name}"
        for path in files
        if path not in NOT_SCANNED and "__pycache__" not in path.parts
        for name in _results_named_under_docs(path.read_text(errors="replace"))
    ]
    assert not stale, "results are under results/ now:\n" + "\n".join(stale)
