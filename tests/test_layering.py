"""The package's layering: the core never imports the application, imports only go down, no cycles
(imports inside functions included).

Layer order (docs/architecture.md): ``tolerances < ops < lie < mesh < dec < nn < frames < hexmesh``; the
jobs (``training/``), ``studies/`` and ``benchmarks/`` sit on top. The checks walk the source
tree, so they hold for whatever modules each layer holds.
"""
from __future__ import annotations

import ast
import functools
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "torchconn"
LAYERS = ("tolerances", "ops", "lie", "mesh", "dec", "nn", "frames", "hexmesh")
CORE = LAYERS[:-2]
APPLICATION_PREFIXES = ("torchconn.frames", "torchconn.hexmesh", "torchconn.training", "training", "studies", "benchmarks")
MESH_IO_DEPENDENCIES = ("meshio", "igl", "pymeshlab")


# ----------------------------------------------------------------------------- import in a subprocess
_IMPORT_CORE = r"""
import importlib, json, pkgutil, sys
blocked = set(sys.argv[2].split(",")) if sys.argv[2] else set()

class Blocker:
    # Make the named top-level packages unimportable, as if they were not installed.
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in blocked:
            raise ImportError(f"{name} is blocked by the test")

sys.meta_path.insert(0, Blocker())
import torchconn as tc
on_import = sorted(sys.modules)
imported = ["torchconn"]
for layer in sys.argv[1].split(","):
    mod = importlib.import_module(f"torchconn.{layer}")
    imported.append(mod.__name__)
    if hasattr(mod, "__path__"):
        for info in pkgutil.walk_packages(mod.__path__, prefix=mod.__name__ + "."):
            importlib.import_module(info.name)
            imported.append(info.name)
out = {"on_import": on_import, "imported": imported, "modules": sorted(sys.modules)}
if sys.argv[3] == "lazy":
    # after the core's walk (recorded above): every top-level name resolves, loading its layer
    out["missing"] = [n for n in tc.__all__ if not hasattr(tc, n)]
    out["frames_resolved"] = "torchconn.frames" in sys.modules and tc.frames.__name__ == "torchconn.frames"
    out["callables"] = all(callable(f) for f in (tc.so3.exp, tc.curvature.two_prong, tc.io.box))
    try:
        tc.no_such_name
        out["unknown_name"] = "resolved"
    except AttributeError as exc:
        out["unknown_name"] = f"AttributeError: {exc}"
print(json.dumps(out))
"""


def _import_core(blocked: tuple[str, ...] = (), lazy: bool = False) -> dict:
    """Import ``torchconn`` and walk every module of the core in a fresh process (the packages of
    ``blocked`` unimportable); ``lazy``: then resolve every top-level name of ``torchconn``."""
    proc = subprocess.run(
        [sys.executable, "-c", _IMPORT_CORE, ",".join(CORE), ",".join(blocked), "lazy" if lazy else ""],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def core_process() -> dict:
    """One fresh process for two tests (each fresh process costs 5-12 s on 2 loaded cores): the
    core's walk, then the top-level names resolved."""
    return _import_core(lazy=True)


def test_core_imports_without_the_application(core_process):
    result = core_process
    # every layer of the core was walked, down to the modules of its subpackages
    for layer in CORE:
        assert f"torchconn.{layer}" in result["imported"]
    assert len(result["imported"]) > len(CORE) + 1
    leaked = [m for m in result["modules"] if m.startswith(APPLICATION_PREFIXES)]
    assert leaked == [], f"importing the core loaded application modules: {leaked}"


def test_core_imports_without_mesh_io_dependencies():
    """libigl, pymeshlab and meshio are the optional ``io`` extra: the core imports without them."""
    result = _import_core(blocked=MESH_IO_DEPENDENCIES)
    assert "torchconn.mesh" in result["imported"]
    assert not [m for m in result["modules"] if m.split(".")[0] in MESH_IO_DEPENDENCIES]


def test_top_level_names_resolve_lazily(core_process):
    """``import torchconn`` loads no application layer; every name of ``__all__`` resolves (the
    lazy ones load their layer); an unknown name is an ``AttributeError``."""
    result = core_process
    assert "torchconn.frames" not in result["on_import"]
    assert result["missing"] == [], result["missing"]
    assert result["frames_resolved"] and result["callables"]
    assert result["unknown_name"].startswith("AttributeError"), result["unknown_name"]


# ----------------------------------------------------------------------------- static import graph
def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PKG.rglob("*.py"))}


@functools.lru_cache(maxsize=None)
def _parse(path: Path) -> ast.Module:
    """The syntax tree of a source file, parsed once per test session (three tests walk them all)."""
    return ast.parse(path.read_text())


def _resolve_from(module: str, path: Path, node: ast.ImportFrom) -> str:
    """Absolute name of the module a ``from X import ...`` statement names as X."""
    if node.level == 0:
        return node.module or ""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    base = package.split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _root_reexports(modules: dict[str, Path]) -> dict[str, str]:
    """Name re-exported by ``torchconn/__init__.py`` -> the torchconn module it comes from."""
    out = {}
    for node in ast.walk(_parse(modules["torchconn"])):
        if isinstance(node, ast.ImportFrom) and node.level >= 1:
            source = _resolve_from("torchconn", modules["torchconn"], node)
            for alias in node.names:
                sub = f"{source}.{alias.name}"
                out[alias.asname or alias.name] = sub if sub in modules else source
    return out


