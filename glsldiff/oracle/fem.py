"""Linear (P1) finite elements for the diffusion equation on tetrahedra.

Weak form of ``div(kappa grad phi) - mu phi = 0`` with the boundary condition
``phi + 2 C kappa dphi/dn = q``: for every test function ``v``

    int kappa grad(phi).grad(v) + int mu phi v + int_surface phi v / (2C) = int_surface q v / (2C).

With P1 elements on tetrahedra this is ``A phi = b``, ``A = K + diag(mu m) + M_s / (2C)``,
``b = a q / (2C)``: ``K`` the stiffness matrix (per tetrahedron ``kappa_t V_t grad(l_i).grad(l_j)``:
the cotangent weights of TransCut eqs. 10-14), ``m`` the lumped node volumes (``V_t / 4`` per
corner), ``a`` the lumped surface areas (``A_f / 3`` per corner of each surface triangle) and
``M_s`` the surface mass matrix: consistent (``A_f (1 + delta_ij) / 12`` per surface triangle,
the default; lumped on every edge of a :attr:`TetGeometry.crease_nodes` or
:attr:`TetGeometry.flat_surface_nodes` node, see there) or
lumped (``diag(a)``, ``TetProblem.boundary_mass``). Per
tetrahedron ``kappa_t`` is the mean of its corners' ``kappa`` (mm), ``mu`` (mm^-1) is per node.
Units: lengths mm, ``K`` and ``A`` in mm, ``b`` in mm^2 times the source's units.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pyamg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import ArrayLike, NDArray

from glsldiff.core import cache
from glsldiff.core.interrupt import interruptible
from glsldiff.core.jit import kernel
from glsldiff.core.rng import pinned_global_rng
from glsldiff.core.errors import InputError
from glsldiff.grids.tetrahedral.pillow import six_volumes, unique_tet_edges
from glsldiff.grids.tetrahedral.shapes import SHAPE_TARGET, shape_quality
from glsldiff.mesh import vertex_areas
from glsldiff.oracle.assembly import LinearSystem
from glsldiff.system.report import REFERENCE_TOL, SolveReport
from glsldiff.system.tet_problem import TetProblem

__all__ = ["TetGeometry", "assemble_p1", "assemble_tet", "cached_tet_geometry", "positive_couplings",
           "solve_matrix_reference", "solve_system_direct", "solve_tet_direct", "tet_geometry", "tet_rhs",
           "DIRECT_MAX_NODES"]

logger = logging.getLogger(__name__)

#: Above this many unknowns per channel the reference solve is pyamg (SuperLU fills in).
DIRECT_MAX_NODES = 20_000

#: Part of every cached geometry's key: bump it when a factor of :data:`CACHED_FACTORS` changes.
GEOMETRY_CACHE_VERSION = 4      # 2: no local_stiffness (the assembly recomputes it per tetrahedron); int32 edges;
#                                 3: the surface mass is lumped at crease nodes; 4: and at flat tetrahedra's
#: A surface node where two of its surface triangles' normals differ by more than this (degrees)
#: is a crease node: the consistent surface mass is lumped on its edges (:attr:`TetGeometry.surface_mass`).
CREASE_LUMP_DEG = 60.0
#: The :class:`TetGeometry` factors :func:`cached_tet_geometry` keeps on disk: what assembling
#: a system needs (40 MB at 800k tetrahedra; computed: 0.4-1 s, nearly all of it the edges).
#: Not the ``local_stiffness`` (103 MB) nor the ``gradients`` (77 MB): the assembly's kernel
#: (:func:`_stiffness_sums`) recomputes each tetrahedron's entries from its corners in less time
#: than reading them back.
CACHED_FACTORS = ("volumes", "degenerate", "_edges", "node_volumes", "node_areas", "surface_mass")


@dataclass(frozen=True, eq=False)
class TetGeometry:
    """Per-tetrahedron and per-node geometric factors of a tetrahedral mesh.

    ``positions`` ``(n, 3)`` mm, ``tets`` ``(T, 4)`` right-handed, ``surface`` ``(F, 3)``
    boundary triangles."""

    positions: NDArray[np.float64]
    tets: NDArray[np.int64]
    surface: NDArray[np.int64]
    inert: NDArray[np.bool_] | None = None     # (T,) tetrahedra to treat as degenerate (the grid's slivers)

    @cached_property
    def volumes(self) -> NDArray[np.float64]:
        """``(T,)`` signed volumes, mm^3 (:func:`~glsldiff.grids.tetrahedral.pillow.six_volumes`:
        the bits of ``np.einsum`` over ``np.cross``, without its ``(T, 4, 3)`` temporaries)."""
        return six_volumes(self.positions, self.tets) / 6.0

    @cached_property
    def degenerate(self) -> NDArray[np.bool_]:
        """``(T,)`` tetrahedra of (numerically) zero volume, and the grid's :attr:`inert` ones:
        they carry no stiffness (their gradients are undefined or their cotangents huge: a flat
        tetrahedron of a collapsed mapping, a sliver fTetWild left); the lumped masses keep
        their (tiny) volume."""
        v = np.abs(self.volumes)
        flat = v <= 1e-12 * float(v.max(initial=0.0))
        return flat if self.inert is None else flat | self.inert

    @cached_property
    def gradients(self) -> NDArray[np.float64]:
        """``(T, 4, 3)`` gradients of the barycentric coordinates ``grad(l_i)`` (mm^-1; 0 for
        :attr:`degenerate` tetrahedra). With edges ``e_k = x_k - x_0``, ``grad l_1 = (e_2 x e_3) /
        6V`` and cyclically, ``grad l_0 = -(sum of the others)`` (:func:`_gradients`; the
        bits of :func:`gradients_numpy`)."""
        return _gradients(self.positions, self.tets, self.volumes, self.degenerate)

    @cached_property
    def local_stiffness(self) -> NDArray[np.float64]:
        """``(T, 4, 4)`` ``V_t grad(l_i).grad(l_j)`` (mm) of each tetrahedron (0 for
        :attr:`degenerate` ones; :func:`_local_stiffness`, the bits of :func:`local_stiffness_numpy`).
        Not what the assembly reads (:meth:`stiffness_sums` recomputes the entries)."""
        return self.local_stiffness_of(np.arange(len(self.tets)))

    def local_stiffness_of(self, tets: NDArray[np.int64]) -> NDArray[np.float64]:
        """``(t, 4, 4)`` :attr:`local_stiffness` of the tetrahedra ``tets`` (indices) alone."""
        tets = np.asarray(tets, dtype=np.int64)
        return _local_stiffness(self.positions, self.tets[tets], self.volumes[tets], self.degenerate[tets])

    def stiffness_sums(self, kappa: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(off, diag)``: ``(E, C)`` the stiffness entry of each unique edge (:attr:`_edges`)
        and ``(n, C)`` the diagonal, for node ``kappa`` ``(n, C)`` mm: ``sum_t kappa_t K^t``
        over the tetrahedra in order (:func:`_stiffness_sums`, no per-tetrahedron arrays)."""
        edges, tet_edges = self._edges
        return _stiffness_sums(self.positions, self.tets, self.volumes, self.degenerate, tet_edges,
                               np.ascontiguousarray(kappa, dtype=np.float64), len(edges))

    def recovered_gradient(self, phi: NDArray[np.float64]) -> NDArray[np.float64]:
        """``(n, 3, C)`` gradient of the P1 field ``phi`` ``(n, C)`` at the nodes: the mean of
        the constant gradients of the tetrahedra around each node, weighted by their volumes."""
        g = np.einsum("tkj,tkc->tjc", self.gradients, phi[self.tets])            # (T, 3, C)
        v = np.where(~self.degenerate, np.abs(self.volumes), 0.0)
        acc = np.zeros((len(self.positions),) + g.shape[1:])
        np.add.at(acc, self.tets.ravel(), np.repeat(g * v[:, None, None], 4, axis=0))
        w = np.bincount(self.tets.ravel(), np.repeat(v, 4), minlength=len(self.positions))
        return acc / np.maximum(w, 1e-300)[:, None, None]

    @cached_property
    def node_volumes(self) -> NDArray[np.float64]:
        """``(n,)`` lumped volumes ``sum V_t / 4``, mm^3."""
        return np.bincount(self.tets.ravel(), np.repeat(np.abs(self.volumes) / 4.0, 4), minlength=len(self.positions))

    @cached_property
    def node_areas(self) -> NDArray[np.float64]:
        """``(n,)`` lumped surface areas ``sum A_f / 3``, mm^2."""
        return vertex_areas(self.positions, self.surface)

    @cached_property
    def crease_nodes(self) -> NDArray[np.bool_]:
        """``(n,)`` surface nodes where the surface turns sharply: two of the node's surface
        triangles have normals more than :data:`CREASE_LUMP_DEG` apart (a crease or corner of a
        CAD part, a thin part's rim, a tip)."""
        X, f = self.positions, self.surface
        out = np.zeros(len(X), dtype=bool)
        if len(f) == 0:
            return out
        nrm = np.cross(X[f[:, 1]] - X[f[:, 0]], X[f[:, 2]] - X[f[:, 0]])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1), 1e-300)[:, None]
        order = np.argsort(f.ravel(), kind="stable")
        node, tri = f.ravel()[order], order // 3
        first = np.flatnonzero(np.r_[True, node[1:] != node[:-1]])
        deg = np.diff(np.r_[first, len(node)])
        slot = np.arange(len(node)) - np.repeat(first, deg)
        N = np.full((len(first), int(deg.max()), 3), np.nan)      # each node's triangle normals, padded
        N[np.repeat(np.arange(len(first)), deg), slot] = nrm[tri]
        gram = np.nan_to_num(np.einsum("sik,sjk->sij", N, N), nan=1.0)
        out[node[first]] = gram.min(axis=(1, 2)) < np.cos(np.radians(CREASE_LUMP_DEG))
        return out

    @cached_property
    def flat_surface_nodes(self) -> NDArray[np.bool_]:
        """``(n,)`` surface nodes of a tetrahedron below the shape target
        (:data:`~glsldiff.grids.tetrahedral.shapes.SHAPE_TARGET`, shape quality
        ``6 sqrt(2) V / l^3``): nearly flat tetrahedra, whose stiffness already couples their
        nodes with large positive entries (obtuse dihedral angles)."""
        flat = np.zeros(len(self.positions), dtype=bool)
        flat[self.tets[shape_quality(self.positions, self.tets) < SHAPE_TARGET].ravel()] = True
        on_surface = np.zeros(len(self.positions), dtype=bool)
        on_surface[self.surface.ravel()] = True
        return flat & on_surface

    @cached_property
    def surface_mass(self) -> sp.csr_matrix:
        """``(n, n)`` surface mass ``int l_i l_j dA``, mm^2: consistent (``A_f (1 + delta_ij) / 12``
        per surface triangle) but on the edges of :attr:`crease_nodes` and
        :attr:`flat_surface_nodes`, whose entries are lumped onto the diagonal. Its row sums are
        :attr:`node_areas`, its pattern lies inside the stiffness pattern since surface triangles
        are tetrahedron faces.

        Why lumped at creases: the source ``a q / (2C)`` is lumped, and where ``q`` jumps (a lit
        face beside an unlit one across a crease) the consistent entries' positive couplings
        ``A_f / (24 C)`` pull the unlit side's fluence below zero (back-lit couplingdown and
        fandisk: down to -6 % of the largest; dark specks along the creases). Against well-shaped
        reference meshes (0.15 mm tetgen meshes of 6 mm balls of the grid's own domain) lumping
        there is also the more accurate: a couplingdown crease 4.8 -> 1.3 % RMS of the fluence
        (max 13 -> 5 %), the elk's ring-to-plate crease 1.7 -> 0.6 % (docs/guide/tetrahedral.md).
        Elsewhere the consistent mass stays (the sphere bench's smooth surfaces: lower error
        than lumped). At flat tetrahedra for the same reason: there the consistent entries add to
        the stiffness's positive couplings, and the fluence dipped below zero next to them (the
        back-lit elk's ring: -1.2 % of the largest with the consistent entries, -0.38 % lumped;
        docs/guide/tetrahedral.md)."""
        X, f = self.positions, self.surface
        A = 0.5 * np.linalg.norm(np.cross(X[f[:, 1]] - X[f[:, 0]], X[f[:, 2]] - X[f[:, 0]]), axis=1)
        local = (np.ones((3, 3)) + np.eye(3)) / 12.0
        n = len(X)
        rows, cols = np.repeat(f, 3, axis=1).ravel(), np.tile(f, (1, 3)).ravel()
        vals = (A[:, None, None] * local).ravel()
        lumped = self.crease_nodes | self.flat_surface_nodes
        lump = (rows != cols) & (lumped[rows] | lumped[cols])
        cols = np.where(lump, rows, cols)            # a lumped entry moves onto its row's diagonal
        return sp.csr_matrix((vals, (rows, cols)), shape=(n, n))

    @cached_property
    def _edges(self) -> tuple[NDArray[np.integer], NDArray[np.integer]]:
        """The mesh's unique edges ``(E, 2)`` (``i < j``, lexicographic) and each tetrahedron's
        six edges ``(T, 6)`` as indices into them, in the order of
        :data:`glsldiff.grids.tetrahedral.pillow.TET_EDGES`; int32 where the counts allow (half the
        memory: 27 MB less on the bunny). (Sorting the ``6 T`` edge keys once is 2-3x cheaper
        than summing the ``16 T`` local entries into a CSR pattern: 1.2 s against 5 s at 790k
        tetrahedra, measured.)"""
        edges, tet_edges = unique_tet_edges(self.tets, len(self.positions))
        if max(len(self.positions), len(edges)) < np.iinfo(np.int32).max:
            edges, tet_edges = edges.astype(np.int32), tet_edges.astype(np.int32)
        return edges, tet_edges

    def stiffness(self, kappa: ArrayLike) -> sp.csr_matrix:
        """``K`` for node ``kappa`` (n,) mm (a scalar: homogeneous): the local entries summed
        per edge and per node, then one linear-time COO-to-CSR conversion."""
        n = len(self.positions)
        k = np.broadcast_to(np.asarray(kappa, dtype=np.float64), (n,))
        off, diag = (x[:, 0] for x in self.stiffness_sums(k[:, None]))
        edges = self._edges[0]
        i, j, d = edges[:, 0], edges[:, 1], np.arange(n)
        K = sp.coo_matrix((np.concatenate([off, off, diag]), (np.concatenate([i, j, d]), np.concatenate([j, i, d]))),
                          shape=(n, n)).tocsr()
        K.sort_indices()
        return K


