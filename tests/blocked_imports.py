"""Run the real command line in a subprocess in which some installed modules cannot be
imported, as on an install without an optional extra.

A ``sitecustomize`` module put first on ``PYTHONPATH`` adds an import finder that refuses the
modules named in ``IMUNOISE_TEST_BLOCK`` (comma-separated top-level names) and everything
below them.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.shared_paths import REPO

SITECUSTOMIZE = '''
import os
import sys

_BLOCKED = {n for n in os.environ.get("IMUNOISE_TEST_BLOCK", "").split(",") if n}


class _Refuse:
    """Finder that makes the blocked modules look uninstalled."""

    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in _BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


sys.meta_path.insert(0, _Refuse())
'''


def run_without(modules: list[str], args: list[str], folder: Path,
                cwd: Path | None = None, timeout: float = 120
                ) -> subprocess.CompletedProcess[str]:
    """``python ARGS`` with ``modules`` not importable; ``folder`` holds the sitecustomize."""
    (folder / "sitecustomize.py").write_text(SITECUSTOMIZE)
    env = dict(os.environ, IMUNOISE_TEST_BLOCK=",".join(modules),
               PYTHONPATH=os.pathsep.join([str(folder), str(REPO)]))
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env,
                          cwd=cwd or folder, timeout=timeout)
