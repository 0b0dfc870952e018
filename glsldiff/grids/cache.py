"""On-disk cache of built polygrids: the polycube search, mapping and weights of a mesh take
tens of seconds (13 s for the default bunny), the same every run.

Entries are keyed by the mesh's vertex and face bytes, the build parameters and
:data:`CACHE_VERSION` (bump it when the construction changes). The folder is
``$GLSLDIFF_CACHE``, else ``$XDG_CACHE_HOME/glsldiff``, else ``~/.cache/glsldiff``;
``GLSLDIFF_CACHE=off`` turns the cache off. Entries are Python pickles written by this
module into the user's own cache folder; a file that does not load is rebuilt and replaced.
"""
from __future__ import annotations

import hashlib
import logging
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from glsldiff.core.io import atomic_path
from glsldiff.grids.polygrid import Polygrid, build_polygrid
from glsldiff.mesh import Mesh

log = logging.getLogger(__name__)

#: Part of every key: entries of an older construction are never read.
CACHE_VERSION = 1


def cache_dir() -> Path | None:
    """The cache folder, or ``None`` when ``GLSLDIFF_CACHE=off``."""
    env = os.environ.get("GLSLDIFF_CACHE", "").strip()
    if env.lower() in ("off", "0", "no", "false"):
        return None
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "glsldiff"


def polygrid_key(mesh: Mesh, **params: Any) -> str:
    """Hex digest of the mesh's arrays and the build parameters."""
    h = hashlib.sha256()
    h.update(f"polygrid v{CACHE_VERSION}".encode())
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    h.update(repr(sorted(params.items())).encode())
    return h.hexdigest()[:32]


def cached_polygrid(mesh: Mesh, **params: Any) -> tuple[Polygrid, bool]:
    """:func:`~glsldiff.grids.polygrid.build_polygrid` ``(mesh, **params)`` through the cache;
    returns the polygrid and whether it came from the cache."""
    folder = cache_dir()
    path = None if folder is None else folder / f"polygrid-{polygrid_key(mesh, **params)}.pkl"
    if path is not None and path.is_file():
        try:
            with open(path, "rb") as f:
                pg = pickle.load(f)
            if isinstance(pg, Polygrid):
                return pg, True
        except Exception as exc:  # a damaged or foreign entry: rebuild it
            log.warning("polygrid cache entry %s unreadable (%s): rebuilding it", path, exc)
    pg = build_polygrid(mesh, **params)
    if path is not None:
        try:
            with atomic_path(path) as tmp, open(tmp, "wb") as f:
                pickle.dump(pg, f, protocol=pickle.HIGHEST_PROTOCOL)
        except OSError as exc:  # a read-only or full cache folder costs speed, not the render
            log.warning("polygrid cache %s not written (%s)", path, exc)
    return pg, False
