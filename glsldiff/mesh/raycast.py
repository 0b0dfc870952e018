"""Nearest ray-triangle hits over a mesh's faces (numba kernels, mm).

:func:`first_hits` builds, once per mesh, a bounding volume hierarchy of the faces for rays: a
binary tree split by the binned surface area heuristic down to leaves of at most :data:`LEAF`
faces (:func:`_build`; a tighter tree for rays than the Morton-ordered
:class:`~glsldiff.mesh.accel.BVH` of the closest-point queries). Each ray then walks the tree
with a stack (:func:`_first_hits`, rays in parallel): nearer child first, skipping the boxes it
enters outside ``[t_min, t_best]``, and tests the faces of the leaves it reaches with the
Moller-Trumbore algorithm (both sides of a face count).
"""
from __future__ import annotations

import weakref

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core import checks
from glsldiff.core.jit import kernel, prange
from glsldiff.mesh.types import Mesh

__all__ = ["first_hits"]

#: Most faces in a leaf of the ray tree.
LEAF = 4
#: Bins per axis of the surface area heuristic.
BINS = 16
#: Rays per parallel work item (each sets up one traversal stack).
CHUNK = 64


class _Tree:
    """A mesh's ray tree. Node ``k`` has box ``boxes[k] = (min, max)`` (6,), mm; ``nodes[k] =
    (first, count)``: children ``first``, ``first + 1`` when ``count == 0``, else a leaf of the
    faces ``faces[first:first + count]``, whose corner ``a`` and edges ``b - a``, ``c - a`` are
    ``corners[first:first + count]`` (9,). ``depth``: levels below the root."""

    def __init__(self, triangles: NDArray[np.float64]) -> None:
        t = np.ascontiguousarray(triangles, dtype=np.float64)
        order, self.boxes, self.nodes, self.depth = _build(
            np.ascontiguousarray(t.min(axis=1)), np.ascontiguousarray(t.max(axis=1)),
            np.ascontiguousarray(t.mean(axis=1)), LEAF, BINS)
        tri = t[order]
        self.corners = np.ascontiguousarray(np.hstack([tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]]))
        self.faces = order


_TREES: weakref.WeakKeyDictionary[Mesh, _Tree] = weakref.WeakKeyDictionary()


def _tree(mesh: Mesh) -> _Tree:
    """``mesh``'s ray tree, built on first use."""
    tree = _TREES.get(mesh)
    if tree is None:
        tree = _TREES[mesh] = _Tree(mesh.triangles)
    return tree


@kernel
def _half_area(b: NDArray) -> float:
    """Half the surface area of box ``b = (min, max)``."""
    x, y, z = b[3] - b[0], b[4] - b[1], b[5] - b[2]
    return x * y + y * z + z * x


