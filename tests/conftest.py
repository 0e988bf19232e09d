"""Fixtures shared by the whole suite."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.shared_paths import ABSENT, SHARED_DATA, SHARED_REFERENCE


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
