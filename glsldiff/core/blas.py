"""The thread count of the BLAS behind numpy's and scipy's compiled routines (OpenBLAS), set
with threadpoolctl.

OpenBLAS wakes its worker threads around its calls; on a busy machine with few cores the
waits dominate small, frequent calls (L-BFGS-B on a few thousand unknowns: 8 ms per
iteration on 2 shared cores, 0.2 ms on one thread). Its dot product runs on one thread up
to :data:`DOT_SERIAL_LENGTH` elements whatever the thread count, so below that length one
thread gives the same bits as many; above it the partial sums, and so the result's last
bits, depend on the thread count (the default bunny's grid differs with
``OPENBLAS_NUM_THREADS=1``), so callers keep the default there.
"""
from __future__ import annotations

from typing import Any

from threadpoolctl import threadpool_limits

__all__ = ["DOT_SERIAL_LENGTH", "blas_threads"]

#: Longest vector OpenBLAS's dot product sums on one thread (kernel/x86_64/ddot.c).
DOT_SERIAL_LENGTH = 10_000


def blas_threads(threads: int) -> Any:
    """A context manager: the block runs with the BLAS libraries on ``threads`` threads."""
    return threadpool_limits(limits=threads, user_api="blas")
