"""The package's import graph, read from the source with `ast`: no cycles, few function-level imports.

Every `import` and `from ... import` in `fieldtool/` is collected, at module level and inside functions
alike, with relative imports resolved and `from pkg import name` counted as an import of `pkg.name` when
`pkg/name.py` (or `pkg/name/`) exists. An edge A -> B means module A imports module B (or a package
B's `__init__`). Imports under `if TYPE_CHECKING:` are skipped: they never run.

Two rules (issue 24, design.md): no module reaches itself through its imports (a cycle is printed as
`a -> b -> a`), and at most MAX_LAZY imports sit inside functions, each justified by a measured
start-up cost (the list is printed when over).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PKG = "fieldtool"
MAX_LAZY = 30


def _modules() -> dict[str, Path]:
    """Dotted module name -> source file, for every .py file of the package."""
    out: dict[str, Path] = {}
    for path in sorted((ROOT / PKG).rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _is_package(name: str, modules: dict[str, Path]) -> bool:
    return name in modules and modules[name].name == "__init__.py"


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """ids of import nodes under `if TYPE_CHECKING:` (never executed)."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If):
            test = node.test
            name = test.id if isinstance(test, ast.Name) else test.attr if isinstance(test, ast.Attribute) else ""
            if name == "TYPE_CHECKING":
                for sub in node.body:
                    for inner in ast.walk(sub):
                        skip.add(id(inner))
    return skip


def _imports(name: str, path: Path, modules: dict[str, Path]) -> tuple[list[str], list[tuple[int, str]]]:
    """(every module that module `name` imports, [(line, what) for each import statement inside a function])."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    skip = _type_checking_nodes(tree)
    package = name if _is_package(name, modules) else name.rpartition(".")[0]
    found: list[str] = []
    lazy: list[tuple[int, str]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda)
            if id(child) in skip:
                continue
            if isinstance(child, ast.Import | ast.ImportFrom) and in_function:
                lazy.append((child.lineno, ast.unparse(child)))
            if isinstance(child, ast.Import):
                for alias in child.names:
                    found.append(alias.name)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base_parts = package.split(".")
                    if child.level > 1:
                        base_parts = base_parts[: -(child.level - 1)]
                    base = ".".join(base_parts + ([child.module] if child.module else []))
                else:
                    base = child.module or ""
                found.append(base)
                for alias in child.names:
                    sub = f"{base}.{alias.name}"
                    if sub in modules:
                        found.append(sub)
            visit(child, inner)

    visit(tree, False)
    return found, lazy


def _resolve(target: str, modules: dict[str, Path]) -> str | None:
    """The package module that importing `target` loads last (its longest known prefix), or None."""
    parts = target.split(".")
    while parts:
        cand = ".".join(parts)
        if cand in modules:
            return cand
        parts.pop()
    return None


def build_graph() -> tuple[dict[str, set[str]], list[tuple[str, int, str]]]:
    """(module -> modules it imports, [(module, line, statement) for every function-level import])."""
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    lazy: list[tuple[str, int, str]] = []
    for name, path in modules.items():
        targets, statements = _imports(name, path, modules)
        lazy.extend((name, line, what) for line, what in statements)
        for target in targets:
            if not target.startswith(PKG):
                continue
            dep = _resolve(target, modules)
            if dep is not None and dep != name:
                graph[name].add(dep)
    return graph, lazy


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per strongly connected component of more than one module (Tarjan), as a closed path."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    counter = [0]
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp: list[str] = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                components.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)

    cycles: list[list[str]] = []
    for comp in components:
        members = set(comp)
        start = comp[0]
        # shortest path back to `start` inside the component (breadth first)
        prev: dict[str, str] = {}
        frontier = [start]
        seen = {start}
        end = None
        while frontier and end is None:
            nxt: list[str] = []
            for v in frontier:
                for w in sorted(graph[v] & members):
                    if w == start:
                        end = v
                        break
                    if w not in seen:
                        seen.add(w)
                        prev[w] = v
                        nxt.append(w)
                if end is not None:
                    break
            frontier = nxt
        path = [start]
        v = end
        while v is not None and v != start:
            path.append(v)
            v = prev.get(v)
        cycles.append([start, *reversed(path[1:]), start])
    return cycles


def test_graph_sees_known_edges():
    """The reader must find real edges, or the two tests below pass on an empty graph."""
    graph, _ = build_graph()
    assert "fieldtool.processing.piv" in graph["fieldtool.run.velocimetry"]
    assert "fieldtool.run.velocimetry" in graph["fieldtool.run.pipeline"]
    assert len(graph) > 50 and sum(len(v) for v in graph.values()) > 100


def test_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycles(graph) == [["a", "b", "c", "a"]]
    assert find_cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    graph, _ = build_graph()
    cycles = find_cycles(graph)
    assert not cycles, "import cycles:\n" + "\n".join("  " + " -> ".join(c) for c in cycles)


def test_few_function_level_imports():
    _, lazy = build_graph()
    listing = "\n".join(f"  {m}:{line}  {t}" for m, line, t in lazy)
    assert len(lazy) <= MAX_LAZY, f"{len(lazy)} function-level imports (at most {MAX_LAZY}):\n{listing}"


if __name__ == "__main__":  # `python tests/run/test_import_graph.py`: print the cycles and the lazy imports
    g, lz = build_graph()
    for c in find_cycles(g):
        print("cycle:", " -> ".join(c))
    for m, line, t in lz:
        print(f"lazy: {m}:{line}  {t}")
    print(len(lz), "function-level imports")


def function_lengths() -> list[tuple[int, str]]:
    """(lines, "module:qualname") of every top-level function and method of the package, its nested
    functions counted in it; longest first."""
    rows: list[tuple[int, str]] = []

    def walk(node, path: Path, prefix: str, nested: bool) -> None:
        for n in ast.iter_child_nodes(node):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if not nested:
                    rows.append((n.end_lineno - n.lineno + 1, f"{path.relative_to(ROOT)}:{prefix}{n.name}"))
                walk(n, path, f"{prefix}{n.name}.", True)
            elif isinstance(n, ast.ClassDef):
                walk(n, path, f"{prefix}{n.name}.", nested)

    for path in sorted((ROOT / PKG).rglob("*.py")):
        walk(ast.parse(path.read_text()), path, "", False)
    return sorted(rows, reverse=True)


def test_no_function_over_120_lines():
    """A function, its nested functions included, fits on a screen or two (issue 24): at most 120 lines."""
    rows = function_lengths()
    assert len(rows) > 500  # the walk found the package's functions
    long = [r for r in rows if r[0] > 120]
    assert not long, "functions over 120 lines: " + ", ".join(f"{name} ({n})" for n, name in long)
