"""The pass-2 fluence of a tetrahedral grid at any point: a regular lattice over the grid, each
lattice point the P1 interpolant of the tetrahedron that holds it, read trilinearly.

The transport split's gather (:mod:`glsldiff.physics.split`, :mod:`glsldiff.render.single`)
integrates the collided fluence along refracted view rays; its samples fall anywhere inside the
object. Locating each sample in the tetrahedra every time the camera moves would cost a k-d
query per sample; instead the lattice's weights (4 per point: barycentric in the tetrahedron
containing it) are found once per grid (:class:`FluenceLattice`), and a new solution costs one
sparse product. Lattice points outside the grid but within one spacing of it take the closest
point of the nearest tetrahedron (clamped barycentric weights), so rays that start on the
render mesh, which lies within about a node spacing of the grid's boundary, read the boundary
values; points farther out read 0. Every weight is >= 0: a non-negative fluence stays
non-negative.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

__all__ = ["FluenceLattice"]

_CANDIDATES = 12     # nearest tetrahedra (by centroid) tried per lattice point
_CHUNK = 65536


class FluenceLattice:
    """Sampling of node values of a tetrahedral grid (``positions`` ``(n, 3)`` mm, ``tets``
    ``(T, 4)``) on a lattice of spacing ``spacing`` mm (default: the grid's mean edge)."""

    def __init__(self, positions: NDArray, tets: NDArray, spacing: float | None = None) -> None:
        P = np.asarray(positions, dtype=np.float64)
        T = np.asarray(tets, dtype=np.int64)
        corners = P[T]                                                        # (T, 4, 3)
        if spacing is None:
            spacing = float(np.linalg.norm(corners[:, 1] - corners[:, 0], axis=1).mean())
        self.spacing = float(spacing)
        lo, hi = P.min(axis=0) - self.spacing, P.max(axis=0) + self.spacing
        self.shape = tuple(int(np.ceil((hi[i] - lo[i]) / self.spacing)) + 1 for i in range(3))
        self.lo = lo
        axes = [lo[i] + self.spacing * np.arange(self.shape[i]) for i in range(3)]
        X, Y, Z = np.meshgrid(*axes, indexing="ij")
        pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
        # barycentric maps: l_i(x) = G_i . (x - P_0) + [i = 0]
        e = corners[:, 1:] - corners[:, :1]                                   # (T, 3, 3) rows e1 e2 e3
        det = np.linalg.det(e)
        ok = np.abs(det) > 1e-12 * float(np.abs(det).max(initial=1.0))
        inv = np.zeros_like(e)
        inv[ok] = np.linalg.inv(e[ok])                                        # columns: grad l_1..3
        self._origin = corners[:, 0]
        self._grad = np.transpose(inv, (0, 2, 1))                             # (T, 3, 3): rows grad l_1..3
        centroids = corners.mean(axis=1)
        tree = cKDTree(centroids[ok])
        alive = np.flatnonzero(ok)
        # lattice points near the grid: within the largest tetrahedron's reach of a centroid
        reach = float(np.linalg.norm(corners - centroids[:, None], axis=2).max()) + self.spacing
        d0, _ = tree.query(pts, k=1, distance_upper_bound=reach)
        near = np.flatnonzero(np.isfinite(d0))
        rows, cols, vals = [], [], []
        k = min(_CANDIDATES, len(alive))
        for s in range(0, len(near), _CHUNK):
            idx = near[s:s + _CHUNK]
            x = pts[idx]
            _, cand = tree.query(x, k=k)
            cand = alive[cand.reshape(len(idx), k)]                           # (m, k) tetrahedra
            rel = x[:, None, :] - self._origin[cand]                          # (m, k, 3)
            l123 = np.einsum("mkij,mkj->mki", self._grad[cand], rel)
            lam = np.concatenate([1.0 - l123.sum(axis=2, keepdims=True), l123], axis=2)   # (m, k, 4)
            worst = lam.min(axis=2)
            best = worst.argmax(axis=1)
            pick = np.arange(len(idx))
            lb = lam[pick, best]                                              # (m, 4)
            inside = worst[pick, best] >= -1e-9
            # outside every candidate: the nearest one's clamped weights, only within one spacing
            w = np.clip(lb, 0.0, None)
            w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
            close = inside | (np.linalg.norm(x - (w[:, :, None] * P[T[cand[pick, best]]]).sum(axis=1), axis=1)
                              <= self.spacing)
            tv = T[cand[pick, best]]
            r = np.repeat(idx[close], 4)
            rows.append(r)
            cols.append(tv[close].ravel())
            vals.append(w[close].ravel())
        self.weights = sp.csr_matrix((np.concatenate(vals) if vals else np.zeros(0),
                                      (np.concatenate(rows) if rows else np.zeros(0, int),
                                       np.concatenate(cols) if cols else np.zeros(0, int))),
                                     shape=(len(pts), len(P)))
        self._values: NDArray[np.float64] | None = None

    def set_values(self, node_values: NDArray) -> None:
        """Node values ``(n, C)`` (e.g. the collided fluence per channel) onto the lattice."""
        v = np.asarray(node_values, dtype=np.float64)
        self._values = np.asarray(self.weights @ v).reshape(self.shape + (v.shape[1],))

    def __call__(self, points: NDArray) -> NDArray[np.float64]:
        """``(M, C)`` trilinear lattice values at ``points`` ``(M, 3)`` mm (0 outside the lattice)."""
        if self._values is None:
            raise RuntimeError("FluenceLattice: set_values before sampling")
        c = ((np.asarray(points, dtype=np.float64) - self.lo) / self.spacing).T
        out = np.empty((c.shape[1], self._values.shape[3]))
        for ch in range(self._values.shape[3]):
            out[:, ch] = map_coordinates(self._values[..., ch], c, order=1, mode="constant", cval=0.0)
        return out
