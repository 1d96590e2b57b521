"""No import cycles in ``dejaview/``: what infers sits above the backends, the backends above the
simulator, and no module imports one that imports it back.

The test reads every module's source with ``ast`` (nothing is imported) and builds two graphs.
``import a.b.c`` also runs the ``__init__`` of ``a`` and ``a.b``, so an import adds an edge to each
package on the way that is not already a parent of the importing module.

- **Module-level** imports: statements executed when the module is imported, including those in
  module-level ``try``/``if`` blocks, but not ``if TYPE_CHECKING:`` blocks. No cycle at all.
- **Every** import, function-level ones included (they run on first use: a lazy import hides a
  cycle from the import machinery, not from the layering). No cycle either, except the
  ``ALLOWED`` edges: a constructor named after its source (``Scene.from_xml``,
  ``Scene.to_xml``, ``World.from_scene``) lives on the model class and calls the reader one floor up.

Any other cycle fails, naming its modules.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "dejaview"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PACKAGE.rglob("*.py")}


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
    for target in found:
        if not target.startswith("dejaview"):
            continue
        parts = target.split(".")
        for i in range(1, len(parts) + 1):
            prefix = ".".join(parts[:i])
            if prefix in modules and prefix != name and prefix not in own_parents:
                out.add(prefix)
    return out


def import_graph(function_level: bool = False) -> dict[str, set[str]]:
    """module -> dejaview modules it imports: at module level, or anywhere (``function_level``)."""
    modules = _modules()
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


MAX_MODULE_LINES = 600


def test_no_module_over_the_size_limit():
    """A module past ~600 lines holds more than one thing: split it along its seam (issue 23)."""
    long = {name: n for name, path in _modules().items()
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"
