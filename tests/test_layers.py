"""The import graph of the whole package, read from the sources (ast, as tests/test_sim.py
reads ivdrem.sim's): no import circle between two modules, and no import running back up
the documented order of layers (docs/developers.md, "Layout").

Every ``import`` and ``from ... import`` of a module counts, at its top level or inside a
function: an import moved into a function to dodge a circle is still a dependency.  A
command-line face (``cli`` modules, the preflight, ``__main__``) is the last layer whatever
package holds it.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

import ivdrem

ROOT = Path(ivdrem.__file__).resolve().parent
DOCS = ROOT.parent / "docs" / "developers.md"

#: the layers, each importing only those before it; names on one layer (``sim / laws``)
#: import neither each other.  "base": the package's root and its private leaf modules
#: (``ivdrem._*``, the compile cache).  Written once more in docs/developers.md, checked below.
LAYERS = ("base", "models", "blocks", "sim / laws", "pycontrol", "diagrams", "experiments",
          "fmu", "controller", "reports", "plants", "cli")

#: edges a change in progress still has, each with its reason (edge -> why), listed exactly so
#: that any other edge fails; each is an xfail below, which passes once its edge is gone.
#: None is left: the package has no circle and no import against the order.
KNOWN: dict = {}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules():
    return {module_name(p): p for p in ROOT.rglob("*.py") if "__pycache__" not in p.parts}


def _targets(module, node, is_package, modules):
    """The modules of ivdrem an import node names (a name imported from a package that is
    one of its submodules counts as that submodule)."""
    if isinstance(node, ast.Import):
        return {a.name for a in node.names if a.name.split(".")[0] == "ivdrem"}
    base = module.split(".") if is_package else module.split(".")[:-1]
    if node.level:
        base = base[:len(base) - node.level + 1]
        name = ".".join(base + ([node.module] if node.module else []))
    else:
        name = node.module or ""
    if name.split(".")[0] != "ivdrem":
        return set()
    return {f"{name}.{a.name}" if f"{name}.{a.name}" in modules else name for a in node.names}


def import_graph():
    """{module: {module of ivdrem it imports}} of every module of the package."""
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                deps |= _targets(name, node, path.name == "__init__.py", modules)
        # a module's own package (its __init__ runs first anyway) is no dependency
        graph[name] = {d for d in deps if d != name and not name.startswith(d + ".")}
    return graph


def layer(module: str) -> int:
    """The index in LAYERS of a module's layer."""
    parts = module.split(".")
    if parts[-1] in ("cli", "__main__", "_preflight") or parts[1:2] == ["cli"]:
        return LAYERS.index("cli")
    if len(parts) == 1 or (len(parts) == 2 and parts[1].startswith("_")) \
            or parts[1] == "compile_cache":
        return LAYERS.index("base")
    for i, names in enumerate(LAYERS):
        if parts[1] in names.split(" / "):
            return i
    raise AssertionError(f"module {module} is on no layer of LAYERS: add its package there "
                         "and in docs/developers.md")


def _package(module):
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def back_up_imports(graph=None):
    """[(importer, imported)] of `graph` (default: the package's) running against LAYERS: to a
    later layer, or across one layer (sim and laws) between different packages."""
    out = []
    for m, deps in (import_graph() if graph is None else graph).items():
        for d in deps:
            lm, ld = layer(m), layer(d)
            if ld > lm or (ld == lm and lm != LAYERS.index("base")
                           and _package(m) != _package(d) and lm != LAYERS.index("cli")):
                out.append((m, d))
    return sorted(out)


def circles(graph):
    """The import circles of `graph`: its strongly connected parts of two or more modules
    (Tarjan), each a sorted list."""
    index, low, on, stack, out = {}, {}, set(), [], []

    def visit(m):
        index[m] = low[m] = len(index)
        stack.append(m)
        on.add(m)
        for d in sorted(graph.get(m, ())):
            if d not in graph:
                continue
            if d not in index:
                visit(d)
                low[m] = min(low[m], low[d])
            elif d in on:
                low[m] = min(low[m], index[d])
        if low[m] == index[m]:
            part = []
            while True:
                d = stack.pop()
                on.discard(d)
                part.append(d)
                if d == m:
                    break
            if len(part) > 1:
                out.append(sorted(part))
    for m in sorted(graph):
        if m not in index:
            visit(m)
    return sorted(out)


def test_every_module_is_on_a_layer():
    for m in import_graph():
        layer(m)


def test_the_docs_state_the_order():
    """docs/developers.md writes the same order (base first, as this test's LAYERS)."""
    text = DOCS.read_text(encoding="utf-8")
    assert " → ".join(LAYERS) in text, "docs/developers.md does not state LAYERS"


def test_no_import_circle():
    """No module imports another that imports it back (through any chain), the known
    edges apart."""
    graph = {m: {d for d in deps if (m, d) not in KNOWN} for m, deps in import_graph().items()}
    assert circles(graph) == []


def test_circles_are_found():
    """The circle search finds a circle of three and one of two (a check that can fail)."""
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"e"}, "e": {"d", "a"}, "f": set()}
    assert circles(graph) == [["a", "b", "c"], ["d", "e"]]


def test_back_up_imports_are_found():
    """The layer rule flags an import of a later layer and one across a layer (a check that
    can fail), and lets a command-line face import anything."""
    graph = {"ivdrem.models.base": {"ivdrem.sim.compiled", "ivdrem._atomic"},
             "ivdrem.sim.plan": {"ivdrem.laws", "ivdrem.blocks._core", "ivdrem.sim.errors"},
             "ivdrem.reports.cli": {"ivdrem.plants.cli", "ivdrem.cli"},
             "ivdrem.fmu.plant": {"ivdrem.controller.codegen"}}
    assert back_up_imports(graph) == [("ivdrem.fmu.plant", "ivdrem.controller.codegen"),
                                      ("ivdrem.models.base", "ivdrem.sim.compiled"),
                                      ("ivdrem.sim.plan", "ivdrem.laws")]


def test_no_import_runs_back_up_the_layers():
    """Every import reads a module on an earlier layer (or of its own package)."""
    found = [e for e in back_up_imports() if e not in KNOWN]
    assert found == [], "\n".join(f"{a} -> {b}" for a, b in found)


@pytest.mark.parametrize("edge", [pytest.param(e, marks=pytest.mark.xfail(reason=why))
                                  for e, why in sorted(KNOWN.items())],
                         ids=lambda e: f"{e[0]}->{e[1]}")
def test_known_edges(edge):
    """The known edges, one each: xfail while the edge is there, pass once it is gone."""
    assert edge[1] not in import_graph()[edge[0]]


def test_every_module_says_what_it_is():
    """Each module opens with a docstring whose first line says what it holds."""
    missing = [m for m, p in _modules().items()
               if not (ast.get_docstring(ast.parse(p.read_text(encoding="utf-8"))) or "").strip()]
    assert missing == []
