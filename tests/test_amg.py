"""Tests for glsldiff.oracle.amg: the Jacobi spectral estimates behind the smoothing damping and
the smoothed-aggregation prolongations (pyamg run one level at a time).

References: dense ``eigvalsh`` of ``D^-1/2 A D^-1/2`` (ARPACK to 1e-10 past 2000 unknowns);
one ``pyamg.smoothed_aggregation_solver`` call. Matrices: P1 systems of a pillowed sphere
(glsldiff.oracle.fem.assemble_tet) with constant and with random node kappa, mu (contrast
1e8), 7-point operators with random conductances (contrast 1e12, anisotropy 1e-4), a 7-point
Laplacian.
"""
from __future__ import annotations

import copy

import numpy as np
import pyamg
import pytest
import scipy.sparse as sp

from glsldiff.core.blas import blas_threads
from glsldiff.core.rng import pinned_global_rng
from glsldiff.grids.tetrahedral.fem_grid import build_fem_grid
from glsldiff.mesh import sphere_mesh
from glsldiff.oracle.amg import AMG_DEFAULTS, build_prolongations, jacobi_lambda_bound, jacobi_lambda_max
from glsldiff.oracle.fem import assemble_tet
from glsldiff.system.tet_problem import TetProblem

from gather_systems import laplacian7   # tests/gather_systems.py


def heterogeneous7(m: int, contrast: float, anisotropy: float, seed: int) -> sp.csr_matrix:
    """``m^3`` 7-point ``-div(k grad)`` with log-uniform node ``k`` over ``contrast`` (harmonic
    means on the edges, z edges scaled by ``anisotropy``) plus a small mass."""
    k = np.exp(np.random.default_rng(seed).uniform(0.0, np.log(contrast), m**3))
    idx = np.arange(m**3).reshape(m, m, m)
    rows, cols, vals = [], [], []
    for axis, w in ((0, 1.0), (1, 1.0), (2, anisotropy)):
        a = np.take(idx, range(m - 1), axis=axis).ravel()
        b = np.take(idx, range(1, m), axis=axis).ravel()
        ke = w * 2.0 * k[a] * k[b] / (k[a] + k[b])
        rows += [a, b]
        cols += [b, a]
        vals += [-ke, -ke]
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(m**3, m**3))
    return (A + sp.diags(-np.asarray(A.sum(axis=1)).ravel() + 1e-3 * k.min())).tocsr()


def contrast_p1(seed: int) -> list[sp.csr_matrix]:
    """P1 channel matrices of the 10 mm sphere (n = 4) with random node kappa over 1e-4..1e4, a
    sharp interface (half the nodes at 1e-4) and mu over 1e-3..10."""
    g = build_fem_grid(sphere_mesh(10.0, subdivisions=3), n=4, cube_size=5.0)
    rng = np.random.default_rng(seed)
    N = len(g.positions)
    kappa = np.exp(rng.uniform(np.log(1e-4), np.log(1e4), (N, 3)))
    kappa[: N // 2] = 1e-4 * np.array([1.0, 10.0, 100.0])
    mu = np.exp(rng.uniform(np.log(1e-3), np.log(10.0), (N, 3)))
    s = assemble_tet(TetProblem(g, kappa, mu, np.ones((len(g.surface_nodes), 3)), C=2.0))
    return [s.block(c)[0].tocsr() for c in range(3)]


def exact_lambda_max(A: sp.csr_matrix) -> float:
    s = 1.0 / np.sqrt(A.diagonal())
    with blas_threads(1):
        return float(np.linalg.eigvalsh(s[:, None] * A.toarray() * s[None, :]).max())


def test_lambda_bound_is_just_above_lambda_max(fem_system):
    """The Lanczos estimate is >= ``lambda_max(D^-1 A)`` (dense; ARPACK to 1e-10 above 2000
    unknowns) and at most ``tol`` (2e-3) above it on every matrix (measured +0.13 to +0.2 %),
    kappa contrasts up to 1e12 included; below 400 unknowns it is the dense eigenvalue."""
    mats = [fem_system[0][0], contrast_p1(1)[2], laplacian7(10, 0.3, 0.05, 0.25)]
    mats += [heterogeneous7(10, 1e8, 1.0, s) for s in range(2)] + [heterogeneous7(10, 1e12, 1e-4, 2)]
    mats.append(heterogeneous7(8, 1e10, 1e-2, 4))
    for i, A in enumerate(mats):
        assert A.shape[0] > 400
        lam = exact_lambda_max(A) if A.shape[0] < 2000 else jacobi_lambda_max(A, tol=1e-10)
        bound = jacobi_lambda_bound(A)
        assert lam <= bound <= lam * (1.0 + 2e-3), (i, lam, bound)
    small = heterogeneous7(7, 1e6, 1.0, 3)
    assert jacobi_lambda_bound(small) == pytest.approx(exact_lambda_max(small), rel=1e-12)


def one_call(A: sp.csr_matrix, amg: dict | None, max_coarse: int, max_levels: int) -> list[sp.csr_matrix]:
    """The prolongations of one ``smoothed_aggregation_solver`` call (the reference)."""
    with pinned_global_rng():
        ml = pyamg.smoothed_aggregation_solver(sp.csr_matrix(A), symmetry="symmetric", max_coarse=max_coarse,
                                               max_levels=max_levels, keep=False, **{**AMG_DEFAULTS, **(amg or {})})
    return [sp.csr_matrix(lv.P) for lv in ml.levels[:-1]]


def same_as_one_call(A: sp.csr_matrix, amg: dict | None, max_coarse: int, max_levels: int) -> int:
    """Assert that ``build_prolongations`` gives :func:`one_call`'s prolongations bit for bit
    and leaves ``amg`` as it was; the number of prolongations."""
    given = copy.deepcopy(amg)
    got = build_prolongations(A, max_coarse, max_levels, given)
    assert given == amg
    want = one_call(A, copy.deepcopy(amg), max_coarse, max_levels)
    assert len(got) == len(want)
    for P, Q in zip(got, want):
        assert P.shape == Q.shape and np.array_equal(P.indptr, Q.indptr) and np.array_equal(P.indices, Q.indices)
        assert np.array_equal(P.data, Q.data)
    return len(got)


@pytest.mark.parametrize("amg", [None, {"smooth": "jacobi"}, {"improve_candidates": None},
                                 {"smooth": ("energy", {"degree": 2}), "aggregate": "naive"},
                                 {"strength": ["evolution", "symmetric"]},
                                 {"strength": ("symmetric", {"theta": 0.0})}])
def test_prolongations_are_one_pyamg_calls(fem_system, amg):
    """``build_prolongations`` (pyamg one level at a time under the evolution strength; one
    call otherwise) gives one pyamg call's prolongations bit for bit, options levelled as pyamg
    levels them (improved candidates on the first level only, lists per level), with three
    coarsening depths; the caller's options are left as they were."""
    with blas_threads(1):        # as GlslSparseMultigrid runs it (and 2-4x faster on busy cores)
        depths = [same_as_one_call(fem_system[0][0], amg, *limits) for limits in ((300, 10), (50, 3), (10, 10))]
    assert max(depths) >= 2
