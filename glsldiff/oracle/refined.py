"""How far a tetrahedral grid's P1 solution is from the converged one: the same problem on the
grid's regular 1:8 refinement (:func:`glsldiff.grids.tetrahedral.pillow.subdivide_tets`).

The refined grid keeps the grid's boundary (the new surface nodes are midpoints of the old
surface edges) and carries the P1 interpolants of the node material and of the boundary
source, so it solves the same continuous problem at half the spacing; every tetrahedron's
eight children have its shape. The difference between the two solutions, at the grid's own
surface nodes, is the discretisation error of the solve on this grid: too coarse a spacing
for the light, stretched or obtuse tetrahedra (the positive couplings of :mod:`glsldiff.oracle.fem`).
Where the error falls as h^2 the coarse grid's error is about 4/3 of it (Richardson). It does
not see how well the grid's surface follows the mesh (both share that surface).

Cost: the refined grid has about 8x the tetrahedra and 7-8x the nodes (the default bunny grid,
143k nodes: 1.1M nodes, 6.3M tetrahedra, about 50 s to build and assemble one channel and
12 s for a pyamg solve on 2 cores). Lengths mm; ``B`` is the renderer's ``p1`` exitant
bracket (:mod:`glsldiff.physics.exitance`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Sequence

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError
from glsldiff.grids.tetrahedral.pillow import edge_lookup, subdivide_tets
from glsldiff.oracle.fem import TetGeometry, assemble_p1, solve_matrix_reference, tet_geometry
from glsldiff.physics.exitance import exitant_bracket
from glsldiff.system.tet_problem import TetProblem

__all__ = ["RefinedComparison", "RefinedError", "RefinedGrid", "extend_p1", "refine_grid"]


@dataclass(eq=False)
class RefinedGrid:
    """A tetrahedral grid (the protocol of :class:`glsldiff.system.tet_problem.TetProblem`):
    ``positions`` ``(n, 3)`` mm, right-handed ``tets`` ``(T, 4)``, outward ``surface`` ``(F, 3)``."""

    positions: NDArray[np.float64]
    tets: NDArray[np.int64]
    surface: NDArray[np.int64]

    @cached_property
    def surface_nodes(self) -> NDArray[np.int64]:
        return np.unique(self.surface)

    @cached_property
    def active(self) -> NDArray[np.bool_]:
        a = np.zeros(len(self.positions), dtype=bool)
        a[self.tets.ravel()] = True
        return a


def refine_grid(grid: Any) -> tuple[RefinedGrid, NDArray[np.int64]]:
    """The 1:8 refinement of a tetrahedral grid's tetrahedra and the ``(E, 2)`` edges whose
    midpoints are its new nodes (node ``n + e`` for edge ``e``; the grid's nodes keep their
    indices). Each surface triangle becomes its four midpoint children, outward as before."""
    X = np.asarray(grid.positions, dtype=np.float64)
    X8, T8, edges = subdivide_tets(X, np.asarray(grid.tets, dtype=np.int64))
    n = len(X)
    f = np.asarray(grid.surface, dtype=np.int64)

    def mid(a: NDArray[np.int64], b: NDArray[np.int64]) -> NDArray[np.int64]:
        at, found = edge_lookup(edges, n, a, b)
        if not found.all():
            raise InputError("a surface triangle's edge is no tetrahedron's edge: the grid's surface is not "
                             "the boundary of its tetrahedra")
        return n + at
    a, b, c = f.T
    ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
    surface = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return RefinedGrid(X8, T8, surface), edges


def extend_p1(values: NDArray[np.float64], edges: NDArray[np.int64]) -> NDArray[np.float64]:
    """P1 interpolant of node ``values`` at the edge midpoints, appended."""
    return np.concatenate([values, 0.5 * (values[edges[:, 0]] + values[edges[:, 1]])])


@dataclass
class RefinedError:
    """One source's comparison: relative RMS and max (over the largest ``|B|``) of the grid's
    ``B`` against the refined grid's at the grid's surface nodes; surface nodes with negative
    fluence on each grid (the discrete maximum principle failing)."""

    rel_rms: float
    rel_max: float
    negative_surface: int
    negative_surface_refined: int
    seconds: float


def _system(geo: TetGeometry, kappa: NDArray[np.float64], mu: NDArray[np.float64], C: float, boundary_mass: str,
            active: NDArray[np.bool_]) -> tuple[sp.csr_matrix, NDArray[np.int64]]:
    """One channel's matrix over the ``active`` nodes and their indices."""
    A, _ = assemble_p1(geo, kappa, mu, 0.0, C, boundary_mass)
    idx = np.flatnonzero(active)
    return A[idx][:, idx].tocsr(), idx