def gradients_numpy(positions: NDArray[np.float64], tets: NDArray[np.int64], volumes: NDArray[np.float64],
                    degenerate: NDArray[np.bool_]) -> NDArray[np.float64]:
    """:attr:`TetGeometry.gradients` in numpy (the reference of :func:`_gradients`; ``(T, 4, 3)``
    temporaries)."""
    P = positions[tets]
    e1, e2, e3 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]
    det = 6.0 * volumes
    ok = ~degenerate
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    G = np.empty((len(P), 4, 3))
    G[:, 1], G[:, 2], G[:, 3] = np.cross(e2, e3), np.cross(e3, e1), np.cross(e1, e2)
    G[:, 1:] *= inv[:, None, None]
    G[:, 0] = -G[:, 1:].sum(axis=1)
    return G


def local_stiffness_numpy(positions: NDArray[np.float64], tets: NDArray[np.int64], volumes: NDArray[np.float64],
                          degenerate: NDArray[np.bool_]) -> NDArray[np.float64]:
    """:attr:`TetGeometry.local_stiffness` in numpy (the reference of :func:`_local_stiffness`)."""
    G = gradients_numpy(positions, tets, volumes, degenerate)
    return np.where(~degenerate, np.abs(volumes), 0.0)[:, None, None] * np.einsum("tik,tjk->tij", G, G)


