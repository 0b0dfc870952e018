"""The :class:`Mesh` type: a closed triangle surface (coordinates in mm) with cached derived
properties (normals, volume, area, genus) and acceleration structures, plus the array-level
checks, geometry and topology helpers that it, the loader and the queries share.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from glsldiff.core.checks import points as check_points
from glsldiff.core.errors import InputError

#: Faces meeting at a larger angle than this (degrees) do not share corner normals
#: (:attr:`Mesh.corner_normals`): a sharp edge.
CREASE_DEG = 45.0
from glsldiff.mesh.accel import BVH, RayIndex, faces_around_vertices

if TYPE_CHECKING:  # pragma: no cover
    import trimesh


@dataclass(frozen=True, eq=False)
class Mesh:
    """A closed, two-manifold, outward oriented triangle mesh (coordinates in mm).

    Parameters
    ----------
    vertices
        ``(V, 3)`` float64 vertex positions, mm.
    faces
        ``(F, 3)`` int64 vertex indices, counter-clockwise seen from outside.
    name
        Label used in messages.
    repairs
        What the load-time repair changed, e.g. ``{"degenerate_faces": 2}``; only
        non-zero counts are listed.

    Use :func:`glsldiff.mesh.load_mesh` or :func:`glsldiff.mesh.mesh_from_arrays` to get a
    validated mesh; the constructor only checks array shapes and index ranges.
    """

    vertices: NDArray[np.float64]
    faces: NDArray[np.int64]
    name: str = ""
    repairs: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        label = self.name or "mesh"
        v = np.array(self.vertices, dtype=np.float64, order="C")
        f = np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3:
            raise InputError(f"{label}: vertices must have shape (V, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3:
            raise InputError(f"{label}: faces must have shape (F, 3), got {f.shape}")
        if f.size and not np.issubdtype(f.dtype, np.integer):
            raise InputError(f"{label}: faces must be integer vertex indices, got dtype {f.dtype}")
        f = np.array(f, dtype=np.int64, order="C")
        check_face_indices(f, len(v), label)
        v.setflags(write=False)
        f.setflags(write=False)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)
        object.__setattr__(self, "repairs", dict(self.repairs))

    def __repr__(self) -> str:
        return (f"Mesh(name={self.name!r}, vertices={len(self.vertices)}, faces={len(self.faces)}, "
                f"extents={np.round(self.extents, 4).tolist()} mm, repairs={self.repairs})")

    # ---- geometry ---------------------------------------------------------------------
    @cached_property
    def tm(self) -> "trimesh.Trimesh":
        """The mesh as ``trimesh.Trimesh`` (``process=False``: arrays kept as they are)."""
        import trimesh  # heavy import, loaded only where a mesh is built

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    @cached_property
    def triangles(self) -> NDArray[np.float64]:
        """``(F, 3, 3)`` corner positions per face, mm."""
        return self.vertices[self.faces]

    @cached_property
    def volume(self) -> float:
        """Enclosed volume, mm^3 (positive for outward orientation)."""
        return signed_volume(self.vertices, self.faces)

    @cached_property
    def area(self) -> float:
        """Surface area, mm^2."""
        return float(0.5 * np.linalg.norm(self._face_cross, axis=1).sum())

    @cached_property
    def bounds(self) -> NDArray[np.float64]:
        """``(2, 3)`` axis-aligned bounding box ``[min, max]``, mm."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @property
    def extents(self) -> NDArray[np.float64]:
        """``(3,)`` bounding-box edge lengths, mm."""
        return self.bounds[1] - self.bounds[0]

    @cached_property
    def genus(self) -> int:
        """Genus of the surface, ``(2 * components - (V - E + F)) / 2``."""
        v, e, f = euler_counts(self.faces)
        comps = component_count(self.faces, len(self.vertices))
        return int((2 * comps - (v - e + f)) // 2)

    @cached_property
    def _face_cross(self) -> NDArray[np.float64]:
        t = self.triangles
        return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])

    @cached_property
    def face_normals(self) -> NDArray[np.float64]:
        """``(F, 3)`` unit outward face normals (zero for a degenerate face)."""
        return normalize(self._face_cross)

    @cached_property
    def vertex_normals(self) -> NDArray[np.float64]:
        """``(V, 3)`` unit vertex normals, area-weighted mean of the adjacent face normals."""
        acc = np.zeros_like(self.vertices)
        for k in range(3):  # |cross| = 2 * area: the area weighting
            np.add.at(acc, self.faces[:, k], self._face_cross)
        return normalize(acc)

    @cached_property
    def corner_normals(self) -> NDArray[np.float64]:
        """``(F, 3, 3)`` unit normal at each face corner: the area-weighted mean of the normals
        of the faces around that vertex that lie within :data:`CREASE_DEG` of this face's
        normal (smoothing groups). Equal to :attr:`vertex_normals` on a smooth surface; on a
        flat face next to a sharp edge or corner it is the face's own normal, where the plain
        vertex normals would tilt it towards the neighbouring faces."""
        f = self.faces
        cross, nf = self._face_cross, self.face_normals
        corner_vertex = f.ravel()
        around, start = faces_around_vertices(f, len(self.vertices))
        rep = np.diff(start)[corner_vertex]                        # faces around each corner's vertex
        owner = np.repeat(np.arange(len(corner_vertex)), rep)
        pos = np.arange(len(owner)) - np.repeat(np.cumsum(rep) - rep, rep)
        partner = around[start[corner_vertex[owner]] + pos]        # a face around the vertex
        keep = np.einsum("ij,ij->i", nf[owner // 3], nf[partner]) >= math.cos(math.radians(CREASE_DEG))
        o, c = owner[keep], cross[partner[keep]]
        acc = np.stack([np.bincount(o, weights=c[:, k], minlength=len(corner_vertex)) for k in range(3)], axis=1)
        return normalize(acc).reshape(len(f), 3, 3)

    # ---- acceleration structures (built on first query) --------------------------------
    @cached_property
    def _ray_indices(self) -> list[RayIndex | None]:
        return [None, None, None]

    def ray_index(self, axis: int) -> RayIndex:
        """:class:`~glsldiff.mesh.accel.RayIndex` for rays parallel to coordinate ``axis``,
        built on first use."""
        indices = self._ray_indices
        if indices[axis] is None:
            indices[axis] = RayIndex(self.vertices, self.faces, axis)
        return indices[axis]  # type: ignore[return-value]

    @cached_property
    def bvh(self) -> BVH:
        """:class:`~glsldiff.mesh.accel.BVH` of the faces, for closest-point queries."""
        return BVH(self.vertices, self.faces)


# ---- array-level geometry and topology -----------------------------------------------------
def query_points(value: ArrayLike, name: str = "points") -> NDArray[np.float64]:
    """Finite query positions (mm) as ``(N, 3)``; a single ``(3,)`` point becomes ``(1, 3)``."""
    try:
        single = np.shape(value) == (3,)
    except ValueError:  # a ragged list: the check names it
        single = False
    return check_points([value] if single else value, name)


def check_face_indices(faces: NDArray[np.integer], n_vertices: int, label: str) -> None:
    """Raise InputError unless every face index lies in ``0..n_vertices - 1``."""
    if faces.size and (faces.min() < 0 or faces.max() >= n_vertices):
        raise InputError(f"{label}: faces index vertices outside 0..{n_vertices - 1} "
                         f"(found {faces.min()}..{faces.max()}); fix the face list")


def normalize(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rows of ``x`` scaled to unit length (zero rows stay zero)."""
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, n, out=np.zeros_like(x), where=n > 0)


def vertex_areas(v: NDArray[np.float64], f: NDArray[np.int64]) -> NDArray[np.float64]:
    """``(V,)`` lumped surface area per vertex, mm^2: a third of the area of every face ``f``
    around it (0 for vertices of no face)."""
    v, f = np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    return np.bincount(f.ravel(), np.repeat(area / 3.0, 3), minlength=len(v))


def signed_volume(v: NDArray[np.float64], f: NDArray[np.int64]) -> float:
    """Volume enclosed by faces ``f`` over vertices ``v``, mm^3 (positive if outward)."""
    if len(f) == 0:
        return 0.0
    c = v.mean(axis=0)  # shift for accuracy
    a, b, d = v[f[:, 0]] - c, v[f[:, 1]] - c, v[f[:, 2]] - c
    return float(np.einsum("ij,ij->i", a, np.cross(b, d)).sum() / 6.0)


def unique_edges(faces: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Undirected edges ``(E, 2)`` (sorted pairs) and how many faces use each."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    n = int(faces.max()) + 1 if faces.size else 1
    key, counts = np.unique(e[:, 0] * n + e[:, 1], return_counts=True)
    return np.stack([key // n, key % n], axis=1), counts


def n_directed_edges(faces: NDArray[np.int64]) -> int:
    """Number of distinct directed edges (twice the undirected ones iff coherently oriented)."""
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    n = int(faces.max()) + 1 if faces.size else 1
    return int(np.unique(e[:, 0] * n + e[:, 1]).size)


def euler_counts(faces: NDArray[np.int64]) -> tuple[int, int, int]:
    """``(V, E, F)``: referenced vertices, undirected edges, faces."""
    edges, _ = unique_edges(faces)
    return int(np.unique(faces).size), int(len(edges)), int(len(faces))


def vertex_labels(faces: NDArray[np.int64], n_vertices: int) -> tuple[int, NDArray[np.int64]]:
    """Connected components of the vertex graph: ``(count, label per vertex)``."""
    e = faces[:, [0, 1, 1, 2]].reshape(-1, 2)
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    return connected_components(g, directed=False)


def component_count(faces: NDArray[np.int64], n_vertices: int) -> int:
    """Number of connected components that hold at least one face."""
    if len(faces) == 0:
        return 0
    _, labels = vertex_labels(faces, n_vertices)
    return int(np.unique(labels[faces[:, 0]]).size)
