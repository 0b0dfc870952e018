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

from glsldiff.core import cache
from glsldiff.core.errors import InputError
from glsldiff.grids.tetrahedral.pillow import TET_EDGES
from glsldiff.oracle.assembly import LinearSystem, row_entries
from glsldiff.oracle.fem import TetGeometry

__all__ = ["P1Pattern", "P1System", "P1Update", "cached_p1_pattern"]

#: Part of every cached pattern's key: bump it when :class:`P1Pattern` changes.
PATTERN_CACHE_VERSION = 1


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


@dataclass(frozen=True, eq=False)
class P1Pattern:
    """The fixed sparsity pattern of a grid's P1 matrix over its active nodes and where each
    element's entries go in it (a function of the grid alone: :func:`cached_p1_pattern` keeps it
    on disk with the grid). ``index`` grid node -> active index (-1: inactive); ``indptr``,
    ``indices`` the CSR pattern (every edge between active nodes both ways, and the diagonal);
    ``pos_ij``, ``pos_ji`` each unique edge's two positions (-1: an edge to an inactive node),
    ``pos_ii`` each node's diagonal position; ``surface_mass`` the consistent surface mass on the
    pattern (mm^2); ``node_tets``, ``node_ptr`` the tetrahedra of each node (CSR)."""

    index: NDArray[np.int64]
    indptr: NDArray[np.int32]
    indices: NDArray[np.int32]
    pos_ij: NDArray[np.int64]
    pos_ji: NDArray[np.int64]
    pos_ii: NDArray[np.int64]
    surface_mass: NDArray[np.float64]
    node_tets: NDArray[np.int64]
    node_ptr: NDArray[np.int64]

    @classmethod
    def build(cls, geo: TetGeometry, active: NDArray[np.bool_]) -> "P1Pattern":
        n_all = len(geo.positions)
        act = np.flatnonzero(active)
        n = act.size
        index = np.full(n_all, -1, dtype=np.int64)
        index[act] = np.arange(n)
        edges = geo._edges[0]
        ai, aj = index[edges[:, 0]], index[edges[:, 1]]
        live = (ai >= 0) & (aj >= 0)
        d = np.arange(n)
        rows = np.concatenate([ai[live], aj[live], d])
        cols = np.concatenate([aj[live], ai[live], d])
        order = np.lexsort((cols, rows))
        inv = np.empty_like(order)
        inv[order] = np.arange(order.size)
        ne = int(live.sum())
        pos_ij = np.full(len(edges), -1, dtype=np.int64)
        pos_ji = np.full(len(edges), -1, dtype=np.int64)
        pos_ij[live], pos_ji[live] = inv[:ne], inv[ne:2 * ne]
        pos_ii = np.full(n_all, -1, dtype=np.int64)
        pos_ii[act] = inv[2 * ne:]
        indices = cols[order].astype(np.int32)
        indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))]).astype(np.int32)
        sm = geo.surface_mass.tocoo()
        r, c = index[sm.row], index[sm.col]
        ok = (r >= 0) & (c >= 0)
        keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr)) * n + indices
        want = r[ok] * n + c[ok]
        at = np.searchsorted(keys, want)
        if at.size and (np.any(at >= keys.size) or np.any(keys[np.minimum(at, keys.size - 1)] != want)):
            raise InputError("a surface triangle's edge is not an edge of a tetrahedron: the grid's surface does not "
                             "match its tetrahedra")
        flat = geo.tets.ravel()
        return cls(index, indptr, indices, pos_ij, pos_ji, pos_ii,
                   np.bincount(at, sm.data[ok], minlength=indices.size),
                   np.argsort(flat, kind="stable") // 4,
                   np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=n_all))]))


