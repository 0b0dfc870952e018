"""Chandrasekhar's H-function: exact light transport in a homogeneous half-space with
isotropic scattering and an index-matched boundary (Chandrasekhar 1960, "Radiative Transfer",
chapter IV), the reference the incidence split of :mod:`glsldiff.physics.exitance` follows.

For single-scattering albedo ``a`` (here the reduced one, ``sigma_s' / sigma_t'``), ``H(mu)``
solves ``H(mu) = 1 + (a / 2) mu H(mu) int_0^1 H(mu') / (mu + mu') dmu'``. With it:

* the radiance reflected towards the cosine ``mu`` per unit irradiance arriving at cosine
  ``mu0`` is ``a H(mu) H(mu0) / (4 pi (mu + mu0))`` (all orders of scattering);
* the total reflectance of light arriving at ``mu0`` is ``1 - H(mu0) sqrt(1 - a)``;
* the light reaching the diffusive depth (the amplitude of the deep field, and so what
  diffuses away from where it entered) is proportional to ``H(mu0)``: ``H(1) / <H>`` = 1.26
  times more at normal incidence than for diffuse light at albedo 1, against 1 for the
  Marshak source. The 1-D transport oracle (:mod:`glsldiff.oracle.slab_transport`) shows the
  same: a 20 mm slab transmits 1.26x more of normally incident light than of diffuse light.

The functions interpolate a table computed once and kept in the on-disk cache (albedo on a
grid uniform in ``sqrt(1 - a)``, 129 x 129 values, bilinear): accurate to about 1e-4.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core import cache

__all__ = ["d_function", "h_function", "h_mean", "reflected_share"]

_N_ALBEDO = 129
_N_MU = 129


def _solve_h(a: float, nodes: NDArray[np.float64], weights: NDArray[np.float64]) -> NDArray[np.float64]:
    """H at the Gauss ``nodes`` for albedo ``a``: fixed-point iteration of the standard form
    ``H(mu) = 1 / (1 - (a / 2) mu int_0^1 H(mu') / (mu + mu') dmu')`` (it converges for every
    ``a <= 1``, slowly at 1: 2e-4 short of H(1) = 2.9078 there)."""
    H = np.ones_like(nodes)
    kernel = weights[None, :] / (nodes[:, None] + nodes[None, :])
    for _ in range(20000):
        new = 1.0 / (1.0 - 0.5 * a * nodes * (kernel @ H))
        done = np.max(np.abs(new - H)) < 1e-13
        H = new
        if done:
            break
    return H


def _h_at(a: float, nodes: NDArray[np.float64], weights: NDArray[np.float64], H: NDArray[np.float64],
          mu_out: NDArray[np.float64]) -> NDArray[np.float64]:
    """H at ``mu_out`` from its values ``H`` at the Gauss ``nodes`` (the equation of
    :func:`_solve_h` evaluated there)."""
    out_kernel = weights[None, :] / (mu_out[:, None] + nodes[None, :])
    return 1.0 / (1.0 - 0.5 * a * mu_out * (out_kernel @ H))


#: Part of the cached tables' key: bump it when the tables' method changes.
TABLES_CACHE_VERSION = 1


@lru_cache(maxsize=1)
def _tables() -> tuple[NDArray[np.float64], ...]:
    """``(u, mu, H, D, M)``: ``u = sqrt(1 - a)`` and ``mu`` grids, ``H[u, mu]``,
    ``D[u, mu] = 2 int_0^1 t H(t) / (mu + t) dt`` and ``M[u] = <H>``; from the on-disk cache
    (:mod:`glsldiff.core.cache`) once computed (0.25 s)."""
    key = cache.digest(f"h-function tables v{TABLES_CACHE_VERSION}", _N_ALBEDO, _N_MU)
    return cache.memo("hfunction", key, tuple, _build_tables)


def _build_tables() -> tuple[NDArray[np.float64], ...]:
    """:func:`_tables` computed."""
    x, w = np.polynomial.legendre.leggauss(96)
    nodes, weights = 0.5 * (x + 1.0), 0.5 * w
    u = np.linspace(0.0, 1.0, _N_ALBEDO)
    mu = np.linspace(0.0, 1.0, _N_MU)
    H = np.empty((_N_ALBEDO, _N_MU))
    D = np.empty((_N_ALBEDO, _N_MU))
    M = np.empty(_N_ALBEDO)
    for i, ui in enumerate(u):
        a = 1.0 - ui * ui
        Hg = _solve_h(a, nodes, weights)       # one fixed point per albedo, evaluated at both grids
        H[i] = _h_at(a, nodes, weights, Hg, mu)
        Hn = _h_at(a, nodes, weights, Hg, nodes)
        D[i] = 2.0 * ((weights * nodes * Hn)[None, :] / (mu[:, None] + nodes[None, :])).sum(axis=1)
        M[i] = 2.0 * float((weights * nodes * Hn).sum())
    return u, mu, H, D, M


def _bilinear(table: NDArray[np.float64], albedo: ArrayLike, mu: ArrayLike) -> NDArray[np.float64]:
    u_grid, mu_grid = _tables()[:2]
    a = np.clip(np.asarray(albedo, dtype=np.float64), 0.0, 1.0)
    m = np.clip(np.asarray(mu, dtype=np.float64), 0.0, 1.0)
    a, m = np.broadcast_arrays(a, m)
    fu = np.sqrt(1.0 - a) * (len(u_grid) - 1)
    fm = m * (len(mu_grid) - 1)
    i = np.clip(np.floor(fu).astype(np.int64), 0, len(u_grid) - 2)
    j = np.clip(np.floor(fm).astype(np.int64), 0, len(mu_grid) - 2)
    du, dm = fu - i, fm - j
    return ((1 - du) * (1 - dm) * table[i, j] + du * (1 - dm) * table[i + 1, j]
            + (1 - du) * dm * table[i, j + 1] + du * dm * table[i + 1, j + 1])


def h_function(albedo: ArrayLike, mu: ArrayLike) -> NDArray[np.float64]:
    """``H(mu)`` for the (reduced) single-scattering albedo ``albedo`` (broadcast)."""
    return _bilinear(_tables()[2], albedo, mu)


def h_mean(albedo: ArrayLike) -> NDArray[np.float64]:
    """``<H> = 2 int_0^1 H(mu) mu dmu``, the mean of ``H`` over diffuse (cosine-weighted) light."""
    u_grid, _, _, _, M = _tables()
    return np.interp(np.sqrt(1.0 - np.clip(np.asarray(albedo, dtype=np.float64), 0.0, 1.0)), u_grid, M)


def d_function(albedo: ArrayLike, mu: ArrayLike) -> NDArray[np.float64]:
    """``D(mu) = 2 int_0^1 t H(t) / (mu + t) dt``: what diffuse light of unit irradiance reflects
    towards ``mu``, over ``a H(mu) / (4 pi)``."""
    return _bilinear(_tables()[3], albedo, mu)


def reflected_share(albedo: ArrayLike, mu0: ArrayLike, mu: ArrayLike) -> NDArray[np.float64]:
    """The half-space's reflected radiance towards ``mu`` for light arriving at ``mu0``, as a
    share of what diffuse light of the same irradiance gives towards ``mu``:
    ``H(mu0) / ((mu + mu0) D(mu))`` with ``D(mu) = 2 int_0^1 t H(t) / (mu + t) dt``
    (1 on average over diffuse light, for every ``mu``)."""
    H0 = h_function(albedo, mu0)
    return H0 / ((np.asarray(mu, dtype=np.float64) + np.asarray(mu0, dtype=np.float64)) * d_function(albedo, mu))
