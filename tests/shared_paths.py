"""Where the shared reference material sits: ``../shared`` beside the repository.

A user's clone has no ``../shared``; tests that need it skip with a reason (see the
``shared_data`` fixture in ``tests/conftest.py``). Paths here do not depend on the working
directory.
"""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared"
SHARED_DATA = SHARED / "data"
SHARED_REFERENCE = SHARED / "reference"
ABSENT = ("the shared reference folder ../shared is absent "
          "(it sits beside the repository, not in a user's clone)")
