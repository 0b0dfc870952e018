"""Built polygrids through the on-disk cache (:mod:`glsldiff.core.cache`): the polycube
search, mapping and weights of a mesh take tens of seconds (13 s for the default bunny), the
same every run.

Entries are keyed by the mesh's vertex and face bytes, the build parameters and
:data:`CACHE_VERSION` (bump it when the construction changes).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from glsldiff.core import cache
from glsldiff.grids.polygrid import Polygrid, build_polygrid
from glsldiff.mesh import Mesh

#: Part of every key: entries of an older construction are never read.
CACHE_VERSION = 1


def polygrid_key(mesh: Mesh, **params: Any) -> str:
    """Hex digest of the mesh's arrays and the build parameters."""
    return cache.digest(f"polygrid v{CACHE_VERSION}", np.asarray(mesh.vertices, dtype=np.float64),
                        np.asarray(mesh.faces, dtype=np.int64), sorted(params.items()))


def cached_polygrid(mesh: Mesh, **params: Any) -> tuple[Polygrid, bool]:
    """:func:`~glsldiff.grids.polygrid.build_polygrid` ``(mesh, **params)`` through the cache;
    returns the polygrid and whether it came from the cache."""
    key = polygrid_key(mesh, **params)
    pg = cache.load("polygrid", key, Polygrid)
    if pg is not None:
        return pg, True
    pg = build_polygrid(mesh, **params)
    cache.store("polygrid", key, pg)
    return pg, False
