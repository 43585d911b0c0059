"""Rules the code keeps, read from the source with ``ast`` (nothing here imports the package).

* No function (methods and nested functions included) longer than :data:`MAX_LINES` lines in ``prml2_edge/`` and
  ``benchmarks/``, nor than :data:`MAX_LINES_PLAUSIBILITY` in the plausibility checks
  (``prml2_edge/runtime/plausibility/``, or ``plausibility.py`` while it is one file). Length is
  ``end_lineno - lineno + 1`` of the ``def`` (decorators not counted, docstring counted).
* No import circle among the ``prml2_edge`` modules, counting every import: module level, inside functions
  (the lazy ones) and under ``TYPE_CHECKING``. The layering between packages is ``tests/test_layers.py``'s.
"""

from __future__ import annotations

import ast
from itertools import pairwise
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "prml2_edge"
MAX_LINES = 80
MAX_LINES_PLAUSIBILITY = 60


def _functions(path: Path):
    """(name, first line, length in lines) of every function and method in ``path``, nested ones included."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node.name, node.lineno, node.end_lineno - node.lineno + 1


def _too_long(paths, limit: int) -> list[str]:
    return [f"{p.relative_to(REPO)}:{line} {name}() is {n} lines (at most {limit})"
            for p in paths for name, line, n in _functions(p) if n > limit]


def test_no_function_is_longer_than_80_lines():
    paths = sorted(PACKAGE.rglob("*.py")) + sorted((REPO / "benchmarks").rglob("*.py"))
    assert PACKAGE / "cli" / "main.py" in paths and REPO / "benchmarks" / "latency.py" in paths, REPO
    long = _too_long(paths, MAX_LINES)
    assert not long, "split by meaning into named helpers:\n" + "\n".join(long)


def test_no_plausibility_function_is_longer_than_60_lines():
    runtime = PACKAGE / "runtime"
    paths = sorted((runtime / "plausibility").rglob("*.py")) + sorted(runtime.glob("plausibility.py"))
    assert paths, "prml2_edge/runtime/plausibility(.py) not found"
    long = _too_long(paths, MAX_LINES_PLAUSIBILITY)
    assert not long, "split by meaning into named helpers:\n" + "\n".join(long)


def _modules() -> dict[str, Path]:
    """Dotted module name -> source file, for every module and package of ``prml2_edge``."""
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(REPO).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _imported(name: str, path: Path, modules: dict[str, Path]) -> dict[str, int]:
    """The ``prml2_edge`` modules that module ``name`` imports, anywhere in it, each with the line of its first
    import. ``from P import X`` counts as importing ``P.X`` where that is a module, else ``P``."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    out: dict[str, int] = {}
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package, one level up per extra dot
                base = ".".join(package[:len(package) - node.level + 1] + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        for target in targets:
            if target in modules and target != name:
                out.setdefault(target, node.lineno)
    return out


def _circles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, without recursion)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def _cycle(graph: dict[str, dict[str, int]], component: list[str]) -> list[str]:
    """One shortest import cycle through the first module of ``component``: [a, b, ..., a]."""
    members, start = set(component), component[0]
    paths = {start: [start]}
    queue = [start]
    while queue:
        v = queue.pop(0)
        for w in sorted(graph[v]):
            if w == start:
                return paths[v] + [start]
            if w in members and w not in paths:
                paths[w] = paths[v] + [w]
                queue.append(w)
    return component  # not reached: a component of more than one module holds a cycle through each member


def test_no_import_circle_among_the_modules():
    modules = _modules()
    assert "prml2_edge.cli.main" in modules, f"no prml2_edge package under {REPO}"
    graph = {name: _imported(name, path, modules) for name, path in modules.items()}
    problems = []
    for component in _circles(graph):
        cycle = _cycle(graph, component)
        steps = [f"  {a} imports {b} ({modules[a].relative_to(REPO)}:{graph[a][b]})" for a, b in pairwise(cycle)]
        problems.append(" -> ".join(cycle) + "\n" + "\n".join(steps)
                        + (f"\n  (the circle holds {len(component)} modules: {', '.join(component)})"
                           if len(component) > len(cycle) - 1 else ""))
    assert not problems, ("import circles (a lazy import inside a function counts too: move the code that needs "
                          "both modules into the higher one, or let the caller compose them):\n"
                          + "\n".join(problems))


def test_the_rules_see_what_they_check(tmp_path):
    """The readers find a long nested function, and a circle made only of imports inside functions."""
    src = tmp_path / "m.py"
    src.write_text("def outer():\n    def inner():\n" + "        x = 1\n" * 80 + "    return inner\n")
    assert [(name, n) for name, _, n in _functions(src) if n > MAX_LINES] == [("outer", 83), ("inner", 81)]
    graph = {"p.a": {"p.b": 3}, "p.b": {"p.c": 5}, "p.c": {"p.a": 7}, "p.d": {"p.a": 1}}
    assert _circles(graph) == [["p.a", "p.b", "p.c"]]
    assert _cycle(graph, ["p.a", "p.b", "p.c"]) == ["p.a", "p.b", "p.c", "p.a"]
    pkg = tmp_path / "prml2_edge" / "data"
    pkg.mkdir(parents=True)
    (pkg / "a.py").write_text("def f():\n    from prml2_edge.data import b\n    from . import c\n")
    mods = {"prml2_edge.data": pkg / "__init__.py", "prml2_edge.data.a": pkg / "a.py",
            "prml2_edge.data.b": pkg / "b.py", "prml2_edge.data.c": pkg / "c.py"}
    assert _imported("prml2_edge.data.a", pkg / "a.py", mods) == {"prml2_edge.data.b": 2, "prml2_edge.data.c": 3}
