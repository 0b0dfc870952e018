"""Exact closest points on a closed mesh's surface (coordinates in mm).

:func:`closest_points` finds, for each query point, the nearest face by a vectorised
branch-and-bound descent of the mesh's :class:`~glsldiff.mesh.accel.BVH` (leaves of 4
triangles in Morton order), seeded with the distance to the faces around the nearest
vertex, then the exact point on that face (Ericson, *Real-Time Collision Detection*,
5.1.5: :func:`closest_on_triangles`).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.jit import kernel
from glsldiff.mesh.accel import PAIR_CHUNK
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
    d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2
    d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    d3 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2
    d4 = ac0 * bp0 + ac1 * bp1 + ac2 * bp2
    d5 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2
    d6 = ac0 * cp0 + ac1 * cp1 + ac2 * cp2
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


def _exact(mesh: Mesh, pi: NDArray[np.int64], fi: NDArray[np.int64], p: NDArray[np.float64]
           ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Squared distances and barycentrics of points ``p[pi]`` to their faces ``fi``."""
    t = mesh.triangles[fi]
    bary = closest_on_triangles(p[pi], t[:, 0], t[:, 1], t[:, 2])
    cp = np.einsum("ij,ijk->ik", bary, t)
    d2 = ((p[pi] - cp) ** 2).sum(axis=1)
    return d2, bary


def _update(best: NDArray[np.float64], best_f: NDArray[np.int64], pi: NDArray[np.int64],
            fi: NDArray[np.int64], d2: NDArray[np.float64]) -> None:
    """Lower ``best``/``best_f`` by the pairs (pi, fi, d2); ``pi`` must be non-decreasing."""
    if len(pi) == 0:
        return
    start = np.flatnonzero(np.r_[True, pi[1:] != pi[:-1]])
    gmin = np.minimum.reduceat(d2, start)
    group = np.repeat(np.arange(len(start)), np.diff(np.r_[start, len(pi)]))
    hit = np.flatnonzero(d2 == gmin[group])
    first = hit[np.r_[True, group[hit][1:] != group[hit][:-1]]]  # first minimum per point
    pts = pi[first]
    better = d2[first] < best[pts]
    best[pts[better]] = d2[first][better]
    best_f[pts[better]] = fi[first][better]


def _closest_faces(mesh: Mesh, p: NDArray[np.float64], exact: bool = True) -> NDArray[np.int64]:
    """Index of the face nearest to each point (branch and bound over the BVH; with
    ``exact=False`` the nearest of the faces around the nearest vertex, the bound's start)."""
    bvh = mesh.bvh
    n = len(p)
    # upper bound: the faces around the nearest vertex
    _, vi = bvh.tree.query(p)
    s, e = bvh.vf_start[vi], bvh.vf_start[vi + 1]
    cnt = e - s
    pi = np.repeat(np.arange(n), cnt)
    k = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    fi = bvh.vf_order[np.repeat(s, cnt) + k]
    best = np.full(n, np.inf)
    best_f = np.zeros(n, dtype=np.int64)
    d2, _ = _exact(mesh, pi, fi, p)
    _update(best, best_f, pi, fi, d2)
    if not exact:
        return best_f
    bound = best * (1 + 1e-9) + 1e-300
    # descend the tree, keeping nodes whose box is within the bound
    pts = np.arange(n)
    nodes = np.zeros(n, dtype=np.int64)
    for level in range(bvh.depth + 1):
        bmin, bmax = bvh.boxes[level]
        pp = p[pts]
        gap = np.maximum(np.maximum(bmin[nodes] - pp, pp - bmax[nodes]), 0.0)
        keep = (gap ** 2).sum(axis=1) <= bound[pts]
        pts, nodes = pts[keep], nodes[keep]
        if level < bvh.depth:
            pts = np.repeat(pts, 2)
            nodes = (np.repeat(nodes, 2) * 2 + np.tile([0, 1], len(nodes)))
    # exact distances to the faces of the surviving leaves, in chunks
    step = max(1, PAIR_CHUNK // bvh.LEAF)
    for i in range(0, len(pts), step):
        lp, ln = pts[i:i + step], nodes[i:i + step]
        fi = bvh.leaf_faces[ln].ravel()
        pi = np.repeat(lp, bvh.LEAF)
        ok = fi >= 0
        pi, fi = pi[ok], fi[ok]
        d2, _ = _exact(mesh, pi, fi, p)
        _update(best, best_f, pi, fi, d2)
    return best_f


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
    faces = np.empty(len(p), dtype=np.int64)
    step = 8192  # bounds the tree frontier
    for i in range(0, len(p), step):
        faces[i:i + step] = _closest_faces(mesh, p[i:i + step], exact)
    t = mesh.triangles[faces]
    bary = closest_on_triangles(p, t[:, 0], t[:, 1], t[:, 2])
    cp = np.einsum("ij,ijk->ik", bary, t)
    dist = np.linalg.norm(p - cp, axis=1)
    vn = mesh.corner_normals[faces]
    normal = normalize(np.einsum("ij,ijk->ik", bary, vn))
    return cp, dist, faces, normal