@kernel(inline=True)
def _tet_gradients(X: NDArray[np.float64], tets: NDArray[np.int64], t: int, volume: float, dead: bool
                   ) -> tuple[float, ...]:
    """The 12 components of ``grad l_0 .. grad l_3`` of tetrahedron ``t`` (mm^-1): the
    floating-point operations of :func:`gradients_numpy` (``np.cross``'s products, the
    reciprocal of ``6 V`` times each cross product, ``grad l_0`` minus the others summed in order)."""
    i, j, k, m = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    a0, a1, a2 = X[j, 0] - X[i, 0], X[j, 1] - X[i, 1], X[j, 2] - X[i, 2]
    b0, b1, b2 = X[k, 0] - X[i, 0], X[k, 1] - X[i, 1], X[k, 2] - X[i, 2]
    c0, c1, c2 = X[m, 0] - X[i, 0], X[m, 1] - X[i, 1], X[m, 2] - X[i, 2]
    inv = 0.0 if dead else 1.0 / (6.0 * volume)
    p0, p1, p2 = (b1 * c2 - b2 * c1) * inv, (b2 * c0 - b0 * c2) * inv, (b0 * c1 - b1 * c0) * inv   # e2 x e3
    q0, q1, q2 = (c1 * a2 - c2 * a1) * inv, (c2 * a0 - c0 * a2) * inv, (c0 * a1 - c1 * a0) * inv   # e3 x e1
    r0, r1, r2 = (a1 * b2 - a2 * b1) * inv, (a2 * b0 - a0 * b2) * inv, (a0 * b1 - a1 * b0) * inv   # e1 x e2
    return (-((p0 + q0) + r0), -((p1 + q1) + r1), -((p2 + q2) + r2), p0, p1, p2, q0, q1, q2, r0, r1, r2)


