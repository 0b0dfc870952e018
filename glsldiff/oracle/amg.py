"""The CPU side of algebraic multigrid for the GPU solvers (:mod:`glsldiff.solve.gather_multigrid`):
smoothed-aggregation prolongations (pyamg), Galerkin coarse operators and the Jacobi spectral
estimate behind every damping choice (:mod:`glsldiff.solve.gather`)."""
from __future__ import annotations

import inspect
from typing import Any

import numpy as np
import pyamg
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from pyamg.util.utils import levelize_smooth_or_improve_candidates, levelize_strength_or_aggregation

from glsldiff.core.blas import blas_threads
from glsldiff.core.rng import pinned_global_rng

__all__ = ["jacobi_lambda_max", "jacobi_lambda_bound", "build_prolongations", "galerkin", "AMG_DEFAULTS"]

_DENSE_EIG = 400          # below this many unknowns the eigenvalue is computed densely
#: pyamg options of the hierarchy (see :mod:`glsldiff.solve.gather_multigrid` for the measurements).
AMG_DEFAULTS: dict[str, Any] = {"strength": ("symmetric", {"theta": 0.0}), "smooth": ("energy", {"degree": 1})}


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
        with blas_threads(1):    # ARPACK's short BLAS calls: threads cost more than they do (2-4x here)
            return float(spla.eigsh(S, k=1, which="LA", tol=tol, ncv=min(n - 1, 24), maxiter=50 * n,
                                    v0=v0, return_eigenvectors=False)[0])
    except spla.ArpackNoConvergence as exc:
        if len(exc.eigenvalues):
            return float(np.max(exc.eigenvalues))
        return float((abs(A).sum(axis=1).A1 / d).max())


def jacobi_lambda_bound(A: sp.spmatrix | sp.sparray, tol: float = 2e-3, maxiter: int = 100) -> float:
    """An upper estimate of the largest eigenvalue of ``D^-1 A`` (``D = diag(A)``) of a symmetric
    ``A`` with positive diagonal, cheaper than :func:`jacobi_lambda_max`: ``theta + r``, the
    largest Ritz value of a Lanczos run on ``D^-1/2 A D^-1/2`` (fixed random start, no
    reorthogonalisation) plus its residual norm, at the first step where ``r <= tol * theta``
    (at most ``maxiter`` steps; dense below 400 unknowns, exact). An eigenvalue lies within
    ``r`` of ``theta``; with ``theta`` the top Ritz value it is ``lambda_max``, so the estimate is
    at most ``tol`` relative above it and, in practice, not below (measured: +0.13 to +0.2 % on
    the bunny's multigrid levels, 2k-147k unknowns, P1 spheres with kappa contrasts to 1e8 and
    7-point operators to 1e12 and anisotropy 1e-4). 16-41 matrix products there, no restarts:
    0.4 s CPU for the bunny's 9 level matrices against 1.5 s for :func:`jacobi_lambda_max`."""
    A = sp.csr_matrix(A, dtype=np.float64)
    s = 1.0 / np.sqrt(A.diagonal())
    n = A.shape[0]
    if n <= _DENSE_EIG:
        return float(np.linalg.eigvalsh(s[:, None] * A.toarray() * s[None, :]).max())
    with blas_threads(1):        # short vector calls: OpenBLAS's threads cost more than they do
        return _lanczos_bound(A, s, tol, maxiter)


def _lanczos_bound(A: sp.csr_matrix, s: NDArray[np.float64], tol: float, maxiter: int) -> float:
    """:func:`jacobi_lambda_bound`'s Lanczos run on ``diag(s) A diag(s)``."""
    n = A.shape[0]
    v = np.random.default_rng(0).standard_normal(n)
    v /= np.linalg.norm(v)
    v_old = np.zeros(n)
    alphas: list[float] = []
    betas: list[float] = []
    beta = 0.0
    for k in range(1, min(maxiter, n) + 1):
        w = s * (A @ (s * v)) - beta * v_old
        alpha = float(v @ w)
        w -= alpha * v
        beta = float(np.linalg.norm(w))
        alphas.append(alpha)
        betas.append(beta)
        theta, y = sla.eigh_tridiagonal(np.array(alphas), np.array(betas[:-1]), select="i",
                                        select_range=(k - 1, k - 1))
        r = abs(beta * y[-1, 0])
        if r <= tol * theta[0] or beta <= 1e-12 * theta[0]:     # converged, or an invariant subspace
            break
        v_old, v = v, w / beta
    return float(theta[0] + r)


