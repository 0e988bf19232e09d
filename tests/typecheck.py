"""Type-check the library as it installs: ``python -m tests.typecheck`` (part of make test).

The folders ``core/ analysis/ daq/ live/ fleet/ web/`` install as ``imunoise.core`` and so on
(pyproject's package-dir mapping), which mypy cannot follow from the checkout, nor through the
editable install's import hook. So a tree of symbolic links with the installed layout is kept in
``.mypy_cache/tree/imunoise`` and mypy checks the package ``imunoise`` there, with the settings
of ``[tool.mypy]`` in pyproject.toml and its incremental cache in ``.mypy_cache``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
TREE = REPO / ".mypy_cache" / "tree"


def build_tree(tree: Path = TREE) -> Path:
    """The link tree of the installed layout (rebuilt each time: cheap, and never stale)."""
    mapping = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-dir"]
    top = tree / "imunoise"
    if top.exists():
        for entry in top.iterdir():
            entry.unlink()
    top.mkdir(parents=True, exist_ok=True)
    mapped = {name.split(".", 1)[1]: folder for name, folder in mapping.items() if "." in name}
    for entry in sorted((REPO / mapping["imunoise"]).iterdir()):
        if entry.name != "__pycache__" and (entry.suffix == ".py" or entry.is_dir()):
            (top / entry.name).symlink_to(entry)
    for name, folder in mapped.items():
        (top / name).symlink_to(REPO / folder)
    return tree


def main() -> int:
    tree = build_tree()
    env = dict(os.environ, MYPYPATH=str(tree))
    return subprocess.call([sys.executable, "-m", "mypy", "--config-file",
                            str(REPO / "pyproject.toml"), "-p", "imunoise"], cwd=REPO, env=env)


if __name__ == "__main__":
    sys.exit(main())
