"""The on-disk cache folder and its entries: results that take seconds to recompute and are
the same every run (built polygrids, converged pass-2 solutions, a grid's P1 geometric factors
and render-mesh interpolation, the half-space tables).

The folder is ``$GLSLDIFF_CACHE``, else ``$XDG_CACHE_HOME/glsldiff``, else
``~/.cache/glsldiff``; ``GLSLDIFF_CACHE=off`` turns the cache off. Entries are Python pickles
written by this module into the user's own cache folder, named by a digest of everything
they depend on; a file that does not load is ignored (and rebuilt by the caller), and a
folder that cannot be written costs speed, never the result.
"""
from __future__ import annotations

import hashlib
import logging
import os
import pickle
from pathlib import Path
from typing import Any, Callable, TypeVar

import numpy as np

from glsldiff.core.io import atomic_path

log = logging.getLogger(__name__)

T = TypeVar("T")


def cache_dir() -> Path | None:
    """The cache folder, or ``None`` when ``GLSLDIFF_CACHE=off``."""
    env = os.environ.get("GLSLDIFF_CACHE", "").strip()
    if env.lower() in ("off", "0", "no", "false"):
        return None
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "glsldiff"


def digest(*parts: Any) -> str:
    """Hex digest of ``parts``: numpy arrays by dtype, shape and bytes, anything else by
    ``repr`` (which must then be deterministic: numbers, strings, tuples, sorted items)."""
    h = hashlib.sha256()
    for p in parts:
        if isinstance(p, np.ndarray):
            a = np.ascontiguousarray(p)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        else:
            h.update(repr(p).encode())
        h.update(b"\0")
    return h.hexdigest()[:32]


def entry_path(kind: str, key: str) -> Path | None:
    """Where the ``kind`` entry with ``key`` lives, or ``None`` with the cache off."""
    folder = cache_dir()
    return None if folder is None else folder / f"{kind}-{key}.pkl"


def load(kind: str, key: str, expect: type | tuple[type, ...]) -> Any | None:
    """The cached ``kind`` entry for ``key`` if it exists, loads and is an ``expect``; else None."""
    path = entry_path(kind, key)
    if path is None or not path.is_file():
        return None
    try:
        with open(path, "rb") as f:
            value = pickle.load(f)
    except Exception as exc:  # a damaged or foreign entry: the caller recomputes it
        log.warning("cache entry %s unreadable (%s): recomputing it", path, exc)
        return None
    return value if isinstance(value, expect) else None


def store(kind: str, key: str, value: Any) -> None:
    """Write ``value`` as the ``kind`` entry for ``key`` (atomically; failures only logged)."""
    path = entry_path(kind, key)
    if path is None:
        return
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)
    except OSError as exc:
        log.warning("cache %s not written (%s)", path, exc)


def memo(kind: str, key: str, expect: type | tuple[type, ...], compute: Callable[[], T]) -> T:
    """The cached ``kind`` entry for ``key``; else ``compute()``, stored under it."""
    value = load(kind, key, expect)
    if value is None:
        value = compute()
        store(kind, key, value)
    return value
