"""Acceleration structures over a triangle mesh's arrays (coordinates in mm), built once per
mesh on its first query and cached by :class:`glsldiff.mesh.types.Mesh`.

:class:`RayIndex`
    Faces binned on a 2-D grid across a coordinate axis, with edge functions evaluated
    once per *undirected* edge (vertex order canonical), so the two faces sharing an edge
    always agree on which side a ray passes; a ray exactly on a projected edge or vertex is
    decided by symbolic perturbation (the ray is moved by (eps, eps^2) across the axis).
    Hence no crossing is missed or counted twice. Used by :mod:`glsldiff.mesh.inside`.
:class:`BVH`
    Implicit complete binary tree of axis-aligned boxes over the faces in Morton order
    (leaves of :attr:`BVH.LEAF` faces), plus a k-d tree of the vertices and the faces
    around each vertex. Used by :mod:`glsldiff.mesh.closest`.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

#: (ray, face) or (point, face) pairs processed at once by the queries.
PAIR_CHUNK = 2_000_000


class RayIndex:
    """Faces binned across coordinate ``axis``, for exact ray casting along +``axis``.

    The vertices are permuted so that ``axis`` becomes the third coordinate ("z"); rays
    are given by their two other coordinates ``((axis+1) % 3, (axis+2) % 3)``.
    """

    def __init__(self, vertices: NDArray[np.float64], faces: NDArray[np.int64], axis: int = 2) -> None:
        if axis != 2:
            vertices = np.ascontiguousarray(vertices[:, [(axis + 1) % 3, (axis + 2) % 3, axis]])
        v, f = vertices, faces
        t = v[f]
        xy = t[:, :, :2]
        self.z = t[:, :, 2]
        # edges k: (f[k], f[k+1]); canonical direction from the smaller vertex index
        a_idx = f
        b_idx = np.roll(f, -1, axis=1)
        flip = a_idx > b_idx
        lo = np.where(flip, b_idx, a_idx)
        hi = np.where(flip, a_idx, b_idx)
        self.ax = v[lo, 0]
        self.ay = v[lo, 1]
        self.dx = v[hi, 0] - self.ax
        self.dy = v[hi, 1] - self.ay
        self.sgn = np.where(flip, -1, 1).astype(np.int8)
        # bins
        lo_xy = v[:, :2].min(axis=0)
        ext = np.maximum(v[:, :2].max(axis=0) - lo_xy, 1e-300)
        n_cells = max(1.0, 2.0 * len(f))
        h = math.sqrt(ext[0] * ext[1] / n_cells)
        shape = np.clip(np.ceil(ext / h), 1, 4096).astype(np.int64)
        self.lo, self.cell = lo_xy, ext / shape
        self.shape = shape
        c0 = self.cell_of(xy.min(axis=1))
        c1 = self.cell_of(xy.max(axis=1))
        w = c1 - c0 + 1
        cnt = w[:, 0] * w[:, 1]
        tri = np.repeat(np.arange(len(f)), cnt)
        k = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        wx = np.repeat(w[:, 0], cnt)
        cx = np.repeat(c0[:, 0], cnt) + k % wx
        cy = np.repeat(c0[:, 1], cnt) + k // wx
        cid = cy * shape[0] + cx
        order = np.argsort(cid, kind="stable")
        self.tris = tri[order]
        self.start = np.searchsorted(cid[order], np.arange(shape[0] * shape[1] + 1))

    def cell_of(self, xy: NDArray[np.float64]) -> NDArray[np.int64]:
        c = np.floor((xy - self.lo) / self.cell).astype(np.int64)
        return np.clip(c, 0, self.shape - 1)

    def crossings(self, rays: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.float64],
                                                            NDArray[np.int64]]:
        """Crossings of the +z lines through ``rays`` (R, 2): (ray index, z, sign), the sign
        +1 through a face seen counter-clockwise from +z, -1 otherwise."""
        c = self.cell_of(rays)
        cid = c[:, 1] * self.shape[0] + c[:, 0]
        n = self.start[cid + 1] - self.start[cid]
        out_r, out_z, out_s = [], [], []
        ends = np.cumsum(n)
        r0 = 0
        while r0 < len(rays):
            base = ends[r0 - 1] if r0 else 0
            r1 = max(int(np.searchsorted(ends, base + PAIR_CHUNK, side="right")), r0 + 1)
            ids = np.arange(r0, r1)
            cnt = n[r0:r1]
            pr = np.repeat(ids, cnt)
            k = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            pt = self.tris[self.start[cid[pr]] + k]
            r, z, s = self._test(pr, pt, rays)
            out_r.append(r), out_z.append(z), out_s.append(s)
            r0 = r1
        return (np.concatenate(out_r), np.concatenate(out_z), np.concatenate(out_s))

    def _test(self, pr: NDArray[np.int64], pt: NDArray[np.int64], rays: NDArray[np.float64]
              ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]]:
        px = rays[pr, 0][:, None]
        py = rays[pr, 1][:, None]
        dx, dy = self.dx[pt], self.dy[pt]
        e = dx * (py - self.ay[pt]) - dy * (px - self.ax[pt])  # identical for both faces of an edge
        side = np.sign(e)
        tie = side == 0  # ray exactly on the projected edge: perturb by (eps, eps^2)
        if tie.any():
            side[tie] = np.where(dy[tie] != 0, -np.sign(dy[tie]), np.sign(dx[tie]))
        t = side.astype(np.int8) * self.sgn[pt]  # side in the face's own edge direction
        inside = (t[:, 0] == t[:, 1]) & (t[:, 1] == t[:, 2]) & (t[:, 0] != 0)
        w = e[inside] * self.sgn[pt[inside]]  # w_k: edge k, opposite corner k+2
        den = w.sum(axis=1)
        zc = self.z[pt[inside]]
        with np.errstate(invalid="ignore", divide="ignore"):
            z = (w[:, 1] * zc[:, 0] + w[:, 2] * zc[:, 1] + w[:, 0] * zc[:, 2]) / den
        ok = den != 0
        return pr[inside][ok], z[ok], t[inside, 0][ok].astype(np.int64)


def faces_around_vertices(faces: NDArray[np.int64], n_vertices: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """``(order, start)``: the faces around vertex ``i`` are ``order[start[i]:start[i + 1]]``
    (in face order)."""
    vf = faces.ravel()
    corners = np.argsort(vf, kind="stable")
    return corners // 3, np.searchsorted(vf[corners], np.arange(n_vertices + 1))


class BVH:
    """Implicit complete binary tree over faces in Morton order, leaves of LEAF faces.

    Attributes
    ----------
    depth
        Tree depth; ``boxes[level]`` holds the ``2**level`` node boxes ``(min, max)``, mm.
    leaf_faces
        ``(2**depth, LEAF)`` face indices per leaf, -1 for padding.
    tree
        k-d tree of the vertices.
    vf_order, vf_start
        Faces around vertex ``i``: ``vf_order[vf_start[i]:vf_start[i + 1]]``.
    """

    LEAF = 4

    def __init__(self, vertices: NDArray[np.float64], faces: NDArray[np.int64]) -> None:
        t = vertices[faces]
        cen = t.mean(axis=1)
        lo, hi = cen.min(axis=0), cen.max(axis=0)
        q = np.floor((cen - lo) / np.maximum(hi - lo, 1e-300) * 1023.999).astype(np.uint64)
        code = np.zeros(len(t), dtype=np.uint64)
        for bit in range(10):
            for axis in range(3):
                code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
        order = np.argsort(code, kind="stable")
        n_leaf = max(1, -(-len(t) // self.LEAF))
        self.depth = int(math.ceil(math.log2(n_leaf))) if n_leaf > 1 else 0
        n_pad = (1 << self.depth) * self.LEAF
        leaf = np.full(n_pad, -1, dtype=np.int64)
        leaf[: len(order)] = order
        self.leaf_faces = leaf.reshape(-1, self.LEAF)
        tmin, tmax = t.min(axis=1), t.max(axis=1)
        valid = self.leaf_faces >= 0
        idx = np.where(valid, self.leaf_faces, 0)
        bmin = np.where(valid[..., None], tmin[idx], np.inf).min(axis=1)
        bmax = np.where(valid[..., None], tmax[idx], -np.inf).max(axis=1)
        self.boxes = [(bmin, bmax)]
        for _ in range(self.depth):
            bmin = bmin.reshape(-1, 2, 3).min(axis=1)
            bmax = bmax.reshape(-1, 2, 3).max(axis=1)
            self.boxes.append((bmin, bmax))
        self.boxes.reverse()  # boxes[level], level 0 = root
        #: ``(2^(depth+1) - 1, 3)`` min and max corners of every node, node ``2^level - 1 + k``
        #: being ``boxes[level]``'s ``k``-th (an implicit heap: children ``2 i + 1``, ``2 i + 2``)
        self.heap_boxes = (np.concatenate([b[0] for b in self.boxes]), np.concatenate([b[1] for b in self.boxes]))
        self.tree = cKDTree(vertices)
        self.vf_order, self.vf_start = faces_around_vertices(faces, len(vertices))
