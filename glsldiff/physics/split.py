r"""The transport split: the exitant radiance of a lit translucent object as exact local
transport plus the diffusion's far field, right at every albedo and never negative.

Why: the P1 exitance of classical diffusion (:mod:`glsldiff.physics.exitance`, ``B = a phi - b
q``) is a difference of two terms; below an albedo of 2/3 it is negative on every lit surface
(the homogeneous half-space's ``B`` is ``q (a / (1 + 2 C sqrt(kappa mu)) - b)``), and between
0.7 and 0.95 it is 20-60 % too dark against Monte Carlo. What it gets right is the far field:
light that travelled several mean free paths from where it entered.

The split (``[options].model = "split"``, :mod:`glsldiff.render.renderer`), per surface point,
channel and view (outside cosine ``nu_o``), for beams ``k`` of external irradiance ``E_k``
arriving at outside cosine ``nu_k``:

* unscattered light (:mod:`glsldiff.render.unscattered`) and single scattering (exact: the
  half-space's closed form :func:`local_single`, or the 3-D march of
  :mod:`glsldiff.render.single`);
* the light scattered two or more times, ``L_ms``, from two estimates that are both >= 0:
  ``M = sum_k E_k R_ms(nu_k, nu_o)``, the exact multiple scattering of a homogeneous
  half-space of the point's albedo lit as the point is (:mod:`glsldiff.physics.adding_doubling`,
  smooth Fresnel boundary, every albedo), and the diffusion model's value ``X`` at the point
  with ``X_loc``, what that same model gives on that half-space. Then (:func:`combine`)

  .. math::

      L_{ms} = M \min(1, X / X_{loc}) + (X - X_{loc})^+ \,[f\,M / X_{loc} + (1 - f)\,c],
      \qquad f = X_{loc} / X,

  ``c`` the far field's radiance per unit ``X``. Where the point is lit like a half-space
  (``X = X_loc``) this is the exact ``M``; where the grid holds less (a shadow's edge, a convex
  edge, a thin part lit from one side) ``M`` is scaled down with it; light from elsewhere (the
  excess) is converted like the local light while it is a small part, like the far field
  where it dominates; unlit points get ``c X``. The two diffusion models of the renderer:

  - ``"gather"`` (the first-collision volume source; grids that resolve the mean free path):
    ``X`` is the collided fluence gathered along the refracted view ray,
    ``F_t(nu_o) / eta^2 int sigma_s phi_c / (4 pi) e^{-tau} ds`` (light scattered at least
    twice: exact where ``phi_c`` is), ``X_loc`` its closed form for a half-space
    (:func:`gathered_halfspace`), ``c = 1``. In 1-D against adding-doubling (albedo 0.5-0.99,
    normal light): 0.92-0.96 of the exact multiple scattering below a lit half-space, 0.83-1.06
    of what crosses slabs of 2-16 mean free paths.
  - ``"surface"`` (the Marshak surface source, any grid): ``X`` is the fluence at the surface
    node, ``X_loc = q / (1 + 2 C sqrt(kappa mu))`` (:func:`marshak_halfspace`), ``c = a
    P(nu_o) / (2 C)``: the outgoing flux ``phi / (2 C)`` of the Robin condition, spread over
    the exit angles as a deep diffusive field leaves a half-space (``P``, adding-doubling), times
    the albedo ``a`` (the share of the entering light that scatters at all: the Marshak source
    counts all of it).

Every term is >= 0 when ``X`` is; at albedo 0 all of them are 0.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.physics.adding_doubling import HalfspaceTables
from glsldiff.physics.optics import fresnel_transmittance

__all__ = ["ExternalBeam", "combine", "external_beams", "gathered_halfspace", "local_multiple", "local_single",
           "marshak_halfspace", "outside_cosine"]

Array = NDArray[np.float64]
#: A beam at the surface: external irradiance ``(N, 3)`` and outside cosine ``(N,)``.
ExternalBeam = tuple[Array, Array]


def outside_cosine(eta: float, t: ArrayLike) -> Array:
    """The outside cosine of a direction that refracts to inside cosine ``t`` (Snell; 0 for
    ``t`` inside the total-internal-reflection band)."""
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    return np.sqrt(np.clip(1.0 - eta * eta * (1.0 - t * t), 0.0, 1.0))


def external_beams(beams: Sequence[tuple[ArrayLike, ArrayLike]], eta: float) -> list[ExternalBeam]:
    """Pass 1's beams (transmitted irradiance, refracted cosine) as external ones: ``E / F_t(nu)``
    at the outside cosine ``nu``."""
    out = []
    for E, t in beams:
        nu = outside_cosine(eta, t)
        ft = np.asarray(fresnel_transmittance(eta, nu), dtype=np.float64)
        out.append((np.asarray(E, dtype=np.float64) / np.maximum(ft, 1e-12)[:, None], nu))
    return out


def local_multiple(tables: HalfspaceTables, albedo: ArrayLike, beams: Sequence[ExternalBeam],
                   nu_o: ArrayLike) -> Array:
    """``M = sum_k E_k R_ms(nu_k, nu_o)`` ``(N, 3)``: the exact radiance scattered two or more times
    that a half-space of ``albedo`` ``(N, 3)`` sends towards outside cosine ``nu_o`` ``(N,)``."""
    a = np.asarray(albedo, dtype=np.float64)
    out = np.zeros_like(a)
    no = np.asarray(nu_o, dtype=np.float64)[:, None]
    for E, nu in beams:
        out += E * tables.multiple(a, np.asarray(nu)[:, None], no)
    return out


def local_single(eta: float, albedo: ArrayLike, beams: Sequence[ExternalBeam], nu_o: ArrayLike) -> Array:
    """Single scattering of a half-space, ``sum_k E_k F_t(nu_k) F_t(nu_o) a / (4 pi eta^2 (t_k +
    t_o))`` ``(N, 3)`` (:mod:`glsldiff.physics.single`'s transport model, isotropic phase; ``t``
    the refracted cosines)."""
    a = np.asarray(albedo, dtype=np.float64)
    no = np.clip(np.asarray(nu_o, dtype=np.float64), 0.0, 1.0)
    t_o = np.sqrt(np.clip(1.0 - (1.0 - no * no) / (eta * eta), 0.0, 1.0))[:, None]
    f_o = np.asarray(fresnel_transmittance(eta, no), dtype=np.float64)[:, None] * (no > 0)[:, None]
    out = np.zeros_like(a)
    for E, nu in beams:
        nu = np.clip(np.asarray(nu, dtype=np.float64), 0.0, 1.0)
        t = np.sqrt(np.clip(1.0 - (1.0 - nu * nu) / (eta * eta), 0.0, 1.0))[:, None]
        ft = np.asarray(fresnel_transmittance(eta, nu), dtype=np.float64)[:, None] * (nu > 0)[:, None]
        out += E * ft * f_o * a / (4.0 * math.pi * eta * eta * np.maximum(t + t_o, 1e-12))
    return out


def marshak_halfspace(q: ArrayLike, kappa: ArrayLike, mu: ArrayLike, C: float) -> Array:
    """The Marshak model's fluence at the surface of a half-space with source ``q``:
    ``q / (1 + 2 C sqrt(kappa mu))`` (kappa mm, mu mm^-1)."""
    k, m = np.asarray(kappa, dtype=np.float64), np.asarray(mu, dtype=np.float64)
    return np.asarray(q, dtype=np.float64) / (1.0 + 2.0 * C * np.sqrt(np.maximum(k * m, 0.0)))


def gathered_halfspace(beams_t: Sequence[tuple[ArrayLike, ArrayLike]], kappa: ArrayLike, mu: ArrayLike,
                       t_o: ArrayLike, f_o: ArrayLike, eta: float, C: float) -> Array:
    r"""``X_loc`` of the gather model ``(N, 3)``: the collided fluence of a homogeneous half-space
    lit by ``beams_t`` (transmitted irradiance ``E``, refracted cosine ``t``), by the diffusion
    with the first-collision source and the Robin condition ``phi - 2 C kappa phi' = 0``, gathered
    towards the inside view cosine ``t_o`` ``(N,)`` with the exit factor ``f_o = F_t / eta^2``
    ``(N,)``. Per beam, with ``beta = sigma_t / t``, ``lam = sigma_t / t_o``, ``s = sqrt(mu /
    kappa)``:

    .. math:: \frac{\sigma_s^2 E}{4\pi t_o t\,\kappa}\,
              \frac{1 + 2C\kappa(s + \beta + \lambda)}{(s + \beta)(\beta + \lambda)(s + \lambda)(1 + 2C\kappa s)}

    (``phi_c = A e^{-beta z} + B e^{-s z}`` integrated against ``e^{-lam z}``; no singularity at
    ``s = beta``)."""
    k = np.asarray(kappa, dtype=np.float64)
    m = np.asarray(mu, dtype=np.float64)
    st = 1.0 / (3.0 * k)
    ss = np.maximum(st - m, 0.0)
    s = np.sqrt(np.maximum(m / k, 0.0))
    to = np.maximum(np.asarray(t_o, dtype=np.float64), 1e-6)[:, None]
    lam = st / to
    out = np.zeros_like(k)
    for E, t in beams_t:
        tt = np.asarray(t, dtype=np.float64)[:, None]
        ok = tt > 1e-6
        ts = np.where(ok, tt, 1.0)
        beta = st / ts
        g = ss * ss * np.asarray(E, dtype=np.float64) / (4.0 * math.pi * to * ts * k) * \
            (1.0 + 2.0 * C * k * (s + beta + lam)) / ((s + beta) * (beta + lam) * (s + lam) * (1.0 + 2.0 * C * k * s))
        out += np.where(ok, g, 0.0)
    return out * np.asarray(f_o, dtype=np.float64)[:, None]


def combine(M: ArrayLike, X: ArrayLike, X_loc: ArrayLike, c_far: ArrayLike) -> Array:
    """``L_ms`` of the module docstring from the exact local ``M``, the model's ``X`` and its
    half-space value ``X_loc`` (all >= 0) and the far field's radiance per unit ``X``, ``c_far``;
    broadcast. Never negative for non-negative inputs; ``M`` where ``X = X_loc``."""
    M, X, Xl, c = (np.asarray(v, dtype=np.float64) for v in (M, X, X_loc, c_far))
    X = np.maximum(X, 0.0)
    tiny = 1e-300
    below = M * np.where(Xl > 0, np.minimum(X / np.maximum(Xl, tiny), 1.0), 0.0)
    excess = np.maximum(X - Xl, 0.0)
    f = np.where(X > 0, np.minimum(Xl / np.maximum(X, tiny), 1.0), 0.0)
    sens = np.where(Xl > 0, M / np.maximum(Xl, tiny), 0.0)
    return below + excess * (f * sens + (1.0 - f) * c)
