"""Mesh: closed triangle surfaces (coordinates in mm), loaded, repaired and validated, and the
point queries the polycube and the mapping need.

A :class:`Mesh` is a closed, two-manifold, single-component, outward oriented triangle
surface. Modules:

``types``
    :class:`Mesh` and its cached properties (normals, volume, area, genus, acceleration
    structures); array-level geometry and topology helpers.
``load``
    :func:`load_mesh`, :func:`mesh_from_arrays` (pymeshlab read, repair, topology checks),
    :func:`cached_load_mesh` (the same through the on-disk cache), the built-in :data:`SAMPLE_MESHES`.
``primitives``
    :func:`sphere_mesh`, :func:`box_mesh`, :func:`torus_mesh`.
``accel``
    Ray index and bounding-volume hierarchy built on a mesh's first query.
``inside``
    :func:`contains`, :func:`contains_grid`, :func:`axis_hits` by exact ray crossings.
``closest``
    :func:`closest_points`, exact closest surface points.
``ops``
    :func:`subdivide` and other operations returning a new mesh; :func:`surface_samples`.
``smoothing``
    :func:`screened_smoothing`: ``u - lambda^2 Lap_s u = q`` along the surface.
"""
from glsldiff.mesh.closest import closest_points
from glsldiff.mesh.inside import axis_hits, contains, contains_grid
from glsldiff.mesh.load import (COMPONENT_MODES, MAX_HOLE_EDGES, SAMPLE_MESHES, cached_load_mesh, load_mesh,
                                mesh_from_arrays, sample_mesh_path)
from glsldiff.mesh.ops import subdivide, surface_samples
from glsldiff.mesh.primitives import GENERATED_MESHES, box_mesh, generated_mesh, sphere_mesh, torus_mesh
from glsldiff.mesh.smoothing import screened_smoothing
from glsldiff.mesh.types import Mesh, vertex_areas

__all__ = [
    "Mesh",
    "screened_smoothing",
    "load_mesh",
    "cached_load_mesh",
    "mesh_from_arrays",
    "sample_mesh_path",
    "SAMPLE_MESHES",
    "MAX_HOLE_EDGES",
    "COMPONENT_MODES",
    "sphere_mesh",
    "box_mesh",
    "torus_mesh",
    "generated_mesh",
    "GENERATED_MESHES",
    "contains",
    "contains_grid",
    "axis_hits",
    "closest_points",
    "subdivide",
    "surface_samples",
    "vertex_areas",
]
