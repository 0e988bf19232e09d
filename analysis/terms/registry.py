"""The vocabulary of terms: every module of this package that defines ``TERM`` (a
:class:`~imunoise.analysis.terms.base.Term` instance) or ``TERMS`` (several) is registered, ordered
by ``Term.order``. Adding a term is adding its module; nothing else lists term names."""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from imunoise.analysis.terms.base import Term, TermError

_SKIP = {"base", "registry", "spec"}

TERMS: dict[str, Term] = {}
"""Registered terms by name, in vocabulary order."""


def register(term: Term) -> Term:
    """Add ``term`` to the vocabulary (a second term of the same name is an error)."""
    if term.name in TERMS and TERMS[term.name] is not term:
        raise TermError(f"two terms are called {term.name!r}")
    TERMS[term.name] = term
    ordered = sorted(TERMS.values(), key=lambda t: (t.order, t.name))
    TERMS.clear()
    TERMS.update((t.name, t) for t in ordered)
    return term


def _discover() -> None:
    # the modules beside this one (not the package object, whose import runs this module)
    for info in pkgutil.iter_modules([str(Path(__file__).parent)]):
        if info.name in _SKIP or info.name.startswith("_"):
            continue
        module = importlib.import_module(f"imunoise.analysis.terms.{info.name}")
        found = list(getattr(module, "TERMS", ()))
        if hasattr(module, "TERM"):
            found.append(module.TERM)
        for term in found:
            register(term)


def term_names(*, live: bool | None = None, kind: str | None = None) -> tuple[str, ...]:
    """Names of the registered terms in vocabulary order; ``live=True`` keeps those the live
    service can fit, ``kind`` those of one kind (``"additive"``, ``"filter"``)."""
    return tuple(n for n, t in TERMS.items()
                 if (live is None or t.live == live) and (kind is None or t.kind == kind))


def get_term(name: str) -> Term:
    """The term called ``name``; :class:`TermError` naming the valid terms otherwise."""
    try:
        return TERMS[name]
    except KeyError:
        raise TermError(f"unknown term {name!r}; valid terms: {', '.join(TERMS)}") from None


def validate_params(name: str, params: dict[str, float], fs_hz: float | None = None) -> None:
    """Raise :class:`TermError` naming any parameter of term ``name`` that is missing, unknown,
    not finite or outside its physical range (a frequency also below Nyquist)."""
    get_term(name).validate(dict(params), fs_hz)


Model = Sequence[tuple[str, dict[str, float]]]


def _split(model: Model) -> tuple[list[tuple[Term, dict]], list[tuple[Term, dict]]]:
    additive, filters = [], []
    for name, params in model:
        term = get_term(name)
        (filters if term.kind == "filter" else additive).append((term, params))
    return additive, filters


def model_avar(model: Model, tau_s: np.ndarray, fs_hz: float, *, checked: bool = True
               ) -> np.ndarray:
    """Allan variance (units^2) of a model ``[(term, params)]`` at ``tau_s`` (s).

    Independent additive terms add. A filter term (at most one) replaces the sum of the
    ``role == "noise"`` terms by their filtered Allan variance; the other terms add as they are.
    ``checked=False`` skips the parameter checks (inner loops of a fit)."""
    tau = np.atleast_1d(np.asarray(tau_s, dtype=np.float64))
    fs = float(fs_hz)
    additive, filters = _split(model)
    if len(filters) > 1:
        raise TermError("a model holds at most one output filter")
    total = np.zeros_like(tau)
    through = filters[0] if filters else None
    noise = []
    for term, params in additive:
        if through is not None and term.role == "noise":
            noise.append((term, params))
            continue
        total += term.avar(tau, fs, **params) if checked else term.avar_fast(tau, fs, params)
    if through is not None:
        term, params = through
        total += term.filtered_avar(noise, tau, fs, params)
    return total


def model_psd(model: Model, f_hz: np.ndarray, fs_hz: float, *, continuous_only: bool = False
              ) -> np.ndarray:
    """One-sided PSD (units^2/Hz) of a model; a filter multiplies the noise terms' PSD.
    ``continuous_only`` leaves out spectral lines and record-driven terms (for plotting a
    density)."""
    f = np.atleast_1d(np.asarray(f_hz, dtype=np.float64))
    fs = float(fs_hz)
    additive, filters = _split(model)
    noise = np.zeros_like(f)
    other = np.zeros_like(f)
    for term, params in additive:
        if continuous_only and (not term.continuous_psd or term.role == "regressor"):
            continue
        if term.role == "noise":
            noise += term.psd(f, fs, **params)
        else:
            other += term.psd(f, fs, **params)
    for term, params in filters:
        noise = noise * term.response(f, fs, params)
    return noise + other