@kernel(inline=True)
def _dot3(g: tuple[float, ...], a: int, b: int) -> float:
    """``grad l_a . grad l_b`` of :func:`_tet_gradients`' tuple, summed as ``np.einsum`` sums
    three products (the first and third first)."""
    return (g[3 * a] * g[3 * b] + g[3 * a + 2] * g[3 * b + 2]) + g[3 * a + 1] * g[3 * b + 1]


@kernel
def _gradients(X: NDArray[np.float64], tets: NDArray[np.int64], volumes: NDArray[np.float64],
               degenerate: NDArray[np.bool_]) -> NDArray[np.float64]:
    """:func:`gradients_numpy`, bit for bit, without its temporaries."""
    G = np.empty((len(tets), 4, 3))
    for t in range(len(tets)):
        g = _tet_gradients(X, tets, t, volumes[t], degenerate[t])
        for a in range(4):
            for k in range(3):
                G[t, a, k] = g[3 * a + k]
    return G


@kernel
def _local_stiffness(X: NDArray[np.float64], tets: NDArray[np.int64], volumes: NDArray[np.float64],
                     degenerate: NDArray[np.bool_]) -> NDArray[np.float64]:
    """:func:`local_stiffness_numpy` (``(T, 4, 4)`` ``|V| grad l_a . grad l_b``), bit for bit."""
    K = np.empty((len(tets), 4, 4))
    for t in range(len(tets)):
        dead = degenerate[t]
        g = _tet_gradients(X, tets, t, volumes[t], dead)
        v = 0.0 if dead else abs(volumes[t])
        for a in range(4):
            for b in range(4):
                K[t, a, b] = v * _dot3(g, a, b)
    return K


