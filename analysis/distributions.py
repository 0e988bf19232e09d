"""Tail probabilities and quantiles of the chi-square, normal, Student t and F distributions.

The same numbers as ``scipy.stats.chi2``, ``norm``, ``t`` and ``f`` for the methods used here
(``sf``, ``cdf``, ``isf``, ``ppf``, ``logsf``, ``logcdf``), computed by the special functions
that scipy.stats itself calls, with its conventions at the edges: a point outside the support
has probability 0 or 1, ``isf(0)`` is the upper end of the support and ``isf(1)`` the lower,
a probability outside [0, 1] or a degree of freedom that is not positive gives NaN.

Written here rather than imported because importing ``scipy.stats`` builds every one of its
distributions and parses their docstrings: about half a second each time a command starts,
which every ``imunoise fit`` or ``diagnose`` paid, several hundred times over in a batch.
Scalars in give numpy scalars out, arrays give arrays, as scipy.stats does.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.special as sc

__all__ = ["chi2", "f", "norm", "t"]


def _out(value: np.ndarray) -> Any:
    """A 0-d result as a numpy scalar, as scipy.stats gives it."""
    return value[()] if value.ndim == 0 else value


def _quantile(q: Any, fn: Any, lo: float, hi: float, bad: Any = False) -> Any:
    """``fn(q)`` for ``0 < q < 1``, ``lo`` at q = 0 and ``hi`` at q = 1, NaN outside [0, 1] or
    where ``bad`` (a degree of freedom that is not positive)."""
    q = np.asarray(q, dtype=np.float64)
    inner = (q > 0.0) & (q < 1.0)
    with np.errstate(all="ignore"):
        v = fn(np.where(inner, q, 0.5))
    v = np.where(inner, v, np.where(q == 0.0, lo, np.where(q == 1.0, hi, np.nan)))
    return _out(np.where(bad, np.nan, v).astype(np.float64))


def _positive(*dfs: Any) -> Any:
    """Where any degree of freedom is not a positive number."""
    bad: Any = False
    for df in dfs:
        bad = bad | ~(np.asarray(df, dtype=np.float64) > 0.0)
    return bad


class _Chi2:
    """The chi-square distribution with ``df`` degrees of freedom (support x >= 0)."""

    @staticmethod
    def _prob(x: Any, df: Any, fn: Any, below: float) -> Any:
        x = np.asarray(x, dtype=np.float64)
        with np.errstate(all="ignore"):
            v = np.where(x < 0.0, below, fn(df, np.maximum(x, 0.0)))
        return _out(np.where(_positive(df), np.nan, v).astype(np.float64))

    def sf(self, x: Any, df: Any) -> Any:
        """P(X > x)."""
        return self._prob(x, df, sc.chdtrc, 1.0)

    def cdf(self, x: Any, df: Any) -> Any:
        """P(X <= x)."""
        return self._prob(x, df, sc.chdtr, 0.0)

    def logsf(self, x: Any, df: Any) -> Any:
        """log P(X > x): above the median the log of the tail, below it log1p of minus the
        other tail, so that neither side loses digits (-inf where it underflows)."""
        return self._log_tail(x, df, upper=True)

    def logcdf(self, x: Any, df: Any) -> Any:
        """log P(X <= x), computed as :meth:`logsf` is."""
        return self._log_tail(x, df, upper=False)

    def _log_tail(self, x: Any, df: Any, upper: bool) -> Any:
        x = np.asarray(x, dtype=np.float64)
        near, far = (self.sf, self.cdf) if upper else (self.cdf, self.sf)
        beyond = x > self.ppf(0.5, df) if upper else x < self.ppf(0.5, df)
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.where(beyond, np.log(np.asarray(near(x, df))),
                         np.log1p(-np.asarray(far(x, df))))
        return _out(np.asarray(v, dtype=np.float64))

    def isf(self, q: Any, df: Any) -> Any:
        """The x with P(X > x) = q."""
        return _quantile(q, lambda p: sc.chdtri(df, p), np.inf, 0.0, _positive(df))

    def ppf(self, q: Any, df: Any) -> Any:
        """The x with P(X <= x) = q."""
        return _quantile(q, lambda p: 2.0 * sc.gammaincinv(np.asarray(df) / 2.0, p), 0.0,
                         np.inf, _positive(df))


class _Norm:
    """The standard normal distribution."""

    def sf(self, x: Any) -> Any:
        """P(Z > x)."""
        return _out(np.asarray(sc.ndtr(-np.asarray(x, dtype=np.float64))))

    def cdf(self, x: Any) -> Any:
        """P(Z <= x)."""
        return _out(np.asarray(sc.ndtr(np.asarray(x, dtype=np.float64))))

    def isf(self, q: Any) -> Any:
        """The z with P(Z > z) = q."""
        return _quantile(q, lambda p: -sc.ndtri(p), np.inf, -np.inf)

    def ppf(self, q: Any) -> Any:
        """The z with P(Z <= z) = q."""
        return _quantile(q, sc.ndtri, -np.inf, np.inf)


class _T:
    """Student's t distribution with ``df`` degrees of freedom."""

    def sf(self, x: Any, df: Any) -> Any:
        """P(T > x)."""
        with np.errstate(all="ignore"):
            v = sc.stdtr(df, -np.asarray(x, dtype=np.float64))
        return _out(np.where(_positive(df), np.nan, v).astype(np.float64))

    def isf(self, q: Any, df: Any) -> Any:
        """The x with P(T > x) = q."""
        return _quantile(q, lambda p: -sc.stdtrit(df, p), np.inf, -np.inf, _positive(df))

    def ppf(self, q: Any, df: Any) -> Any:
        """The x with P(T <= x) = q."""
        return _quantile(q, lambda p: sc.stdtrit(df, p), -np.inf, np.inf, _positive(df))


class _F:
    """The F distribution with ``dfn`` and ``dfd`` degrees of freedom (support x >= 0)."""

    def sf(self, x: Any, dfn: Any, dfd: Any) -> Any:
        """P(F > x)."""
        x = np.asarray(x, dtype=np.float64)
        with np.errstate(all="ignore"):
            v = np.where(x < 0.0, 1.0, sc.fdtrc(dfn, dfd, np.maximum(x, 0.0)))
        return _out(np.where(_positive(dfn, dfd), np.nan, v).astype(np.float64))


chi2 = _Chi2()
norm = _Norm()
t = _T()
f = _F()
