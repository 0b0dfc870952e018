"""Multiresolution polygrid (Wang et al. 2008, section 5.3, figure 8), CPU side.

A coarser level keeps the polycube and halves the nodes per cube edge (``n -> n/2``):
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

:class:`Transfer` holds the grid-transfer operators used by the coarse-to-fine solve and
the multigrid of :mod:`glsldiff.solve.multilevel`, as sparse matrices that the GLSL passes are
tested against: prolongation ``P`` copies each fine node's value from its parent (from the
nearest active coarse node where the parent was removed, at convex polycube edges);
restriction ``R`` averages, at each coarse node, its children of the same kind (interior
rows from interior children, boundary rows from boundary children: the two kinds of row
have different units).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from glsldiff.core.errors import InputError
from glsldiff.grids.graph import BOUNDARY, INACTIVE, INTERIOR
from glsldiff.grids.lattice import Lattice
from glsldiff.grids.polygrid import Polygrid, node_weights

# the 27 lattice offsets (x, y, z) searched for a substitute parent
_AROUND = np.stack(np.meshgrid([0, -1, 1], [0, -1, 1], [0, -1, 1], indexing="ij"), -1).reshape(-1, 3)


def _mean_matrix(rows: NDArray[np.int64], cols: NDArray[np.int64], shape: tuple[int, int]) -> sp.csr_matrix:
    """Row-normalised 0/1 matrix: each row averages its listed columns (empty rows stay 0)."""
    m = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=shape)
    count = np.asarray(m.sum(axis=1)).ravel()
    return sp.diags(np.where(count > 0, 1.0 / np.maximum(count, 1), 0.0)) @ m


@dataclass(frozen=True, eq=False)
class Transfer:
    """Operators between a fine level (``N_f`` nodes) and its coarse level (``N_c``).

    Attributes
    ----------
    parent
        ``(N_f,)`` coarse flat index of each fine node's parent.
    source
        ``(N_f,)`` coarse node each active fine node copies from (its parent, or the
        nearest active coarse node when the parent was removed); -1 at removed fine nodes.
    restrict_kind
        ``(N_c, N_f)`` mean over the children of the coarse node's own kind.
    restrict_all
        ``(N_c, N_f)`` mean over the existing children (material, positions).
    """

    parent: NDArray[np.int64]
    source: NDArray[np.int64]
    restrict_kind: sp.csr_matrix
    restrict_all: sp.csr_matrix

    @cached_property
    def prolong(self) -> sp.csr_matrix:
        """``(N_f, N_c)`` injection from :attr:`source` (rows of removed fine nodes are 0)."""
        ok = np.flatnonzero(self.source >= 0)
        return sp.csr_matrix((np.ones(ok.size), (ok, self.source[ok])),
                             shape=(self.source.size, self.restrict_all.shape[0]))


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
    return coarse, Transfer(parent, source, restrict_kind.tocsr(), restrict_all.tocsr())


@dataclass(eq=False)
class Hierarchy:
    """A polygrid and its coarser levels; ``grids[0]`` is the finest (the original).

    ``transfers[l]`` maps between ``grids[l]`` (fine) and ``grids[l + 1]`` (coarse).
    """

    grids: list[Polygrid]
    transfers: list[Transfer]

    @classmethod
    def build(cls, pg: Polygrid, levels: int = 3, **weight_options: Any) -> "Hierarchy":
        """``levels`` levels (1 = the polygrid alone); each halves ``n``."""
        if not isinstance(levels, (int, np.integer)) or levels < 1:
            raise InputError(f"levels={levels!r} must be an integer >= 1")
        grids, transfers = [pg], []
        for _ in range(levels - 1):
            coarse, t = coarsen(grids[-1], **weight_options)
            grids.append(coarse)
            transfers.append(t)
        return cls(grids, transfers)

    @property
    def levels(self) -> int:
        return len(self.grids)

    def restrict_q(self, q: NDArray, level: int) -> NDArray[np.float64]:
        """A finest-level source (node array ``shape + (3,)``) at ``level``, per boundary node."""
        x = np.asarray(q, dtype=np.float64).reshape(-1, 3)
        for t in self.transfers[:level]:
            x = t.restrict_kind @ x
        return x[self.grids[level].lattice.boundary]

    def depth(self, level: int) -> NDArray[np.float64]:
        """``(N,)`` distance of every node of ``level`` to the nearest boundary node of the
        finest level (a sample of the surface), mm; 0 at boundary nodes of the finest level."""
        tree = self._surface_tree
        d, _ = tree.query(self.grids[level].positions)
        return d

    @cached_property
    def _surface_tree(self) -> cKDTree:
        return cKDTree(self.grids[0].boundary_positions)

    def prolong_phi(self, phi: NDArray, level: int) -> NDArray[np.float64]:
        """Fluence on ``level`` (node array) copied to ``level - 1`` (parent injection)."""
        t = self.transfers[level - 1]
        fine = self.grids[level - 1]
        return (t.prolong @ np.asarray(phi, dtype=np.float64).reshape(-1, 3)).reshape(fine.shape + (3,))

    def stats(self) -> list[dict[str, Any]]:
        """Per level: n, h (mm), node counts by kind, texture size, weight fallbacks."""
        rows = []
        for i, g in enumerate(self.grids):
            rows.append({"level": i, "n": g.n, "h_mm": g.lattice.h, "interior": g.n_interior,
                         "boundary": g.n_boundary, "texture": "x".join(map(str, g.texture_size)),
                         "fallback": g.weight_stats.fallback if g.weight_stats else 0})
        return rows


__all__ = ["Hierarchy", "Transfer", "coarsen", "INTERIOR", "BOUNDARY"]
