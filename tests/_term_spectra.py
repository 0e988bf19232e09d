"""A term's Allan variance against the integral of its own spectrum (the terms' tests)."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.terms import get_term


def assert_avar_integrates_the_psd(name: str, params: dict[str, float], m: np.ndarray,
                                   fs_hz: float, rtol: float = 1e-4) -> None:
    """Term ``name`` with ``params`` (``sigma`` 1) has unit variance, and its Allan variance
    at averaging factors ``m`` equals its PSD integrated through the Allan filter
    ``|H_m(u)|^2 = 4 sin^4(pi u m) / (m^2 sin^2(pi u))`` (u = f / fs) on 2e6 frequencies."""
    term = get_term(name)
    u = np.linspace(0.0, 0.5, 2_000_001)[1:]
    du = u[1] - u[0]
    s = term.psd(u * fs_hz, fs_hz, **params)
    assert np.sum(s) * du * fs_hz == pytest.approx(1.0, rel=rtol)
    numeric = [0.5 * fs_hz * du * np.sum(s * 4 * np.sin(np.pi * u * k) ** 4
                                         / (k * k * np.sin(np.pi * u) ** 2)) for k in m]
    np.testing.assert_allclose(term.avar(m / fs_hz, fs_hz, **params), numeric, rtol=rtol)