@kernel
def _build(lo: NDArray, hi: NDArray, cen: NDArray, leaf: int, bins: int
           ) -> tuple[NDArray, NDArray, NDArray, int]:
    """``(order, boxes, nodes, depth)`` of the tree (:class:`_Tree`) over the faces with boxes
    ``lo``, ``hi`` and centroids ``cen`` (F, 3): each node is split where the binned centroids
    minimise the surface area heuristic (an even split when they all coincide)."""
    n = len(cen)
    order = np.arange(n)
    boxes = np.empty((2 * n - 1, 6))
    nodes = np.zeros((2 * n - 1, 2), dtype=np.int64)
    todo = np.empty((n, 4), dtype=np.int64)  # (node, first, end, level); disjoint ranges: n at most
    todo[0] = (0, 0, n, 0)
    n_todo, n_nodes, depth = 1, 1, 0
    box = np.empty(6)
    cbox = np.empty(6)
    bin_n = np.empty(bins, dtype=np.int64)
    bin_box = np.empty((bins, 6))
    right_n = np.empty(bins, dtype=np.int64)
    right_area = np.empty(bins)
    acc = np.empty(6)
    while n_todo > 0:
        n_todo -= 1
        k, a, b, level = todo[n_todo, 0], todo[n_todo, 1], todo[n_todo, 2], todo[n_todo, 3]
        depth = max(depth, level)
        box[:3], box[3:], cbox[:3], cbox[3:] = np.inf, -np.inf, np.inf, -np.inf
        for j in range(a, b):
            f = order[j]
            for c in range(3):
                box[c] = min(box[c], lo[f, c])
                box[3 + c] = max(box[3 + c], hi[f, c])
                cbox[c] = min(cbox[c], cen[f, c])
                cbox[3 + c] = max(cbox[3 + c], cen[f, c])
        boxes[k] = box
        if b - a <= leaf:
            nodes[k, 0], nodes[k, 1] = a, b - a
            continue
        best, best_axis, best_split = np.inf, -1, 0
        for axis in range(3):
            ext = cbox[3 + axis] - cbox[axis]
            if not ext > 0.0:
                continue
            scale = bins / ext
            bin_n[:] = 0
            bin_box[:, :3], bin_box[:, 3:] = np.inf, -np.inf
            for j in range(a, b):
                f = order[j]
                q = min(bins - 1, int((cen[f, axis] - cbox[axis]) * scale))
                bin_n[q] += 1
                for c in range(3):
                    bin_box[q, c] = min(bin_box[q, c], lo[f, c])
                    bin_box[q, 3 + c] = max(bin_box[q, 3 + c], hi[f, c])
            acc[:3], acc[3:] = np.inf, -np.inf
            count = 0
            for q in range(bins - 1, 0, -1):  # bins q.. on the right
                for c in range(3):
                    acc[c] = min(acc[c], bin_box[q, c])
                    acc[3 + c] = max(acc[3 + c], bin_box[q, 3 + c])
                count += bin_n[q]
                right_n[q] = count
                right_area[q] = _half_area(acc) if count else 0.0
            acc[:3], acc[3:] = np.inf, -np.inf
            count = 0
            for q in range(1, bins):  # bins ..q - 1 on the left
                for c in range(3):
                    acc[c] = min(acc[c], bin_box[q - 1, c])
                    acc[3 + c] = max(acc[3 + c], bin_box[q - 1, 3 + c])
                count += bin_n[q - 1]
                if count == 0 or right_n[q] == 0:
                    continue
                cost = _half_area(acc) * count + right_area[q] * right_n[q]
                if cost < best:
                    best, best_axis, best_split = cost, axis, q
        mid = (a + b) // 2
        if best_axis >= 0:
            scale = bins / (cbox[3 + best_axis] - cbox[best_axis])
            i, j = a, b - 1
            while i <= j:
                if min(bins - 1, int((cen[order[i], best_axis] - cbox[best_axis]) * scale)) < best_split:
                    i += 1
                else:
                    order[i], order[j] = order[j], order[i]
                    j -= 1
            mid = i
        nodes[k, 0], nodes[k, 1] = n_nodes, 0
        todo[n_todo] = (n_nodes + 1, mid, b, level + 1)
        todo[n_todo + 1] = (n_nodes, a, mid, level + 1)
        n_todo += 2
        n_nodes += 2
    return order, boxes[:n_nodes].copy(), nodes[:n_nodes].copy(), depth


@kernel
def _inverse(d: float) -> float:
    """``1 / d``; ``inf`` for ``d = -0`` too, so that a ray in a slab plane is in the slab
    whatever the sign of its zero (:func:`_enter`)."""
    return 1.0 / d if d != 0.0 else np.inf


@kernel
def _enter(boxes: NDArray, k: int, ox: float, oy: float, oz: float, ix: float, iy: float, iz: float,
           t_min: float, lim: float) -> float:
    """Where the ray ``o + t d`` (``i = 1 / d``) enters box ``k`` if it is in it somewhere in
    ``[t_min, lim]``, else NaN. Slab test; a NaN on an axis (0 * inf: the ray runs in a slab
    plane) counts as ``-inf`` at the lower plane, ``inf`` at the upper."""
    enter, leave = -np.inf, np.inf
    for a in range(3):
        o = ox if a == 0 else (oy if a == 1 else oz)
        i = ix if a == 0 else (iy if a == 1 else iz)
        t0 = (boxes[k, a] - o) * i
        t1 = (boxes[k, 3 + a] - o) * i
        t0 = t0 if t0 == t0 else -np.inf
        t1 = t1 if t1 == t1 else np.inf
        enter = max(enter, min(t0, t1))
        leave = min(leave, max(t0, t1))
    return enter if leave >= max(enter, t_min) and enter <= lim else np.nan


