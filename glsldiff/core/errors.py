"""Exceptions raised by glsldiff.

Every error a user can cause (bad input, a missing GL backend, a solver that
diverged) is a :class:`GlsldiffError`, so callers and the CLI can catch one type.
"""
from __future__ import annotations


class GlsldiffError(Exception):
    """Base class of all glsldiff errors; the message names the field and the fix."""


class InputError(GlsldiffError, ValueError):
    """An input array or parameter is malformed (shape, NaN, sign, range)."""


class BackendError(GlsldiffError, RuntimeError):
    """No usable OpenGL context (EGL or OSMesa) could be created."""


class SolverError(GlsldiffError, RuntimeError):
    """A solver produced a non-finite result or could not run."""
