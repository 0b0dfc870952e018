"""Node connectivity shared by every diffusion discretisation (regular grid, polygrid).

A discretisation is a flat array of nodes (inactive/removed ones included, so that the
array maps one to one onto packed texels) with, per node, a kind:

* **interior** nodes carry the diffusion equation over six neighbours ``j`` with
  Laplacian weights ``w_j`` (mm^-2; ``1/h^2`` on a regular grid, paper appendix B on a
  polygrid), neighbour order ``x-, x+, y-, y+, z-, z+`` (lattice directions);
* **boundary** nodes carry the boundary condition (paper eq. 9, second line) with one
  interior partner at distance ``d`` (mm) along the inward normal;
* **inactive** (removed) nodes carry nothing and are read by no other node.

:func:`glsldiff.oracle.assembly.assemble` turns a graph plus material into the sparse system;
the GLSL solvers apply the same rows as Jacobi sweeps.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

INACTIVE, INTERIOR, BOUNDARY = 0, 1, 2
NEIGHBOURS = ("x-", "x+", "y-", "y+", "z-", "z+")


@dataclass(frozen=True, eq=False)
class NodeGraph:
    """Connectivity over ``kind.size`` flat nodes.

    Attributes
    ----------
    kind
        ``(N,)`` int8: INACTIVE, INTERIOR or BOUNDARY.
    neighbours
        ``(n_interior, 6)`` flat node indices of each interior node's neighbours, rows
        in the order of ``flatnonzero(kind == INTERIOR)``.
    weights
        ``(n_interior, 6)`` scaled Laplacian weights ``w_j * scale`` (dimensionless; all
        > 0 for a convergent Jacobi). The Laplacian at node ``i`` is
        ``sum_j weights_ij (f_j - f_i) / scale_i``.
    scale
        ``(n_interior,)`` row scale, mm^2 (``h^2`` on a regular grid, where every scaled
        weight is 1; ``6 / sum_j w_j`` on a polygrid).
    link
        ``(n_boundary,)`` flat index of each boundary node's interior partner, rows in
        the order of ``flatnonzero(kind == BOUNDARY)``.
    d
        ``(n_boundary,)`` distance boundary node -> partner, mm.
    """

    kind: NDArray[np.int8]
    neighbours: NDArray[np.int64]
    weights: NDArray[np.float64]
    scale: NDArray[np.float64]
    link: NDArray[np.int64]
    d: NDArray[np.float64]

    @cached_property
    def interior(self) -> NDArray[np.int64]:
        """Flat indices of the interior nodes (row order of ``neighbours``)."""
        return np.flatnonzero(self.kind == INTERIOR)

    @cached_property
    def boundary(self) -> NDArray[np.int64]:
        """Flat indices of the boundary nodes (row order of ``link``)."""
        return np.flatnonzero(self.kind == BOUNDARY)

    @cached_property
    def active(self) -> NDArray[np.int64]:
        """Flat indices of the nodes that carry an unknown, increasing."""
        return np.flatnonzero(self.kind != INACTIVE)

    @property
    def size(self) -> int:
        return int(self.kind.size)

    def check(self) -> None:
        """Raise ``ValueError`` if the graph is inconsistent (a programming error)."""
        n_i, n_b = self.interior.size, self.boundary.size
        if self.neighbours.shape != (n_i, 6) or self.weights.shape != (n_i, 6):
            raise ValueError(f"neighbours/weights must be ({n_i}, 6)")
        if self.scale.shape != (n_i,) or not np.all(self.scale > 0):
            raise ValueError(f"scale must be ({n_i},) and > 0")
        if self.link.shape != (n_b,) or self.d.shape != (n_b,):
            raise ValueError(f"link/d must be ({n_b},)")
        if n_i and self.kind[self.neighbours].min() == INACTIVE:
            raise ValueError("an interior node reads an inactive node")
        if n_b and np.any(self.kind[self.link] != INTERIOR):
            raise ValueError("a boundary node links to a node that is not interior")
        if n_b and not np.all(self.d > 0):
            raise ValueError("boundary distances d must be > 0")


def edge_adjacency(edges: NDArray[np.int64], n: int) -> sp.csr_matrix:
    """``(n, n)`` 0/1 adjacency of the undirected ``edges`` ``(E, 2)`` (repeats count once)."""
    A = sp.coo_matrix((np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                      shape=(n, n)).tocsr()
    A.data[:] = 1.0
    return A


def mean_operator(A: sp.csr_matrix) -> sp.csr_matrix:
    """Row-normalised ``A``: the mean over each node's neighbours (isolated nodes: zero rows)."""
    return sp.diags(1.0 / np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1)) @ A
