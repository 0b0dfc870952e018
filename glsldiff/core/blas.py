"""The thread count of the BLAS behind numpy's and scipy's compiled routines (OpenBLAS), set
with threadpoolctl.

OpenBLAS wakes its worker threads around its calls; on a busy machine with few cores the
waits dominate small, frequent calls (L-BFGS-B on a few thousand unknowns: 8 ms per
iteration on 2 shared cores, 0.2 ms on one thread; on 19,614 unknowns 27-68 s against 2.6 s
for 300 iterations). One thread also makes the result's last bits independent of the
machine's core count (OpenBLAS splits the partial sums of vectors over 10,000 long by thread).
"""
from __future__ import annotations

from typing import Any

from threadpoolctl import threadpool_limits

__all__ = ["blas_threads"]


def blas_threads(threads: int) -> Any:
    """A context manager: the block runs with the BLAS libraries on ``threads`` threads."""
    return threadpool_limits(limits=threads, user_api="blas")
