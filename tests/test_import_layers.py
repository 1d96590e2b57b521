"""The packages of ``dejaview/`` are layers, each importing only those below it, and no module
imports one that imports it back.

The order, lowest first (``LAYERS``; packages on one line are independent of each other):

    errors
    untrusted_xml, parallel  hardened XML parsing; the process pool
    geometry                 meshes, packings, SDF, fcl checks, numpy transforms, robot files
    scene                    the scene model, its XML reader/writer and validation
    sim                      World, State, the engines, trajectory CSV
    losses
    backends, io             the backend protocol and backends; MJCF export/import
    inference
    heatmap
    server
    cli
    dejaview, __main__       the package's lazy attributes (``dejaview.solve``) and ``python -m``

The test reads every module's source with ``ast`` (nothing is imported) and builds two graphs.
``import a.b.c`` also runs the ``__init__`` of ``a`` and ``a.b``, so an import adds an edge to each
package on the way that is not already a parent of the importing module.

- **Module-level** imports: statements executed when the module is imported, including those in
  module-level ``try``/``if`` blocks, but not ``if TYPE_CHECKING:`` blocks. No cycle at all.
- **Every** import, function-level ones included (they run on first use: a lazy import hides a
  cycle from the import machinery, not from the layering). No cycle either, except the
  ``ALLOWED`` edges: a constructor named after its source (``Scene.from_xml``,
  ``Scene.to_xml``, ``World.from_scene``) lives on the model class and calls the reader one floor up.
  And every import between packages goes down ``LAYERS``.

Any other cycle fails, naming its modules; so does an import up or across the layers.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "dejaview"


LAYERS = (
    ("errors",),
    ("untrusted_xml", "parallel", "memory", "result_set"),
    ("geometry",),
    ("scene",),
    ("sim",),
    ("losses",),
    ("backends", "io"),
    ("inference",),
    ("heatmap",),
    ("server",),
    ("cli",),
    ("", "__main__"),  # "": the package's own __init__
)
"""The packages (and top-level modules) of ``dejaview/``, lowest first; see the module docstring."""


def _module_name(path: Path, package: Path = PACKAGE) -> str:
    parts = list(path.relative_to(package.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules(package: Path = PACKAGE) -> dict[str, Path]:
    return {_module_name(p, package): p for p in package.rglob("*.py")}


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


ALLOWED = {
    ("dejaview.scene.model", "dejaview.scene.xml"),  # Scene.from_xml / from_string
    ("dejaview.scene.model", "dejaview.scene.writer"),  # Scene.to_xml
    ("dejaview.sim.world", "dejaview.sim.build"),  # World.from_scene
}


def _module_level_imports(tree: ast.Module):
    """Import nodes executed at import time (not in functions, classes' methods or TYPE_CHECKING)."""
    stack = list(tree.body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If):
            if not _is_type_checking(node.test):
                stack.extend(node.body)
            stack.extend(node.orelse)
        elif isinstance(node, (ast.Try, ast.With)):
            stack.extend(node.body)
            for handler in getattr(node, "handlers", ()):
                stack.extend(handler.body)
            stack.extend(getattr(node, "orelse", ()))
            stack.extend(getattr(node, "finalbody", ()))
        elif isinstance(node, ast.ClassDef):
            stack.extend(n for n in node.body if not isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)))


