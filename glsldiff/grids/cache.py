"""Built polygrids and tetrahedral (pillowed) grids through the on-disk cache (:mod:`glsldiff.core.cache`): the polycube
search, mapping and weights of a mesh take tens of seconds (13 s for the default bunny), the
same every run.

Entries are keyed by the mesh's vertex and face bytes, the build parameters and
:data:`CACHE_VERSION` (bump it when the construction changes).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from glsldiff.core import cache
from glsldiff.grids.fem_grid import FemGrid, build_fem_grid
from glsldiff.grids.polygrid import Polygrid, build_polygrid
from glsldiff.mesh import Mesh

#: Part of every key: entries of an older construction are never read.
CACHE_VERSION = 16


def polygrid_key(mesh: Mesh, kind: str = "polygrid", **params: Any) -> str:
    """Hex digest of the grid kind, the mesh's arrays and the build parameters."""
    return cache.digest(f"{kind} v{CACHE_VERSION}", np.asarray(mesh.vertices, dtype=np.float64),
                        np.asarray(mesh.faces, dtype=np.int64), sorted(params.items()))


def _cached(kind: str, build: Any, cls: type, mesh: Mesh, params: dict[str, Any]) -> tuple[Any, bool]:
    key = polygrid_key(mesh, kind, **params)
    grid = cache.load(kind, key, cls)
    if grid is not None:
        return grid, True
    grid = build(mesh, **params)
    cache.store(kind, key, grid)
    return grid, False


def cached_polygrid(mesh: Mesh, **params: Any) -> tuple[Polygrid, bool]:
    """:func:`~glsldiff.grids.polygrid.build_polygrid` ``(mesh, **params)`` through the cache;
    returns the polygrid and whether it came from the cache."""
    return _cached("polygrid", build_polygrid, Polygrid, mesh, params)


def cached_fem_grid(mesh: Mesh, **params: Any) -> tuple[FemGrid, bool]:
    """:func:`~glsldiff.grids.fem_grid.build_fem_grid` ``(mesh, **params)`` through the cache."""
    return _cached("femgrid", build_fem_grid, FemGrid, mesh, params)
