"""Keeping BLAS single-threaded around many short vector operations.

The Allan kernels call tens of thousands of dot products on cache-sized chunks. A
multi-threaded BLAS hands each to a pool of spinning threads, which on a busy two-core
machine costs tens of times the work itself; one thread is faster.
"""

from __future__ import annotations

from contextlib import AbstractContextManager

from threadpoolctl import ThreadpoolController

_CONTROLLER = ThreadpoolController()


def single_thread_blas() -> AbstractContextManager:
    """Context manager limiting every loaded BLAS library to one thread (about 30 us)."""
    return _CONTROLLER.limit(limits=1, user_api="blas")
