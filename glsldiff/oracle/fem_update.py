"""The P1 system of :mod:`glsldiff.oracle.fem` on a fixed pattern, updated in place when node
materials change (interactive editing, Wang et al. 2008 section 5.4, on tetrahedra).

Every entry of ``A = K(kappa) + diag(mu m) + M_s / (2C)`` is linear in the node material:
an off-diagonal entry ``(i, j)`` is ``sum_t kappa_t K^t_ij`` over the tetrahedra ``t`` holding
the edge ``ij`` (``kappa_t`` the mean of ``t``'s corners), a diagonal entry adds ``mu_i m_i``.
A change of the material at nodes ``S`` therefore changes only the entries of the
tetrahedra around ``S`` (stiffness) and the diagonal at ``S`` (absorption): :meth:`P1System.set_material`
re-sums exactly those, in time proportional to the edit, not to the grid.

The pattern is fixed once per grid (every edge of a tetrahedron between two active nodes and
the diagonal, explicit zeros kept), so the three channel matrices and the block-diagonal
:class:`~glsldiff.oracle.assembly.LinearSystem` share one ``(3, nnz)`` value array: an update
changes them all without copies. Units: ``K``, ``A`` mm; ``b`` mm^2 times the source's units.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError
from glsldiff.grids.pillow import TET_EDGES
from glsldiff.oracle.assembly import LinearSystem
from glsldiff.oracle.fem import TetGeometry

__all__ = ["P1System", "P1Update"]


@dataclass(frozen=True)
class P1Update:
    """What one :meth:`P1System.set_material` changed: ``rows`` (sorted active indices whose
    row of ``A`` changed, neighbours of the edited nodes included), ``nodes`` (edited nodes,
    grid indices), ``tetrahedra`` (how many tetrahedra were re-summed: 0 when only ``mu``
    changed) and ``diagonal_only`` (only diagonal entries changed: an absorption edit)."""

    rows: NDArray[np.int64]
    nodes: NDArray[np.int64]
    tetrahedra: int

    @property
    def diagonal_only(self) -> bool:
        return self.tetrahedra == 0


class P1System:
    """The P1 system of one grid over its active nodes with a material that changes in place.

    Parameters
    ----------
    geo
        The grid's :class:`~glsldiff.oracle.fem.TetGeometry`.
    active
        ``(n,)`` bool: the grid's nodes that are unknowns.
    C
        The Robin boundary constant.
    kappa, mu
        ``(n, 3)`` node material (mm, mm^-1).

    Attributes
    ----------
    values
        ``(3, nnz)`` the entries of the three channel matrices (one pattern).
    system
        The :class:`~glsldiff.oracle.assembly.LinearSystem` (``b`` zero until
        :meth:`set_rhs`); its ``A`` and ``diag`` share :attr:`values`.
    """

    def __init__(self, geo: TetGeometry, active: ArrayLike, C: float, kappa: ArrayLike, mu: ArrayLike,
                 boundary_mass: str = "consistent") -> None:
        n_all = len(geo.positions)
        act = np.asarray(active, dtype=bool)
        if act.shape != (n_all,):
            raise InputError(f"active has shape {act.shape}; expected ({n_all},)")
        self.geo, self.C = geo, float(C)
        self.active = np.flatnonzero(act)
        n = self.active.size
        self._index = np.full(n_all, -1, dtype=np.int64)
        self._index[self.active] = np.arange(n)
        edges, self._tet_edges = geo._edges
        ai, aj = self._index[edges[:, 0]], self._index[edges[:, 1]]
        live = (ai >= 0) & (aj >= 0)
        d = np.arange(n)
        rows = np.concatenate([ai[live], aj[live], d])
        cols = np.concatenate([aj[live], ai[live], d])
        order = np.lexsort((cols, rows))
        inv = np.empty_like(order)
        inv[order] = np.arange(order.size)
        ne = int(live.sum())
        # CSR position of every edge's two entries (-1: an edge to an inactive node) and of the diagonal
        self._pos_ij = np.full(len(edges), -1, dtype=np.int64)
        self._pos_ji = np.full(len(edges), -1, dtype=np.int64)
        self._pos_ij[live], self._pos_ji[live] = inv[:ne], inv[ne:2 * ne]
        self._pos_ii = np.full(n_all, -1, dtype=np.int64)
        self._pos_ii[self.active] = inv[2 * ne:]
        self.indices = cols[order].astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))]).astype(np.int32)
        nnz = self.indices.size
        # the material-independent part: the Robin term on the pattern
        if boundary_mass == "lumped":
            robin = sp.diags(geo.node_areas / (2.0 * self.C)).tocoo()
        else:
            robin = (geo.surface_mass / (2.0 * self.C)).tocoo()
        r, c = self._index[robin.row], self._index[robin.col]
        ok = (r >= 0) & (c >= 0)
        at = self._find(r[ok], c[ok])
        self._robin = np.bincount(at, robin.data[ok], minlength=nnz)
        # node -> tetrahedra incidence (which tetrahedra an edit re-sums)
        flat = geo.tets.ravel()
        self._node_tets = np.argsort(flat, kind="stable") // 4
        self._node_ptr = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=n_all))])
        self._Kl = geo.local_stiffness
        self.values = np.zeros((3, nnz))
        self.kappa = np.zeros((n_all, 3))
        self.mu = np.zeros((n_all, 3))
        self.system = LinearSystem(sp.csr_matrix((self.values.reshape(-1), self._block_indices(),
                                                  self._block_indptr()), shape=(3 * n, 3 * n)),
                                   np.zeros(3 * n), self.values[:, self._pos_ii[self.active]].reshape(-1),
                                   self.active)
        self._assemble(np.asarray(kappa, dtype=np.float64), np.asarray(mu, dtype=np.float64))

    # ---- pattern ------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Unknowns per channel."""
        return int(self.active.size)

    def _find(self, r: NDArray[np.int64], c: NDArray[np.int64]) -> NDArray[np.int64]:
        """CSR positions of the entries ``(r, c)`` (active indices), which must be in the pattern."""
        keys = np.repeat(np.arange(self.n, dtype=np.int64), np.diff(self.indptr)) * self.n + self.indices
        at = np.searchsorted(keys, r * self.n + c)
        if at.size and (np.any(at >= keys.size) or np.any(keys[np.minimum(at, keys.size - 1)] != r * self.n + c)):
            raise InputError("a surface triangle's edge is not an edge of a tetrahedron: the grid's surface does not "
                             "match its tetrahedra")
        return at

    def _block_indices(self) -> NDArray[np.int64]:
        return np.concatenate([self.indices.astype(np.int64) + c * self.n for c in range(3)])

    def _block_indptr(self) -> NDArray[np.int64]:
        nnz = self.indices.size
        return np.concatenate([self.indptr[:-1].astype(np.int64) + c * nnz for c in range(3)] + [[3 * nnz]])

    def matrices(self) -> list[sp.csr_matrix]:
        """The three channel matrices ``(n, n)`` (views of :attr:`values`: they follow updates)."""
        return [sp.csr_matrix((self.values[c], self.indices, self.indptr), shape=(self.n, self.n)) for c in range(3)]

    def row_positions(self, rows: NDArray[np.int64]) -> NDArray[np.int64]:
        """The pattern positions of every entry of ``rows`` (active indices), row by row."""
        start, stop = self.indptr[rows].astype(np.int64), self.indptr[rows + 1].astype(np.int64)
        counts = stop - start
        return np.repeat(start - np.cumsum(counts) + counts, counts) + np.arange(int(counts.sum()))

    # ---- assembly -----------------------------------------------------------------------------
    def _stiffness_terms(self, tets: NDArray[np.int64], kt: NDArray[np.float64]
                         ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Pattern positions and ``(3, m)`` values of ``tets``' stiffness with tetrahedron
        diffusion ``kt`` ``(len(tets), 3)`` (both triangles of every edge, and the diagonal)."""
        Kl = self._Kl[tets]
        e = self._tet_edges[tets]                                         # (t, 6)
        off = Kl[:, TET_EDGES[:, 0], TET_EDGES[:, 1]]                     # (t, 6)
        dia = np.diagonal(Kl, axis1=1, axis2=2)                           # (t, 4)
        pos = np.concatenate([self._pos_ij[e].ravel(), self._pos_ji[e].ravel(), self._pos_ii[self.geo.tets[tets]].ravel()])
        val = np.concatenate([(off[:, :, None] * kt[:, None, :]).reshape(-1, 3)] * 2
                             + [(dia[:, :, None] * kt[:, None, :]).reshape(-1, 3)])
        ok = pos >= 0
        return pos[ok], val[ok].T

    def _assemble(self, kappa: NDArray[np.float64], mu: NDArray[np.float64]) -> None:
        n_all = len(self.geo.positions)
        self.kappa[:] = np.broadcast_to(kappa, (n_all, 3))
        self.mu[:] = np.broadcast_to(mu, (n_all, 3))
        tets = np.arange(len(self.geo.tets))
        pos, val = self._stiffness_terms(tets, self.kappa[self.geo.tets].mean(axis=1))
        nnz = self.indices.size
        for c in range(3):
            self.values[c] = np.bincount(pos, val[c], minlength=nnz) + self._robin
        da = self._pos_ii[self.active]
        self.values[:, da] += (self.mu[self.active] * self.geo.node_volumes[self.active, None]).T
        self._check_diagonal(self.active)
        self._sync_diag(np.arange(self.n))

    def _check_diagonal(self, nodes: NDArray[np.int64]) -> None:
        d = self.values[:, self._pos_ii[nodes]]
        if not np.all(d > 0):
            raise InputError(f"{int(np.any(d <= 0, axis=0).sum())} nodes belong only to tetrahedra of zero volume; "
                             "the grid's mapping collapsed there (try another cube count or n)")

    def _sync_diag(self, rows: NDArray[np.int64]) -> None:
        diag = self.system.diag.reshape(3, self.n)
        diag[:, rows] = self.values[:, self._pos_ii[self.active[rows]]]

    def set_material(self, kappa: ArrayLike, mu: ArrayLike) -> P1Update:
        """Make the system that of node material ``(kappa, mu)`` ``(n_nodes, 3)``, re-summing
        only the entries of the nodes that changed (equal to a fresh assembly to round-off)."""
        kappa = np.asarray(kappa, dtype=np.float64)
        mu = np.asarray(mu, dtype=np.float64)
        dk = np.any(kappa != self.kappa, axis=1)
        dm = np.any(mu != self.mu, axis=1)
        nodes = np.flatnonzero(dk | dm)
        touched: list[NDArray[np.int64]] = []
        tets = np.zeros(0, dtype=np.int64)
        if dk.any():
            kn = np.flatnonzero(dk)
            start, stop = self._node_ptr[kn], self._node_ptr[kn + 1]
            counts = stop - start
            idx = np.repeat(start - np.cumsum(counts) + counts, counts) + np.arange(int(counts.sum()))
            tets = np.unique(self._node_tets[idx])
            kt_old = self.kappa[self.geo.tets[tets]].mean(axis=1)
            self.kappa[kn] = kappa[kn]
            kt_new = self.kappa[self.geo.tets[tets]].mean(axis=1)
            pos, val = self._stiffness_terms(tets, kt_new - kt_old)
            for c in range(3):
                np.add.at(self.values[c], pos, val[c])
            touched.append(self._index[self.geo.tets[tets].ravel()])
        if dm.any():
            mn = np.flatnonzero(dm)
            live = mn[self._index[mn] >= 0]
            self.values[:, self._pos_ii[live]] += ((mu[live] - self.mu[live]) * self.geo.node_volumes[live, None]).T
            self.mu[mn] = mu[mn]
            touched.append(self._index[live])
        rows = np.unique(np.concatenate(touched)) if touched else np.zeros(0, dtype=np.int64)
        rows = rows[rows >= 0]
        self._check_diagonal(self.active[rows])
        self._sync_diag(rows)
        return P1Update(rows, nodes, int(tets.size))

    def set_rhs(self, b: ArrayLike) -> None:
        """Set the right-hand side ``(n, 3)`` over the active nodes."""
        bb = np.asarray(b, dtype=np.float64)
        if bb.shape != (self.n, 3):
            raise InputError(f"b has shape {bb.shape}; expected ({self.n}, 3)")
        self.system.b = bb.T.reshape(-1).copy()
