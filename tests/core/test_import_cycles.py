"""No module of the project imports itself back, directly or through others.

A cycle between two modules makes their import order matter (a name is missing when the other
module is half-initialised) and ties two concepts into one. The graph is every absolute or
relative import statement of every module of the installed ``imunoise`` namespace, also one
inside a function (it runs when the function does), except those under ``if TYPE_CHECKING:``,
which never run. ``from a.b import c`` is an edge to the module ``a.b.c`` when that is a module,
else to ``a.b``; importing a submodule runs its package's ``__init__`` too, but the package
importing its own submodules is how a package is made, so only the module named counts.
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

from tests.shared_paths import REPO


def _modules(root: Path) -> dict[str, Path]:
    """Module name -> source file, from pyproject's package-dir mapping (the wheel's layout)."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    out: dict[str, Path] = {}
    for name, folder in config["package-dir"].items():
        base = root / folder
        for path in base.rglob("*.py"):
            rel = path.relative_to(base).with_suffix("").parts
            if rel[-1] == "__init__":
                rel = rel[:-1]
            out[".".join((*name.split("."), *rel))] = path
    return out


def _type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(path: Path, module: str, modules: dict[str, Path]) -> set[str]:
    """The project modules that ``module`` (source ``path``) imports when it runs."""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _type_checking(child):
                for other in child.orelse:
                    visit(other)
                continue
            if isinstance(child, ast.Import):
                found.update(a.name for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package[:len(package) - child.level + 1]
                    source = ".".join(base + ([child.module] if child.module else []))
                else:
                    source = child.module or ""
                for alias in child.names:
                    sub = f"{source}.{alias.name}"
                    found.add(sub if sub in modules else source)
            visit(child)

    visit(ast.parse(path.read_text(), filename=str(path)))
    return {m for m in found if m in modules and m != module}


def import_graph(root: Path = REPO) -> dict[str, set[str]]:
    """Module -> the project modules it imports."""
    modules = _modules(root)
    return {m: _imports(p, m, modules) for m, p in modules.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    out.append(sorted(component))
    return out


def test_no_module_imports_itself_back():
    graph = import_graph()
    found = cycles(graph)
    described = [" <-> ".join(c) + ": " + "; ".join(
        f"{m} -> {sorted(graph[m] & set(c))}" for m in c) for c in found]
    assert not found, "import cycles:\n" + "\n".join(described)


def test_the_graph_has_the_imports_it_should():
    """The walker sees an import inside a function, a relative one and a submodule named in
    ``from package import module`` (so that the cycle test can fail)."""
    graph = import_graph()
    assert "imunoise.pipeline.channel_analysis" in graph["imunoise.pipeline.streamed_analysis"]
    assert "imunoise.pipeline.documents" in graph["imunoise.commands.analyze"]
    assert "imunoise.analysis.terms.spec" in graph["imunoise.analysis.terms"]


def test_a_cycle_is_found(tmp_path, monkeypatch):
    """Two modules importing each other, one of them inside a function and one through a
    relative import, and a third only under TYPE_CHECKING: one cycle of two."""
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "a.py").write_text("def f():\n    from imunoise.pkg.b import g\n")
    (tmp_path / "pkg" / "b.py").write_text("from . import a\n")
    (tmp_path / "pkg" / "c.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from imunoise.pkg import a\n"
        "from imunoise.pkg import b\n")
    (tmp_path / "pyproject.toml").write_text(
        '[tool.setuptools.package-dir]\n"imunoise.pkg" = "pkg"\n')
    monkeypatch.setattr(__import__(__name__, fromlist=["REPO"]), "REPO", tmp_path)
    graph = import_graph(tmp_path)
    assert graph["imunoise.pkg.c"] == {"imunoise.pkg.b"}
    assert cycles(graph) == [["imunoise.pkg.a", "imunoise.pkg.b"]]
