"""Mesh operations that return a new mesh (coordinates in mm)."""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from glsldiff.mesh.closest import closest_on_triangles
from glsldiff.mesh.types import Mesh, normalize


def subdivide(mesh: Mesh, max_edge: float) -> Mesh:
    """``mesh`` with every edge split down to ``max_edge`` mm (e.g. a 12-triangle box shaded
    per vertex needs vertices at about the node spacing); ``mesh`` itself when no edge is
    longer. Imports trimesh (heavy) only when it splits."""
    return smooth_subdivide(mesh, max_edge)[0]


def smooth_subdivide(mesh: Mesh, max_edge: float) -> tuple[Mesh, NDArray[np.float64]]:
    """:func:`subdivide` and the new mesh's shading normals ``(V, 3)``: at a vertex the split
    put inside an old face (or on its edge), the old face's corner normals
    (:attr:`Mesh.corner_normals`, smoothing groups) interpolated at the vertex's barycentrics,
    averaged over the old faces that hold it, so a coarse curved surface shades smoothly instead
    of showing its flat faces; ``mesh.vertex_normals`` when nothing was split."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    edges = np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2)
    if edges.max() <= max_edge:
        return mesh, mesh.vertex_normals
    import trimesh.remesh   # heavy import, needed only for coarse meshes

    v2, f2, parent = trimesh.remesh.subdivide_to_size(v, f, max_edge=max_edge, return_index=True)
    v2, f2 = np.asarray(v2, float), np.asarray(f2, np.int64)
    a, b, c = (mesh.triangles[parent, k] for k in range(3))  # each new face's old triangle
    corners = mesh.corner_normals[parent]                    # (F2, 3 corners, 3)
    acc = np.zeros_like(v2)
    for k in range(3):                                       # each new face's corner k
        bary = closest_on_triangles(v2[f2[:, k]], a, b, c)   # the vertex lies on its old face
        np.add.at(acc, f2[:, k], np.einsum("fj,fjc->fc", bary, corners))
    return Mesh(v2, f2, name=mesh.name), normalize(acc)


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
