"""Input checks shared by every layer: each returns the value in canonical form or raises
:class:`~glsldiff.core.errors.InputError` with one line naming the input and what it must be.

Lengths are in mm and coefficients in mm^-1 wherever a caller says so in ``name``/``unit``.
"""
from __future__ import annotations

import math
import numbers
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError

__all__ = ["real", "integer", "boolean", "vector3", "unit_vector", "rgb", "finite_array", "points",
           "unit_rows", "radiance_map", "choice", "finite_values", "require"]


def real(value: Any, name: str, lo: float = -math.inf, hi: float = math.inf, lo_open: bool = False,
         hi_open: bool = False) -> float:
    """A finite real number in ``[lo, hi]`` (``(`` / ``)`` with ``lo_open`` / ``hi_open``)."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    x = float(value) if ok else float("nan")
    if not math.isfinite(x) or (x <= lo if lo_open else x < lo) or (x >= hi if hi_open else x > hi):
        rng = (f"{'(' if lo_open or lo == -math.inf else '['}{lo:g}, "
               f"{hi:g}{')' if hi_open or hi == math.inf else ']'}")
        raise InputError(f"{name} must be a number in {rng}, got {value!r}")
    return x


def integer(value: Any, name: str, lo: int, hi: int) -> int:
    """An integer (not a bool) in ``[lo, hi]``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise InputError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return int(value)


def boolean(value: Any, name: str) -> bool:
    """True/False (or 1/0)."""
    if not (isinstance(value, (bool, np.bool_)) or (isinstance(value, (int, np.integer)) and value in (0, 1))):
        raise InputError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def vector3(value: Any, name: str) -> NDArray[np.float64]:
    """Three finite numbers as a ``(3,)`` float64 array."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be 3 finite numbers, got {value!r}") from None
    if a.shape != (3,) or not np.isfinite(a).all():
        raise InputError(f"{name} must be 3 finite numbers, got {value!r}")
    return a


def unit_vector(value: Any, name: str) -> tuple[float, float, float]:
    """A non-zero direction, normalised."""
    a = vector3(value, name)
    n = float(np.linalg.norm(a))
    if not n > 1e-12:
        raise InputError(f"{name} must be a non-zero direction vector, got {value!r}")
    return tuple(float(x) for x in a / n)  # type: ignore[return-value]


def rgb(value: Any, name: str, unit: str = "") -> tuple[float, float, float]:
    """Three finite non-negative numbers (a scalar is repeated for R, G, B)."""
    what = f"3 finite non-negative numbers (RGB{', ' + unit if unit else ''})"
    try:
        a = np.asarray(value, dtype=np.float64)
        if a.ndim == 0 or a.shape == (1,):
            a = np.repeat(a.reshape(()), 3)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be {what}, got {value!r}") from None
    if a.shape != (3,) or not np.isfinite(a).all() or (a < 0).any():
        raise InputError(f"{name} must be {what}, got {value!r}")
    return tuple(float(x) for x in a)  # type: ignore[return-value]


def finite_array(value: Any, name: str, shape_tail: tuple[int, ...] | None = None) -> NDArray[np.float64]:
    """A finite float64 array; with ``shape_tail``, of shape ``(n,) + shape_tail`` (an empty
    1-D input becomes ``(0,) + shape_tail``)."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric array, got {type(value).__name__}") from None
    if shape_tail is not None:
        if a.ndim == 1 and a.size == 0:
            a = a.reshape((0,) + shape_tail)
        if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail:
            want = "(N, " + ", ".join(map(str, shape_tail)) + ")"
            raise InputError(f"{name} must have shape {want}, got {a.shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        raise InputError(f"{name} has {int(bad.sum())} non-finite values (NaN/inf); pass finite numbers")
    return a


def points(value: ArrayLike, name: str = "points") -> NDArray[np.float64]:
    """Finite positions (mm) as an ``(N, 3)`` array; an empty input gives ``(0, 3)``."""
    return finite_array(value, name, (3,))


def unit_rows(value: ArrayLike, name: str, n: int | None = None) -> NDArray[np.float64]:
    """``(N, 3)`` directions, one per point when ``n`` is given, normalised row by row."""
    a = points(value, name)
    if n is not None and len(a) != n:
        raise InputError(f"{name} must have one row per point: {len(a)} rows for {n} points")
    length = np.linalg.norm(a, axis=1)
    if (length < 1e-12).any():
        raise InputError(f"{name} has {int((length < 1e-12).sum())} zero-length rows; pass unit vectors")
    return a / length[:, None]


def radiance_map(image: Any, name: str) -> NDArray[np.float64]:
    """A float64 copy of an ``(H, W, 3)`` radiance map, finite and >= 0."""
    try:
        img = np.array(image, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric (H, W, 3) array") from None
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise InputError(f"{name} must have shape (H, W, 3), got {img.shape}")
    if not np.isfinite(img).all():
        raise InputError(f"{name} has {int((~np.isfinite(img)).sum())} non-finite values (NaN/inf); "
                         "radiance must be finite")
    if (img < 0).any():
        raise InputError(f"{name} has {int((img < 0).sum())} negative values (min {img.min():g}); "
                         "radiance must be >= 0")
    return img


def choice(value: Any, name: str, options: Sequence[Any]) -> Any:
    """One of ``options`` (returned as given)."""
    if value not in options:
        raise InputError(f"{name}={value!r}; choose one of {tuple(options)}")
    return value


def _where(bad: NDArray[np.bool_]) -> str:
    """' at e.g. index (i, j)' for the first True entry of ``bad`` ('' for 0-d arrays)."""
    return f" at e.g. index {tuple(int(i) for i in np.argwhere(bad)[0])}" if bad.ndim else ""


def finite_values(value: ArrayLike, name: str) -> NDArray[np.float64]:
    """A number or array of any shape as float64, every entry finite; the error counts the
    NaN and inf entries and gives the index of the first."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numeric (a number or an array of numbers): {exc}") from None
    bad = ~np.isfinite(a)
    if bad.any():
        counts = [(int(np.isnan(a).sum()), "NaN"), (int(np.isinf(a).sum()), "inf")]
        what = " and ".join(f"{n} {kind}" for n, kind in counts if n)
        raise InputError(f"{name} has {what} value(s){_where(bad)}; replace them with finite numbers")
    return a


def require(a: NDArray[np.float64], bad: NDArray[np.bool_], name: str, rule: str, fix: str) -> None:
    """Entry-wise rule on an array: raise "``name`` must be ``rule``" with the count, an
    example value and its index, and ``fix``, if any entry of the mask ``bad`` is set."""
    if bad.any():
        raise InputError(f"{name} must be {rule} but has {int(bad.sum())} value(s) violating it "
                         f"(e.g. {a[bad].flat[0]:g}){_where(bad)}; {fix}")
