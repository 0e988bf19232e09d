"""The packages depend on each other in one direction only.

``core`` is below everything; ``analysis`` and ``daq`` sit side by side on it and never import
each other; the live runtime, the fleet catalogue and the HTTP layer come above them; the
command line ``imunoise`` is the top. Inside the ``imunoise`` folder, the analysis pipeline
(``imunoise/pipeline``: reading, channel analysis, the JSON documents) and the file exports
(``imunoise/export``) are layers of their own below the commands; the Python API
(``imunoise/api`` and the package's ``__init__``, which loads it on first use) sits on the
pipeline beside the commands; the package's few modules that carry no logic of their own
(its version, its error types, the progress display, the optional extras) form ``base``,
which every layer above ``core`` may use. Every import counts, also one inside a function.
"""

from __future__ import annotations

import ast
from pathlib import Path

from tests.shared_paths import REPO

# layer -> the project layers it may import
ALLOWED: dict[str, set[str]] = {
    "core": set(),
    "base": {"core"},
    "analysis": {"core"},
    "daq": {"core"},
    "live": {"core", "analysis", "daq"},
    "fleet": {"core", "analysis"},
    "pipeline": {"core", "base", "analysis", "daq"},
    "export": {"core", "base", "analysis", "pipeline"},
    "api": {"core", "base", "analysis", "pipeline"},
    "web": {"core", "base", "analysis", "live", "fleet", "pipeline"},
    "imunoise": {"core", "base", "analysis", "daq", "live", "web", "fleet", "pipeline", "export",
                 "api"},
}

# Where an allowed edge is narrower than the whole layer: (importer, imported) -> the only
# modules of the imported layer it may use. The HTTP layer shows the documents the command line
# prints (one builder, so live and batch numbers cannot be written out differently), and those
# builders import only ``core`` and ``analysis`` (checked below); the rest of the pipeline reads
# files through ``daq``, which the HTTP layer never does.
NARROW: dict[tuple[str, str], set[str]] = {
    ("web", "pipeline"): {"imunoise.pipeline.documents"},
}

# folder of each layer, relative to the repository (``imunoise`` minus its layered folders and
# the ``base`` modules)
FOLDERS: dict[str, str] = {
    "core": "core", "analysis": "analysis", "daq": "daq", "live": "live", "fleet": "fleet",
    "web": "web", "pipeline": "imunoise/pipeline", "export": "imunoise/export",
    "api": "imunoise", "imunoise": "imunoise", "base": "imunoise",
}
BASE_MODULES = {"imunoise.version", "imunoise.errors", "imunoise.progress", "imunoise.extras"}
"""The modules of the ``base`` layer: ``version.py``, ``errors.py``, ``progress.py``,
``extras.py`` of ``imunoise/``."""


def _layer(module: str) -> str:
    """The layer of an imported module: ``imunoise.analysis.fit`` -> ``analysis``,
    ``imunoise.pipeline.reading`` -> ``pipeline``, ``imunoise.errors`` -> ``base``; a module of
    the command-line package itself (``imunoise.cli``) -> ``imunoise``; anything else -> its
    top-level name (a package that is not ours)."""
    parts = module.split(".")
    if parts[0] != "imunoise":
        return parts[0]
    if module in BASE_MODULES:
        return "base"
    if module == "imunoise" or parts[1] == "api":
        return "api"
    if len(parts) > 1 and parts[1] in ALLOWED and parts[1] not in ("imunoise", "base"):
        return parts[1]
    return "imunoise"


def _module_name(path: Path, root: Path) -> str:
    """``imunoise/pipeline/reading.py`` -> ``imunoise.pipeline.reading``, ``analysis/fit.py``
    -> ``imunoise.analysis.fit``, ``x/__init__.py`` -> its package."""
    rel = path.relative_to(root).with_suffix("").parts
    if rel[-1] == "__init__":
        rel = rel[:-1]
    return ".".join(rel if rel and rel[0] == "imunoise" else ("imunoise", *rel))


def _files(layer: str, root: Path) -> list[Path]:
    """The source files of one layer."""
    files = sorted((root / FOLDERS[layer]).rglob("*.py"))
    if FOLDERS[layer] != "imunoise":
        return files
    return [f for f in files if (_layer(_module_name(f, root)) == layer)]


def _imports(path: Path) -> list[str]:
    """Every module an absolute import statement of ``path`` names (``from a import b`` names
    ``a``)."""
    names: list[str] = []
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
    return names


def _edges() -> dict[tuple[str, str], list[str]]:
    """(importer layer, imported layer) -> the files where that import happens."""
    edges: dict[tuple[str, str], list[str]] = {}
    for pkg in ALLOWED:
        for path in _files(pkg, REPO):
            for name in _imports(path):
                top = _layer(name)
                if top in ALLOWED and top != pkg:
                    edges.setdefault((pkg, top), []).append(str(path.relative_to(REPO)))
    return edges


def test_no_import_goes_against_the_layers():
    bad = {f"{a} -> {b}": sorted(set(files)) for (a, b), files in _edges().items()
           if b not in ALLOWED[a]}
    assert not bad, f"imports against the layers: {bad}"


def test_narrow_edges_use_only_their_modules():
    """The HTTP layer imports from the pipeline only its documents, and those import nothing
    that reads files (only ``core`` and ``analysis``)."""
    bad = []
    for (importer, imported), allowed in NARROW.items():
        for path in _files(importer, REPO):
            bad += [f"{path.relative_to(REPO)}: {name}" for name in _imports(path)
                    if _layer(name) == imported and name not in allowed]
        for module in allowed:
            path = REPO / (module.replace(".", "/") + ".py")
            bad += [f"{path.relative_to(REPO)}: {name}" for name in _imports(path)
                    if _layer(name) not in ("core", "analysis") and name.startswith("imunoise")]
    assert not bad, bad


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
    (tmp_path / "imunoise" / "pipeline").mkdir(parents=True)
    (tmp_path / "imunoise" / "pipeline" / "p.py").write_text("from imunoise.cli import main\n")
    (tmp_path / "imunoise" / "errors.py").write_text("from imunoise.export import files\n")
    for folder in FOLDERS.values():
        (tmp_path / folder).mkdir(parents=True, exist_ok=True)
    monkeypatch.setattr(__import__(__name__, fromlist=["REPO"]), "REPO", tmp_path)
    assert _edges() == {("analysis", "daq"): ["analysis/m.py"],
                        ("pipeline", "imunoise"): ["imunoise/pipeline/p.py"],
                        ("base", "export"): ["imunoise/errors.py"]}


def test_every_import_of_the_project_names_the_imunoise_namespace():
    """``analysis``, ``core`` and the rest install only as ``imunoise.analysis`` ...: an import
    of the bare name works in a checkout and fails for every user of the wheel."""
    bare = {"core", "analysis", "daq", "live", "fleet", "web"}  # folders at the top
    found = []
    for folder in [*bare, "imunoise", "tests", "bench", "examples"]:
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