@kernel
def _stiffness_sums(X: NDArray[np.float64], tets: NDArray[np.int64], volumes: NDArray[np.float64],
                    degenerate: NDArray[np.bool_], tet_edges: NDArray[np.int64], kappa: NDArray[np.float64],
                    n_edges: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(off, diag)`` of :meth:`TetGeometry.stiffness_sums`: per tetrahedron in order, its
    ``kappa_t`` (the corners' mean: ``0.25 k`` summed, the bits of ``mean(axis=1)``) times its
    :func:`_local_stiffness` entries (the bits of :func:`local_stiffness_numpy`), added onto
    its six edges (:data:`~glsldiff.grids.tetrahedral.pillow.TET_EDGES` order) and four nodes:
    the sums of a ``bincount`` or a sparse scatter in tetrahedron order, bit for bit."""
    n, C = kappa.shape
    off = np.zeros((n_edges, C))
    diag = np.zeros((n, C))
    for t in range(len(tets)):
        dead = degenerate[t]
        g = _tet_gradients(X, tets, t, volumes[t], dead)
        v = 0.0 if dead else abs(volumes[t])
        ko = (v * _dot3(g, 0, 1), v * _dot3(g, 0, 2), v * _dot3(g, 0, 3), v * _dot3(g, 1, 2), v * _dot3(g, 1, 3),
              v * _dot3(g, 2, 3))
        kd = (v * _dot3(g, 0, 0), v * _dot3(g, 1, 1), v * _dot3(g, 2, 2), v * _dot3(g, 3, 3))
        for c in range(C):
            kt = 0.0
            for a in range(4):
                kt += 0.25 * kappa[tets[t, a], c]
            for e in range(6):
                off[tet_edges[t, e], c] += ko[e] * kt
            for a in range(4):
                diag[tets[t, a], c] += kd[a] * kt
    return off, diag


def assemble_p1(geo: TetGeometry, kappa: ArrayLike, mu: ArrayLike, q: ArrayLike, C: float,
                boundary_mass: str = "consistent") -> tuple[sp.csr_matrix, NDArray[np.float64]]:
    """``(A, b)`` of one channel (module docstring): ``kappa``, ``mu`` per node (or scalars),
    ``q`` per node (only surface nodes' values matter); ``boundary_mass`` ``"consistent"`` or
    ``"lumped"``."""
    n = len(geo.positions)
    mu_n = np.broadcast_to(np.asarray(mu, dtype=np.float64), (n,))
    q_n = np.broadcast_to(np.asarray(q, dtype=np.float64), (n,))
    if boundary_mass == "lumped":
        A = geo.stiffness(kappa) + sp.diags(mu_n * geo.node_volumes + geo.node_areas / (2.0 * C))
    else:
        A = geo.stiffness(kappa) + sp.diags(mu_n * geo.node_volumes) + geo.surface_mass / (2.0 * C)
    return A.tocsr(), geo.node_areas * q_n / (2.0 * C)


def _block_diagonal(blocks: list[sp.csr_matrix]) -> sp.csr_matrix:
    """``diag(blocks)`` of square CSR blocks, by offsetting their arrays (scipy's block_diag
    goes through COO: 1.5 s on a 120k-node system)."""
    sizes = [b.shape[0] for b in blocks]
    offsets = np.cumsum([0] + sizes[:-1])
    nnz = np.cumsum([0] + [b.nnz for b in blocks[:-1]])
    data = np.concatenate([b.data for b in blocks])
    indices = np.concatenate([b.indices.astype(np.int64) + o for b, o in zip(blocks, offsets)])
    indptr = np.concatenate([b.indptr[:-1].astype(np.int64) + z for b, z in zip(blocks, nnz)] + [[sum(b.nnz for b in blocks)]])
    n = int(sum(sizes))
    return sp.csr_matrix((data, indices, indptr), shape=(n, n))


def tet_geometry(grid: object) -> TetGeometry:
    """The :class:`TetGeometry` of a tetrahedral grid (see :mod:`glsldiff.system.tet_problem`)."""
    inert = getattr(grid, "inert", None)
    return TetGeometry(np.asarray(grid.positions, dtype=np.float64), np.asarray(grid.tets),  # type: ignore[attr-defined]
                       np.asarray(grid.surface), None if inert is None else np.asarray(inert, dtype=bool))  # type: ignore[attr-defined]


def cached_tet_geometry(grid: object) -> TetGeometry:
    """:func:`tet_geometry` of ``grid`` with its :data:`CACHED_FACTORS` read from the on-disk
    cache (:mod:`glsldiff.core.cache`; computed and written on a miss), keyed by the grid's
    positions, tetrahedra, surface and inert tetrahedra: the same arrays as computing them."""
    geo = tet_geometry(grid)
    if cache.cache_dir() is None:
        return geo                       # cache off: the factors stay lazy
    key = cache.digest(f"tetgeo v{GEOMETRY_CACHE_VERSION}", geo.positions, geo.tets, geo.surface,
                       "no inert" if geo.inert is None else geo.inert)
    factors = cache.memo("tetgeo", key, dict, lambda: {name: getattr(geo, name) for name in CACHED_FACTORS})
    if set(factors) == set(CACHED_FACTORS):
        geo.__dict__.update(factors)     # what the cached_property values would be
    return geo


def tet_rhs(problem: TetProblem, geo: TetGeometry | None = None) -> NDArray[np.float64]:
    """``(n_active, 3)`` right-hand side ``a q / (2C)`` over the active nodes (a new source
    needs only this, not a new matrix)."""
    geo = tet_geometry(problem.grid) if geo is None else geo
    active = np.flatnonzero(problem.grid.active)
    return (geo.node_areas[:, None] * problem.node_source() / (2.0 * problem.C))[active]


def assemble_tet(problem: TetProblem, geo: TetGeometry | None = None) -> LinearSystem:
    """The :class:`~glsldiff.oracle.assembly.LinearSystem` (three channels, channel-major, over
    the grid's active nodes) of a :class:`~glsldiff.system.tet_problem.TetProblem`; pass the
    grid's ``geo`` (:func:`tet_geometry`) to reuse its geometric factors across materials."""
    g = problem.grid
    geo = tet_geometry(g) if geo is None else geo
    active = np.flatnonzero(g.active)
    if geo.degenerate.any():
        logger.info("%d tetrahedra of zero volume carry no stiffness or mass", int(geo.degenerate.sum()))
    q = problem.node_source()
    blocks, rhs = [], []
    for c in range(3):
        A, b = assemble_p1(geo, problem.kappa[:, c], problem.mu[:, c], q[:, c], problem.C, problem.boundary_mass)
        blocks.append(A[active][:, active])
        rhs.append(b[active])
    A = _block_diagonal(blocks)
    diag = A.diagonal()
    if not np.all(diag > 0):
        raise InputError(f"{int((diag <= 0).sum() // 3)} nodes belong only to tetrahedra of zero volume; the "
                         "grid's mapping collapsed there (try another cube count or n)")
    return LinearSystem(A, np.concatenate(rhs), diag, active)


def solve_matrix_reference(A: sp.spmatrix, b: NDArray[np.float64], max_direct: int = DIRECT_MAX_NODES,
                    maxiter: int = 200) -> tuple[NDArray[np.float64], str]:
    """``(x, method)`` of one symmetric positive definite system: SuperLU up to ``max_direct``
    unknowns, above it pyamg (smoothed aggregation + CG) to a relative residual of
    :data:`~glsldiff.system.report.REFERENCE_TOL` within ``maxiter`` cycles. ``b`` ``(n,)`` or
    ``(n, k)``: k right-hand sides share one factorisation / hierarchy."""
    b = np.asarray(b, dtype=np.float64)
    if A.shape[0] <= max_direct:
        return interruptible(spla.splu, sp.csc_matrix(A)).solve(b), "direct (SuperLU)"
    with pinned_global_rng():
        ml = pyamg.smoothed_aggregation_solver(sp.csr_matrix(A), symmetry="symmetric")
    cols = b.reshape(len(b), -1)
    x = np.stack([ml.solve(cols[:, k], tol=REFERENCE_TOL, maxiter=maxiter, accel="cg") for k in range(cols.shape[1])],
                 axis=1)
    return x.reshape(b.shape), f"pyamg to {REFERENCE_TOL:g}"


def solve_system_direct(s: LinearSystem) -> NDArray[np.float64]:
    """``x`` ``(3n,)`` (channel-major) of an assembled P1 system: :func:`solve_matrix_reference` per
    channel."""
    x = np.zeros(3 * s.n)
    for c in range(3):
        x[c * s.n:(c + 1) * s.n] = solve_matrix_reference(*s.block(c))[0]
    return x


def positive_couplings(A: sp.spmatrix) -> int:
    """How many node pairs couple with a positive off-diagonal entry of one channel's ``A``
    (each breaks the discrete maximum principle: P1 on tetrahedra with obtuse dihedral angles,
    or the consistent surface mass; where such entries dominate, the solution can dip below 0)."""
    C = sp.coo_matrix(A)
    return int(((C.row < C.col) & (C.data > 0)).sum())


def solve_tet_direct(problem: TetProblem) -> tuple[NDArray[np.float64], SolveReport]:
    """Exact discrete solution (SuperLU per channel; pyamg to a 1e-12 residual above
    :data:`~glsldiff.oracle.solvers.DIRECT_MAX_NODES` nodes): fluence ``(n, 3)`` and report."""
    t0 = time.perf_counter()
    s = assemble_tet(problem)
    x = solve_system_direct(s)
    phi = np.zeros((problem.n_nodes, 3))
    phi[s.active] = x.reshape(3, s.n).T
    rep = SolveReport(method="scipy-direct" if s.n <= DIRECT_MAX_NODES else "pyamg-sa-cg", nodes=s.n, sweeps=0,
                      residual=s.residual(x), seconds=time.perf_counter() - t0, converged=True,
                      radiance=problem.exitant_radiance(phi))
    return phi, rep
