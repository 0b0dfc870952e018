"""Reproducible runs of libraries that draw from numpy's legacy global random state.

pyamg starts its spectral-radius estimates (the smoothed-aggregation set-up) from
``np.random.rand`` vectors, so two set-ups of the same matrix differ in their last digits;
the polygrid's harmonic placement solves with it, and the untangling's L-BFGS amplified those
digits into different grids from run to run (measured: a bone grid's node positions differed
between two builds). :func:`pinned_global_rng` fixes that state for the duration of a call and
restores the caller's afterwards.
"""
from __future__ import annotations

import contextlib
from typing import Iterator

import numpy as np

__all__ = ["pinned_global_rng"]


@contextlib.contextmanager
def pinned_global_rng(seed: int = 0) -> Iterator[None]:
    """Seed numpy's global random state inside the block; restore it on exit."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)