@kernel(parallel=True)
def _first_hits(o: NDArray, d: NDArray, boxes: NDArray, nodes: NDArray, corners: NDArray,
                faces: NDArray, depth: int, t_min: float, t_max: float, best: NDArray,
                best_f: NDArray) -> None:
    """Fills ``best``, ``best_f`` (inf, -1 where no hit) for the rays ``o``, ``d`` (N, 3)."""
    n = len(o)
    for ch in prange((n + CHUNK - 1) // CHUNK):
        stack = np.empty(depth + 1, dtype=np.int64)  # the farther children of the path, to visit
        stack_t = np.empty(depth + 1)  # where the ray enters them
        for i in range(ch * CHUNK, min(n, (ch + 1) * CHUNK)):
            ox, oy, oz = o[i, 0], o[i, 1], o[i, 2]
            dx, dy, dz = d[i, 0], d[i, 1], d[i, 2]
            ix, iy, iz = _inverse(dx), _inverse(dy), _inverse(dz)
            t_best, f_best = np.inf, -1
            sp = 0
            e = _enter(boxes, 0, ox, oy, oz, ix, iy, iz, t_min, t_max)
            if e == e:
                stack[0], stack_t[0] = 0, e
                sp = 1
            while sp > 0:
                sp -= 1
                node = stack[sp]
                lim = min(t_best, t_max)
                if stack_t[sp] > lim:
                    continue
                while nodes[node, 1] == 0:  # down to a leaf, nearer child first
                    c0 = nodes[node, 0]
                    c1 = c0 + 1
                    e0 = _enter(boxes, c0, ox, oy, oz, ix, iy, iz, t_min, lim)
                    e1 = _enter(boxes, c1, ox, oy, oz, ix, iy, iz, t_min, lim)
                    if e0 == e0 and e1 == e1:
                        if e1 < e0:
                            c0, c1, e0, e1 = c1, c0, e1, e0
                        stack[sp], stack_t[sp] = c1, e1
                        sp += 1
                        node = c0
                    elif e0 == e0:
                        node = c0
                    elif e1 == e1:
                        node = c1
                    else:
                        node = -1
                        break
                if node < 0:
                    continue
                for s in range(nodes[node, 0], nodes[node, 0] + nodes[node, 1]):
                    # Moller-Trumbore; corners[s] = (a, e1 = b - a, e2 = c - a)
                    ax, ay, az = corners[s, 0], corners[s, 1], corners[s, 2]
                    e1x, e1y, e1z = corners[s, 3], corners[s, 4], corners[s, 5]
                    e2x, e2y, e2z = corners[s, 6], corners[s, 7], corners[s, 8]
                    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x  # d x e2
                    det = e1x * px + e1y * py + e1z * pz
                    if not abs(det) > 1e-300:
                        continue
                    inv_det = 1.0 / det
                    sx, sy, sz = ox - ax, oy - ay, oz - az
                    u = (sx * px + sy * py + sz * pz) * inv_det
                    if not u >= 0.0:
                        continue
                    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x  # s x e1
                    v = (dx * qx + dy * qy + dz * qz) * inv_det
                    if not (v >= 0.0 and u + v <= 1.0):
                        continue
                    t = (e2x * qx + e2y * qy + e2z * qz) * inv_det
                    if t > t_min and t <= t_max and t < t_best:
                        t_best, f_best = t, faces[s]
            best[i] = t_best
            best_f[i] = f_best


def first_hits(mesh: Mesh, origins: ArrayLike, directions: ArrayLike, t_min: float = 1e-6,
               t_max: float = np.inf) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The first face each ray ``origins + t directions`` (N, 3), ``t_min < t <= t_max``,
    hits: ``(t (N,), face (N,))``, ``inf`` and -1 where it hits none. Directions need not be
    unit (``t`` is then in their units). A finite ``t_max`` bounds the work: only boxes the
    ray enters before it are visited."""
    o = checks.points(origins, "origins")
    d = checks.finite_array(directions, "directions", (3,))
    if len(d) != len(o):
        raise ValueError(f"{len(o)} origins but {len(d)} directions")
    n = len(o)
    best = np.empty(n)
    best_f = np.empty(n, dtype=np.int64)
    if n:
        tree = _tree(mesh)
        # writable C-ordered inputs: one compiled signature
        _first_hits(np.require(o, requirements="CW"), np.require(d, requirements="CW"), tree.boxes,
                    tree.nodes, tree.corners, tree.faces, tree.depth, float(t_min), float(t_max),
                    best, best_f)
    return best, best_f
