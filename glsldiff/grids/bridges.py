"""Topology repair of a cube set that bridges near-contacts into handles.

Where two parts of a mesh come closer than a cube (a camel's tail against its rump, its legs
against each other), the thresholded cubes of :mod:`glsldiff.grids.polycube` fill the gap and
join the parts: the cube set gets a handle the mesh does not have (CGAL's camel: genus 1-2 at
every threshold and at 12,000-20,000 cubes, the mesh genus 0). :func:`repair_bridges` keeps the
cubes that a topology-preserving growth reaches:

1. **Growth** (:func:`grow_simple`): from the fullest cube, add the allowed cubes face-adjacent
   to the set in decreasing inside fraction, each only where it is simple (it keeps the
   components, cavities and genus: Bertrand's topological numbers) and keeps the surface
   two-manifold (:func:`glsldiff.grids.cubeset.addable`); a cube refused is tried again
   whenever one of its 26 neighbours is added. The result is one component without cavity,
   of genus 0: where the two fronts of a handle meet, the cubes that would close it stay out.
2. **Clusters back**: the cubes left out, in 26-connected clusters by decreasing largest
   fraction, are put back where the whole set stays one manifold component without cavity
   and its genus no higher than the mesh's: clusters that only waited on each other (two
   cubes each of which alone would touch the set at an edge) return, and so do the clusters
   that close the mesh's own handles; those that would bridge a near-contact stay out, and
   so do pieces apart from the fullest cube's (a leg cut off below the threshold).

The cube sets that already have the mesh's topology never come here (the polycube search
tries the thresholds first), so their grids do not change.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from glsldiff.core.jit import kernel
from glsldiff.grids.cubeset import MANIFOLD, SIX, Topology, topology_of

__all__ = ["BridgeRepair", "grow_simple", "repair_bridges", "simple_cell"]

#: Most clusters of left-out cubes tried back (largest fraction first; one topology each).
MAX_CLUSTER_TRIALS = 100


@kernel
def simple_cell(occ: NDArray[np.bool_], x: int, y: int, z: int, manifold: NDArray[np.bool_]) -> bool:
    """Whether the empty cell ``(x, y, z)`` of ``occ`` (not on its border) can be filled keeping
    the topology and a two-manifold surface: :func:`glsldiff.grids.cubeset.addable` as a
    compiled loop (one 6-component of cubes in the 18-neighbourhood touching its faces, one
    26-component of empty cells in its 26-neighbourhood, ``manifold`` of the eight blocks)."""
    nb = np.zeros(27, np.bool_)
    for i in range(27):
        nb[i] = occ[x - 1 + i // 9, y - 1 + (i // 3) % 3, z - 1 + i % 3]
    if nb[13]:
        return False
    seen = np.zeros(27, np.bool_)
    stack = np.empty(27, np.int64)
    # cubes: 6-connected within the 18-neighbourhood, starting at a face neighbour
    start = -1
    for f in (4, 10, 12, 14, 16, 22):
        if nb[f]:
            start = f
            break
    if start < 0:
        return False
    seen[start], stack[0], top = True, start, 1
    while top > 0:
        top -= 1
        i = stack[top]
        a, b, c = i // 9, (i // 3) % 3, i % 3
        for d in range(6):
            s = 1 if d % 2 == 0 else -1
            na, nb_, nc = a + s * (d // 2 == 0), b + s * (d // 2 == 1), c + s * (d // 2 == 2)
            if na < 0 or na > 2 or nb_ < 0 or nb_ > 2 or nc < 0 or nc > 2:
                continue
            j = na * 9 + nb_ * 3 + nc
            ones = (na == 1) + (nb_ == 1) + (nc == 1)
            if j != 13 and ones >= 1 and nb[j] and not seen[j]:
                seen[j], stack[top] = True, j
                top += 1
    for f in (4, 10, 12, 14, 16, 22):
        if nb[f] and not seen[f]:
            return False
    # empty cells: one 26-component in the 26-neighbourhood
    start = -1
    for i in range(27):
        seen[i] = False
        if start < 0 and i != 13 and not nb[i]:
            start = i
    if start < 0:
        return False
    seen[start], stack[0], top = True, start, 1
    while top > 0:
        top -= 1
        i = stack[top]
        a, b, c = i // 9, (i // 3) % 3, i % 3
        for j in range(27):
            if j == 13 or nb[j] or seen[j]:
                continue
            if abs(j // 9 - a) <= 1 and abs((j // 3) % 3 - b) <= 1 and abs(j % 3 - c) <= 1:
                seen[j], stack[top] = True, j
                top += 1
    for i in range(27):
        if i != 13 and not nb[i] and not seen[i]:
            return False
    # the eight 2x2x2 blocks around the cell stay two-manifold
    nb[13] = True
    for blk in range(8):
        bx, by, bz = blk & 1, (blk >> 1) & 1, (blk >> 2) & 1
        code = 0
        for bit in range(8):
            if nb[(bx + (bit & 1)) * 9 + (by + ((bit >> 1) & 1)) * 3 + bz + ((bit >> 2) & 1)]:
                code |= 1 << bit
        if not manifold[code]:
            return False
    return True


@kernel
def _grow(allowed: NDArray[np.bool_], frac: NDArray[np.float64], seed: NDArray[np.int64],
          manifold: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Step 1 of the module docstring on ``allowed`` (an empty border layer) from ``seed``."""
    occ = np.zeros(allowed.shape, np.bool_)
    waiting = np.zeros(allowed.shape, np.bool_)
    occ[seed[0], seed[1], seed[2]] = True
    heap = [(0.0, 0, 0, 0)]
    heap.pop()
    x, y, z = seed[0], seed[1], seed[2]
    added = True
    while True:
        if added:   # the cell (x, y, z) just joined: its face neighbours and the cells waiting next to it
            for dx in range(-1, 2):
                for dy in range(-1, 2):
                    for dz in range(-1, 2):
                        u, v, w = x + dx, y + dy, z + dz
                        face = abs(dx) + abs(dy) + abs(dz) == 1
                        if allowed[u, v, w] and not occ[u, v, w] and (face or waiting[u, v, w]):
                            waiting[u, v, w] = False
                            heapq.heappush(heap, (-frac[u, v, w], u, v, w))
        if len(heap) == 0:
            break
        _, x, y, z = heapq.heappop(heap)
        added = False
        if occ[x, y, z]:
            continue
        if simple_cell(occ, x, y, z, manifold):
            occ[x, y, z] = True
            added = True
        else:
            waiting[x, y, z] = True
    return occ


