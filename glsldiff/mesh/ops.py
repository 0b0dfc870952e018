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
