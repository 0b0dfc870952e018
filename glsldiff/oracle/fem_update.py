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
:class:`~glsldiff.oracle.assembly.ChannelSystem` over them share one ``(3, nnz)`` value array: an
update changes them all without copies. Units: ``K``, ``A`` mm; ``b`` mm^2 times the source's units.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from glsldiff.core import cache
from glsldiff.core.errors import InputError
from glsldiff.core.jit import kernel
from glsldiff.grids.tetrahedral.pillow import TET_EDGES
from glsldiff.oracle.assembly import ChannelSystem, row_entries
from glsldiff.oracle.fem import TetGeometry

__all__ = ["P1Pattern", "P1System", "P1Update", "cached_p1_pattern"]

#: Part of every cached pattern's key: bump it when :class:`P1Pattern` changes.
PATTERN_CACHE_VERSION = 5   # 2: the surface mass at its positions only; no node -> tetrahedra lists;
#                               3: the surface mass is lumped at crease nodes; 4: int32 pos_ij, pos_ji;
#                               5: the surface mass is lumped at flat tetrahedra's surface nodes too


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
    ``pos_ij``, ``pos_ji`` each unique edge's two positions (-1: an edge to an inactive node;
    int32 where the pattern's entries allow),
    ``pos_ii`` each node's diagonal position; ``surface_pos``, ``surface_mass`` the consistent
    surface mass (mm^2) at the pattern positions it fills (ascending; the surface's few percent
    of the entries)."""

    index: NDArray[np.int64]
    indptr: NDArray[np.int32]
    indices: NDArray[np.int32]
    pos_ij: NDArray[np.integer]
    pos_ji: NDArray[np.integer]
    pos_ii: NDArray[np.int64]
    surface_pos: NDArray[np.int64]
    surface_mass: NDArray[np.float64]

    @classmethod
    def build(cls, geo: TetGeometry, active: NDArray[np.bool_]) -> "P1Pattern":
        n_all = len(geo.positions)
        act = np.flatnonzero(active)
        n = act.size
        index = np.full(n_all, -1, dtype=np.int64)
        index[act] = np.arange(n)
        indptr64, indices, pos_ij, pos_ji, diag = _csr_pattern(geo._edges[0], index, n)
        indptr = indptr64.astype(np.int32)
        if indices.size < np.iinfo(np.int32).max:     # the edge positions in int32: 8 MB less on the bunny
            pos_ij, pos_ji = pos_ij.astype(np.int32), pos_ji.astype(np.int32)
        pos_ii = np.full(n_all, -1, dtype=np.int64)
        pos_ii[act] = diag
        sm = geo.surface_mass.tocoo()
        r, c = index[sm.row], index[sm.col]
        ok = (r >= 0) & (c >= 0)
        keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr)) * n + indices
        want = r[ok] * n + c[ok]
        at = np.searchsorted(keys, want)
        if at.size and (np.any(at >= keys.size) or np.any(keys[np.minimum(at, keys.size - 1)] != want)):
            raise InputError("a surface triangle's edge is not an edge of a tetrahedron: the grid's surface does not "
                             "match its tetrahedra")
        surface_pos, where = np.unique(at, return_inverse=True)
        return cls(index, indptr, indices, pos_ij, pos_ji, pos_ii, surface_pos,
                   np.bincount(where.ravel(), sm.data[ok], minlength=surface_pos.size))


@kernel
def _csr_pattern(edges: NDArray[np.int64], index: NDArray[np.int64], n: int
                 ) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.int64], NDArray[np.int64],
                            NDArray[np.int64]]:
    """The CSR pattern over the ``n`` active nodes of the unique ``edges`` (``i < j``, in
    lexicographic order, as :func:`~glsldiff.grids.tetrahedral.pillow.unique_tet_edges` gives
    them) and the diagonal: ``(indptr, indices, pos_ij, pos_ji, pos_ii)`` with each row's
    columns ascending (the pattern of a ``lexsort`` by row and column, built without one): a
    row's lower entries first (its edges as the larger node, met in edge order: ascending),
    then its diagonal, then its upper entries (its own edges, contiguous and ascending).
    ``index`` grid node -> active index (-1: inactive); an edge to an inactive node gets -1."""
    E = len(edges)
    indptr = np.zeros(n + 1, dtype=np.int64)
    for r in range(n):
        indptr[r + 1] = 1
    for e in range(E):
        a, b = index[edges[e, 0]], index[edges[e, 1]]
        if a >= 0 and b >= 0:
            indptr[a + 1] += 1
            indptr[b + 1] += 1
    for r in range(n):
        indptr[r + 1] += indptr[r]
    fill = indptr[:-1].copy()
    indices = np.empty(indptr[n], dtype=np.int32)
    pos_ij = np.full(E, -1, dtype=np.int64)
    pos_ji = np.full(E, -1, dtype=np.int64)
    pos_ii = np.empty(n, dtype=np.int64)
    for e in range(E):                      # lower entries: row b, column a
        a, b = index[edges[e, 0]], index[edges[e, 1]]
        if a >= 0 and b >= 0:
            indices[fill[b]] = a
            pos_ji[e] = fill[b]
            fill[b] += 1
    for r in range(n):
        indices[fill[r]] = r
        pos_ii[r] = fill[r]
        fill[r] += 1
    for e in range(E):                      # upper entries: row a, column b
        a, b = index[edges[e, 0]], index[edges[e, 1]]
        if a >= 0 and b >= 0:
            indices[fill[a]] = b
            pos_ij[e] = fill[a]
            fill[a] += 1
    return indptr, indices, pos_ij, pos_ji, pos_ii


@kernel
def _node_tets(tets: NDArray[np.int64], n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The tetrahedra of each of ``n`` nodes, ascending, as CSR ``(node_tets, node_ptr)``: a
    counting sort (``argsort(tets.ravel(), kind="stable") // 4``, linear)."""
    ptr = np.zeros(n + 1, dtype=np.int64)
    for t in range(len(tets)):
        for a in range(4):
            ptr[tets[t, a] + 1] += 1
    for i in range(n):
        ptr[i + 1] += ptr[i]
    fill = ptr[:-1].copy()
    out = np.empty(4 * len(tets), dtype=np.int64)
    for t in range(len(tets)):
        for a in range(4):
            v = tets[t, a]
            out[fill[v]] = t
            fill[v] += 1
    return out, ptr


