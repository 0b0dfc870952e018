"""Mesh operations that return a new mesh (coordinates in mm)."""
from __future__ import annotations

import numpy as np

from glsldiff.mesh.types import Mesh


def subdivide(mesh: Mesh, max_edge: float) -> Mesh:
    """``mesh`` with every edge split down to ``max_edge`` mm (e.g. a 12-triangle box shaded
    per vertex needs vertices at about the node spacing); ``mesh`` itself when no edge is
    longer. Imports trimesh (heavy) only when it splits."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    edges = np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2)
    if edges.max() <= max_edge:
        return mesh
    import trimesh.remesh   # heavy import, needed only for coarse meshes

    v2, f2 = trimesh.remesh.subdivide_to_size(v, f, max_edge=max_edge)
    return Mesh(np.asarray(v2, float), np.asarray(f2, np.int64), name=mesh.name)


def surface_samples(mesh: Mesh, spacing: float, seed: int = 0) -> np.ndarray:
    """``(P, 3)`` points spread uniformly by area over the surface, about one per
    ``spacing^2`` mm^2 (at least one per triangle, stratified per triangle, reproducible by
    ``seed``), plus the vertices."""
    V, F = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    k = np.maximum(1, np.ceil(area / spacing ** 2)).astype(np.int64)
    idx = np.repeat(np.arange(len(F)), k)
    rng = np.random.default_rng(seed)
    u, v = rng.random(len(idx)), rng.random(len(idx))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    return np.concatenate([a[idx] + u[:, None] * (b - a)[idx] + v[:, None] * (c - a)[idx], V])
