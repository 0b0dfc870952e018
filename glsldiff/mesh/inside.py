"""Inside test and axis-line hits by exact ray crossing counts (coordinates in mm).

Every query point casts a ray along +z, and the signed crossings (+1 through a face seen
counter-clockwise from +z, -1 otherwise) above the point add up to its winding number
(1 inside, 0 outside for an outward closed surface). The crossings come from the mesh's
:class:`~glsldiff.mesh.accel.RayIndex`, whose edge functions and symbolic perturbation
make every crossing count exactly once, unlike a plain parity test. Points sharing an xy
position share one ray, so sampling a regular grid (:func:`contains_grid`) costs one ray
per column.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError
from glsldiff.core.jit import kernel
from glsldiff.mesh.types import Mesh, query_points


def axis_hits(mesh: Mesh, points: ArrayLike, axis: ArrayLike) -> NDArray[np.float64]:
    """Nearest surface point of each point (N, 3) mm along the line through it parallel to
    coordinate ``axis`` (N,) in {0, 1, 2}, searching both directions; NaN rows where the
    line misses the mesh. Distinct points on parallel lines never share a hit, unlike
    closest points, which collapse onto convex features."""
    p = query_points(points)
    ax = np.asarray(axis, dtype=np.int64).ravel()
    if ax.shape != (len(p),) or np.any((ax < 0) | (ax > 2)):
        raise InputError("axis_hits: axis must hold one of 0, 1, 2 per point")
    out = np.full_like(p, np.nan)
    for a in range(3):
        sel = np.flatnonzero(ax == a)
        if sel.size == 0:
            continue
        perm = [(a + 1) % 3, (a + 2) % 3]
        rays, ray_of = np.unique(p[sel][:, perm], axis=0, return_inverse=True)
        cr, cz, _ = mesh.ray_index(a).crossings(rays)
        ray_of = ray_of.ravel()
        # per point: the crossing nearest to its own coordinate along the axis
        order = np.lexsort((cz, cr))
        cr, cz = cr[order], cz[order]
        start = np.searchsorted(cr, np.arange(len(rays) + 1))
        coord = p[sel, a]
        hit = np.full(sel.size, np.nan)
        best = np.full(sel.size, np.inf)
        counts = start[ray_of + 1] - start[ray_of]
        for k in range(int(counts.max(initial=0))):
            idx = np.flatnonzero(counts > k)
            z = cz[start[ray_of[idx]] + k]
            dist = np.abs(z - coord[idx])
            better = dist < best[idx]
            hit[idx[better]], best[idx[better]] = z[better], dist[better]
        rows = sel[np.isfinite(hit)]
        out[rows] = p[rows]
        out[rows, a] = hit[np.isfinite(hit)]
    return out


def winding(mesh: Mesh, rays: NDArray[np.float64], ray_of: NDArray[np.int64],
            z: NDArray[np.float64]) -> NDArray[np.int64]:
    """Winding number of points ``(rays[ray_of], z)``: signed crossings strictly above."""
    cr, cz, cs = mesh.ray_index(2).crossings(rays)
    n_r = len(rays)
    total = np.bincount(cr, weights=cs, minlength=n_r).astype(np.int64)
    before = np.cumsum(total) - total
    ray = np.concatenate([cr, ray_of])
    zz = np.concatenate([cz, z])
    kind = np.concatenate([np.zeros(len(cr), np.int8), np.ones(len(z), np.int8)])
    val = np.concatenate([cs, np.zeros(len(z), np.int64)])
    order = np.lexsort((kind, zz, ray))
    cum = np.cumsum(val[order])
    pos = np.empty(len(order), dtype=np.int64)
    pos[order] = np.arange(len(order))
    q = pos[len(cr):]
    below = cum[q] - before[ray_of]  # crossings at z' <= z
    return total[ray_of] - below


def contains(mesh: Mesh, points: ArrayLike) -> NDArray[np.bool_]:
    """Whether each point (N, 3) mm lies inside the closed mesh.

    Exact signed ray-crossing count along +z (see the module docstring); points on the
    surface may go either way. 1e5 random points take about 0.3 s on the 56K-face bunny.
    """
    p = query_points(points)
    out = np.zeros(len(p), dtype=bool)
    lo, hi = mesh.bounds
    cand = np.flatnonzero(((p >= lo) & (p <= hi)).all(axis=1))
    if cand.size == 0:
        return out
    rays, ray_of = np.unique(p[cand, :2], axis=0, return_inverse=True)
    out[cand] = winding(mesh, rays, ray_of.ravel(), p[cand, 2]) > 0
    return out


def contains_grid(mesh: Mesh, xs: ArrayLike, ys: ArrayLike, zs: ArrayLike) -> NDArray[np.bool_]:
    """Inside test on the regular grid ``xs x ys x zs`` (mm); returns ``(nx, ny, nz)`` bool.

    One ray per (x, y) column, so much cheaper than :func:`contains` on the same points.
    """
    ax = [np.asarray(a, dtype=np.float64).ravel() for a in (xs, ys, zs)]
    for name, a in zip("xyz", ax):
        if a.size == 0 or not np.isfinite(a).all():
            raise InputError(f"contains_grid: {name}s must be a non-empty finite 1-D array (mm)")
    gx, gy = np.meshgrid(ax[0], ax[1], indexing="ij")
    rays = np.stack([gx.ravel(), gy.ravel()], axis=1)
    cr, cz, cs = mesh.ray_index(2).crossings(rays)
    inside = _column_inside(cr, cz, np.asarray(cs, dtype=np.int64), len(rays), ax[2])
    return inside.reshape(ax[0].size, ax[1].size, ax[2].size)


@kernel
def _column_inside(cr: NDArray[np.int64], cz: NDArray[np.float64], cs: NDArray[np.int64], n_rays: int,
                   zs: NDArray[np.float64]) -> NDArray[np.bool_]:
    """``(n_rays, len(zs))`` whether the :func:`winding` number of the point ``(ray r, zs[j])``
    is positive: the signed crossings ``(cr, cz, cs)`` of ray ``r`` strictly above ``zs[j]``
    summed, without sorting every point with every crossing (a ray has a few crossings; the
    bunny's polycube search: 0.9 s -> 0.05 s)."""
    start = np.zeros(n_rays + 1, dtype=np.int64)
    for k in range(len(cr)):
        start[cr[k] + 1] += 1
    for r in range(n_rays):
        start[r + 1] += start[r]
    fill = start[:-1].copy()
    z, sign = np.empty(len(cr)), np.empty(len(cr), dtype=np.int64)
    for k in range(len(cr)):
        f = fill[cr[k]]
        z[f], sign[f] = cz[k], cs[k]
        fill[cr[k]] = f + 1
    out = np.empty((n_rays, len(zs)), dtype=np.bool_)
    for r in range(n_rays):
        for j in range(len(zs)):
            w = 0
            for i in range(start[r], start[r + 1]):
                if z[i] > zs[j]:
                    w += sign[i]
            out[r, j] = w > 0
    return out
