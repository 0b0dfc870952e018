"""Special functions of the sphere series (:mod:`glsldiff.oracle.sphere_series`): large-n
Gauss-Legendre rules and modified spherical Bessel functions of the first kind in a form that
does not overflow (ratios ``t_l`` and logarithms ``log G_l``; see that module's docstring)."""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

from glsldiff.core import checks

__all__ = ["gauss_legendre", "bessel_ratio_t", "log_bessel_g", "log_sinhc"]


def _legendre_and_derivative(n: int, x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``P_n(x)`` and ``P_n'(x)`` by the three-term recurrence (|x| < 1)."""
    p0, p1 = np.ones_like(x), x.copy()
    for j in range(1, n):
        p0, p1 = p1, ((2 * j + 1) * x * p1 - j * p0) / (j + 1)
    return p1, n * (p0 - x * p1) / (1.0 - x * x)


@lru_cache(maxsize=24)
def _gauss_legendre_cached(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    if n <= 64:
        x, w = special.roots_legendre(n)
        return np.asarray(x, dtype=np.float64), np.asarray(w, dtype=np.float64)
    # non-negative half of the nodes (symmetry), Tricomi's initial guess, Newton on the recurrence
    k = np.arange(1, n // 2 + 1, dtype=np.float64)
    x = (1.0 - (n - 1.0) / (8.0 * n ** 3)) * np.cos(math.pi * (4.0 * k - 1.0) / (4.0 * n + 2.0))
    for it in range(12):
        p1, dp = _legendre_and_derivative(n, x)
        dx = p1 / dp
        x = x - dx
        if np.abs(dx).max() < 1e-15 and it >= 1:
            break
    _, dp = _legendre_and_derivative(n, x)
    w = 2.0 / ((1.0 - x * x) * dp * dp)
    if n % 2:
        xs = np.concatenate([-x, [0.0], x[::-1]])
        p0, p1 = np.ones(1), np.zeros(1)        # P_{n-1}(0) for the middle node's weight
        for j in range(1, n - 1):
            p0, p1 = p1, -j * p0 / (j + 1)
        w0 = 2.0 / (n * p1[0]) ** 2
        ws = np.concatenate([w, [w0], w[::-1]])
    else:
        xs = np.concatenate([-x, x[::-1]])
        ws = np.concatenate([w, w[::-1]])
    return xs, ws


def gauss_legendre(n: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``n``-point Gauss-Legendre nodes (ascending) and weights on [-1, 1], accurate to rounding
    for large n (Newton-refined; cached). Read-only arrays."""
    n = checks.integer(n, "n", 1, 1 << 20)
    x, w = _gauss_legendre_cached(n)
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w


def bessel_ratio_t(x: ArrayLike, l_max: int) -> NDArray[np.float64]:
    """``t_l(x) = (2l+3) i_{l+1}(x) / (x i_l(x))`` for l = 0..l_max, shape ``x.shape + (l_max+1,)``.

    In (0, 1]; 1 at x = 0. Backward recurrence from well above ``max(l_max, 2 x)``.
    """
    xa = np.asarray(x, dtype=np.float64)
    xf = xa.ravel()
    T = np.empty((xf.size, l_max + 1))
    if xf.size == 0:
        return T.reshape(xa.shape + (l_max + 1,))
    x2 = xf * xf
    top = max(l_max, int(math.ceil(2.0 * float(xf.max())))) + 64
    t = np.ones_like(xf)
    for l in range(top, -1, -1):
        t = 1.0 / (1.0 + x2 * t / ((2 * l + 3) * (2 * l + 5)))
        if l <= l_max:
            T[:, l] = t
    return T.reshape(xa.shape + (l_max + 1,))


def log_sinhc(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """log(sinh x / x) for x >= 0, without overflow."""
    out = np.zeros_like(x)
    big = x > 1.0
    xb = x[big]
    out[big] = xb - np.log(2.0 * xb) + np.log1p(-np.exp(-2.0 * xb))
    xs = x[~big]
    with np.errstate(invalid="ignore", divide="ignore"):
        v = np.where(xs > 0.0, np.sinh(xs) / np.where(xs > 0.0, xs, 1.0), 1.0)
    out[~big] = np.log(v)
    return out


def log_bessel_g(x: ArrayLike, l_max: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(log G_l(x), t_l(x))`` for l = 0..l_max, ``G_l(x) = (2l+1)!! i_l(x) / x^l`` (>= 1).

    ``i_l(x) = x^l / (2l+1)!! * exp(log G_l(x))``; shapes ``x.shape + (l_max+1,)``.
    """
    xa = np.asarray(x, dtype=np.float64)
    T = bessel_ratio_t(xa, l_max)
    logG = np.empty_like(T)
    logG[..., 0] = log_sinhc(xa)
    if l_max > 0:
        logG[..., 1:] = logG[..., :1] + np.cumsum(np.log(T[..., :-1]), axis=-1)
    return logG, T
