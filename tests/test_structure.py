"""The package's shape (issue 35): no import circles between geonav's modules, and no
function long enough to hide several jobs.

Both checks read the source with :mod:`ast`; nothing is imported. An import counts when
it runs as the module loads: a statement at module level, also inside a module-level
``if``/``try``/``with`` or a class body, but not inside a function (a deferred import)
and not under ``if TYPE_CHECKING:`` (never run).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "geonav"

#: Most lines a function may span (``def`` line to its last line, decorators not counted);
#: STYLE.md rule 8 says to look for the seam past ~80.
MAX_FUNCTION_LINES = 100


def module_names(root: Path) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is a package ``__init__``) for every .py under
    ``root`` (a package folder; its own name is the first part)."""
    found = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        if is_pkg:
            parts = parts[:-1]
        found[".".join(parts)] = (path, is_pkg)
    return found


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _load_time_imports(body: list[ast.stmt]) -> list[ast.Import | ast.ImportFrom]:
    """The import statements of a module body that run when it loads."""
    out: list[ast.Import | ast.ImportFrom] = []
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            out.append(node)
        elif isinstance(node, ast.If):
            if not _is_type_checking(node.test):
                out += _load_time_imports(node.body)
            out += _load_time_imports(node.orelse)
        elif isinstance(node, ast.Try):
            out += _load_time_imports(node.body)
            for handler in node.handlers:
                out += _load_time_imports(handler.body)
            out += _load_time_imports(node.orelse) + _load_time_imports(node.finalbody)
        elif isinstance(node, (ast.With, ast.For, ast.While, ast.ClassDef)):
            out += _load_time_imports(node.body)
    return out


def _targets(node: ast.Import | ast.ImportFrom, module: str, is_pkg: bool,
             known: dict[str, tuple[Path, bool]]) -> set[str]:
    """The modules of ``known`` that one import statement of ``module`` loads."""
    if isinstance(node, ast.Import):
        return {a.name for a in node.names if a.name in known}
    if node.level:  # relative: from the package of the module, up level - 1
        package = module.split(".") if is_pkg else module.split(".")[:-1]
        package = package[:len(package) - (node.level - 1)]
        base = ".".join(package + ([node.module] if node.module else []))
    else:
        base = node.module or ""
    out = set()
    for alias in node.names:
        sub = f"{base}.{alias.name}"
        if sub in known:  # "from pkg import module"
            out.add(sub)
        elif base in known:  # "from module import name"
            out.add(base)
    return out


def import_graph(root: Path) -> dict[str, set[str]]:
    """Module -> the package's modules it imports as it loads."""
    known = module_names(root)
    graph = {}
    for module, (path, is_pkg) in known.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        deps: set[str] = set()
        for node in _load_time_imports(tree.body):
            deps |= _targets(node, module, is_pkg, known)
        deps.discard(module)
        graph[module] = deps
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (``[a, b, ..., a]``) per strongly connected group of modules."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return [_cycle_through(group, graph) for group in groups]


def _cycle_through(group: list[str], graph: dict[str, set[str]]) -> list[str]:
    """A shortest path from the group's first module back to itself, inside the group."""
    start, members = group[0], set(group)
    paths = {start: [start]}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v] & members):
                if w == start:
                    return paths[v] + [start]
                if w not in paths:
                    paths[w] = paths[v] + [w]
                    nxt.append(w)
        frontier = nxt
    raise AssertionError(f"{group} is not a cycle")  # a strongly connected group always is


def long_functions(root: Path, limit: int = MAX_FUNCTION_LINES) -> list[tuple[str, int]]:
    """``("path:qualified.name", lines)`` of every function over ``limit`` lines, longest
    first; path relative to ``root``."""
    found = []
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        rel = path.relative_to(root).as_posix()

        def walk(node: ast.AST, prefix: str, rel: str = rel) -> None:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    name = f"{prefix}{child.name}"
                    if not isinstance(child, ast.ClassDef):
                        lines = child.end_lineno - child.lineno + 1
                        if lines > limit:
                            found.append((f"{rel}:{name}", lines))
                    walk(child, f"{name}.")
                else:
                    walk(child, prefix)

        walk(tree, "")
    return sorted(found, key=lambda item: -item[1])


# -- the checks themselves, on a small package made for them --------------------------------

@pytest.fixture
def toy_package(tmp_path):
    """pkg/a.py -> pkg/sub/b.py -> (relative, "from .. import a") pkg/a.py: one circle;
    pkg/c.py imports a only inside a function and under TYPE_CHECKING: none."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from . import b\n")
    (pkg / "a.py").write_text("import os\nfrom pkg.sub.b import thing\n")
    (pkg / "sub" / "b.py").write_text("try:\n    from .. import a\nexcept ImportError:\n"
                                      "    a = None\nthing = 1\n")
    (pkg / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                              "    from pkg import a\n\n\ndef f():\n    from pkg import a\n\n"
                              "    return a\n")
    return pkg


def test_the_import_walker_follows_relative_imports_and_skips_deferred_ones(toy_package):
    graph = import_graph(toy_package)
    assert graph["pkg.a"] == {"pkg.sub.b"}
    assert graph["pkg.sub.b"] == {"pkg.a"}  # "from .. import a", inside a module-level try
    assert graph["pkg.sub"] == {"pkg.sub.b"}  # "from . import b"
    assert graph["pkg.c"] == set()  # in a function, or under TYPE_CHECKING
    assert import_cycles(graph) == [["pkg.a", "pkg.sub.b", "pkg.a"]]
    assert import_cycles({"x": {"y"}, "y": set()}) == []


def test_the_length_check_measures_from_def_to_last_line(toy_package):
    assert long_functions(toy_package, limit=3) == [("c.py:f", 4)]
    assert long_functions(toy_package, limit=4) == []


# -- geonav ----------------------------------------------------------------------------------

def test_no_import_circle_in_geonav():
    cycles = import_cycles(import_graph(PACKAGE))
    assert not cycles, "import circles (move the shared names to the lower module): " + \
        "; ".join(" -> ".join(c) for c in cycles)


def test_no_function_over_100_lines():
    long = long_functions(PACKAGE)
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines (find their seams): " + \
        ", ".join(f"{name} ({n})" for name, n in long)
