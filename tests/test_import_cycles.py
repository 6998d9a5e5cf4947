"""No import cycles among psao's modules.

Every module under src/psao is parsed (not imported) and each import of a psao module it makes, at module
level or inside a function, is an edge of a graph: `from psao.x import y` goes to psao.x.y when that is a
module, else to psao.x; a relative import is resolved against the importing package. Importing psao.a.b runs
psao/a/__init__.py first, so an edge to a package's child also goes to the package's __init__ when that
__init__ imports psao modules itself (an __init__ that imports nothing cannot close a cycle). The test fails
naming one cycle, as a chain of modules with the line of each import.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
ROOT = "psao"


def module_files(src: Path = SRC) -> dict[str, Path]:
    """Dotted module name -> file, for every module under src/psao (a package under its own name)."""
    out = {}
    for path in sorted((src / ROOT).rglob("*.py")):
        parts = list(path.relative_to(src).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = path
    return out


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str | None:
    """The absolute module an ImportFrom names (before its imported names are looked at)."""
    if node.level == 0:
        return node.module
    base = module.split(".") if is_package else module.split(".")[:-1]
    if node.level > 1:
        base = base[:len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(module: str, path: Path, modules: dict[str, Path]) -> list[tuple[str, int]]:
    """(imported psao module, line) for every import in the file, at any depth (functions included)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    found = []

    def known(name: str | None) -> str | None:
        # the longest prefix of name that is a psao module (import psao.a.b.c where c is a class: psao.a.b)
        while name:
            if name in modules:
                return name
            name = name.rpartition(".")[0]
        return None

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == ROOT and (target := known(alias.name)):
                    found.append((target, node.lineno))
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(module, is_package, node)
            if not base or base.split(".")[0] != ROOT:
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                target = sub if sub in modules else known(base)
                if target:
                    found.append((target, node.lineno))
    return [(t, line) for t, line in found if t != module]


def import_graph(src: Path = SRC) -> dict[str, dict[str, int]]:
    """module -> {imported module: first line importing it}, parent packages' __init__ included where they
    import anything of psao themselves."""
    modules = module_files(src)
    direct = {m: imports_of(m, p, modules) for m, p in modules.items()}
    active = {m for m, p in modules.items() if p.name == "__init__.py" and direct[m]}
    graph: dict[str, dict[str, int]] = {}
    for m, edges in direct.items():
        out = graph.setdefault(m, {})
        for target, line in edges:
            chain = target.split(".")
            # importing psao.a.b.c runs psao/__init__, psao/a/__init__ and psao/a/b/__init__ first
            for k in range(1, len(chain) + 1):
                t = ".".join(chain[:k])
                if t == m or (k < len(chain) and t not in active) or m.startswith(t + "."):
                    # a module's own enclosing packages are already importing when it runs
                    continue
                out.setdefault(t, line)
    return graph


def find_cycle(graph: dict[str, dict[str, int]]) -> list[str] | None:
    """One cycle as [a, b, ..., a], or None: depth-first search, iterative."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = {m: WHITE for m in graph}
    for start in sorted(graph):
        if colour[start] != WHITE:
            continue
        stack = [(start, iter(sorted(graph[start])))]
        path = [start]
        colour[start] = GREY
        while stack:
            node, children = stack[-1]
            for child in children:
                if child not in colour:
                    continue
                if colour[child] == GREY:
                    return path[path.index(child):] + [child]
                if colour[child] == WHITE:
                    colour[child] = GREY
                    path.append(child)
                    stack.append((child, iter(sorted(graph[child]))))
                    break
            else:
                colour[node] = BLACK
                path.pop()
                stack.pop()
    return None


def describe(cycle: list[str], graph: dict[str, dict[str, int]]) -> str:
    return "\n".join(f"  {a}  (line {graph[a][b]}) imports  {b}" for a, b in zip(cycle, cycle[1:]))


def test_no_import_cycles():
    graph = import_graph()
    assert len(graph) > 50, "found too few modules: is SRC right?"
    cycle = find_cycle(graph)
    if cycle is not None:
        pytest.fail("import cycle among psao's modules:\n" + describe(cycle, graph), pytrace=False)


def test_finds_a_cycle(tmp_path):
    """The checker itself: a package whose modules import each other (one inside a function) is caught."""
    pkg = tmp_path / ROOT / "sub"
    pkg.mkdir(parents=True)
    (tmp_path / ROOT / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from psao.sub.b import thing\n")
    (pkg / "b.py").write_text("def f():\n    from . import c\n")
    (pkg / "c.py").write_text("import psao.sub.a as a\n")
    (pkg / "d.py").write_text("from psao.sub import a\n")
    graph = import_graph(tmp_path)
    cycle = find_cycle(graph)
    assert cycle is not None and set(cycle) == {"psao.sub.a", "psao.sub.b", "psao.sub.c"}
    (pkg / "c.py").write_text("x = 1\n")
    assert find_cycle(import_graph(tmp_path)) is None


def private_imports(src: Path = SRC) -> list[str]:
    """'module:line name' for every `from psao.X import _name` in src/psao that takes a private name of
    another module (a name with one leading underscore; dunders are not private)."""
    found = []
    modules = module_files(src)
    for module, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                target = _resolve(module, path.name == "__init__.py", node)
                if target is None or target == module or target.split(".")[0] != ROOT:
                    continue
                found += [f"{module}:{node.lineno} {a.name}" for a in node.names
                          if a.name.startswith("_") and not a.name.startswith("__")]
    return found


def test_no_private_imports_across_modules():
    assert private_imports() == []


def test_finds_a_private_import(tmp_path):
    pkg = tmp_path / ROOT
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def _hidden():\n    pass\n")
    (pkg / "b.py").write_text("def f():\n    from psao.a import _hidden\n    return _hidden\n")
    assert private_imports(tmp_path) == ["psao.b:2 _hidden"]
