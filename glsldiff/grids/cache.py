"""Built polygrids and tetrahedral (pillowed) grids through the on-disk cache (:mod:`glsldiff.core.cache`): the polycube
search, mapping and weights of a mesh take tens of seconds (13 s for the default bunny), the
same every run.

Entries are keyed by the mesh's vertex and face bytes, the build parameters and
:data:`CACHE_VERSION` (bump it when the construction changes).
"""
from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from glsldiff.core import cache
from glsldiff.grids.tetrahedral.adapt import AdaptReport, SourceFunction, refine_for_source
from glsldiff.grids.tetrahedral.fem_grid import FemGrid, build_fem_grid
from glsldiff.grids.polygrid import Polygrid, build_polygrid
from glsldiff.mesh import Mesh

#: Part of every key: entries of an older construction are never read.
CACHE_VERSION = 20   # 20: the shape step again after the split; 19: the other repaired polycubes mapped in turn (18: harmonic map on one BLAS thread)


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
    """:func:`~glsldiff.grids.tetrahedral.fem_grid.build_fem_grid` ``(mesh, **params)`` through the cache."""
    return _cached("femgrid", build_fem_grid, FemGrid, mesh, params)


def cached_refined_grid(grid: FemGrid, grid_key: str, source: SourceFunction, **params: Any
                        ) -> tuple[FemGrid, AdaptReport, bool]:
    """:func:`~glsldiff.grids.tetrahedral.adapt.refine_for_source` ``(grid, source, **params)`` through the
    cache: keyed by ``grid_key`` (the unrefined grid's, :func:`polygrid_key`), the parameters
    and the source at the grid's surface nodes (the lights' footprint: a scene whose lights do
    not change reads the refined grid back; one entry per light set, the size of the grid's);
    returns the grid, the refinement's report and whether it came from the cache."""
    t0 = time.perf_counter()
    q0 = np.asarray(source(grid.boundary_positions, grid.normals), dtype=np.float64)
    key = cache.digest(f"adapt v{CACHE_VERSION}", grid_key, q0, sorted(params.items()))
    hit = cache.load("adapt", key, tuple)
    if hit is not None and len(hit) == 2 and isinstance(hit[0], FemGrid) and isinstance(hit[1], AdaptReport):
        return hit[0], replace(hit[1], seconds=time.perf_counter() - t0), True   # its seconds: this read's
    pending = [q0]

    def reuse(P: np.ndarray, N: np.ndarray) -> np.ndarray:   # its first call asks for the same nodes
        return pending.pop() if pending else source(P, N)
    refined, rep = refine_for_source(grid, reuse, **params)
    cache.store("adapt", key, (refined, rep))
    return refined, rep, False