def _levelled(opts: dict[str, Any], max_levels: int, max_coarse: int
              ) -> tuple[dict[str, list[Any]], int, int]:
    """The per-level options of ``pyamg.smoothed_aggregation_solver`` (strength, aggregation,
    prolongation smoothing, candidate improvement) as the lists it makes of them (its defaults
    where ``opts`` has none; popped from ``opts``), and ``max_levels``, ``max_coarse`` as a
    predefined coarsening sets them."""
    defaults = inspect.signature(pyamg.smoothed_aggregation_solver).parameters
    per = {k: opts.pop(k, defaults[k].default) for k in ("strength", "aggregate", "smooth", "improve_candidates")}
    per = {k: list(v) if isinstance(v, list) else v for k, v in per.items()}    # pyamg extends lists in place
    for k in ("strength", "aggregate"):
        max_levels, max_coarse, per[k] = levelize_strength_or_aggregation(per[k], max_levels, max_coarse)
    for k in ("smooth", "improve_candidates"):
        per[k] = levelize_smooth_or_improve_candidates(per[k], max_levels)
    return per, max_levels, max_coarse


def build_prolongations(A: sp.spmatrix | sp.sparray, max_coarse: int = 300, max_levels: int = 10,
                        amg: dict[str, Any] | None = None) -> list[sp.csr_matrix]:
    """Smoothed-aggregation prolongations ``P_0, P_1, ...`` of the symmetric matrix ``A`` (pyamg;
    ``amg``: further options of ``pyamg.smoothed_aggregation_solver``, default
    :data:`AMG_DEFAULTS`; reproducible: numpy's global random state is seeded for the call and
    restored).

    With the evolution strength on every level (the default), pyamg runs one level at a time,
    each coarse operator handed back to it sorted: its own are BSR products with unsorted
    indices, on which the energy smoothing's ``abs()`` runs scipy's BSR ``sum_duplicates``, a
    Python loop (0.6 of 2.4 s CPU on the bunny's 147k-node grid). The evolution strength sorts
    its matrix first, the options are levelled as pyamg levels them and the random stream is
    one, so the ``P_l`` are one call's, bit for bit (the bunny; spheres under 6 option sets).
    Other strengths read the index order (aggregates visit neighbours in it): one call."""
    A = sp.csr_matrix(A)
    opts = {**AMG_DEFAULTS, **(amg or {})}
    one_call = {k: list(v) if isinstance(v, list) else v for k, v in opts.items()}   # pyamg extends lists in place
    per, max_levels, max_coarse = _levelled(opts, max_levels, max_coarse)
    # np.random seeded (pyamg's spectral-radius estimates start from it); one BLAS thread (the
    # bunny's set-up on 2 busy cores: 4.9 s against 5.9-13 s on OpenBLAS's threads)
    with pinned_global_rng(), blas_threads(1):
        if not all(_option_name(v) in ("evolution", "ode") for v in per["strength"][:max_levels - 1]):
            ml = pyamg.smoothed_aggregation_solver(A, symmetry="symmetric", max_coarse=max_coarse,
                                                   max_levels=max_levels, keep=False, **one_call)
            return [sp.csr_matrix(lv.P, dtype=np.float64) for lv in ml.levels[:-1]]
        B = opts.pop("B", None)
        Ps: list[sp.csr_matrix] = []
        while len(Ps) + 1 < max_levels and A.shape[0] > max_coarse:
            level = {k: [v[len(Ps)]] for k, v in per.items()}
            ml = pyamg.smoothed_aggregation_solver(A, B=B, symmetry="symmetric", max_coarse=max_coarse, max_levels=2,
                                                   keep=False, **level, **opts)
            Ps.append(sp.csr_matrix(ml.levels[0].P, dtype=np.float64))
            B, Ac = ml.levels[1].B, ml.levels[1].A
            A = Ac.tocsr()           # pyamg's class (sparse array), canonical by compiled code
            A.sum_duplicates()
            if Ac.format == "bsr":   # and its format
                A = A.tobsr(blocksize=Ac.blocksize)
    return Ps


def _option_name(v: Any) -> Any:
    """A pyamg option's method: ``"evolution"`` of ``"evolution"`` or ``("evolution", {...})``."""
    return v[0] if isinstance(v, tuple) else v


def galerkin(A: sp.spmatrix | sp.sparray, P: sp.spmatrix | sp.sparray,
             R: sp.spmatrix | sp.sparray | None = None) -> sp.csr_matrix:
    """``P^T A P`` (CSR, sorted, symmetrised against rounding); ``R``: ``P^T`` as CSR, made once
    for the channels of a level (else scipy transposes ``P`` per product)."""
    Ac = sp.csr_matrix((sp.csr_matrix(P.T) if R is None else R) @ (A @ P))
    Ac = sp.csr_matrix(0.5 * (Ac + Ac.T))
    Ac.sum_duplicates()
    Ac.sort_indices()
    return Ac
