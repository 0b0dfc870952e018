"""Sharp features of a mesh: its crease edges (dihedral angle above a threshold) and corner
vertices, and closest points restricted to them. The tetrahedral grid's surface mapping keeps
nodes that land on a crease on that crease and nodes that land on a corner on that corner,
so that relaxation does not round off a box's edges (lengths in mm)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from glsldiff.mesh.types import Mesh

__all__ = ["Features", "mesh_features"]


@dataclass(frozen=True, eq=False)
class Features:
    """Crease segments ``(E, 2, 3)`` mm and corner points ``(K, 3)`` mm of a mesh."""

    segments: NDArray[np.float64]
    corners: NDArray[np.float64]

    @cached_property
    def _tree(self) -> cKDTree | None:
        return cKDTree(self.segments.mean(axis=1)) if len(self.segments) else None

    def closest_on_creases(self, points: NDArray[np.float64], candidates: int = 8
                           ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Closest points on the crease segments and their distances (inf without creases)."""
        p = np.asarray(points, dtype=np.float64)
        if self._tree is None or len(p) == 0:
            return p.copy(), np.full(len(p), np.inf)
        k = min(candidates, len(self.segments))
        _, idx = self._tree.query(p, k=k)
        idx = idx.reshape(len(p), k)
        a, b = self.segments[idx, 0], self.segments[idx, 1]             # (P, k, 3)
        ab = b - a
        t = np.clip(np.einsum("pkc,pkc->pk", p[:, None] - a, ab) / np.maximum(np.einsum("pkc,pkc->pk", ab, ab),
                                                                               1e-300), 0.0, 1.0)
        c = a + t[..., None] * ab
        d = np.linalg.norm(c - p[:, None], axis=2)
        j = np.argmin(d, axis=1)
        return c[np.arange(len(p)), j], d[np.arange(len(p)), j]

    def corner_distance(self, points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Distance to the nearest corner and its index (inf / -1 without corners)."""
        if len(self.corners) == 0:
            return np.full(len(points), np.inf), np.full(len(points), -1)
        d, i = cKDTree(self.corners).query(points)
        return d, i


def mesh_features(mesh: Mesh, angle_deg: float = 45.0) -> Features:
    """Crease edges: edges whose two faces' normals differ by more than ``angle_deg``.
    Corners: vertices on three or more creases, or on two that meet at more than
    ``angle_deg``."""
    f = np.asarray(mesh.faces)
    n = mesh.face_normals
    e = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    face = np.repeat(np.arange(len(f)), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, face = e[order], face[order]
    same = np.all(e[1:] == e[:-1], axis=1)
    first = np.flatnonzero(same)                 # pairs (first, first+1) share an edge (closed manifold)
    cosang = np.einsum("ij,ij->i", n[face[first]], n[face[first + 1]])
    crease = e[first][cosang < np.cos(np.radians(angle_deg))]
    v = np.asarray(mesh.vertices, dtype=np.float64)
    segments = v[crease]
    corners = np.zeros(0, dtype=np.int64)
    if len(crease):
        ends = crease.ravel()
        count = np.bincount(ends, minlength=len(v))
        many = np.flatnonzero(count >= 3)
        # two creases meeting at an angle: pair each count-2 vertex's two segment ends
        order = np.argsort(ends, kind="stable")
        at = order[count[ends[order]] == 2].reshape(-1, 2)           # (K, 2) positions in ends
        vi = ends[at[:, 0]]
        other = crease.ravel()[at ^ 1]                                # the far end of each segment
        d0, d1 = v[other[:, 0]] - v[vi], v[other[:, 1]] - v[vi]
        c = np.einsum("ij,ij->i", d0, d1) / np.maximum(np.linalg.norm(d0, axis=1) * np.linalg.norm(d1, axis=1),
                                                       1e-300)
        corners = np.concatenate([many, vi[c > -np.cos(np.radians(angle_deg))]])
    return Features(segments, v[corners])
