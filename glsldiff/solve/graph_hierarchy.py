"""TransCut's multiresolution graph solver (Li et al. 2012, section 4;
``../shared/notes/transcut.md`` section 3), on the CPU with scipy.sparse.

No coarse meshes: each level ``l + 1`` keeps a subset ``P^{l+1}`` of level ``l``'s vertices,

1. a maximal independent set of the level's graph by Luby's rule on unique random priorities
   (the paper's 32-bit hashed code: random high bits, vertex index low bits; here a random
   permutation, unique by construction), then **graph enhancement**: while two adjacent dropped
   vertices share no retained neighbour, an independent set of those vertices joins ``P^{l+1}``;
2. the **two-ring edges** ``E^{l+1}``: every pair of retained neighbours of a dropped vertex,
   plus the level's edges between two retained vertices;
3. the **interpolation** (eq. 16) ``phi_i = sum_j lambda_ij phi_j / lambda_i`` over the retained
   one-ring neighbours ``j`` of a dropped vertex, ``lambda_ij = 1 / |x_i - x_j|`` (mm^-1);
   a retained vertex copies its coarse value;
4. the **coarse operator** (eq. 17): the retained vertices' fine equations with (16)
   substituted, ``M^{l+1} = S M^l P`` (``S`` selects the retained rows: injection, ``b^{l+1} =
   S b^l``). Not Galerkin, so not symmetric: coarse levels are solved by BiCG.

The paper's coarse operator is not consistent: it enforces the fine equations of the retained
vertices on an interpolation that reproduces constants only, so a linear field's interpolation
error O(h |grad phi|) meets the fine Laplacian's O(1/h^2) weights. Solved exactly, its two-level
cascade starts 34-88 % (relative L2) from the fine answer on 1.3k-19k-node test balls, and BiCG
needs 200-1100 iterations there. ``coarse = "galerkin"`` keeps the hierarchy and interpolation
but takes ``M^{l+1} = P^T M^l P``, ``b^{l+1} = P^T b^l`` (symmetric positive definite: CG on
every level; the next level's graph is this matrix's pattern, up to three rings): 9 / 6 / 4 %
on the same balls, falling with refinement. Yet only the cascade's start depends on it, and on
the 1 M-tetrahedron bunny (``glsldiff tet bunny --refine 1``) the paper's operator reached 1 % /
0.1 % sooner (0.17 / 0.31 s of solve against 0.24 / 0.49 s; Jacobi-CG from zero 0.28 / 0.62 s)
and builds 4x faster (2.4 s against 9.1 s): ``"paper"`` is the default.

The solve is the paper's coarse-to-fine cascade: BiCG on the coarsest level from zero, each
solution interpolated up as the next level's start, conjugate gradients (Jacobi-preconditioned)
on level 0. A coarse level that does not converge within its budget hands its last iterate on
(the paper's "move on to the next finer level"); one whose BiCG broke down or left a larger
residual than its start hands the start on (recorded as a fallback). With ``x0`` (a warm start: relighting, painting)
the cascade is skipped. The paper gives no tolerances or level counts: ``coarse_tol`` and
``levels`` are ours (defaults measured in ``glsldiff tet``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError

__all__ = ["GraphLevel", "GraphHierarchy", "independent_set", "coarsen_graph", "jacobi_cg", "COARSE_OPERATORS"]

#: The coarse operators: TransCut's eq. 17 (injection) and the Galerkin product (module docstring).
COARSE_OPERATORS = ("galerkin", "paper")

_BIG = np.iinfo(np.int64).max


def jacobi_cg(M: sp.spmatrix, b: NDArray[np.float64], tol: float, x0: NDArray[np.float64] | None = None,
              maxiter: int = 20_000, callback: Callable[[NDArray[np.float64]], None] | None = None
              ) -> NDArray[np.float64]:
    """Jacobi-preconditioned conjugate gradients (scipy) on ``M x = b`` to a relative residual
    ``tol``: the fine level of the hierarchy and its plain peer."""
    return spla.cg(M, b, x0=x0, rtol=tol, maxiter=maxiter, M=sp.diags(1.0 / M.diagonal()), callback=callback)[0]


def _graph(M: sp.spmatrix) -> sp.csr_matrix:
    """The symmetric adjacency (bool CSR, no diagonal) of ``M``'s structural pattern."""
    A = sp.csr_matrix(M, copy=True)
    A.data = np.ones_like(A.data, dtype=bool)
    A = (A + A.T).tocsr()
    A.setdiag(False)
    A.eliminate_zeros()
    A.sort_indices()
    return A.astype(bool)


