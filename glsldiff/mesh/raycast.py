"""Nearest ray-triangle hits over a mesh's :class:`~glsldiff.mesh.accel.BVH` (numpy, mm).

:func:`first_hits` descends the BVH level by level for all rays at once, keeping the (ray,
node) pairs whose box the ray enters within ``[t_min, t_best]``, then tests the faces of the
surviving leaves with the Moller-Trumbore algorithm (both sides of a face count).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core import checks
from glsldiff.mesh.accel import PAIR_CHUNK
from glsldiff.mesh.types import Mesh

__all__ = ["first_hits"]


def _box_entry(o: NDArray, inv: NDArray, bmin: NDArray, bmax: NDArray) -> tuple[NDArray, NDArray]:
    """Slab test: ray parameters where each ray enters and leaves its box."""
    with np.errstate(invalid="ignore", over="ignore"):
        t0, t1 = (bmin - o) * inv, (bmax - o) * inv
    t0 = np.where(np.isnan(t0), -np.inf, t0)
    t1 = np.where(np.isnan(t1), np.inf, t1)
    return np.minimum(t0, t1).max(axis=1), np.maximum(t0, t1).min(axis=1)


def _test_leaves(mesh: Mesh, o: NDArray, d: NDArray, rays: NDArray, nodes: NDArray, t_min: float,
                 best: NDArray, best_f: NDArray) -> None:
    """Moller-Trumbore against the faces of leaf ``nodes[i]`` for ray ``rays[i]`` (each ray at
    most once); keeps the nearest hit beyond ``t_min`` in ``best``, ``best_f``."""
    bvh, tri = mesh.bvh, mesh.triangles
    step = max(1, PAIR_CHUNK // bvh.LEAF)
    for i in range(0, len(rays), step):
        fi = bvh.leaf_faces[nodes[i:i + step]].ravel()
        ri = np.repeat(rays[i:i + step], bvh.LEAF)
        ok = fi >= 0
        ri, fi = ri[ok], fi[ok]
        a, b, c = tri[fi, 0], tri[fi, 1], tri[fi, 2]
        e1, e2, dd = b - a, c - a, d[ri]
        p = np.cross(dd, e2)
        det = np.einsum("ij,ij->i", e1, p)
        good = np.abs(det) > 1e-300
        inv_det = np.where(good, 1.0 / np.where(good, det, 1.0), 0.0)
        s = o[ri] - a
        u = np.einsum("ij,ij->i", s, p) * inv_det
        qv = np.cross(s, e1)
        v = np.einsum("ij,ij->i", dd, qv) * inv_det
        t = np.einsum("ij,ij->i", e2, qv) * inv_det
        hit = good & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > t_min)
        ri, fi, t = ri[hit], fi[hit], t[hit]
        order = np.lexsort((t, ri))
        ri, fi, t = ri[order], fi[order], t[order]
        first = np.r_[True, ri[1:] != ri[:-1]] if len(ri) else np.zeros(0, dtype=bool)
        ri, fi, t = ri[first], fi[first], t[first]
        better = t < best[ri]
        best[ri[better]], best_f[ri[better]] = t[better], fi[better]


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
    bvh = mesh.bvh
    n = len(o)
    best = np.full(n, float(t_max))
    best_f = np.full(n, -1, dtype=np.int64)
    with np.errstate(divide="ignore"):
        inv = 1.0 / d
    rays = np.arange(n)
    nodes = np.zeros(n, dtype=np.int64)
    for level in range(bvh.depth + 1):
        bmin, bmax = bvh.boxes[level]
        enter, leave = _box_entry(o[rays], inv[rays], bmin[nodes], bmax[nodes])
        keep = (leave >= np.maximum(enter, t_min)) & (enter <= best[rays]) & (bmin[nodes, 0] <= bmax[nodes, 0])
        rays, nodes = rays[keep], nodes[keep]
        if level < bvh.depth:
            rays = np.repeat(rays, 2)
            nodes = np.repeat(nodes, 2) * 2 + np.tile([0, 1], len(nodes))
    if len(rays) == 0:
        best[:] = np.inf
        return best, best_f
    # the leaves each ray enters, nearest first: round r tests every ray's r-th leaf, skipping
    # leaves entered beyond the ray's best hit so far
    enter, _ = _box_entry(o[rays], inv[rays], bvh.boxes[bvh.depth][0][nodes], bvh.boxes[bvh.depth][1][nodes])
    order = np.lexsort((enter, rays))
    rays, nodes, enter = rays[order], nodes[order], enter[order]
    first = np.r_[True, rays[1:] != rays[:-1]]
    start = np.flatnonzero(first)
    rank = np.arange(len(rays)) - np.repeat(start, np.diff(np.r_[start, len(rays)]))
    by_rank = np.argsort(rank, kind="stable")
    bounds = np.searchsorted(rank[by_rank], np.arange(rank.max() + 2))
    for r in range(rank.max() + 1):
        sel = by_rank[bounds[r]:bounds[r + 1]]
        sel = sel[enter[sel] <= best[rays[sel]]]
        if len(sel):
            _test_leaves(mesh, o, d, rays[sel], nodes[sel], t_min, best, best_f)
    best[best_f < 0] = np.inf
    return best, best_f
