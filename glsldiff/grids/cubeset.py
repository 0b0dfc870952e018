"""Topology of cube sets (polycubes): 2x2x2 configurations, manifold test, connected
components, cavities and genus.

A cube set is an ``(N, 3)`` array of integer cube coordinates ``(ix, iy, iz)``. Its surface
is two-manifold where no 2x2x2 block holds a configuration in which two cubes (or two empty
cells) share only an edge or a vertex (:data:`MANIFOLD`); :func:`surface_topology` gives the
component count, cavities and genus that :mod:`glsldiff.grids.polycube` compares with the mesh's.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from glsldiff.core.errors import InputError

# ---------------------------------------------------------------------------------------
# Local configurations of 2x2x2 cells around a lattice vertex
# ---------------------------------------------------------------------------------------
OFFSETS = np.array([(b & 1, (b >> 1) & 1, (b >> 2) & 1) for b in range(8)], dtype=np.int64)


def connected(bits: list[int]) -> bool:
    """Whether cells (bit indices of a 2x2x2 block) are 6-connected inside the block."""
    if len(bits) <= 1:
        return True
    seen, todo = {bits[0]}, [bits[0]]
    while todo:
        b = todo.pop()
        for axis in range(3):
            n = b ^ (1 << axis)
            if n in bits and n not in seen:
                seen.add(n)
                todo.append(n)
    return len(seen) == len(bits)


def manifold_table() -> NDArray[np.bool_]:
    """For each of the 256 block configurations: is the cube surface a disk at the vertex?

    It is iff the occupied cells and the empty cells of the block are each 6-connected
    (no two cubes, and no two holes, meeting only at an edge or at the vertex).
    """
    table = np.zeros(256, dtype=bool)
    for code in range(256):
        full = [b for b in range(8) if code >> b & 1]
        empty = [b for b in range(8) if not code >> b & 1]
        table[code] = connected(full) and connected(empty)
    return table


MANIFOLD = manifold_table()


def block_codes(occ: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Configuration code of the 2x2x2 block around every lattice vertex of ``occ``.

    ``occ`` must have an empty border; the result has shape ``occ.shape - 1``: vertex
    ``(i, j, k)`` is the corner shared by cells ``(i..i+1, j..j+1, k..k+1)``.
    """
    nx, ny, nz = occ.shape
    code = np.zeros((nx - 1, ny - 1, nz - 1), dtype=np.int64)
    for b, (dx, dy, dz) in enumerate(OFFSETS):
        code |= occ[dx:nx - 1 + dx, dy:ny - 1 + dy, dz:nz - 1 + dz].astype(np.int64) << b
    return code


_S6 = ndimage.generate_binary_structure(3, 1)
_FACES = _S6.copy()
_FACES[1, 1, 1] = False
_N18 = ndimage.generate_binary_structure(3, 2)
_N18[1, 1, 1] = False


def addable(occ: NDArray[np.bool_], cell: ArrayLike) -> bool:
    """Whether filling the empty ``cell`` of ``occ`` (at least one cell from the border) keeps
    the cube set's topology and a two-manifold surface: the cell is simple (Bertrand's
    topological numbers: one 6-component of cubes in its 18-neighbourhood touching its faces,
    one 26-component of empty cells in its 26-neighbourhood) and the eight 2x2x2 blocks
    around it stay :data:`MANIFOLD`."""
    x, y, z = (int(v) for v in cell)
    nb = occ[x - 1:x + 2, y - 1:y + 2, z - 1:z + 2].copy()
    if nb.shape != (3, 3, 3) or nb[1, 1, 1]:
        return False
    full = nb & _N18
    labels, _ = ndimage.label(full, _S6)
    if len(np.unique(labels[_FACES & full])) != 1:
        return False
    empty = ~nb
    empty[1, 1, 1] = False
    if ndimage.label(empty, np.ones((3, 3, 3), dtype=bool))[1] != 1:
        return False
    nb[1, 1, 1] = True
    return bool(MANIFOLD[block_codes(nb)].all())


# ---------------------------------------------------------------------------------------
# Topology
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Topology:
    """Topology of a cube set and of its boundary quad surface.

    Attributes
    ----------
    components
        6-connected components of the cubes.
    cavities
        Enclosed (6-connected) empty regions.
    euler
        ``V - E + F`` of the boundary quad surface.
    surfaces
        Connected components of the boundary surface (quads joined through edges).
    genus
        ``(2 * surfaces - euler) / 2`` (sum over the surfaces; meaningful for a manifold
        surface).
    nonmanifold_edges
        Lattice edges shared by 4 boundary quads (cubes, or holes, meeting only at an edge).
    nonmanifold_vertices
        Lattice vertices whose surrounding surface is not a disk (includes the ends of
        non-manifold edges and vertex-only contacts).
    """

    components: int
    cavities: int
    euler: int
    surfaces: int
    genus: int
    nonmanifold_edges: int
    nonmanifold_vertices: int

    @property
    def manifold(self) -> bool:
        return self.nonmanifold_edges == 0 and self.nonmanifold_vertices == 0


