"""Compiled loops: numba kernels, imported and compiled on their first call.

``@kernel`` (or ``@kernel(parallel=True)`` for loops over ``numba.prange``) wraps a plain
Python function written in numba's subset. Importing the module that defines it costs nothing;
the first call imports numba (about 0.2-0.4 s) and loads the machine code from numba's on-disk
cache (``cache=True``: ``__pycache__`` beside the source, or ``NUMBA_CACHE_DIR``), compiling it
once per machine and signature (seconds). Arithmetic is plain IEEE float64 (no fastmath), so a
kernel gives what the numpy code it replaces gives, up to the order of sums.

``GLSLDIFF_JIT=0`` runs the same functions as interpreted Python (for debugging; slow).
"""
from __future__ import annotations

import functools
import os
import types
from typing import Any, Callable, TypeVar, overload

__all__ = ["kernel", "prange"]

F = TypeVar("F", bound=Callable[..., Any])


def _enabled() -> bool:
    return os.environ.get("GLSLDIFF_JIT", "1") != "0"


def prange(*args: int) -> range:
    """``numba.prange`` inside a parallel kernel (numba replaces it); ``range`` when interpreted."""
    return range(*args)


def _names(code: types.CodeType) -> set[str]:
    """Global names a function's code (and the code nested in it) reads."""
    out = set(code.co_names)
    for c in code.co_consts:
        if isinstance(c, types.CodeType):
            out |= _names(c)
    return out


def _compiled(fn: Callable[..., Any], parallel: bool, inline: bool, suffix: str = "") -> Callable[..., Any]:
    """``fn`` compiled by numba (``fn`` itself with ``GLSLDIFF_JIT=0``); ``suffix`` on its
    qualified name keeps a variant's on-disk cache apart (numba keys the cache by name and
    bytecode, not by its ``parallel`` flag)."""
    if not _enabled():
        return fn
    import numba
    # OpenMP where it loads, else numba's own queue; not TBB (the installed one may be too
    # old, which numba reports as a warning on every run)
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]
    # the kernel sees numba's prange and the compiled form of the kernels it calls
    env = dict(fn.__globals__)
    for name in _names(fn.__code__):
        if hasattr(env.get(name), "_compile"):
            env[name] = env[name]._compile()
    env["prange"] = numba.prange
    body = types.FunctionType(fn.__code__, env, fn.__name__, fn.__defaults__, fn.__closure__)
    body.__qualname__, body.__module__ = fn.__qualname__ + suffix, fn.__module__
    return numba.njit(cache=True, nogil=True, parallel=parallel, inline="always" if inline else "never")(body)


def _wrap(fn: F, parallel: bool, inline: bool) -> F:
    compiled: dict[bool, Callable[..., Any]] = {}

    def compile_(threads: bool = parallel) -> Callable[..., Any]:
        if threads not in compiled:
            compiled[threads] = _compiled(fn, threads, inline, "" if threads == parallel else "_serial")
        return compiled[threads]

    @functools.wraps(fn)
    def call(*args: Any) -> Any:
        return (compiled.get(parallel) or compile_())(*args)

    call._compile = compile_  # type: ignore[attr-defined]
    call.py_func = fn  # type: ignore[attr-defined]
    if parallel:
        # the same loops on the calling thread (``prange`` as ``range``): for a few items, where
        # starting the threads costs more than the work
        call.serial = lambda *args: (compiled.get(False) or compile_(False))(*args)  # type: ignore[attr-defined]
    return call  # type: ignore[return-value]


@overload
def kernel(fn: F) -> F: ...
@overload
def kernel(*, parallel: bool = False, inline: bool = False) -> Callable[[F], F]: ...


def kernel(fn: Any = None, *, parallel: bool = False, inline: bool = False) -> Any:
    """Decorator: ``fn`` compiled with numba on its first call (module docstring); a parallel
    kernel's ``.serial`` runs the same loops on one thread. ``inline``:
    a helper written into the kernels that call it (numba's ``inline="always"``), for helpers
    that take arrays: a call passing an array counts a reference atomically, which the threads of
    a parallel kernel contend for."""
    if fn is not None:
        return _wrap(fn, parallel, inline)
    return lambda f: _wrap(f, parallel, inline)
