"""Primitive closed meshes (lengths in mm): icosphere, axis-aligned box, torus. Each goes
through :func:`glsldiff.mesh.load.mesh_from_arrays`, so it is validated like a loaded file.

trimesh (a core dependency, imported where used: heavy import) builds the triangles.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from glsldiff.core.checks import integer, real, vector3
from glsldiff.core.errors import InputError
from glsldiff.mesh.load import mesh_from_arrays
from glsldiff.mesh.types import Mesh


def sphere_mesh(radius_mm: float, subdivisions: int = 4,
                center: ArrayLike = (0.0, 0.0, 0.0)) -> Mesh:
    """Icosphere of radius ``radius_mm`` mm (vertices on the sphere) around ``center`` mm."""
    import trimesh  # heavy import, loaded only where a mesh is built

    r = real(radius_mm, "sphere radius_mm (mm)", lo=0.0, lo_open=True)
    n = integer(subdivisions, "sphere subdivisions", 0, 7)
    s = trimesh.creation.icosphere(subdivisions=n, radius=r)
    return mesh_from_arrays(s.vertices + vector3(center, "sphere center (mm)"), s.faces, name="sphere")


def box_mesh(extents_mm: ArrayLike, origin: ArrayLike = (0.0, 0.0, 0.0)) -> Mesh:
    """Axis-aligned box from ``origin`` to ``origin + extents_mm`` (mm), 12 triangles."""
    import trimesh  # heavy import, loaded only where a mesh is built

    ext = vector3(extents_mm, "box extents_mm")
    if not (ext > 0).all():
        raise InputError(f"box extents_mm={ext.tolist()} must all be > 0 mm")
    b = trimesh.creation.box(extents=ext)
    return mesh_from_arrays(b.vertices + ext / 2 + vector3(origin, "box origin (mm)"), b.faces, name="box")


#: Closed meshes made from one size (no file): a sphere of that diameter, a torus that wide
#: (ring radius 0.35 size, tube 0.15 size, around z). Scenes and benchmarks name them.
GENERATED_MESHES = ("sphere", "torus")


def generated_mesh(name: str, size_mm: float) -> Mesh:
    """The mesh :data:`GENERATED_MESHES` names, ``size_mm`` mm across."""
    if name == "sphere":
        return sphere_mesh(size_mm / 2.0)
    if name == "torus":
        return torus_mesh(0.35 * size_mm, 0.15 * size_mm)
    raise InputError(f"no generated mesh {name!r}; choose one of {GENERATED_MESHES}")


def torus_mesh(R: float, r: float, major_sections: int = 48, minor_sections: int = 24,
               center: ArrayLike = (0.0, 0.0, 0.0)) -> Mesh:
    """Torus (genus 1) around the z axis: ring radius ``R`` mm, tube radius ``r`` mm."""
    import trimesh  # heavy import, loaded only where a mesh is built

    R = real(R, "torus R (mm)", lo=0.0, lo_open=True)
    r = real(r, "torus r (mm)", lo=0.0, lo_open=True)
    if r >= R:
        raise InputError(f"torus r={r} must be smaller than R={R} (else it self-intersects)")
    for what, n in (("major_sections", major_sections), ("minor_sections", minor_sections)):
        if not isinstance(n, (int, np.integer)) or n < 3:
            raise InputError(f"torus {what}={n!r} must be an integer >= 3")
    t = trimesh.creation.torus(R, r, major_sections=int(major_sections),
                               minor_sections=int(minor_sections))
    return mesh_from_arrays(t.vertices + vector3(center, "torus center (mm)"), t.faces, name="torus")
