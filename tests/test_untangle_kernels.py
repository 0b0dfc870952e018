"""The untangling's compiled loops (glsldiff.grids.fem_grid) against their numpy twins: the
shortfall objective and its gradient on the free nodes (random tetrahedra, some inverted, fixed
and free corners), the tetrahedron volumes (the kernel behind signed_volumes); and the
one-thread BLAS block that L-BFGS-B runs in."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg  # noqa: F401  (loads scipy's BLAS for threadpoolctl to see)

from glsldiff.core import blas
from glsldiff.grids.tetrahedral.fem_grid import _iterations, _shortfall
from glsldiff.grids.tetrahedral.pillow import _signed_volumes_of, signed_volumes, six_volumes


def _numpy_shortfall(x, X, free, tets, target, scale):
    """The objective as numpy computed it before the kernel: all nodes copied, the corner
    gradients of 6 V by cross products, scattered with ``np.add.at``."""
    Y = X.copy()
    Y[free] = x
    P = Y[tets]
    a, b, c = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]
    det = np.einsum("ij,ij->i", np.cross(a, b), c) / scale
    g1, g2, g3 = np.cross(b, c), np.cross(c, a), np.cross(a, b)
    G = np.stack([-(g1 + g2 + g3), g1, g2, g3], axis=1) / scale
    r = np.maximum(target - det, 0.0)
    grad = np.zeros_like(Y)
    np.add.at(grad, tets.ravel(), (-2.0 * r[:, None, None] * G).reshape(-1, 3))
    return float((r * r).sum()), grad[free]


def _problem(seed: int = 0):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(40, 3))
    tets = np.array([rng.choice(40, 4, replace=False) for _ in range(120)])
    free = np.flatnonzero(rng.random(40) < 0.6)
    slot = np.full(40, -1, dtype=np.int64)
    slot[free] = np.arange(len(free))
    det = 6.0 * signed_volumes(X, tets)
    return rng, X, tets, free, slot, det


def test_shortfall_matches_numpy():
    """Value and gradient of the kernel equal the numpy objective's (a third of the
    tetrahedra above their target, some inverted, some with no free corner)."""
    rng, X, tets, free, slot, det = _problem()
    target = np.abs(det) * rng.uniform(0.2, 1.5, len(det))
    scale = 0.37
    x = X[free] + 0.05 * rng.normal(size=(len(free), 3))
    f, g = _shortfall(x, X, slot, tets, target / scale, scale)
    f_np, g_np = _numpy_shortfall(x, X, free, tets, target / scale, scale)
    assert 0 < f and np.isclose(f, f_np, rtol=1e-12)
    np.testing.assert_allclose(g, g_np, rtol=1e-10, atol=1e-12 * np.abs(g_np).max())
    assert (det <= 0).any() and (det > target).any()        # both sides of the hinge occur


def test_shortfall_gradient_is_the_derivative():
    """A central difference of the value along a random direction gives the gradient's."""
    rng, X, tets, free, slot, det = _problem(1)
    target = np.abs(det)
    x, d = X[free].copy(), rng.normal(size=(len(free), 3))
    _, g = _shortfall(x, X, slot, tets, target, 1.0)
    eps = 1e-6
    fp = _shortfall(x + eps * d, X, slot, tets, target, 1.0)[0]
    fm = _shortfall(x - eps * d, X, slot, tets, target, 1.0)[0]
    assert np.isclose((fp - fm) / (2 * eps), float((g * d).sum()), rtol=1e-5)


def test_six_volumes_match_signed_volumes():
    """The kernel behind signed_volumes equals the numpy formula bit for bit (the grid a mesh
    gets must not change), on positions spread over six decades."""
    _, X, tets, _, _, det = _problem(2)
    np.testing.assert_allclose(six_volumes(X, tets), det, rtol=1e-12, atol=1e-14)
    rng = np.random.default_rng(3)
    Y = rng.standard_normal((2000, 3)) * 10.0 ** rng.uniform(-3, 3, (2000, 1))
    T = rng.integers(0, 2000, (50_000, 4))
    assert np.array_equal(signed_volumes(Y, T), _signed_volumes_of(Y[T]))
    assert np.array_equal(six_volumes(Y, T) / 6.0, _signed_volumes_of(Y[T]))


def test_iterations_grow_on_small_problems_only():
    assert _iterations(300, 10, 0) == 300
    assert _iterations(300, 20_000, 3_000_000) == 300
    assert 300 < _iterations(300, 1_500, 3_000_000) <= 3000 and _iterations(300, 10, 3_000_000) == 3000
    assert _iterations(5000, 10, 3_000_000) == 5000


def test_blas_threads_sets_and_restores():
    from threadpoolctl import threadpool_info
    before = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    if not before:
        pytest.skip("no BLAS library found")
    with blas.blas_threads(1):
        assert all(i["num_threads"] == 1 for i in threadpool_info() if i["user_api"] == "blas")
    assert [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"] == before