def grow_simple(allowed: NDArray[np.bool_], frac: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Step 1 of the module docstring: the cubes of ``allowed`` (a dense occupancy with an empty
    border layer; ``frac`` the inside fraction of each cell) that a topology-preserving growth
    from the fullest one reaches: one manifold component of genus 0 without cavity."""
    if not allowed.any():
        return np.zeros_like(allowed)
    seed = np.array(np.unravel_index(int(np.argmax(np.where(allowed, frac, -np.inf))), allowed.shape),
                    dtype=np.int64)
    return _grow(np.ascontiguousarray(allowed), np.ascontiguousarray(frac, dtype=np.float64), seed, MANIFOLD)


@dataclass(frozen=True)
class BridgeRepair:
    """What :func:`repair_bridges` did: the kept occupancy, its topology, the cubes left out
    (count, of which in pieces apart from the fullest cube's, and their inside volume in cubes)
    and the topology it started from."""

    occ: NDArray[np.bool_]
    topology: Topology
    removed: int
    detached: int
    removed_volume: float
    before: Topology

    def matches(self, genus: int) -> bool:
        """One two-manifold component, no cavity, genus ``genus``."""
        t = self.topology
        return t.manifold and (t.components, t.cavities, t.genus) == (1, 0, genus)


def _fits(topo: Topology, genus: int) -> bool:
    return topo.manifold and topo.components == 1 and topo.cavities == 0 and topo.genus <= genus


def repair_bridges(occ: NDArray[np.bool_], frac: NDArray[np.float64], genus: int) -> BridgeRepair:
    """The module docstring's repair of the cube set ``occ`` (dense, an empty border layer; ``frac``
    each cell's inside fraction) for a mesh of genus ``genus``."""
    before = topology_of(occ)
    kept = grow_simple(occ, frac)
    left = occ & ~kept
    labels, k = ndimage.label(left, np.ones((3, 3, 3), dtype=bool))
    if k:
        best = ndimage.maximum(frac, labels, np.arange(1, k + 1))
        for lab in (np.argsort(-np.asarray(best), kind="stable")[:MAX_CLUSTER_TRIALS] + 1):
            trial = kept | (labels == lab)
            if _fits(topology_of(trial), genus):
                kept = trial
    out = occ & ~kept
    pieces = ndimage.label(occ, SIX)[0]
    detached = int((out & (pieces != pieces[kept][0])).sum()) if kept.any() else int(out.sum())
    return BridgeRepair(kept, topology_of(kept), int(out.sum()), detached, float(frac[out].sum()), before)
