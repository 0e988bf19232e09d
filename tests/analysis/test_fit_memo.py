"""A memo shared by several fits gives each curve its own solutions.

The memo's keys name a curve (or a series) by ``id()``; CPython gives a freed object's id to
the next object of its size, so a memo reused across temporary curves returned, before the
memo held its curves, the first curve's fit for every later one (N stayed 0.0994 while the
curve's level doubled, see :func:`test_temporaries_do_reuse_ids` for why this case is real).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from imunoise.analysis.allan import oadev
from imunoise.analysis.fit import fit_allan, fit_series

FS = 100.0
SCALES = (1.0, 2.0, 4.0, 8.0)


@pytest.fixture(scope="module")
def white():
    return np.random.default_rng(1).normal(size=20_000)


def _curve(base, scale: float) -> SimpleNamespace:
    """A curve-like object of the base curve's deviation times ``scale``."""
    return SimpleNamespace(fs_hz=base.fs_hz, tau_s=base.tau_s, m=base.m, dev=base.dev * scale,
                           n_terms=base.n_terms, edf=base.edf)


def test_temporaries_do_reuse_ids(white):
    """The situation the memo must survive happens here: consecutive temporary curves get the
    same id (so the tests below would see a memo keyed by id alone)."""
    base = oadev(white, FS, m="octave", ci=0.95)
    ids = []
    for scale in SCALES:
        curve = _curve(base, scale)
        ids.append(id(curve))
        del curve
    assert len(set(ids)) < len(ids)


def test_a_shared_memo_fits_each_temporary_curve_anew(white):
    base = oadev(white, FS, m="octave", ci=0.95)
    alone = fit_allan(base, "white", intervals="jacobian").terms[0].params["N"]
    memo: dict = {}
    for scale in SCALES:
        got = fit_allan(_curve(base, scale), "white", memo=memo,
                        intervals="jacobian").terms[0].params["N"]
        # the white level scales with the deviation: exactly, the fit being linear in N^2
        assert got == pytest.approx(alone * scale, rel=1e-9)


def test_a_shared_memo_fits_each_temporary_series_anew(white):
    alone = fit_series(white, FS, "white", intervals="jacobian")[0].terms[0].params["N"]
    memo: dict = {}
    for scale in SCALES:
        result, _ = fit_series(white * scale, FS, "white", memo=memo, intervals="jacobian")
        assert result.terms[0].params["N"] == pytest.approx(alone * scale, rel=1e-9)


def test_the_memo_still_serves_the_same_curve(white):
    """Holding the curves keeps the memo's purpose: a second fit of the same curve with the
    same model takes the stored solution (same numbers, one entry)."""
    curve = oadev(white, FS, m="octave", ci=0.95)
    memo: dict = {}
    first = fit_allan(curve, "white,random_walk", memo=memo, intervals="jacobian")
    entries = len(memo)
    second = fit_allan(curve, "white,random_walk", memo=memo, intervals="jacobian")
    assert len(memo) == entries
    assert second.terms[0].params == first.terms[0].params


def test_models_with_starting_values_share_a_memo_without_taking_each_others_fit(white):
    # a model given as (term, params) pairs starts from those values: it has no memo key.
    # Such fits once all stored their solution under the key None, so the second fit with a
    # memo returned the first one's (another curve's, even another model's)
    curves = [_curve(oadev(white, FS, m="octave", ci=0.95), scale) for scale in (1.0, 3.0)]
    given = [("white", {"N": 0.1}), ("random_walk", {"K": 1e-4})]
    alone = [fit_allan(c, given, intervals="jacobian").terms[0].params["N"] for c in curves]
    memo: dict = {}
    shared = [fit_allan(c, given, memo=memo, intervals="jacobian").terms[0].params["N"]
              for c in curves]
    assert shared == pytest.approx(alone, rel=1e-12)
    assert alone[1] == pytest.approx(3.0 * alone[0], rel=1e-6)


def test_profile_terms_leave_the_other_terms_weak_parameters_without_an_interval():
    # white noise alone: the random walk's amplitude is not determined (a profile gives
    # [0, upper]); a candidate refit that reports only the white term's interval skips it
    from imunoise.analysis.terms import get_term

    rng = np.random.default_rng(21)
    fs = 100.0
    x = rng.normal(0.0, 1e-3 * np.sqrt(fs), 200_000)
    full, _ = fit_series(x, fs, "white,random_walk", intervals="jacobian")
    part, _ = fit_series(x, fs, "white,random_walk", intervals="jacobian", profile_terms={0})
    assert [t.params for t in part.terms] == [t.params for t in full.terms]
    assert part.chi2_per_dof == full.chi2_per_dof
    assert part.terms[0].ci95 == full.terms[0].ci95
    assert full.terms[1].ci95["K"][0] == 0.0 and np.isfinite(full.terms[1].ci95["K"][1])
    assert all(np.isnan(v) for v in part.terms[1].ci95["K"])
    assert not get_term("random_walk").resolved("K", part.terms[1].ci95["K"])
