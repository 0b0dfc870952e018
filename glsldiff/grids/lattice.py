"""The polygrid's node lattice inside a polycube (Wang et al. 2008, section 5.1, figure 4 (b)-(c)).

Every cube of the polycube holds an ``n x n x n`` block of nodes at its cell centres
(spacing ``h = size / n``); blocks of face-adjacent cubes join into one lattice, so a
node's six lattice neighbours may live in another cube. Node arrays have shape
``(cubes, n, n, n)`` indexed ``[cube, z, y, x]``, cubes in the polycube's scan-line order:
flattened, that is exactly the texture packing order of figure 6 (cube by cube, x-y slices
by increasing z).

Classification (figure 4 (c)), iterated to a fixed point:

* a node with all six neighbours present is **interior**;
* a node with exactly one missing neighbour lies under a face of the polycube surface:
  a **boundary** node, linked to its one neighbour opposite the missing direction (the
  inward normal), which must be interior;
* a node with two or more missing neighbours lies on a convex polycube edge or corner
  and is **removed** (it keeps its texel, empty); removed nodes count as missing for
  their neighbours, and a boundary node whose partner is not interior is removed too.

So every boundary node links to exactly one interior node, along one lattice axis, and no
interior node reads a removed node. At a convex edge the interior node in the corner of
the interior region is the partner of two boundary nodes (one per face; three at a
corner): on a 6-connected lattice that cannot be avoided without dropping a neighbour, so
the mapping step places such a node consistently for all its boundary nodes, and
:attr:`Lattice.shared_partners` counts them. On an axis-aligned box the result is the
regular grid of :mod:`glsldiff.grids.regular` (edge and corner nodes inactive).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.checks import real, vector3
from glsldiff.core.errors import InputError
from glsldiff.grids.graph import BOUNDARY, INACTIVE, INTERIOR, NEIGHBOURS
from glsldiff.grids.cubeset import cube_coordinates

# lattice step per neighbour slot, (x, y, z) order, matching NEIGHBOURS
STEPS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.int64)
OPPOSITE = np.array([1, 0, 3, 2, 5, 4])


@dataclass(frozen=True, eq=False)
class Lattice:
    """Nodes, kinds and links of a polycube's lattice.

    Parameters
    ----------
    cubes
        ``(k, 3)`` integer cube coordinates ``(ix, iy, iz)``; used in the given order
        (pass them in scan-line order for the paper's packing).
    n
        Nodes per cube edge (>= 2).
    size
        Cube edge, mm.
    origin
        Corner of cube ``(0, 0, 0)``, mm.
    """

    cubes: NDArray[np.int64]
    n: int
    size: float
    origin: NDArray[np.float64]

    @classmethod
    def build(cls, cubes: ArrayLike, n: int, size: float, origin: ArrayLike = (0.0, 0.0, 0.0)) -> "Lattice":
        cubes = cube_coordinates(cubes, distinct=True)
        if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 2:
            raise InputError(f"n={n!r} nodes per cube edge must be an integer >= 2")
        size = real(size, "cube size (mm)", lo=0.0, lo_open=True)
        origin = vector3(origin, "origin (mm)")
        lat = cls(cubes, int(n), size, origin)
        if lat.n_interior == 0:
            raise InputError(f"the polygrid of {len(cubes)} cube(s) with n={n} has no interior node; "
                             "use more nodes per cube (n >= 3) or more cubes")
        return lat

    # ---- sizes ---------------------------------------------------------------------
    @property
    def h(self) -> float:
        """Lattice spacing, mm."""
        return self.size / self.n

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """Node array shape ``(cubes, n, n, n)`` = ``[cube, z, y, x]``."""
        return (len(self.cubes), self.n, self.n, self.n)

    @property
    def size_nodes(self) -> int:
        return len(self.cubes) * self.n ** 3

    @cached_property
    def coords(self) -> NDArray[np.int64]:
        """``(N, 3)`` global lattice coordinates ``(gx, gy, gz)`` of every node."""
        n = self.n
        z, y, x = np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij")
        local = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
        return (self.cubes[:, None, :] * n + local[None]).reshape(-1, 3)

    @cached_property
    def lattice_positions(self) -> NDArray[np.float64]:
        """``(N, 3)`` node positions in the polycube (cell centres), mm."""
        return self.origin + (self.coords + 0.5) * self.h

    @cached_property
    def _cube_table(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Dense cube-coordinate lookup (cube index or -1) over the cubes' bounding box, and its origin."""
        lo = self.cubes.min(axis=0)
        table = np.full(tuple(self.cubes.max(axis=0) - lo + 1), -1, dtype=np.int64)
        table[tuple((self.cubes - lo).T)] = np.arange(len(self.cubes))
        return table, lo

    def index_of(self, g: NDArray[np.int64]) -> NDArray[np.int64]:
        """Flat node index of global lattice coordinates ``(..., 3)``; -1 outside the polycube."""
        n = self.n
        table, lo = self._cube_table
        dims = np.array(table.shape)
        c = np.floor_divide(g, n) - lo
        inside = np.all((c >= 0) & (c < dims), axis=-1)
        cube = np.full(g.shape[:-1], -1, dtype=np.int64)
        cube[inside] = table[tuple(c[inside].T)]
        loc = np.mod(g, n)
        flat = cube * n ** 3 + loc[..., 2] * n * n + loc[..., 1] * n + loc[..., 0]
        return np.where(cube >= 0, flat, -1)

    @cached_property
    def lattice_neighbours(self) -> NDArray[np.int64]:
        """``(N, 6)`` flat index of each node's lattice neighbour per slot, -1 if absent."""
        return self.index_of(self.coords[:, None, :] + STEPS[None])

    # ---- classification (figure 4 (c)) -----------------------------------------------
    @cached_property
    def _classified(self) -> tuple[NDArray[np.int8], NDArray[np.int64]]:
        nb = self.lattice_neighbours
        absent = nb < 0
        count = absent.sum(axis=1)
        kind = np.where(count == 0, INTERIOR, np.where(count == 1, BOUNDARY, INACTIVE)).astype(np.int8)
        out = np.where(count == 1, np.argmax(absent, axis=1), -1)
        for _ in range(self.size_nodes + 1):  # only demotions: terminates
            changed = False
            # an interior node reading a removed node: boundary if that is its only one, else removed
            gone = np.append(kind == INACTIVE, True)[nb]
            i = np.flatnonzero((kind == INTERIOR) & gone.any(axis=1))
            if i.size:
                single = gone[i].sum(axis=1) == 1
                kind[i] = np.where(single, BOUNDARY, INACTIVE)
                out[i] = np.where(single, np.argmax(gone[i], axis=1), -1)
                changed = True
            # a boundary node whose inward partner is not interior is removed
            b = np.flatnonzero(kind == BOUNDARY)
            partner = nb[b, OPPOSITE[out[b]]]
            bad = b[(partner < 0) | (kind[np.maximum(partner, 0)] != INTERIOR)]
            if bad.size:
                kind[bad] = INACTIVE
                changed = True
            if not changed:
                break
        return kind, np.where(kind == BOUNDARY, out, -1)

    @property
    def kind(self) -> NDArray[np.int8]:
        """``(N,)`` INTERIOR, BOUNDARY or INACTIVE (removed) per node."""
        return self._classified[0]

    @property
    def outward_slot(self) -> NDArray[np.int64]:
        """``(N,)`` neighbour slot of the outward direction at boundary nodes, -1 elsewhere."""
        return self._classified[1]

    @cached_property
    def interior(self) -> NDArray[np.int64]:
        return np.flatnonzero(self.kind == INTERIOR)

    @cached_property
    def boundary(self) -> NDArray[np.int64]:
        return np.flatnonzero(self.kind == BOUNDARY)

    @property
    def n_interior(self) -> int:
        return int(self.interior.size)

    @property
    def n_boundary(self) -> int:
        return int(self.boundary.size)

    @property
    def n_removed(self) -> int:
        return int(self.size_nodes - self.n_interior - self.n_boundary)

    @cached_property
    def neighbours(self) -> NDArray[np.int64]:
        """``(n_interior, 6)`` neighbours of the interior nodes (all interior or boundary)."""
        return self.lattice_neighbours[self.interior]

    @cached_property
    def link(self) -> NDArray[np.int64]:
        """``(n_boundary,)`` interior partner of each boundary node (one step inward)."""
        b = self.boundary
        return self.lattice_neighbours[b, OPPOSITE[self.outward_slot[b]]]

    @cached_property
    def outward(self) -> NDArray[np.float64]:
        """``(n_boundary, 3)`` outward unit axis of each boundary node in the polycube."""
        return STEPS[self.outward_slot[self.boundary]].astype(np.float64)

    @cached_property
    def partner_count(self) -> NDArray[np.int64]:
        """``(N,)`` number of boundary nodes whose partner each node is (2 or 3 at convex edges)."""
        return np.bincount(self.link, minlength=self.size_nodes)

    @property
    def shared_partners(self) -> int:
        """Interior nodes that are the partner of more than one boundary node (convex edges)."""
        return int((self.partner_count > 1).sum())

    @cached_property
    def surface_pairs(self) -> NDArray[np.int64]:
        """``(P, 2)`` flat indices of boundary nodes adjacent on the polycube surface:
        lattice neighbours, and across polycube edges the diagonal pairs with different
        outward directions whose two elbow nodes are not boundary nodes."""
        kind = self.kind
        b = self.boundary
        nb = self.lattice_neighbours[b]
        pairs = []
        for s in (1, 3, 5):  # +x, +y, +z: each axis pair once
            other = nb[:, s]
            ok = (other >= 0) & (kind[np.maximum(other, 0)] == BOUNDARY)
            pairs.append(np.stack([b[ok], other[ok]], axis=1))
        coords = self.coords[b]
        out = self.outward_slot[b]
        for a1 in range(3):
            for a2 in range(a1 + 1, 3):
                for s2 in (-1, 1):
                    step = np.zeros(3, dtype=np.int64)
                    step[a1], step[a2] = 1, s2
                    other = self.index_of(coords + step)
                    e1, e2 = np.zeros(3, np.int64), np.zeros(3, np.int64)
                    e1[a1], e2[a2] = 1, s2
                    el1, el2 = self.index_of(coords + e1), self.index_of(coords + e2)
                    okay = (other >= 0) & (kind[np.maximum(other, 0)] == BOUNDARY)
                    okay &= out != self.outward_slot[np.maximum(other, 0)]
                    for el in (el1, el2):
                        okay &= (el < 0) | (kind[np.maximum(el, 0)] != BOUNDARY)
                    pairs.append(np.stack([b[okay], other[okay]], axis=1))
        return np.concatenate(pairs)

    def counts(self) -> dict[str, int]:
        """Node counts by kind."""
        return {"cubes": len(self.cubes), "n": self.n, "nodes": self.size_nodes,
                "interior": self.n_interior, "boundary": self.n_boundary, "removed": self.n_removed,
                "shared_partners": self.shared_partners}


__all__ = ["Lattice", "STEPS", "OPPOSITE", "NEIGHBOURS"]
