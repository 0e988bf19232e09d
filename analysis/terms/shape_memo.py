"""A term's Allan-variance shape remembered for the last few parameter values.

A fit's finite-difference Jacobian moves one parameter at a time, so the shape of every other
term is asked for again at the same parameters: with three resonances in a model that was
most of a fit's time. A term whose Allan variance is its amplitude squared times a shape
(``sigma * sigma * shape``) keeps the shape here; it gets back the very array it computed
before, so a fit's numbers are those without the memo.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable

import numpy as np

KEPT = 256
"""Shapes kept per term (a few kilobytes); the memo empties when full."""


class ShapeMemo:
    """``make()`` remembered under a key (the averaging times and the shape parameters)."""

    def __init__(self, kept: int = KEPT) -> None:
        self._kept = kept
        self._shapes: dict[Hashable, np.ndarray] = {}
        self._lock = threading.Lock()

    def get(self, key: Hashable, make: Callable[[], np.ndarray]) -> np.ndarray:
        """The array ``make()`` gave for ``key`` (read-only), computing it on a miss."""
        with self._lock:
            hit = self._shapes.get(key)
        if hit is not None:
            return hit
        shape = make()
        shape.setflags(write=False)
        with self._lock:
            if len(self._shapes) >= self._kept:
                self._shapes.clear()
            self._shapes[key] = shape
        return shape
