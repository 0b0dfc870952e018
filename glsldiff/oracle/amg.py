"""The CPU side of algebraic multigrid for the GPU solvers (:mod:`glsldiff.solve.gather_multigrid`):
smoothed-aggregation prolongations (pyamg), Galerkin coarse operators and the Jacobi spectral
estimate behind every damping choice (:mod:`glsldiff.solve.gather`)."""
from __future__ import annotations

from typing import Any

import numpy as np
import pyamg
import scipy.sparse as sp

from glsldiff.core.rng import pinned_global_rng
import scipy.sparse.linalg as spla

__all__ = ["jacobi_lambda_max", "build_prolongations", "galerkin", "AMG_DEFAULTS"]

_DENSE_EIG = 400          # below this many unknowns the eigenvalue is computed densely
#: pyamg options of the hierarchy (see :mod:`glsldiff.solve.gather_multigrid` for the measurements).
AMG_DEFAULTS: dict[str, Any] = {"strength": "evolution", "smooth": ("energy", {"degree": 1})}


def jacobi_lambda_max(A: sp.spmatrix | sp.sparray, tol: float = 1e-3) -> float:
    """Largest eigenvalue of ``D^-1 A`` (``D = diag(A)``) of a symmetric ``A`` with positive
    diagonal: the largest eigenvalue of the similar ``D^-1/2 A D^-1/2``, by Lanczos (ARPACK,
    ``tol`` relative; dense below 400 unknowns). If ARPACK does not converge, its best Ritz
    value, or the Gershgorin bound ``max_i sum_j |a_ij| / a_ii`` if it has none."""
    A = sp.csr_matrix(A, dtype=np.float64)
    d = A.diagonal()
    s = sp.diags(1.0 / np.sqrt(d))
    S = (s @ A @ s).tocsr()
    n = S.shape[0]
    if n <= _DENSE_EIG:
        return float(np.linalg.eigvalsh(S.toarray()).max())
    v0 = np.random.default_rng(0).standard_normal(n)
    try:
        return float(spla.eigsh(S, k=1, which="LA", tol=tol, ncv=min(n - 1, 24), maxiter=50 * n,
                                v0=v0, return_eigenvectors=False)[0])
    except spla.ArpackNoConvergence as exc:
        if len(exc.eigenvalues):
            return float(np.max(exc.eigenvalues))
        return float((abs(A).sum(axis=1).A1 / d).max())


def build_prolongations(A: sp.spmatrix | sp.sparray, max_coarse: int = 300, max_levels: int = 10,
                        amg: dict[str, Any] | None = None) -> list[sp.csr_matrix]:
    """Smoothed-aggregation prolongations ``P_0, P_1, ...`` of the symmetric matrix ``A`` (pyamg;
    ``amg``: further options of ``pyamg.smoothed_aggregation_solver``, default
    :data:`AMG_DEFAULTS`; reproducible: numpy's global random state is seeded for the call and
    restored)."""
    opts = {**AMG_DEFAULTS, **(amg or {})}
    with pinned_global_rng():        # pyamg's spectral-radius estimates start from np.random vectors
        ml = pyamg.smoothed_aggregation_solver(sp.csr_matrix(A), symmetry="symmetric", max_coarse=max_coarse,
                                               max_levels=max_levels, keep=False, **opts)
    return [sp.csr_matrix(lv.P, dtype=np.float64) for lv in ml.levels[:-1]]


def galerkin(A: sp.spmatrix | sp.sparray, P: sp.spmatrix | sp.sparray) -> sp.csr_matrix:
    """``P^T A P`` (CSR, sorted, symmetrised against rounding)."""
    Ac = sp.csr_matrix(P.T @ (A @ P))
    Ac = sp.csr_matrix(0.5 * (Ac + Ac.T))
    Ac.sum_duplicates()
    Ac.sort_indices()
    return Ac