def _imports(modules: dict[str, Path]) -> dict[str, list[tuple[str, int, bool]]]:
    """Module -> the torchconn modules it imports, as ``(target, line, at_module_level)``.

    ``from torchconn import so3`` is followed through the re-exports of ``torchconn/__init__``
    (that module is the facade over every layer and is not a node of the graph).
    """
    reexports = _root_reexports(modules)
    graph: dict[str, list[tuple[str, int, bool]]] = {}
    for module, path in modules.items():
        if module == "torchconn":
            continue
        tree = _parse(path)
        top_level = {id(n) for n in tree.body}
        # imports under `if`/`try` at module level run at import time too
        for stmt in tree.body:
            if isinstance(stmt, (ast.If, ast.Try)):
                top_level |= {id(n) for n in ast.walk(stmt)}
        edges = []
        for node in ast.walk(tree):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                source = _resolve_from(module, path, node)
                for alias in node.names:
                    sub = f"{source}.{alias.name}"
                    if source == "torchconn":
                        targets.append(reexports.get(alias.name, sub))
                    else:
                        targets.append(sub if sub in modules else source)
            for target in targets:
                while target and target not in modules:  # `import torchconn.dec.curvature.x` -> owning module
                    target = target.rpartition(".")[0]
                if target.startswith("torchconn.") and target != module:
                    edges.append((target, node.lineno, id(node) in top_level))
        graph[module] = edges
    return graph


def _layer(module: str) -> int:
    name = module.split(".")[1]
    assert name in LAYERS, (
        f"{module} is in no layer: place torchconn/{name} in the layer order of docs/architecture.md "
        f"and tests/test_layering.py {LAYERS}"
    )
    return LAYERS.index(name)


def test_every_module_is_in_a_layer():
    for module in _modules():
        if module != "torchconn":
            _layer(module)


def test_imports_only_go_down_the_layers():
    modules = _modules()
    violations = [
        f"{modules[m].relative_to(ROOT)}:{line}: {m} ({LAYERS[_layer(m)]}) imports {t} ({LAYERS[_layer(t)]})"
        for m, edges in _imports(modules).items()
        for t, line, _ in edges
        if _layer(t) > _layer(m)
    ]
    assert violations == [], "imports going up the layers:\n" + "\n".join(violations)


def _cycles(graph: dict[str, list[str]]) -> list[list[str]]:
    """One cycle per strongly connected component with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return components


def _cycle_report(modules: dict[str, Path], module_level_only: bool) -> list[str]:
    """Each cycle of the import graph of ``modules`` as its modules and the import statements
    between them (``file:line``, marked ``(in a function)`` when not at module level)."""
    imports = _imports(modules)
    graph = {m: sorted({t for t, _, top in edges if top or not module_level_only}) for m, edges in imports.items()}
    report = []
    for component in _cycles(graph):
        members = set(component)
        lines = [
            f"  {modules[m].name if not modules[m].is_relative_to(ROOT) else modules[m].relative_to(ROOT)}:{line}: "
            f"imports {t}" + ("" if top else " (in a function)")
            for m in component for t, line, top in imports[m]
            if t in members and (top or not module_level_only)
        ]
        report.append(" <-> ".join(component) + "\n" + "\n".join(sorted(set(lines))))
    return report


def test_no_import_cycles_between_modules():
    """Module-level imports form no cycle (a package's ``__init__`` counts as its own module)."""
    assert _cycle_report(_modules(), module_level_only=True) == []


def test_no_import_cycles_including_function_level_imports():
    """No cycle either when the imports inside functions and methods count: deferring an import
    into a function hides a cycle, it does not remove it (one home per concept: the lower module
    must not need the upper one). A package ``__init__`` is a module of its own, as above."""
    cycles = _cycle_report(_modules(), module_level_only=False)
    assert cycles == [], "import cycles (function-level imports included):\n" + "\n".join(cycles)


def test_function_level_cycle_is_seen(tmp_path):
    """On a two-module package whose cycle closes inside a method, the module-level check passes
    and the full check names the cycle and the function-level import."""
    (tmp_path / "__init__.py").write_text("")
    (tmp_path / "a.py").write_text("from .b import f\n")
    (tmp_path / "b.py").write_text("def f():\n    return 1\n\n\nclass C:\n    def g(self):\n"
                                   "        from .a import f\n        return f()\n")
    modules = {"torchconn": tmp_path / "__init__.py", "torchconn.a": tmp_path / "a.py",
               "torchconn.b": tmp_path / "b.py"}
    assert _cycle_report(modules, module_level_only=True) == []
    report = _cycle_report(modules, module_level_only=False)
    assert len(report) == 1 and report[0].startswith("torchconn.a <-> torchconn.b")
    assert "b.py:7: imports torchconn.a (in a function)" in report[0] and "a.py:1: imports torchconn.b" in report[0]


def test_cycle_detection_sees_a_cycle():
    assert _cycles({"a": ["b"], "b": ["c"], "c": ["a"], "d": ["a"]}) == [["a", "b", "c"]]


@pytest.mark.parametrize("source,level,module,expected", [
    ("torchconn.dec.curvature", 1, "transport", "torchconn.dec.transport"),
    ("torchconn.dec.curvature", 2, "lie", "torchconn.lie"),
    ("torchconn.dec", 1, "smooth", "torchconn.dec.smooth"),
])
def test_relative_imports_resolve(source, level, module, expected):
    path = Path("__init__.py") if source == "torchconn.dec" else Path("x.py")
    node = ast.ImportFrom(module=module, names=[], level=level)
    assert _resolve_from(source, path, node) == expected
