"""The packages depend on each other in one direction only.

``core`` is below everything; ``analysis`` and ``daq`` sit side by side on it and never import
each other; the live runtime, the fleet catalogue and the HTTP layer come above them; the
command line ``imunoise`` is the top. Every import counts, also one inside a function.
"""

from __future__ import annotations

import ast

from tests.shared_paths import REPO

# package -> the project packages it may import
ALLOWED: dict[str, set[str]] = {
    "core": set(),
    "analysis": {"core"},
    "daq": {"core"},
    "live": {"core", "analysis", "daq"},
    "fleet": {"core", "analysis"},
    "web": {"core", "analysis", "live", "fleet"},
    "imunoise": {"core", "analysis", "daq", "live", "web", "fleet"},
}


def _layer(module: str) -> str:
    """The layer of an imported module: ``imunoise.analysis.fit`` -> ``analysis``; a module of
    the command-line package itself (``imunoise.cli``) -> ``imunoise``; anything else -> its
    top-level name (a package that is not ours)."""
    parts = module.split(".")
    if parts[0] != "imunoise":
        return parts[0]
    if len(parts) > 1 and parts[1] in ALLOWED and parts[1] != "imunoise":
        return parts[1]
    return "imunoise"


def _edges() -> dict[tuple[str, str], list[str]]:
    """(importer package, imported package) -> the files where that import happens."""
    edges: dict[tuple[str, str], list[str]] = {}
    for pkg in ALLOWED:
        for path in sorted((REPO / pkg).rglob("*.py")):
            tree = ast.parse(path.read_text(), filename=str(path))
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    top = _layer(name)
                    if top in ALLOWED and top != pkg:
                        edges.setdefault((pkg, top), []).append(str(path.relative_to(REPO)))
    return edges


def test_no_import_goes_against_the_layers():
    bad = {f"{a} -> {b}": sorted(set(files)) for (a, b), files in _edges().items()
           if b not in ALLOWED[a]}
    assert not bad, f"imports against the layers: {bad}"


def test_no_package_cycle():
    graph: dict[str, set[str]] = {p: set() for p in ALLOWED}
    for a, b in _edges():
        graph[a].add(b)
    state: dict[str, int] = {}

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            assert state.get(nxt) != 1, f"package cycle: {' -> '.join(path + [node, nxt])}"
            if nxt not in state:
                visit(nxt, path + [node])
        state[node] = 2

    for p in graph:
        if p not in state:
            visit(p, [])


def test_the_layer_check_sees_a_backward_import(tmp_path, monkeypatch):
    """The walker itself finds an upward import (so the two tests above can fail)."""
    fake = tmp_path / "analysis"
    fake.mkdir()
    (fake / "m.py").write_text("def f():\n    from imunoise.daq import x\n")
    for pkg in ALLOWED:
        if pkg != "analysis":
            (tmp_path / pkg).mkdir()
    monkeypatch.setattr(__import__(__name__, fromlist=["REPO"]), "REPO", tmp_path)
    assert _edges() == {("analysis", "daq"): ["analysis/m.py"]}


def test_every_import_of_the_project_names_the_imunoise_namespace():
    """``analysis``, ``core`` and the rest install only as ``imunoise.analysis`` ...: an import
    of the bare name works in a checkout and fails for every user of the wheel."""
    bare = {p for p in ALLOWED if p != "imunoise"}
    found = []
    for folder in [*ALLOWED, "tests", "bench", "examples"]:
        for path in sorted((REPO / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                found += [f"{path.relative_to(REPO)}: {n}" for n in names
                          if n.split(".")[0] in bare]
    assert not found, found


def test_the_wheel_lists_every_package_folder():
    import tomllib

    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapping: dict[str, str] = config["package-dir"]
    on_disk = set()
    for name, folder in mapping.items():
        for init in (REPO / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO / folder).parts
            on_disk.add(".".join((name, *rel)))
    assert set(config["packages"]) == on_disk