@kernel
def _fill_values(values: NDArray[np.float64], robin_pos: NDArray[np.int64], robin: NDArray[np.float64],
                 off: NDArray[np.float64], diag: NDArray[np.float64], mu: NDArray[np.float64],
                 node_volumes: NDArray[np.float64], pos_ij: NDArray[np.integer], pos_ji: NDArray[np.integer],
                 pos_ii: NDArray[np.int64], active: NDArray[np.int64]) -> None:
    """``values`` ``(C, nnz)``: the Robin term (``robin`` at the distinct ``robin_pos``, 0
    elsewhere), plus each live edge's ``off`` at its two positions, plus ``diag + mu m`` on
    each active node's diagonal (the sums of :meth:`P1System._assemble`'s numpy form, in its order)."""
    for c in range(values.shape[0]):
        for p in range(values.shape[1]):
            values[c, p] = 0.0
        for k in range(len(robin_pos)):
            values[c, robin_pos[k]] = robin[k]
        for e in range(len(pos_ij)):
            if pos_ij[e] >= 0:
                values[c, pos_ij[e]] += off[e, c]
                values[c, pos_ji[e]] += off[e, c]
        for a in range(len(active)):
            i = active[a]
            values[c, pos_ii[i]] += diag[i, c] + mu[i, c] * node_volumes[i]


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
        The :class:`~glsldiff.oracle.assembly.ChannelSystem` of :meth:`matrices` (``b`` zero
        until :meth:`set_rhs`); its blocks (and its block-diagonal ``A``, made when asked for) share
        :attr:`values`.
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
        # the material-independent part: the Robin term at the pattern positions it fills
        if boundary_mass == "lumped":
            self._robin_pos = self._pos_ii[self.active]
            self._robin = geo.node_areas[self.active] / (2.0 * self.C)
        else:
            self._robin_pos, self._robin = pat.surface_pos, pat.surface_mass / (2.0 * self.C)
        self._node_tets: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None   # made at the first kappa edit
        self.values = np.zeros((3, self.indices.size))
        self._matrices: list[sp.csr_matrix] | None = None
        self.kappa = np.zeros((n_all, 3))
        self.mu = np.zeros((n_all, 3))
        # the channel matrices, not a block-diagonal copy of their indices (24 MB on the bunny):
        # its A is assembled only where something asks for it (tests, benches), sharing values
        self.system = ChannelSystem(self.matrices(), np.zeros(3 * n),
                                    self.values[:, self._pos_ii[self.active]].reshape(-1), self.active)
        self._assemble(np.asarray(kappa, dtype=np.float64), np.asarray(mu, dtype=np.float64))

    # ---- pattern ------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Unknowns per channel."""
        return int(self.active.size)

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
        Kl = self.geo.local_stiffness_of(tets)
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
        # per unique edge and per node first (edge-length arrays: each tetrahedron's entries
        # recomputed from its corners in the kernel, no per-tetrahedron arrays), then onto the pattern
        off, diag = self.geo.stiffness_sums(self.kappa)                    # (n_edges, 3), (n_all, 3)
        _fill_values(self.values, self._robin_pos, self._robin, off, diag, self.mu, self.geo.node_volumes,
                     self._pos_ij, self._pos_ji, self._pos_ii, self.active)
        del off, diag
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
            if self._node_tets is None:     # the tetrahedra of each node (CSR): 26 MB on the bunny, for edits only
                self._node_tets = _node_tets(self.geo.tets, len(self.geo.positions))
            node_tets, node_ptr = self._node_tets
            tets = np.unique(node_tets[row_entries(node_ptr, kn)])
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
