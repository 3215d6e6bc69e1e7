"""The import rules of docs/architecture.md, checked on the package's own source (no import is executed).

- no import cycle between trimag's modules (imports inside functions count too);
- an estimator module imports no sibling estimator: only the estimators' base and shared private modules
  (``base``, ``_common``, ``_finish``, ``_pairs``, ``_quadric``), the numerical core and the support modules;
- the numerical core (``trimag._core``) imports nothing of trimag but itself and ``trimag.errors``;
- at most two module-level chunk/block-size constants (the one chunk setting and the rows of a streamed file);
- the house (issue 29): at most 16 top-level modules, each package imports only the layers below it
  (``LAYERS``, the table of docs/architecture.md), and each package's ``__init__`` says its job.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

import trimag

ROOT = Path(trimag.__file__).parent
SHARED_ESTIMATOR_MODULES = {"base", "_common", "_finish", "_pairs", "_quadric"}


def _modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> set[str]:
    """trimag modules ``name`` imports (at any depth of its code; TYPE_CHECKING blocks excluded)."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue
            if isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")
                    base = base[: len(base) - (child.level - 1)]
                    module = ".".join(base + ([child.module] if child.module else []))
                else:
                    module = child.module or ""
                for alias in child.names:
                    target = f"{module}.{alias.name}"
                    found.add(target if target in MODULES else module)
            elif isinstance(child, ast.Import):
                found.update(alias.name for alias in child.names)
            visit(child)

    visit(ast.parse(path.read_text(encoding="utf-8")))
    return {m for m in found if m in MODULES and m != name}


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _cycles() -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(GRAPH[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(GRAPH):
        if v not in index:
            connect(v)
    return components


def test_the_walk_sees_the_package():
    assert len(MODULES) > 60
    assert "trimag.estimators._finish" in GRAPH["trimag.estimators.ml"]  # relative imports resolved
    assert "trimag._core.chunks" in GRAPH["trimag._core.rowwise"]


def test_no_import_cycle():
    assert _cycles() == []


def test_the_cycle_check_finds_a_cycle():
    GRAPH["trimag._core.chunks"].add("trimag._core.rowwise")
    try:
        assert _cycles() == [["trimag._core.chunks", "trimag._core.rowwise"]]
    finally:
        GRAPH["trimag._core.chunks"].discard("trimag._core.rowwise")


@pytest.mark.parametrize("name", sorted(m for m in MODULES if m.startswith("trimag.estimators.")))
def test_no_estimator_imports_a_sibling_estimator(name):
    siblings = {
        m for m in GRAPH[name]
        if m.startswith("trimag.estimators.") and m.rsplit(".", 1)[1] not in SHARED_ESTIMATOR_MODULES
    }
    assert siblings == set(), f"{name} imports sibling estimator(s) {sorted(siblings)}"


@pytest.mark.parametrize("name", sorted(m for m in MODULES if m.startswith("trimag._core")))
def test_the_core_imports_only_itself_and_errors(name):
    outside = {m for m in GRAPH[name] if not m.startswith("trimag._core") and m != "trimag.errors"}
    assert outside == set(), f"{name} imports {sorted(outside)}"


def test_at_most_two_chunk_size_constants():
    constants = []
    for name, path in MODULES.items():
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
                node, ast.AnnAssign) else []
            for target in targets:
                sized = isinstance(node.value, (ast.Constant, ast.BinOp))  # a number, not e.g. the ContextVar
                if sized and isinstance(target, ast.Name) and re.search(r"BLOCK|CHUNK|PANEL|WORKING_MEMORY", target.id):
                    constants.append(f"{name}.{target.id}")
    assert sorted(constants) == ["trimag._core.chunks.DEFAULT_CHUNK_ROWS", "trimag._core.chunks.WORKING_MEMORY_BYTES"]


def test_no_benchmark_harness_inside_the_package():
    """``trimag.experiments`` holds the four papers' reproductions only; benchmarks live in benchmarks/."""
    experiments = {m.rsplit(".", 1)[1] for m in MODULES if m.startswith("trimag.experiments.")}
    assert experiments == {"wu2013", "scalar_gn", "vehicle12", "zhang2009", "_data", "_output"}


def _experiment_imports() -> list[tuple[str, str, str]]:
    """``(experiment module, imported module, name)`` for every ``from trimag... import name`` in
    ``trimag.experiments`` (at any depth) that reaches outside the experiments package."""
    out = []
    for name, path in MODULES.items():
        if not name.startswith("trimag.experiments"):
            continue
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level:
                base = package.split(".")
                module = ".".join(base[: len(base) - (node.level - 1)] + ([node.module] if node.module else []))
                if not module.startswith("trimag.experiments"):
                    out += [(name, module, alias.name) for alias in node.names]
    return out


def test_experiments_use_only_the_public_api():
    """The reproductions import only public modules' public names (in the module's ``__all__``), as
    ``trimag.experiments`` promises: a reproduction is what a user of the package could write."""
    import importlib

    private = []
    for experiment, module, attr in _experiment_imports():
        public = set(getattr(importlib.import_module(module), "__all__", ()))
        if any(part.startswith("_") for part in module.split(".")) or attr not in public:
            private.append(f"{experiment}: {module}.{attr}")
    assert private == []


def test_the_public_api_check_sees_the_experiments_imports():
    found = {(m, a) for _, m, a in _experiment_imports()}
    assert ("trimag.estimators.gauss_newton", "GaussNewton") in found


def test_only_the_front_ends_import_the_app_layer():
    """The application layer (``trimag.app``, one module per command) sits on top: the library never imports it;
    the front ends (the CLI and ``trimag live``) call its entry points."""
    front_ends = {"trimag.cli", "trimag.live"}
    outside = {
        name: sorted(m for m in GRAPH[name] if m == "trimag.app" or m.startswith("trimag.app."))
        for name in GRAPH if not name.startswith("trimag.app") and _unit(name) not in {"cli", "live"}
    }
    assert {name: found for name, found in outside.items() if found} == {}
    assert front_ends <= set(MODULES)


@pytest.mark.parametrize("name", sorted(m for m in MODULES if m.startswith("trimag.app")))
def test_the_app_layer_does_not_import_its_callers(name):
    callers = {m for m in MODULES if _unit(m) in {"cli", "live"}}
    assert GRAPH[name] & callers == set(), f"{name} imports {sorted(GRAPH[name] & callers)}"


# ---------------------------------------------------------------------------------------------------------------
# The house (issue 29): the jobs' packages and what each may import (docs/architecture.md, "Layers")

FOUNDATION = {"errors", "units", "validation", "_version"}
#: top-level module or package -> the top-level modules and packages it may import (besides itself)
LAYERS: dict[str, set[str]] = {
    "errors": set(),
    "units": {"errors"},
    "validation": {"errors"},
    "_version": set(),
    "_moved": set(),
    "_core": {"errors"},
    "models": {"_core", "errors"},
    "calibration": FOUNDATION | {"_core", "models", "io"},
    "io": FOUNDATION | {"_core", "models", "calibration", "fields"},
    "fields": FOUNDATION | {"_core"},
    "quality": FOUNDATION | {"_core", "models", "calibration", "io", "fields"},
    "aircraft": FOUNDATION | {"_core", "models", "calibration", "io", "_moved"},
    "estimators": FOUNDATION | {"_core", "models", "calibration", "io", "fields", "quality", "aircraft"},
    "vehicle": FOUNDATION | {"_core", "models", "calibration", "io", "fields", "quality"},
    "simulate": FOUNDATION | {"_core", "models", "fields"},
    "parallel": {"_core", "errors"},
    "fitting": FOUNDATION | {"calibration", "estimators", "vehicle"},
    "solvers": {"estimators"},
    "testing": FOUNDATION | {"calibration", "estimators", "models", "simulate"},
    "experiments": FOUNDATION | {"calibration", "models", "io", "fields", "quality", "estimators", "simulate",
                                 "parallel", "solvers"},
    "app": FOUNDATION | {"_core", "models", "calibration", "io", "fields", "quality", "aircraft", "estimators",
                         "vehicle", "simulate", "parallel", "fitting"},
    "live": FOUNDATION | {"_core", "models", "calibration", "io", "fields", "quality", "estimators", "vehicle",
                          "fitting", "app"},
    "cli": FOUNDATION | {"_core", "io", "quality", "vehicle", "parallel", "experiments", "app", "live"},
    "__main__": {"cli"},
    "trimag": FOUNDATION | {"_moved", "calibration", "aircraft", "quality", "estimators", "fitting", "models"},
}
TOP_LEVEL_LIMIT = 16  # modules at the top of src/trimag/, __init__, __main__ and _version not counted


def _unit(name: str) -> str:
    """The top-level module or package ``name`` belongs to (``trimag`` for the package's own ``__init__``)."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else "trimag"


def _layer_violations(graph: dict[str, set[str]]) -> list[str]:
    out = []
    for name, imported in sorted(graph.items()):
        unit = _unit(name)
        allowed = LAYERS.get(unit)
        if allowed is None:
            out.append(f"{name}: {unit!r} is not in the layer table (docs/architecture.md)")
            continue
        out += [f"{name} imports {m}" for m in sorted(imported) if _unit(m) != unit and _unit(m) not in allowed]
    return out


def test_each_package_imports_only_the_layers_below_it():
    assert _layer_violations(GRAPH) == []


def test_the_layer_check_sees_a_violation():
    graph = {"trimag.quality.metrics": {"trimag.estimators.ml"}, "trimag.vehicle.eddy": {"trimag.io.tables"},
             "trimag.gadgets": set()}
    assert _layer_violations(graph) == [
        "trimag.gadgets: 'gadgets' is not in the layer table (docs/architecture.md)",
        "trimag.quality.metrics imports trimag.estimators.ml",
    ]


def test_at_most_16_top_level_modules_each_in_the_layer_table():
    top = sorted(p.stem for p in ROOT.glob("*.py") if p.stem not in {"__init__", "__main__", "_version"})
    assert len(top) <= TOP_LEVEL_LIMIT, top
    packages = sorted(p.parent.name for p in ROOT.glob("*/__init__.py"))
    assert set(top) | set(packages) <= set(LAYERS), sorted(set(top) | set(packages) - set(LAYERS))
    assert {"vehicle", "aircraft", "quality", "fields", "app"} <= set(packages)


@pytest.mark.parametrize("package", sorted(p.parent.name for p in ROOT.glob("*/__init__.py")))
def test_each_package_says_its_job(package):
    """Each package's ``__init__`` opens with a docstring of at least two lines: its job, and what lives there."""
    doc = ast.get_docstring(ast.parse((ROOT / package / "__init__.py").read_text(encoding="utf-8")))
    assert doc is not None and len(doc.split("\n\n")[0].splitlines()) >= 2, package


def test_the_former_paths_still_import_with_a_warning():
    """The modules moved into the job packages keep their former import paths, deprecated (docs/architecture.md,
    "Former paths"): the same module object, one DeprecationWarning naming the new home."""
    import importlib
    import sys
    import warnings

    from trimag._moved import MOVED

    for old, new in MOVED.items():
        sys.modules.pop(old, None)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            module = importlib.import_module(old)
        assert module is importlib.import_module(new), old
        assert [str(w.message).split(" is deprecated")[0] for w in caught
                if issubclass(w.category, DeprecationWarning)] == [old], old
        assert any(new in str(w.message) for w in caught)
    with pytest.warns(DeprecationWarning, match="trimag.app.tolles_lawson.parse_segments"):
        from trimag.aircraft import parse_segments
    assert parse_segments("0:1") == [(0.0, 1.0)]
    sys.modules.pop("trimag.workflow", None)
    with pytest.warns(DeprecationWarning, match="trimag.app"):
        from trimag.workflow import fit_file
    from trimag.app import fit_file as new_fit_file

    assert fit_file is new_fit_file


def _block_loops(sources: dict[str, str] | None = None) -> list[str]:
    """``module:line`` of every ``for ... in range(start, stop, step)`` with a positive step outside the core
    (``sources``: module name -> source text; default the package's modules)."""
    if sources is None:
        sources = {name: path.read_text(encoding="utf-8") for name, path in MODULES.items()}
    loops = []
    for name, text in sources.items():
        if name.startswith("trimag._core"):
            continue
        for node in ast.walk(ast.parse(text)):
            it = node.iter if isinstance(node, ast.For) else None
            if (isinstance(it, ast.Call) and isinstance(it.func, ast.Name) and it.func.id == "range"
                    and len(it.args) == 3 and not isinstance(it.args[2], ast.UnaryOp)):
                loops.append(f"{name}:{node.lineno}")
    return loops


def test_every_chunked_pass_goes_through_the_core():
    """A pass over samples in chunks walks them with ``trimag._core.chunks.row_blocks`` (or the core's
    ``transposed_blocks``), so the one chunk setting governs it: no hand-written block loop outside the core."""
    assert _block_loops() == []


def test_the_block_loop_check_sees_a_block_loop():
    loop = "def f(n, chunk):\n    for start in range(0, n, chunk):\n        pass\n"
    backwards = "for j in range(9, -1, -1):\n    pass\n"
    assert _block_loops({"trimag.x": loop, "trimag.y": backwards, "trimag._core.z": loop}) == ["trimag.x:2"]


def test_the_architecture_doc_maps_the_tree():
    """docs/architecture.md's map names every top-level module and package of ``src/trimag`` and nothing that is
    not there (a moved or new module updates the map)."""
    from _helpers import REPO_DIR

    # the repository's tree and docs (CI installs trimag with `pip install .`: the installed package has no docs)
    doc = REPO_DIR / "docs" / "architecture.md"
    tree = REPO_DIR / "src" / "trimag"
    if not doc.is_file() or not tree.is_dir():
        pytest.skip(f"{doc} is absent: the test runs from the repository")
    text = doc.read_text(encoding="utf-8")
    block = text[text.index("```\nsrc/trimag/"):]
    block = block[: block.index("```", 4)]
    named = set(re.findall(r"\b([a-z_][a-z0-9_]*)/(?=\s)", block))
    named |= set(re.findall(r"\b([a-z_][a-z0-9_]*)\.py\b", block))
    top = {p.stem for p in tree.glob("*.py") if p.stem not in {"__init__", "__main__", "_version"}}
    packages = {p.parent.name for p in tree.glob("*/__init__.py")}
    assert sorted((top | packages) - named) == []
    inner = {p.stem for p in tree.glob("*/*.py")} | {p.parent.name for p in tree.glob("*/*/__init__.py")}
    assert sorted(named - top - packages - inner - {"src", "trimag", "static", "logs"}) == []