def _row_any(A: sp.csr_matrix, mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Per row of the adjacency ``A``: has a neighbour in ``mask``."""
    return (A @ mask.astype(np.int32)) > 0


def independent_set(A: sp.csr_matrix, candidates: NDArray[np.bool_], priority: NDArray[np.int64]
                    ) -> NDArray[np.bool_]:
    """A maximal independent subset of ``candidates`` in the graph ``A`` by Luby's parallel rule:
    a candidate joins when its priority is below every candidate neighbour's; it and its
    neighbours leave the candidates; repeat until none is left."""
    n = A.shape[0]
    Q = np.asarray(candidates, dtype=bool).copy()
    chosen = np.zeros(n, dtype=bool)
    start, deg = A.indptr[:-1], np.diff(A.indptr)
    while Q.any():
        h = np.where(Q, priority, _BIG)
        nb = np.append(h[A.indices], _BIG)                       # a sentinel: reduceat needs start < len
        lowest = np.minimum.reduceat(nb, np.minimum(start, len(nb) - 1))
        lowest[deg == 0] = _BIG
        win = Q & (priority < lowest)
        chosen |= win
        Q &= ~(win | _row_any(A, win))
    return chosen


def coarsen_graph(A: sp.csr_matrix, rng: np.random.Generator) -> tuple[NDArray[np.bool_], int]:
    """``(keep, enhancement rounds)``: the retained vertices of one coarsening step, a maximal
    independent set plus the graph enhancement (module docstring, step 1)."""
    n = A.shape[0]
    priority = rng.permutation(n).astype(np.int64)
    keep = independent_set(A, np.ones(n, dtype=bool), priority)
    rounds = 0
    coo = sp.triu(A, k=1).tocoo()
    i, j = coo.row, coo.col
    while True:
        both = ~keep[i] & ~keep[j]
        ei, ej = i[both], j[both]
        if len(ei) == 0:
            break
        K = A[:, keep].tocsr().astype(np.int32)
        common = np.asarray(K[ei].multiply(K[ej]).sum(axis=1)).ravel()
        lonely = common == 0
        if not lonely.any():
            break
        marked = np.zeros(n, dtype=bool)
        marked[ei[lonely]] = marked[ej[lonely]] = True
        keep |= independent_set(A, marked, priority)
        rounds += 1
    return keep, rounds


def _interpolation(A: sp.csr_matrix, keep: NDArray[np.bool_], X: NDArray[np.float64]) -> sp.csr_matrix:
    """``(n_l, n_{l+1})`` eq. 16: inverse-distance weights from the retained one-ring."""
    n = A.shape[0]
    coarse = np.cumsum(keep) - 1
    coo = A.tocoo()
    sel = ~keep[coo.row] & keep[coo.col]
    r, c = coo.row[sel], coo.col[sel]
    lam = 1.0 / np.maximum(np.linalg.norm(X[r] - X[c], axis=1), 1e-300)
    lam_i = np.bincount(r, lam, minlength=n)
    kept = np.flatnonzero(keep)
    rows = np.concatenate([kept, r])
    cols = np.concatenate([coarse[kept], coarse[c]])
    vals = np.concatenate([np.ones(len(kept)), lam / lam_i[r]])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, int(keep.sum())))


@dataclass(eq=False)
class GraphLevel:
    """One level: its matrix (level 0: the DE matrix), vertex positions (mm), graph, and the
    interpolation ``P`` from the next coarser level (``None`` on the coarsest)."""

    M: sp.csr_matrix
    X: NDArray[np.float64]
    A: sp.csr_matrix
    keep: NDArray[np.bool_] | None = None          # retained into the next level
    P: sp.csr_matrix | None = None
    enhancement_rounds: int = 0


@dataclass(eq=False)
class GraphHierarchy:
    """TransCut's hierarchy over ``M`` (module docstring). ``levels``: the number of levels, the
    fine one included (the paper used 3-4 for 0.5-1 M tetrahedra); coarsening also stops below
    ``min_nodes`` vertices."""

    levels: list[GraphLevel]
    seconds: float
    coarse: str = "paper"
    info: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def build(cls, M: sp.spmatrix, positions: ArrayLike, levels: int = 4, min_nodes: int = 500,
              seed: int = 0, coarse: str = "paper") -> "GraphHierarchy":
        """Build the hierarchy of the square matrix ``M`` over vertices at ``positions``
        ``(n, 3)`` (mm); ``coarse`` one of :data:`COARSE_OPERATORS`."""
        if coarse not in COARSE_OPERATORS:
            raise InputError(f"coarse operator {coarse!r} is not one of {', '.join(COARSE_OPERATORS)}")
        M = sp.csr_matrix(M)
        X = np.asarray(positions, dtype=np.float64)
        if M.shape[0] != M.shape[1] or X.shape != (M.shape[0], 3):
            raise InputError(f"matrix {M.shape} and positions {X.shape} must be (n, n) and (n, 3)")
        if not (isinstance(levels, int) and levels >= 1):
            raise InputError(f"levels {levels!r} must be an integer >= 1")
        t0 = time.perf_counter()
        rng = np.random.default_rng(seed)
        out = [GraphLevel(M, X, _graph(M))]
        while len(out) < levels and out[-1].M.shape[0] > min_nodes:
            lv = out[-1]
            keep, rounds = coarsen_graph(lv.A, rng)
            if keep.all():
                break
            P = _interpolation(lv.A, keep, lv.X)
            if coarse == "paper":
                Mc = (lv.M[keep] @ P).tocsr()
                K = lv.A[~keep][:, keep].astype(np.int32)
                graph = (K.T @ K + lv.A[keep][:, keep].astype(np.int32)).tocsr()        # two-ring edges
            else:
                Mc = (P.T @ lv.M @ P).tocsr()
                graph = Mc
            lv.keep, lv.P, lv.enhancement_rounds = keep, P, rounds
            out.append(GraphLevel(Mc, lv.X[keep], _graph(graph)))
        h = cls(out, time.perf_counter() - t0, coarse)
        h.info = {"nodes": [lv.M.shape[0] for lv in out], "nnz": [lv.M.nnz for lv in out],
                  "enhancement_rounds": [lv.enhancement_rounds for lv in out[:-1]], "build_s": h.seconds}
        return h

    def cascade(self, b: ArrayLike, coarse_tol: float = 1e-3, coarse_maxiter: int = 200
                ) -> tuple[NDArray[np.float64], list[dict[str, Any]]]:
        """The coarse-to-fine start for level 0: BiCG (``paper``) or CG (``galerkin``) on each
        coarse level (coarsest first, from zero, then from the interpolated coarser solution);
        returns the interpolated level-1 solution and one record per coarse level (nodes,
        iterations, residual, fallback, s)."""
        bs = [np.asarray(b, dtype=np.float64)]
        for lv in self.levels[:-1]:
            bs.append(bs[-1][lv.keep] if self.coarse == "paper" else lv.P.T @ bs[-1])
        krylov = spla.bicg if self.coarse == "paper" else spla.cg
        x: NDArray[np.float64] | None = None
        records = []
        for k in range(len(self.levels) - 1, 0, -1):
            t0 = time.perf_counter()
            lv, bk = self.levels[k], bs[k]
            start = np.zeros(len(bk)) if x is None else lv.P @ x      # lv.P: level k + 1 -> k
            count = [0]
            xk, info = krylov(lv.M, bk, x0=start, rtol=coarse_tol, maxiter=coarse_maxiter,
                                 callback=lambda _x: count.__setitem__(0, count[0] + 1))
            bn = float(np.linalg.norm(bk)) or 1.0
            res = float(np.linalg.norm(bk - lv.M @ xk) / bn) if np.all(np.isfinite(xk)) else float("inf")
            start_res = float(np.linalg.norm(bk - lv.M @ start) / bn)
            fallback = not res < start_res          # BiCG made it worse (or broke down): keep the start
            if fallback:
                xk, res = start, start_res
            records.append({"level": k, "nodes": len(bk), "iterations": count[0], "residual": res,
                            "converged": info == 0 and not fallback, "fallback": bool(fallback),
                            "seconds": time.perf_counter() - t0})
            x = xk
        if x is None:
            return np.zeros(len(bs[0])), records
        return self.levels[0].P @ x, records

    def solve(self, b: ArrayLike, tol: float = 1e-8, x0: ArrayLike | None = None, maxiter: int = 20_000,
              coarse_tol: float = 1e-3, coarse_maxiter: int = 200,
              callback: Callable[[NDArray[np.float64]], None] | None = None
              ) -> tuple[NDArray[np.float64], dict[str, Any]]:
        """Solve ``M x = b`` (level 0): the cascade (or ``x0``), then Jacobi-preconditioned CG to
        a relative residual ``tol``. ``callback`` receives the start and every CG iterate.
        Returns ``(x, info)`` (cascade records, CG iterations, residual, converged, seconds)."""
        t0 = time.perf_counter()
        M = self.levels[0].M
        b = np.asarray(b, dtype=np.float64)
        records: list[dict[str, Any]] = []
        if x0 is None:
            start, records = self.cascade(b, coarse_tol, coarse_maxiter)
        else:
            start = np.asarray(x0, dtype=np.float64)
        if callback is not None:
            callback(start)
        count = [0]

        def step(xk: NDArray[np.float64]) -> None:
            count[0] += 1
            if callback is not None:
                callback(xk)

        x = jacobi_cg(M, b, tol, x0=start, maxiter=maxiter, callback=step)
        bn = float(np.linalg.norm(b)) or 1.0
        res = float(np.linalg.norm(b - M @ x) / bn)
        return x, {"cascade": records, "cg_iterations": count[0], "residual": res, "converged": res <= tol * 1.01,
                   "seconds": time.perf_counter() - t0}
