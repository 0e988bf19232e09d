"""Fixtures shared by the whole suite."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import pytest

from tests.shared_paths import ABSENT, SHARED_DATA, SHARED_REFERENCE

# the parsed-record cache (imunoise.daq.readers.record_cache) of this test process, and of the
# commands it starts: a run never meets a user's entries or another run's, and leaves none
_CACHE = tempfile.mkdtemp(prefix="imunoise-test-cache-")
os.environ["IMUNOISE_CACHE_DIR"] = _CACHE
atexit.register(shutil.rmtree, _CACHE, True)

TESTS = Path(__file__).resolve().parent
REALTIME = ("live", "web", "daq", "imunoise/test_record_command.py",
            "imunoise/test_serve_command.py")
"""Tests (folders or files under tests/) whose outcome depends on the host keeping time: live
acquisition against a device's clock, serving while recording, lost-sample counts. `make test`
runs them on their own after the others, which it runs two at a time (``-n 2``), so that no
other test competes with them for the CPUs."""


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark the tests under :data:`REALTIME` ``realtime``."""
    for item in items:
        rel = item.path.resolve().relative_to(TESTS).as_posix()
        if any(rel == r or rel.startswith(r + "/") for r in REALTIME):
            item.add_marker(pytest.mark.realtime)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (real recordings and reference results); skips when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(ABSENT)
    return SHARED_DATA


@pytest.fixture(scope="session")
def shared_reference() -> Path:
    """``../shared/reference`` (hardware facts, the Compose schema); skips when it is absent."""
    if not SHARED_REFERENCE.is_dir():
        pytest.skip(ABSENT)
    return SHARED_REFERENCE