def _targets(name: str, node, modules: dict[str, Path]) -> set[str]:
    """dejaview modules an import statement in module ``name`` executes."""
    package = name if modules[name].name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    if isinstance(node, ast.Import):
        found = {a.name for a in node.names}
    else:
        base = node.module or ""
        if node.level:
            anchor = package.split(".")
            anchor = anchor[:len(anchor) - (node.level - 1)]
            base = ".".join(anchor + ([base] if base else []))
        found.add(base)
        found |= {f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in modules}
    out = set()
    own_parents = {".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 1)}
    top = name.split(".")[0]
    for target in found:
        if target.split(".")[0] != top:
            continue
        parts = target.split(".")
        for i in range(1, len(parts) + 1):
            prefix = ".".join(parts[:i])
            if prefix in modules and prefix != name and prefix not in own_parents:
                out.add(prefix)
    return out


def import_graph(function_level: bool = False, package: Path = PACKAGE) -> dict[str, set[str]]:
    """module -> the package's modules it imports: at module level, or anywhere (``function_level``)."""
    modules = _modules(package)
    graph = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        if function_level:
            nodes = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
        else:
            nodes = list(_module_level_imports(tree))
        graph[name] = set().union(set(), *(_targets(name, n, modules) for n in nodes))
    return graph


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
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
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def layer_of(module: str) -> str:
    """The entry of ``LAYERS`` a module belongs to: ``dejaview.sim.world`` -> ``sim``, ``dejaview`` -> ``""``."""
    return module.split(".")[1] if "." in module else ""


def layer_violations(graph: dict[str, set[str]], layers=LAYERS) -> list[str]:
    """Imports between packages that do not go down ``layers`` (up, or across one line), and modules
    of no layer; one line each."""
    rank = {name: i for i, line in enumerate(layers) for name in line}
    out = []
    for a in sorted(graph):
        if layer_of(a) not in rank:
            out.append(f"{a}: its package {layer_of(a)!r} is in no layer")
            continue
        for b in sorted(graph[a]):
            la, lb = layer_of(a), layer_of(b)
            if la != lb and rank.get(lb, len(layers)) >= rank[la]:
                where = "beside" if rank.get(lb) == rank[la] else "above"
                out.append(f"{a} imports {b}: {lb!r} is {where} {la!r}")
    return out


def test_the_graph_sees_the_imports_it_should():
    """The walk itself: known edges are found, so an empty cycle list means something."""
    graph = import_graph()
    assert "dejaview.sim.world" in graph["dejaview.sim.integrate"]
    assert "dejaview.backends" not in graph["dejaview.inference.solve"]  # imported in a function
    everything = import_graph(function_level=True)
    assert "dejaview.backends" in everything["dejaview.inference.solve"]
    assert "dejaview.sim.native" in everything["dejaview.sim.integrate"]
    # a package on the way counts: dejaview.heatmap.search -> dejaview.inference (its __init__)
    assert "dejaview.inference" in everything["dejaview.heatmap.search"]
    assert set(ALLOWED) <= {(a, b) for a in everything for b in everything[a]}
    assert find_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def _message(cycles) -> str:
    return "import cycles in dejaview/: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_no_import_cycles_at_module_level():
    cycles = find_cycles(import_graph())
    assert not cycles, _message(cycles)


def test_no_import_cycles_counting_function_level_imports():
    graph = import_graph(function_level=True)
    for a, b in ALLOWED:
        graph[a].discard(b)
    cycles = find_cycles(graph)
    assert not cycles, _message(cycles)


def test_layers_import_only_downward_counting_function_level_imports():
    violations = layer_violations(import_graph(function_level=True))
    assert not violations, "imports against dejaview's layers:\n" + "\n".join(violations)


def test_every_layer_names_a_package_that_exists():
    present = {layer_of(m) for m in _modules()}
    assert {name for line in LAYERS for name in line} == present


def test_the_layer_check_fails_on_an_upward_import(tmp_path):
    """The checker itself, on a package made up here: an import up a layer, even one inside a function,
    and one across a line fail; imports down and within a package pass."""
    files = {
        "pkg/__init__.py": "",
        "pkg/low/__init__.py": "from pkg.low import a\n",
        "pkg/low/a.py": "import os\n\ndef f():\n    from pkg.high.b import g\n    return g\n",
        "pkg/side/__init__.py": "from ..low import a\n",
        "pkg/high/__init__.py": "",
        "pkg/high/b.py": "from pkg.low.a import f\nfrom pkg import side\n\ndef g():\n    return f\n",
        "pkg/twin.py": "import pkg.side\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    layers = (("low",), ("side", "twin"), ("high",), ("",))
    graph = import_graph(function_level=True, package=tmp_path / "pkg")
    assert "pkg.high.b" in graph["pkg.low.a"]
    assert layer_violations(graph, layers) == [
        "pkg.low.a imports pkg.high: 'high' is above 'low'",
        "pkg.low.a imports pkg.high.b: 'high' is above 'low'",
        "pkg.twin imports pkg.side: 'side' is beside 'twin'",
    ]
    assert layer_violations(import_graph(package=tmp_path / "pkg"), layers) == [
        "pkg.twin imports pkg.side: 'side' is beside 'twin'"]  # module level: the lazy import is not seen
    assert layer_violations(graph, (("low",), ("side", "twin", "high"))) == [
        "pkg: its package '' is in no layer",
        "pkg.high.b imports pkg.side: 'side' is beside 'high'",
        "pkg.low.a imports pkg.high: 'high' is above 'low'",
        "pkg.low.a imports pkg.high.b: 'high' is above 'low'",
        "pkg.twin imports pkg.side: 'side' is beside 'twin'",
    ]


MAX_MODULE_LINES = 600


def test_no_module_over_the_size_limit():
    """A module past ~600 lines holds more than one thing: split it along its seam (issue 23)."""
    long = {name: n for name, path in _modules().items()
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"