def cube_coordinates(cubes: ArrayLike, what: str = "cubes", distinct: bool = False) -> NDArray[np.int64]:
    """Validated integer cube coordinates ``(k, 3)`` ``(ix, iy, iz)``, k >= 1, as int64 (integral
    floats are accepted); with ``distinct``, no cube may be listed twice."""
    a = np.asarray(cubes)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{what} must be an integer (k, 3) array of cube coordinates "
                         f"(ix, iy, iz), got shape {a.shape}")
    if a.shape[0] == 0:
        raise InputError(f"{what} is empty; a polycube needs at least one cube")
    if a.dtype == bool or not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{what} must hold integer cube coordinates, got dtype {a.dtype}")
    if not np.issubdtype(a.dtype, np.integer):
        if not np.isfinite(a).all() or (a != np.round(a)).any():
            raise InputError(f"{what} must hold integer cube coordinates (ix, iy, iz); found "
                             "non-integer values")
    a = a.astype(np.int64)
    if distinct:
        uniq, counts = np.unique(a, axis=0, return_counts=True)
        if (counts > 1).any():
            raise InputError(f"{what} has {int((counts - 1).sum())} duplicate entr(y/ies), e.g. "
                             f"{uniq[counts > 1][0].tolist()}; list every cube once")
    return a


def occupancy(cubes: NDArray[np.int64], pad: int = 1
               ) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """Dense occupancy with ``pad`` empty layers; returns (occ, coordinate of cell [0,0,0])."""
    lo = cubes.min(axis=0) - pad
    shape = cubes.max(axis=0) - lo + 1 + pad
    occ = np.zeros(tuple(shape), dtype=bool)
    occ[tuple((cubes - lo).T)] = True
    return occ, lo


SIX = np.array([[[0, 0, 0], [0, 1, 0], [0, 0, 0]],
                 [[0, 1, 0], [1, 1, 1], [0, 1, 0]],
                 [[0, 0, 0], [0, 1, 0], [0, 0, 0]]], dtype=bool)


def topology_of(occ: NDArray[np.bool_]) -> Topology:
    """Topology of a dense occupancy grid with an empty border layer."""
    _, n_comp = ndimage.label(occ, structure=SIX)
    _, n_empty = ndimage.label(~occ, structure=SIX)
    shape = np.array(occ.shape)
    vshape = shape + 1  # lattice vertices
    quads, edges = [], []
    for axis in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        diff = occ[tuple(lo)] != occ[tuple(hi)]
        pos = np.argwhere(diff)
        pos[:, axis] += 1  # the face lies on lattice plane i + 1
        u, w = [a for a in range(3) if a != axis]
        eu, ew = np.eye(3, dtype=np.int64)[u], np.eye(3, dtype=np.int64)[w]
        corners = np.stack([pos, pos + eu, pos + eu + ew, pos + ew], axis=1)  # (n, 4, 3)
        vid = np.ravel_multi_index(tuple(np.moveaxis(corners, -1, 0)), tuple(vshape))
        quads.append(vid)
        # edges: (start vertex, direction): pos-u, pos-w, (pos+eu)-w, (pos+ew)-u
        starts = np.stack([pos, pos, pos + eu, pos + ew], axis=1)
        dirs = np.array([u, w, w, u])
        sid = np.ravel_multi_index(tuple(np.moveaxis(starts, -1, 0)), tuple(vshape))
        edges.append(sid * 3 + dirs)
    qv = np.concatenate(quads)
    qe = np.concatenate(edges)
    n_f = len(qv)
    if n_f == 0:
        return Topology(n_comp, max(n_empty - 1, 0), 0, 0, 0, 0, 0)
    uv = np.unique(qv)
    ue, e_inv, e_cnt = np.unique(qe, return_inverse=True, return_counts=True)
    euler = len(uv) - len(ue) + n_f
    e_inv = e_inv.reshape(n_f, 4)
    g = coo_matrix((np.ones(4 * n_f), (np.repeat(np.arange(n_f), 4), n_f + e_inv.ravel())),
                   shape=(n_f + len(ue),) * 2)
    _, lab = connected_components(g, directed=False)
    surfaces = int(np.unique(lab[:n_f]).size)
    codes = block_codes(np.pad(occ, 1))
    bad_v = int((~MANIFOLD[codes]).sum())
    return Topology(components=int(n_comp), cavities=max(int(n_empty) - 1, 0), euler=int(euler),
                    surfaces=surfaces, genus=int((2 * surfaces - euler) // 2),
                    nonmanifold_edges=int((e_cnt > 2).sum()), nonmanifold_vertices=bad_v)


def surface_topology(cubes: ArrayLike) -> Topology:
    """Topology of the cube set ``cubes`` (k, 3) and of its boundary quad surface.

    The surface is made of the cube faces not shared by two cubes; ``euler`` counts its
    unique vertices, edges and quads, and ``genus = (2 * surfaces - euler) / 2``.
    """
    c = cube_coordinates(cubes)
    return topology_of(occupancy(c)[0])
