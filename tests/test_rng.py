"""Reproducible pyamg set-ups (glsldiff.core.rng): the polygrid's harmonic placement and the
AMG hierarchies draw from numpy's global random state through pyamg."""
from __future__ import annotations

import numpy as np
import pyamg

from glsldiff.core.rng import pinned_global_rng


def _prolongator() -> np.ndarray:
    A = pyamg.gallery.poisson((30, 30), format="csr")
    return pyamg.smoothed_aggregation_solver(A, symmetry="symmetric").levels[0].P.toarray()


def test_pinned_setups_are_identical_and_the_callers_state_is_kept():
    np.random.seed(123)
    before = np.random.get_state()[1].copy()
    with pinned_global_rng():
        a = _prolongator()
    assert np.array_equal(np.random.get_state()[1], before)            # the caller's stream goes on untouched
    with pinned_global_rng():
        b = _prolongator()
    assert np.array_equal(a, b)
    c, d = _prolongator(), _prolongator()                                # unpinned: the estimates differ
    assert not np.array_equal(c, d)