def cached_p1_pattern(geo: TetGeometry, active: ArrayLike) -> P1Pattern:
    """:meth:`P1Pattern.build` through the on-disk cache (:mod:`glsldiff.core.cache`), keyed by
    the grid's positions, tetrahedra, surface and active nodes."""
    act = np.asarray(active, dtype=bool)
    key = cache.digest(f"p1 pattern v{PATTERN_CACHE_VERSION}", geo.positions, geo.tets, geo.surface, act)
    return cache.memo("p1pattern", key, P1Pattern, lambda: P1Pattern.build(geo, act))


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
    boundary_mass
        The Robin term: ``"consistent"`` (the surface mass) or ``"lumped"`` (its row sums), as
        :class:`~glsldiff.system.tet_problem.TetProblem`.
    pattern
        The grid's :class:`P1Pattern` (e.g. :func:`cached_p1_pattern`); default: built here.

    Attributes
    ----------
    values
        ``(3, nnz)`` the entries of the three channel matrices (one pattern).
    system
        The :class:`~glsldiff.oracle.assembly.LinearSystem` (``b`` zero until
        :meth:`set_rhs`); its ``A`` and ``diag`` share :attr:`values`.
    """

    def __init__(self, geo: TetGeometry, active: ArrayLike, C: float, kappa: ArrayLike, mu: ArrayLike,
                 boundary_mass: str = "consistent", pattern: "P1Pattern | None" = None) -> None:
        n_all = len(geo.positions)
        act = np.asarray(active, dtype=bool)
        if act.shape != (n_all,):
            raise InputError(f"active has shape {act.shape}; expected ({n_all},)")
        pat = P1Pattern.build(geo, act) if pattern is None else pattern
        self.geo, self.C, self.pattern = geo, float(C), pat
        self.active = np.flatnonzero(act)
        self._index, self._tet_edges = pat.index, geo._edges[1]
        self._pos_ij, self._pos_ji, self._pos_ii = pat.pos_ij, pat.pos_ji, pat.pos_ii
        self.indices, self.indptr = pat.indices, pat.indptr
        n = self.active.size
        # the material-independent part: the Robin term on the pattern
        if boundary_mass == "lumped":
            self._robin = np.zeros(self.indices.size)
            self._robin[self._pos_ii[self.active]] = geo.node_areas[self.active] / (2.0 * self.C)
        else:
            self._robin = pat.surface_mass / (2.0 * self.C)
        self._node_tets, self._node_ptr = pat.node_tets, pat.node_ptr
        self._Kl = geo.local_stiffness
        self.values = np.zeros((3, self.indices.size))
        self._matrices: list[sp.csr_matrix] | None = None
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

    def _block_indices(self) -> NDArray[np.int64]:
        return np.concatenate([self.indices.astype(np.int64) + c * self.n for c in range(3)])

    def _block_indptr(self) -> NDArray[np.int64]:
        nnz = self.indices.size
        return np.concatenate([self.indptr[:-1].astype(np.int64) + c * nnz for c in range(3)] + [[3 * nnz]])

    def matrices(self) -> list[sp.csr_matrix]:
        """The three channel matrices ``(n, n)``, whose ``data`` are the rows of :attr:`values`
        (they follow updates; made once: scipy copies the data it is given and checks the index
        order of every new matrix, 2-5 ms a frame)."""
        if self._matrices is None:
            self._matrices = []
            for c in range(3):
                m = sp.csr_matrix((self.values[c], self.indices, self.indptr), shape=(self.n, self.n))
                m.data = self.values[c]
                self._matrices.append(m)
        return self._matrices

    def row_positions(self, rows: NDArray[np.int64]) -> NDArray[np.int64]:
        """The pattern positions of every entry of ``rows`` (active indices), row by row."""
        return row_entries(self.indptr, rows)

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
        # per unique edge and per node first (edge-length arrays), then onto the pattern: no
        # (16 T, 3) temporaries (a fresh bunny grid's 790k tetrahedra made ~1 GB of them)
        mean, to_edges, to_nodes = self._tet_operators()
        kt = mean @ self.kappa                                              # (T, 3) tetrahedron kappa
        e = to_edges.T @ kt                                                 # (n_edges, 3) off-diagonal sums
        d = to_nodes.T @ kt                                                 # (n_all, 3) diagonal sums
        live = np.flatnonzero(self._pos_ij >= 0)
        pij, pji, da = self._pos_ij[live], self._pos_ji[live], self._pos_ii[self.active]
        e_live = e[live]
        d_act = d[self.active] + self.mu[self.active] * self.geo.node_volumes[self.active, None]
        for c, v in enumerate(self.values):       # row by row: 2x faster than 2-D fancy indexing
            v[:] = self._robin
            v[pij] += e_live[:, c]
            v[pji] += e_live[:, c]
            v[da] += d_act[:, c]
        self._check_diagonal(self.active)
        self._sync_diag(np.arange(self.n))

    def _tet_operators(self) -> tuple[sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]:
        """Sparse ``(T, n_nodes)`` mean over each tetrahedron's nodes, ``(T, n_edges)`` its six
        off-diagonal and ``(T, n_nodes)`` four diagonal stiffness entries (per unit kappa): the
        assembly is then three products (their transposes scatter-add in compiled code: 4x
        faster than ``bincount`` and the ``(T, 4, 3)`` gather on a 790k-tetrahedron bunny)."""
        tets, Kl = self.geo.tets, self._Kl
        T, n_all = len(tets), len(self.geo.positions)
        rows4, rows6 = np.arange(0, 4 * T + 1, 4), np.arange(0, 6 * T + 1, 6)
        off = Kl[:, TET_EDGES[:, 0], TET_EDGES[:, 1]]
        dia = np.diagonal(Kl, axis1=1, axis2=2)
        return (sp.csr_matrix((np.full(4 * T, 0.25), tets.ravel(), rows4), shape=(T, n_all)),
                sp.csr_matrix((off.ravel(), self._tet_edges.ravel(), rows6), shape=(T, len(self._pos_ij))),
                sp.csr_matrix((dia.ravel(), tets.ravel(), rows4), shape=(T, n_all)))

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
            tets = np.unique(self._node_tets[row_entries(self._node_ptr, kn)])
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
