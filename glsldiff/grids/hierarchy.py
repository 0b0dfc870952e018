"""Multiresolution grids (Wang et al. 2008, section 5.3, figure 8), CPU side: a grid and its
coarser levels, with the transfer operators between them as sparse matrices (lengths in mm).

Regular grids (:func:`coarsen_regular`) coarsen vertex-centred, by 2 per axis: coarse node
``(X, Y, Z)`` sits on fine node ``(2X, 2Y, 2Z)`` (161 -> 81 -> 41 nodes, spacing ``h -> 2h``;
every axis needs an odd node count), so each level is again a :class:`RegularGrid` with its
boundary faces where the fine ones are. Prolongation is trilinear interpolation of phi from
the active coarse nodes (weights renormalised where an edge or corner node, which carries no
unknown, drops out); restriction is full weighting (the transpose of the trilinear weights)
normalised per row: ``restrict_kind`` over the fine nodes of the coarse node's own kind
(interior or boundary rows: their units differ), ``restrict_all`` (material) over all fine nodes.

Polygrids (:func:`coarsen`): a coarser level keeps the polycube and halves the nodes per cube
edge (``n -> n/2``):
node ``(cube, z, y, x)`` of the coarse level is the parent of the eight fine nodes
``(cube, 2z+a, 2y+b, 2x+c)``. The coarse lattice is classified again
(:class:`glsldiff.grids.lattice.Lattice`), and

* an interior or removed coarse node sits at the mean position of its existing (not
  removed) children, the paper's "normalized by the number of existing children";
* a boundary coarse node sits at the mean of its *boundary* children, so the coarse
  level keeps the fine level's surface (the mean over all children would sink the
  surface by half a fine spacing); its normal is the normalised mean of theirs;
* kappa and mu are the mean over existing children (paper), the boundary source ``q``
  the mean over boundary children;
* the Laplacian weights are recomputed from the coarse positions (appendix B), so each
  level is a complete :class:`~glsldiff.grids.polygrid.Polygrid` with its own T_w1 / T_w2.

Its prolongation copies each fine node's value from its parent (from the nearest active coarse
node where the parent was removed, at convex polycube edges); its restriction averages, at each
coarse node, its children of the same kind (interior rows from interior children, boundary rows
from boundary children).

:class:`Transfer` holds the operators used by the coarse-to-fine solve and the multigrid of
:mod:`glsldiff.solve.multilevel`; the GLSL transfer pass applies exactly these matrices and is
tested against them.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any, Union

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from glsldiff.core.errors import InputError
from glsldiff.grids.graph import BOUNDARY, INACTIVE, INTERIOR
from glsldiff.grids.lattice import Lattice
from glsldiff.grids.polygrid import Polygrid, node_weights
from glsldiff.grids.regular import RegularGrid

Grid = Union[Polygrid, RegularGrid]

# the 27 lattice offsets (x, y, z) searched for a substitute parent
_AROUND = np.stack(np.meshgrid([0, -1, 1], [0, -1, 1], [0, -1, 1], indexing="ij"), -1).reshape(-1, 3)


def _normalise_rows(m: sp.spmatrix) -> sp.csr_matrix:
    m = sp.csr_matrix(m)
    m.eliminate_zeros()
    total = np.asarray(m.sum(axis=1)).ravel()
    return (sp.diags(np.where(total > 0, 1.0 / np.where(total > 0, total, 1.0), 0.0)) @ m).tocsr()


def _mean_matrix(rows: NDArray[np.int64], cols: NDArray[np.int64], shape: tuple[int, int]) -> sp.csr_matrix:
    """Row-normalised 0/1 matrix: each row averages its listed columns (empty rows stay 0)."""
    return _normalise_rows(sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=shape))


@dataclass(frozen=True, eq=False)
class Transfer:
    """Operators between a fine level (``N_f`` nodes) and its coarse level (``N_c``).

    Attributes
    ----------
    prolong
        ``(N_f, N_c)`` interpolation of phi; rows of inactive fine nodes are 0, the others
        sum to 1 over active coarse nodes.
    restrict_kind
        ``(N_c, N_f)`` weighted mean over the fine nodes of the coarse node's own kind
        (residuals, the boundary source).
    restrict_all
        ``(N_c, N_f)`` weighted mean over the fine nodes (material, positions).
    """

    prolong: sp.csr_matrix
    restrict_kind: sp.csr_matrix
    restrict_all: sp.csr_matrix


def _parents(fine: Lattice, coarse: Lattice) -> NDArray[np.int64]:
    m = coarse.n
    c, z, y, x = np.unravel_index(np.arange(fine.size_nodes), fine.shape)
    return ((c * m + z // 2) * m + y // 2) * m + x // 2


def coarsen(pg: Polygrid, **weight_options: Any) -> tuple[Polygrid, Transfer]:
    """The next coarser level of ``pg`` (``n/2`` nodes per cube edge) and the transfer
    operators between the two (module docstring). ``weight_options`` go to
    :func:`glsldiff.grids.weights.laplacian_weights`."""
    fl = pg.lattice
    if fl.n % 2 or fl.n < 4:
        raise InputError(f"a polygrid level with n={fl.n} nodes per cube edge cannot be coarsened "
                         "(n must be even and >= 4)")
    try:
        cl = Lattice.build(fl.cubes, fl.n // 2, fl.size, fl.origin)
    except InputError as exc:
        raise InputError(f"coarsening n={fl.n} to {fl.n // 2}: {exc}") from exc
    parent = _parents(fl, cl)
    fkind, ckind = fl.kind, cl.kind
    nf, nc = fl.size_nodes, cl.size_nodes
    alive = np.flatnonzero(fkind != INACTIVE)
    restrict_all = _mean_matrix(parent[alive], alive, (nc, nf))
    same = np.flatnonzero((fkind != INACTIVE) & (fkind == ckind[parent]))
    restrict_kind = _mean_matrix(parent[same], same, (nc, nf))

    # positions: interior/removed coarse nodes from all children, boundary ones from boundary children
    pos = restrict_all @ pg.positions
    has_any = np.asarray(restrict_all.sum(axis=1)).ravel() > 0
    pos[~has_any] = cl.lattice_positions[~has_any]
    fb = fl.boundary
    bnd = _mean_matrix(parent[fb], np.arange(fb.size), (nc, fb.size))
    has_b = np.asarray(bnd.sum(axis=1)).ravel() > 0
    cb = cl.boundary
    use = cb[has_b[cb]]
    pos[use] = (bnd @ pg.boundary_positions)[use]
    normals = cl.outward.copy()
    nsum = (bnd @ pg.normals)[cb]
    nlen = np.linalg.norm(nsum, axis=1)
    ok = has_b[cb] & (nlen > 1e-9)
    normals[ok] = nsum[ok] / nlen[ok, None]
    w, ws = node_weights(pos, cl, **weight_options)
    coarse = Polygrid(cl, pos, normals, w, ws, mesh=pg.mesh, polycube=pg.polycube,
                      max_texture_size=pg.max_texture_size)

    # prolongation source: the parent, or the nearest active coarse node around it
    source = np.full(nf, -1, dtype=np.int64)
    direct = alive[ckind[parent[alive]] != INACTIVE]
    source[direct] = parent[direct]
    orphan = alive[ckind[parent[alive]] == INACTIVE]
    if orphan.size:
        cand = cl.index_of(cl.coords[parent[orphan]][:, None, :] + _AROUND[None])
        good = (cand >= 0) & (ckind[np.maximum(cand, 0)] != INACTIVE)
        dist = np.linalg.norm(pos[np.maximum(cand, 0)] - pg.positions[orphan][:, None, :], axis=2)
        dist[~good] = np.inf
        best = np.argmin(dist, axis=1)
        found = np.isfinite(dist[np.arange(orphan.size), best])
        source[orphan[found]] = cand[found, best[found]]
        if not found.all():
            active_c = np.flatnonzero(ckind != INACTIVE)
            _, k = cKDTree(pos[active_c]).query(pg.positions[orphan[~found]])
            source[orphan[~found]] = active_c[k]
    ok = np.flatnonzero(source >= 0)
    prolong = sp.csr_matrix((np.ones(ok.size), (ok, source[ok])), shape=(nf, nc))
    return coarse, Transfer(prolong, restrict_kind.tocsr(), restrict_all.tocsr())


def _interpolation_1d(n: int) -> sp.csr_matrix:
    """``(n, (n + 1) / 2)`` linear interpolation from every second node (``n`` odd)."""
    even, odd = np.arange(0, n, 2), np.arange(1, n, 2)
    rows = np.concatenate([even, odd, odd])
    cols = np.concatenate([even // 2, (odd - 1) // 2, (odd + 1) // 2])
    vals = np.concatenate([np.ones(even.size), np.full(2 * odd.size, 0.5)])
    return sp.csr_matrix((vals, (rows, cols)), shape=(n, (n + 1) // 2))


def coarsen_regular(grid: RegularGrid) -> tuple[RegularGrid, Transfer]:
    """The next coarser level of a regular grid (``(n + 1) / 2`` nodes per axis, spacing
    ``2 h``) and the transfer operators between the two (module docstring)."""
    dims = (grid.nx, grid.ny, grid.nz)
    if any(n % 2 == 0 or n < 5 for n in dims):
        raise InputError(f"a {grid.nx}x{grid.ny}x{grid.nz} regular grid cannot be coarsened: every axis "
                         "needs an odd node count >= 5 (coarse node X sits on fine node 2X), e.g. "
                         "161x161x33 -> 81x81x17")
    coarse = RegularGrid(*((n + 1) // 2 for n in dims), h=2.0 * float(grid.h),
                         max_texture_size=grid.max_texture_size)
    px, py, pz = (_interpolation_1d(n) for n in dims)
    tensor = sp.kron(pz, sp.kron(py, px), format="csr")          # (N_f, N_c), C order [z, y, x]
    fkind, ckind = grid.kind.ravel(), coarse.kind.ravel()
    fine_on = sp.diags((fkind != INACTIVE).astype(np.float64))
    coarse_on = sp.diags((ckind != INACTIVE).astype(np.float64))
    prolong = _normalise_rows(fine_on @ tensor @ coarse_on)
    alive = fkind != INACTIVE
    reached = np.diff(prolong.indptr) > 0
    if np.any(alive & ~reached):
        raise ValueError("an active fine node has no active coarse node to interpolate from")
    weights = tensor.T.tocoo()
    same = (ckind[weights.row] == fkind[weights.col]) & (ckind[weights.row] != INACTIVE)
    restrict_kind = _normalise_rows(sp.csr_matrix((weights.data[same], (weights.row[same], weights.col[same])),
                                                  shape=weights.shape))
    return coarse, Transfer(prolong, restrict_kind, _normalise_rows(weights))


@dataclass(eq=False)
class Hierarchy:
    """A grid (regular or polygrid) and its coarser levels; ``grids[0]`` is the finest (the
    original). ``transfers[l]`` maps between ``grids[l]`` (fine) and ``grids[l + 1]`` (coarse).
    """

    grids: list[Grid]
    transfers: list[Transfer]

    @classmethod
    def build(cls, grid: Grid, levels: int = 3, **weight_options: Any) -> "Hierarchy":
        """``levels`` levels (1 = the grid alone); each halves the nodes per axis (per cube
        edge). ``weight_options`` (polygrids) go to :func:`glsldiff.grids.weights.laplacian_weights`."""
        if not isinstance(levels, (int, np.integer)) or levels < 1:
            raise InputError(f"levels={levels!r} must be an integer >= 1")
        grids, transfers = [grid], []
        for _ in range(levels - 1):
            g = grids[-1]
            coarse, t = coarsen_regular(g) if isinstance(g, RegularGrid) else coarsen(g, **weight_options)
            grids.append(coarse)
            transfers.append(t)
        return cls(grids, transfers)

    @property
    def levels(self) -> int:
        return len(self.grids)

    def restrict_q(self, q: NDArray, level: int) -> NDArray[np.float64]:
        """A finest-level source (node array ``shape + (3,)``) at ``level`` (its node array)."""
        x = np.asarray(q, dtype=np.float64).reshape(-1, 3)
        for t in self.transfers[:level]:
            x = t.restrict_kind @ x
        return x.reshape(self.grids[level].shape + (3,))

    def depth(self, level: int) -> NDArray[np.float64]:
        """``(N,)`` distance of every node of ``level`` to the nearest boundary node of the
        finest level (a sample of the surface), mm; 0 at boundary nodes of the finest level."""
        d, _ = self._surface_tree.query(self.grids[level].positions)
        return d

    @cached_property
    def _surface_tree(self) -> cKDTree:
        return cKDTree(self.grids[0].boundary_positions)

    def prolong_phi(self, phi: NDArray, level: int) -> NDArray[np.float64]:
        """Fluence on ``level`` (node array) interpolated to ``level - 1`` (``Transfer.prolong``)."""
        t = self.transfers[level - 1]
        fine = self.grids[level - 1]
        return (t.prolong @ np.asarray(phi, dtype=np.float64).reshape(-1, 3)).reshape(fine.shape + (3,))


__all__ = ["Hierarchy", "Transfer", "coarsen", "coarsen_regular", "INTERIOR", "BOUNDARY"]
