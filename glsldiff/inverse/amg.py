"""Iterative forward and adjoint solves of the inverse fit: pyamg multigrid + CG.

A SuperLU factor of ``A(kappa, mu)`` grows much faster than the grid (nnz(L+U) 22.6 M at
65k nodes, 253 M at 327k; 7.8 GiB peak per evaluation there, about 60 GiB extrapolated to the
paper's 256x256x20), so above :data:`AUTO_MAX_DIRECT` nodes the fit solves iteratively instead.

**Symmetrisation.** On the regular grid every boundary row ``b`` of ``A`` has one
off-diagonal entry, to its partner ``j``; the interior rows are symmetric. Scaling row ``b``
by ``s_b = A[j, b] / A[b, j]`` (positive) makes ``K = S A`` symmetric, and with its positive
diagonal and diagonal dominance, positive definite (the same scaling the GLSL path uses for its
adjoint, :mod:`glsldiff.inverse.glsl`). So

* forward ``A x = b``  <=>  ``K x = S b``;
* adjoint ``A^T lambda = g``  <=>  ``K nu = g``, ``lambda = S nu`` (``A^T = K S^-1``),

and one multigrid hierarchy of ``K`` with conjugate gradients serves all M forward and all M
adjoint right-hand sides of an evaluation. The hierarchy is classical Ruge-Stueben by default
(set-up 0.3-0.7 s at 65k nodes, 7.5 CG iterations per right-hand side to 1e-10);
smoothed aggregation (``amg="sa"``) took 2-5 s and 9.4 iterations there. The scaling is checked for every matrix
(``||K - K^T|| <= 1e-12 ||K||``); where it fails, each of ``A`` and ``A^T`` gets its own
nonsymmetric hierarchy and BiCGSTAB (:class:`AmgFactorized`, ``symmetric`` false).

**Stopping.** A column stops at the relative residual ``||S b - K x|| / ||S b|| <=`` ``rtol``
(:data:`AMG_RTOL`), checked with the true residual; one that does not get there in ``maxiter``
iterations raises :class:`~glsldiff.core.errors.SolverError` naming the residual reached
(``strict=False`` accepts it and only counts it in :attr:`SolveStats.unconverged`).

**Warm starts.** Each forward and adjoint column starts from the previous evaluation's
solution of the same column (the material changes little between steps), when that guess
has a smaller residual than zero. **Hierarchy reuse** (``reuse``): while the matrix's
diagonal has changed by less than ``reuse`` (relative, max over nodes) since the last full
set-up, only the Galerkin products ``A_{l+1} = P_l^T A_l P_l`` are redone with the old
prolongators ``P_l``; a full set-up follows when an evaluation needs more than 1.5 times the
iterations of the last fresh hierarchy. Measured in docs/guide/inverse.md.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pyamg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from pyamg import amg_core

from glsldiff.core.blas import blas_threads
from glsldiff.core.errors import SolverError
from glsldiff.core.rng import pinned_global_rng

Array = NDArray[np.float64]

#: Relative residual of every forward and adjoint column (symmetrised system).
AMG_RTOL = 1e-10
#: Iterations per column before a solve counts as not converged.
AMG_MAXITER = 200
#: ``solver="auto"``: SuperLU up to this many active nodes, pyamg above (measured crossover,
#: docs/guide/inverse.md).
AUTO_MAX_DIRECT = 10_000
#: Coarsest level size: solved with a sparse LU.
MAX_COARSE = 500
#: Multigrid set-ups (:class:`Hierarchy`).
AMG_KINDS = ("rs", "sa")
#: Symmetry check of the scaled matrix.
SYMMETRY_TOL = 1e-12


def boundary_scaling(A: sp.csr_matrix, boundary: NDArray[np.int64], partner: NDArray[np.int64]) -> Array:
    """Row scales ``s`` (1 at interior rows, ``A[j, b] / A[b, j]`` at boundary rows) that make
    ``diag(s) A`` symmetric on the regular grid."""
    s = np.ones(A.shape[0])
    s[boundary] = np.asarray(A[partner, boundary]).ravel() / np.asarray(A[boundary, partner]).ravel()
    return s


def asymmetry(K: sp.csr_matrix) -> float:
    """``max |K - K^T| / max |K|``."""
    d = abs(K - K.T)
    return float(d.max() / abs(K).max()) if d.nnz else 0.0


class Hierarchy:
    """Multigrid levels of an SPD matrix (pyamg set-up: ``kind`` "rs" classical Ruge-Stueben,
    "sa" smoothed aggregation), a symmetric V-cycle (forward Gauss-Seidel before, backward
    after the coarse correction; sparse LU on the coarsest level) and the Galerkin update for
    a new fine matrix with the same pattern."""

    def __init__(self, K: sp.csr_matrix, kind: str = "rs", max_coarse: int = MAX_COARSE) -> None:
        with pinned_global_rng():   # pyamg's set-up draws random vectors: reproducible fits
            if kind == "rs":
                ml = pyamg.ruge_stuben_solver(K, interpolation="direct", max_coarse=max_coarse, keep=False)
            else:
                ml = pyamg.smoothed_aggregation_solver(K, symmetry="symmetric", max_coarse=max_coarse, keep=False)
        self.kind = kind
        self.P = [lvl.P.tocsr() for lvl in ml.levels[:-1]]
        self.R = [P.T.tocsr() for P in self.P]
        self.A = [K.tocsr()] + [lvl.A.tocsr() for lvl in ml.levels[1:]]
        self.diag = K.diagonal().copy()     # of the matrix the aggregates were built for
        self._coarse()

    def _coarse(self) -> None:
        try:
            self.coarse = spla.splu(self.A[-1].tocsc())
        except RuntimeError as exc:   # "Factor is exactly singular"
            raise SolverError(f"the coarsest multigrid level ({self.A[-1].shape[0]} unknowns) is singular: "
                              f"{exc}") from exc

    def galerkin(self, K: sp.csr_matrix) -> None:
        """The same prolongators, the new matrix: ``A_{l+1} = R_l A_l P_l``."""
        levels = [K.tocsr()]
        for P, R in zip(self.P, self.R):
            levels.append((R @ levels[-1] @ P).tocsr())
        self.A = levels
        self._coarse()

    @property
    def levels(self) -> int:
        return len(self.A)

    def complexity(self) -> float:
        """Operator complexity: nonzeros of all levels over those of the fine matrix."""
        return sum(a.nnz for a in self.A) / self.A[0].nnz

    def vcycle(self, b: Array) -> Array:
        """One V-cycle from zero: an SPD approximation of ``K^-1 b``."""
        return self._cycle(0, np.ascontiguousarray(b))

    def _cycle(self, lvl: int, b: Array) -> Array:
        A = self.A[lvl]
        if lvl == len(self.A) - 1:
            return self.coarse.solve(b)
        x = np.zeros_like(b)
        n = A.shape[0]
        amg_core.gauss_seidel(A.indptr, A.indices, A.data, x, b, 0, n, 1)
        r = b - A @ x
        x += self.P[lvl] @ self._cycle(lvl + 1, self.R[lvl] @ r)
        amg_core.gauss_seidel(A.indptr, A.indices, A.data, x, b, n - 1, -1, -1)
        return x


@dataclass
class KrylovReport:
    """What one block of columns took: iterations per column and the relative residuals."""

    iterations: NDArray[np.int64]
    residuals: Array


def _rownorm(X: Array) -> Array:
    return np.sqrt(np.einsum("ij,ij->i", X, X))


def block_pcg(K: sp.csr_matrix, B: Array, precond: Callable[[Array], Array], X0: Array | None,
              rtol: float, maxiter: int) -> tuple[Array, KrylovReport]:
    """Preconditioned CG on every column of ``B`` ``(n, m)`` (``K`` SPD), the columns advanced
    together (each its own step lengths; vectors stored one per contiguous row). A column
    stops when its *true* residual ``||b - K x||`` is at most ``rtol ||b||``: the recurrence's
    residual drifts at tight tolerances, so it is recomputed at the end and CG restarted from
    it where the two differ."""
    n, m = B.shape
    Bt = np.ascontiguousarray(B.T)
    X = np.zeros((m, n)) if X0 is None else np.ascontiguousarray(X0.T, dtype=np.float64)
    nb = _rownorm(Bt)
    target = rtol * nb
    its = np.zeros(m, dtype=np.int64)
    R = Bt.copy()
    if X0 is not None:
        for j in range(m):
            R[j] -= K @ X[j]
    active = [j for j in range(m) if _rownorm(R[j:j + 1])[0] > target[j]]
    for _ in range(5):   # restarts from the true residual
        if not active:
            break
        for j in active:
            x, r = X[j], R[j]
            z = precond(r)
            p = z.copy()
            rz = float(np.dot(r, z))
            while its[j] < maxiter:
                q = K @ p
                alpha = rz / float(np.dot(p, q))
                x += alpha * p
                r -= alpha * q
                its[j] += 1
                if float(np.dot(r, r)) <= target[j] ** 2:
                    break
                z = precond(r)
                rz_new = float(np.dot(r, z))
                p *= rz_new / rz
                p += z
                rz = rz_new
            r[:] = Bt[j] - K @ x
        active = [j for j in active if _rownorm(R[j:j + 1])[0] > target[j] and its[j] < maxiter]
    res = _rownorm(R) / np.where(nb > 0, nb, 1.0)
    return np.ascontiguousarray(X.T), KrylovReport(its, res)


@dataclass
class AmgState:
    """What an iterative model keeps between evaluations: the hierarchy, the warm starts and
    the iteration count of the last fresh hierarchy."""

    hierarchy: Hierarchy | None = None
    warm: dict = field(default_factory=dict)
    fresh_iterations: float = 0.0
    rebuild: bool = False


def solve_columns(K: sp.csr_matrix, B: Array, hierarchy: Hierarchy, X0: Array | None, rtol: float,
                  maxiter: int) -> tuple[Array, KrylovReport]:
    """``K X = B`` by CG preconditioned with one V-cycle of ``hierarchy`` (zero columns stay zero;
    a warm start ``X0`` is used per column where its residual is below ``||b||``)."""
    with blas_threads(1):   # OpenBLAS threads cost more than they bring on these vector ops
        if X0 is not None:
            R0 = B - K @ X0
            worse = _rownorm(R0.T) >= _rownorm(B.T)
            if worse.all():
                X0 = None
            elif worse.any():
                X0 = X0.copy()
                X0[:, worse] = 0.0
        return block_pcg(K, B, hierarchy.vcycle, X0, rtol, maxiter)


def solve_nonsymmetric(A: sp.csr_matrix, B: Array, ml: pyamg.MultilevelSolver, X0: Array | None, rtol: float,
                       maxiter: int) -> tuple[Array, KrylovReport]:
    """``A X = B`` column by column with BiCGSTAB preconditioned by ``ml`` (a nonsymmetric
    smoothed-aggregation hierarchy of ``A``): the fallback where symmetrisation fails."""
    M = ml.aspreconditioner()
    X = np.zeros(B.shape)
    its = np.zeros(B.shape[1], dtype=np.int64)
    res = np.zeros(B.shape[1])
    with blas_threads(1):
        for j in range(B.shape[1]):
            b = B[:, j]
            nb = float(np.sqrt(b @ b))
            if nb == 0.0:
                continue
            count = [0]

            def tick(_x: Array) -> None:
                count[0] += 1

            x0 = None if X0 is None else X0[:, j]
            X[:, j], _ = spla.bicgstab(A, b, x0=x0, rtol=rtol, atol=0.0, maxiter=maxiter, M=M, callback=tick)
            r = b - A @ X[:, j]
            its[j], res[j] = count[0], float(np.sqrt(r @ r)) / nb
    return X, KrylovReport(its, res)


def nonsymmetric_hierarchy(A: sp.csr_matrix) -> pyamg.MultilevelSolver:
    with pinned_global_rng():
        return pyamg.smoothed_aggregation_solver(A.tocsr(), symmetry="nonsymmetric", max_coarse=MAX_COARSE)
