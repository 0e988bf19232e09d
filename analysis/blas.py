"""Keeping BLAS single-threaded around many short vector operations.

The Allan kernels call tens of thousands of dot products on cache-sized chunks. A
multi-threaded BLAS hands each to a pool of spinning threads, which on a busy two-core
machine costs tens of times the work itself; one thread is faster.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import ParamSpec, TypeVar

from threadpoolctl import ThreadpoolController

_CONTROLLER = ThreadpoolController()


def single_thread_blas() -> AbstractContextManager:
    """Context manager limiting every loaded BLAS library to one thread (about 30 us)."""
    return _CONTROLLER.limit(limits=1, user_api="blas")


_P = ParamSpec("_P")
_R = TypeVar("_R")


def one_blas_thread(fn: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorator: ``fn`` runs with BLAS limited to one thread (:func:`single_thread_blas`).

    For code made of many small matrix operations (a model fit's eigen-decompositions and
    least-squares steps on matrices of a few dozen rows): each is far too small to share,
    and a second BLAS thread only waits to be scheduled on a busy machine."""

    @functools.wraps(fn)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        # a controller made now (under 1 ms) also sees a BLAS loaded after this module, as
        # scipy's own OpenBLAS is when scipy is imported later
        with ThreadpoolController().limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper
