"""Exact closest points on a closed mesh's surface (coordinates in mm).

:func:`closest_points` finds, for each query point, the nearest face by a compiled
branch-and-bound descent of the mesh's :class:`~glsldiff.mesh.accel.BVH` (leaves of 4
triangles in Morton order), seeded with the distance to the faces around the nearest
vertex, then the exact point on that face (Ericson, *Real-Time Collision Detection*,
5.1.5: :func:`closest_on_triangles`).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.jit import kernel, prange
from glsldiff.mesh.types import Mesh, normalize, query_points


def closest_on_triangles(p: NDArray[np.float64], a: NDArray[np.float64], b: NDArray[np.float64],
                         c: NDArray[np.float64]) -> NDArray[np.float64]:
    """Barycentric ``(n, 3)`` of the closest point on triangles (a, b, c) to p (Ericson 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    bp, cp = p - b, p - c

    def dot(u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.einsum("ij,ij->i", u, v)

    d1, d2 = dot(ab, ap), dot(ac, ap)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    n = len(p)
    bary = np.empty((n, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        den = va + vb + vc
        v, w = vb / den, vc / den
        bary[:] = np.stack([1 - v - w, v, w], axis=1)  # interior
        bad = ~np.isfinite(bary).all(axis=1)
        bary[bad] = (1.0, 0.0, 0.0)
        # edge regions and corners, lowest priority first (later assignments win)
        m = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        t = (d4 - d3)[m] / ((d4 - d3)[m] + (d5 - d6)[m])
        bary[m] = np.stack([np.zeros_like(t), 1 - t, t], axis=1)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        t = d2[m] / (d2[m] - d6[m])
        bary[m] = np.stack([1 - t, np.zeros_like(t), t], axis=1)
        m = (d6 >= 0) & (d5 <= d6)
        bary[m] = (0.0, 0.0, 1.0)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        t = d1[m] / (d1[m] - d3[m])
        bary[m] = np.stack([1 - t, t, np.zeros_like(t)], axis=1)
        m = (d3 >= 0) & (d4 <= d3)
        bary[m] = (0.0, 1.0, 0.0)
        m = (d1 <= 0) & (d2 <= 0)
        bary[m] = (1.0, 0.0, 0.0)
    bad = ~np.isfinite(bary).all(axis=1)
    bary[bad] = (1.0, 0.0, 0.0)
    return bary


@kernel
def closest_on_triangle(p0: float, p1: float, p2: float, t: tuple[float, ...]
                         ) -> tuple[float, float, float]:
    """Barycentrics of the closest point to p on the triangle ``t`` (corners a, b, c, 3
    coordinates each): :func:`closest_on_triangles` for one point
    (Ericson 5.1.5; a non-finite result, as of a degenerate triangle, becomes (1, 0, 0)); a
    kernel helper, for compiled loops."""
    ab0, ab1, ab2 = t[3] - t[0], t[4] - t[1], t[5] - t[2]
    ac0, ac1, ac2 = t[6] - t[0], t[7] - t[1], t[8] - t[2]
    ap0, ap1, ap2 = p0 - t[0], p1 - t[1], p2 - t[2]
    bp0, bp1, bp2 = p0 - t[3], p1 - t[4], p2 - t[5]
    cp0, cp1, cp2 = p0 - t[6], p1 - t[7], p2 - t[8]
    # summed as np.einsum sums three products (the first and third first): the numpy path's bits
    d1 = (ab0 * ap0 + ab2 * ap2) + ab1 * ap1
    d2 = (ac0 * ap0 + ac2 * ap2) + ac1 * ap1
    d3 = (ab0 * bp0 + ab2 * bp2) + ab1 * bp1
    d4 = (ac0 * bp0 + ac2 * bp2) + ac1 * bp1
    d5 = (ab0 * cp0 + ab2 * cp2) + ab1 * cp1
    d6 = (ac0 * cp0 + ac2 * cp2) + ac1 * cp1
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    # the corner and edge regions in closest_on_triangles' order of precedence, then the
    # interior; a zero denominator gives NaN (numpy: inf or NaN), replaced by (1, 0, 0) as there
    if d1 <= 0 and d2 <= 0:
        return 1.0, 0.0, 0.0
    if d3 >= 0 and d4 <= d3:
        return 0.0, 1.0, 0.0
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        u = d1 / (d1 - d3) if d1 - d3 != 0.0 else np.nan
        return _finite_or_a(1 - u, u, 0.0)
    if d6 >= 0 and d5 <= d6:
        return 0.0, 0.0, 1.0
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        u = d2 / (d2 - d6) if d2 - d6 != 0.0 else np.nan
        return _finite_or_a(1 - u, 0.0, u)
    if va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
        s = (d4 - d3) + (d5 - d6)
        u = (d4 - d3) / s if s != 0.0 else np.nan
        return _finite_or_a(0.0, 1 - u, u)
    den = va + vb + vc
    if den == 0.0:
        return 1.0, 0.0, 0.0
    v, w = vb / den, vc / den
    return _finite_or_a(1 - v - w, v, w)


@kernel
def _finite_or_a(b0: float, b1: float, b2: float) -> tuple[float, float, float]:
    """Barycentrics (b0, b1, b2), or corner a's (1, 0, 0) where one is not finite."""
    if np.isfinite(b0) and np.isfinite(b1) and np.isfinite(b2):
        return b0, b1, b2
    return 1.0, 0.0, 0.0


@kernel
def face_distance(p0: float, p1: float, p2: float, t: tuple[float, ...]
                  ) -> tuple[float, tuple[float, float, float]]:
    """Squared distance (mm^2) from p to its closest point on the triangle ``t`` (as
    :func:`closest_on_triangle`), and that point's barycentrics: the floating-point operations
    of the numpy path (``einsum`` over the corners, then the squares summed in order); a kernel
    helper, for compiled loops."""
    b = closest_on_triangle(p0, p1, p2, t)
    q0 = (b[0] * t[0] + b[1] * t[3]) + b[2] * t[6] - p0
    q1 = (b[0] * t[1] + b[1] * t[4]) + b[2] * t[7] - p1
    q2 = (b[0] * t[2] + b[1] * t[5]) + b[2] * t[8] - p2
    return q0 * q0 + q1 * q1 + q2 * q2, b


@kernel(inline=True)
def _distance_to_face(tri: NDArray[np.float64], f: int, p0: float, p1: float, p2: float) -> float:
    """Squared distance (mm^2) from p to face ``f`` of ``tri`` ``(F, 3, 3)``."""
    return face_distance(p0, p1, p2, (tri[f, 0, 0], tri[f, 0, 1], tri[f, 0, 2], tri[f, 1, 0], tri[f, 1, 1],
                                      tri[f, 1, 2], tri[f, 2, 0], tri[f, 2, 1], tri[f, 2, 2]))[0]


@kernel(inline=True)
def _box_gap2(lo: NDArray[np.float64], hi: NDArray[np.float64], k: int, p0: float, p1: float, p2: float) -> float:
    """Squared distance (mm^2) from p to box ``k`` (0 inside)."""
    g0 = max(max(lo[k, 0] - p0, p0 - hi[k, 0]), 0.0)
    g1 = max(max(lo[k, 1] - p1, p1 - hi[k, 1]), 0.0)
    g2 = max(max(lo[k, 2] - p2, p2 - hi[k, 2]), 0.0)
    return g0 * g0 + g1 * g1 + g2 * g2


@kernel(inline=True)
def _nearest_face(p0: float, p1: float, p2: float, vertex: int, vf_order: NDArray[np.int64],
                  vf_start: NDArray[np.int64], tri: NDArray[np.float64], lo: NDArray[np.float64],
                  hi: NDArray[np.float64], depth: int, leaf_faces: NDArray[np.int64], exact: bool) -> int:
    """The face nearest to p: first the faces around its nearest ``vertex``, then (``exact``) a
    depth-first descent of the BVH (boxes ``lo``/``hi`` of node ``2^level - 1 + k``), left child
    first, pruned by the best distance so far. Of equally near faces the first met wins, as in
    the breadth-first numpy descent it replaces (which visited the leaves in the same order and
    pruned with the first bound only: a box pruned here holds no nearer face)."""
    best, best_f = np.inf, 0
    for j in range(vf_start[vertex], vf_start[vertex + 1]):
        d2 = _distance_to_face(tri, vf_order[j], p0, p1, p2)
        if d2 < best:
            best, best_f = d2, vf_order[j]
    if not exact:
        return best_f
    stack = np.empty(depth + 2, dtype=np.int64)
    stack[0], top = 0, 1
    while top > 0:
        top -= 1
        node = stack[top]
        if _box_gap2(lo, hi, node, p0, p1, p2) > best * (1 + 1e-9) + 1e-300:
            continue
        leaf = node - ((1 << depth) - 1)
        if leaf < 0:    # an inner node: right child under the left one
            stack[top], stack[top + 1] = 2 * node + 2, 2 * node + 1
            top += 2
            continue
        for f in leaf_faces[leaf]:
            if f >= 0:
                d2 = _distance_to_face(tri, f, p0, p1, p2)
                if d2 < best:
                    best, best_f = d2, f
    return best_f


@kernel(parallel=True)
def _nearest_faces(p: NDArray[np.float64], vertex: NDArray[np.int64], vf_order: NDArray[np.int64],
                   vf_start: NDArray[np.int64], tri: NDArray[np.float64], lo: NDArray[np.float64],
                   hi: NDArray[np.float64], depth: int, leaf_faces: NDArray[np.int64], exact: bool,
                   out: NDArray[np.int64]) -> None:
    """``out[i]``: :func:`_nearest_face` of ``p[i]``, over threads (``.serial``: on this one)."""
    for i in prange(p.shape[0]):
        out[i] = _nearest_face(p[i, 0], p[i, 1], p[i, 2], vertex[i], vf_order, vf_start, tri, lo, hi, depth,
                               leaf_faces, exact)


#: Fewer query points than this are searched on one thread.
SERIAL_POINTS = 512


def _closest_faces(mesh: Mesh, p: NDArray[np.float64], exact: bool = True) -> NDArray[np.int64]:
    """Index of the face nearest to each point (branch and bound over the BVH; with
    ``exact=False`` the nearest of the faces around the nearest vertex, the bound's start)."""
    bvh = mesh.bvh
    _, vi = bvh.tree.query(p, workers=-1)
    lo, hi = bvh.heap_boxes
    out = np.empty(len(p), dtype=np.int64)
    search = _nearest_faces.serial if len(p) < SERIAL_POINTS else _nearest_faces
    search(p, vi.astype(np.int64), bvh.vf_order, bvh.vf_start, mesh.triangles, lo, hi, bvh.depth, bvh.leaf_faces,
           exact, out)
    return out


def closest_points(mesh: Mesh, points: ArrayLike, exact: bool = True
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], NDArray[np.float64]]:
    """Exact closest surface points of ``points`` (N, 3) mm; with ``exact=False``, the closest
    points on the faces around each point's nearest vertex (the same on a well-shaped surface
    for points near it, and several times faster for points deep inside).

    Returns
    -------
    closest
        ``(N, 3)`` closest points on the surface, mm.
    distance
        ``(N,)`` unsigned distance, mm.
    triangle
        ``(N,)`` index of the face holding the closest point.
    normal
        ``(N, 3)`` unit outward normal at the closest point: the face's corner normals
        (:attr:`glsldiff.mesh.types.Mesh.corner_normals`, vertex normals that do not smooth
        across sharp edges) interpolated barycentrically, then normalised.
    """
    p = query_points(points)
    faces = _closest_faces(mesh, p, exact)
    t = mesh.triangles[faces]
    bary = closest_on_triangles(p, t[:, 0], t[:, 1], t[:, 2])
    cp = np.einsum("ij,ijk->ik", bary, t)
    dist = np.linalg.norm(p - cp, axis=1)
    vn = mesh.corner_normals[faces]
    normal = normalize(np.einsum("ij,ijk->ik", bary, vn))
    return cp, dist, faces, normal