class RefinedComparison:
    """A P1 problem's system on its grid and on the grid's 1:8 refinement (one colour
    ``channel`` of its material); :meth:`compare` solves both for boundary sources (the
    renderer's problem: ``Renderer.fem_problem``)."""

    def __init__(self, problem: TetProblem, channel: int = 1) -> None:
        t0 = time.perf_counter()
        if not isinstance(problem, TetProblem):
            raise InputError(f"problem must be a TetProblem (a tetrahedral grid's), not {type(problem).__name__}")
        if channel not in (0, 1, 2):
            raise InputError(f"channel={channel!r} must be 0, 1 or 2")
        self.problem, self.channel = problem, channel
        grid, p = problem.grid, problem
        kap, mu_n = p.kappa[:, channel], p.mu[:, channel]
        self.refined, self._edges = refine_grid(grid)
        fine = self.refined
        self._coarse_geo = tet_geometry(grid)
        self._coarse = _system(self._coarse_geo, kap, mu_n, p.C, p.boundary_mass, np.asarray(grid.active))
        self._fine_geo = TetGeometry(fine.positions, fine.tets, fine.surface)
        self._fine = _system(self._fine_geo, extend_p1(kap, self._edges), extend_p1(mu_n, self._edges), p.C,
                             p.boundary_mass, fine.active)
        self.setup_seconds = time.perf_counter() - t0

    @property
    def nodes(self) -> tuple[int, int]:
        """Unknowns of the grid and of the refined grid."""
        return self._coarse[0].shape[0], self._fine[0].shape[0]

    def _solve(self, system: tuple[sp.csr_matrix, NDArray[np.int64]], areas: NDArray[np.float64],
               q_nodes: NDArray[np.float64]) -> NDArray[np.float64]:
        """``(n, k)`` fluence on every node of a grid for ``k`` sources per node ``(n, k)``."""
        A, idx = system
        b = areas[idx, None] * q_nodes[idx] / (2.0 * self.problem.C)
        x, _ = solve_matrix_reference(A, b, maxiter=400)
        out = np.zeros_like(q_nodes)
        out[idx] = x.reshape(len(idx), -1)
        return out

    def compare(self, sources: Sequence[ArrayLike] | None = None) -> list[RefinedError]:
        """Each source ``(S,)`` or ``(S, 3)`` per surface node of the grid (default: the
        problem's ``q``; its ``channel``) solved on both grids (module docstring)."""
        t0 = time.perf_counter()
        sources = [self.problem.q] if sources is None else sources
        g = self.problem.grid
        sn = np.asarray(g.surface_nodes)
        qs = []
        for q in sources:
            q = np.asarray(q, dtype=np.float64)
            q = q[:, self.channel] if q.ndim == 2 else q
            if q.shape != (len(sn),) or not np.isfinite(q).all():
                raise InputError(f"a source must be finite with one value per surface node ({len(sn)},); got {q.shape}")
            qs.append(q)
        if not qs:
            return []
        n = len(g.positions)
        Q = np.zeros((n, len(qs)))
        Q[sn] = np.stack(qs, axis=1)
        phi = self._solve(self._coarse, self._coarse_geo.node_areas, Q)
        phi_f = self._solve(self._fine, self._fine_geo.node_areas, extend_p1(Q, self._edges))
        secs = (time.perf_counter() - t0) / len(qs)
        out = []
        fine_surface = self.refined.surface_nodes
        for k, q in enumerate(qs):
            B = exitant_bracket(phi[sn, k], q, self.problem.eta, "p1", self.problem.C)
            B_f = exitant_bracket(phi_f[sn, k], q, self.problem.eta, "p1", self.problem.C)
            scale = max(float(np.abs(B_f).max()), 1e-300)
            out.append(RefinedError(float(np.linalg.norm(B - B_f) / max(float(np.linalg.norm(B_f)), 1e-300)),
                                    float(np.abs(B - B_f).max() / scale), int((phi[sn, k] < 0).sum()),
                                    int((phi_f[fine_surface, k] < 0).sum()), secs))
        return out
