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

__all__ = ["ExternalBeam", "collided_halfspace", "combine", "diffusion_weight", "external_beams", "gather_share",
           "gathered_halfspace", "local_multiple", "local_single", "marshak_halfspace", "outside_cosine"]

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


def combine(M: ArrayLike, X: ArrayLike, X_loc: ArrayLike, c_far: ArrayLike, w: ArrayLike = 0.0) -> Array:
    """``L_ms`` of the module docstring from the exact local ``M``, the model's ``X`` and its
    half-space value ``X_loc`` (all >= 0) and the far field's radiance per unit ``X``, ``c_far``;
    broadcast. ``w`` in [0, 1] (:func:`diffusion_weight`): how far the diffusion's own
    sensitivity ``c_far`` is trusted for a departure from the half-space (a deficit scales ``M``
    by ``(X / X_loc)^k``, ``k = 1 + w (c_far X_loc / M - 1)``, which has that slope and stays >= 0;
    an excess is converted at ``w c_far + (1 - w)`` times the ``w = 0`` rate). Never negative for
    non-negative inputs; ``M`` where ``X = X_loc``."""
    M, X, Xl, c, w = (np.asarray(v, dtype=np.float64) for v in (M, X, X_loc, c_far, w))
    X = np.maximum(X, 0.0)
    tiny = 1e-300
    sens = np.where(Xl > 0, M / np.maximum(Xl, tiny), 0.0)
    k = 1.0 + w * np.maximum(np.where(M > 0, c * Xl / np.maximum(M, tiny), 1.0) - 1.0, 0.0)
    below = M * np.where(Xl > 0, np.minimum(X / np.maximum(Xl, tiny), 1.0), 0.0) ** k
    excess = np.maximum(X - Xl, 0.0)
    f = np.where(X > 0, np.minimum(Xl / np.maximum(X, tiny), 1.0), 0.0)
    return below + excess * (w * c + (1.0 - w) * (f * sens + (1.0 - f) * c))


def diffusion_weight(M: ArrayLike, single: ArrayLike, B_loc: ArrayLike) -> Array:
    """How far the Marshak diffusion's own sensitivity to its fluence is trusted (``w`` of
    :func:`combine`): as far as the diffusion reproduces the half-space, ``B_loc / (M + single)``
    clipped to [0, 1] (``B_loc`` its P1 radiance of the local half-space: 1.0 at albedo 0.995, 0.8
    at 0.9, 0 below 2/3, where it is negative).

    Why: where the grid holds less fluence than the half-space (a convex edge, a shadow's border)
    or more (light from elsewhere, curvature), the P1 exitance changes by ``c_far dX`` at fixed
    source; at albedo 0.995 that is 3x the relative change ``M dX / X_loc``, and Monte Carlo
    follows it: the finite 60 mm slab of ``glsldiff validate`` darkens towards its edges only
    with it (mean 1.052 -> 1.009)."""
    M, S, B = (np.asarray(v, dtype=np.float64) for v in (M, single, B_loc))
    exact = M + S
    return np.clip(np.where(exact > 0, B / np.maximum(exact, 1e-300), 0.0), 0.0, 1.0)


#: The gather far field's blend (transport mean free paths from the nearest lit surface point):
#: nearer than the first value the gathered collided fluence, farther than the second the deep
#: field's exitance of the same fluence, linearly between (:func:`gather_share`).
GATHER_DISTANCE = (2.0, 6.0)


def gather_share(distance_mfp: ArrayLike | None, shape: tuple[int, ...]) -> Array:
    """The share of the gathered collided fluence in the gather far field, per point and channel,
    from the point's distance to the nearest lit surface point in transport mean free paths: 1 up
    to :data:`GATHER_DISTANCE` [0], 0 from [1] on (None: 1 everywhere).

    Both estimate what the first-collision diffusion sends out. The gather (the collided fluence
    scattered once more along the view ray) is exact where the fluence is; but within a mean free
    path of the exit face the diffusion's fluence has the wrong shape (the Milne boundary layer),
    and the gather weights that layer most; where the light comes from far away, the deep
    field's exitance (the Robin condition's flux, spread over the exit angles of light that
    crossed the point's distance to the lit surface, :meth:`HalfspaceTables.escape`) uses only
    the field's asymptotic form. Measured against Monte Carlo on 20 x 20 mm slabs back-lit by a
    touching 5 mm patch (eta 1.3, albedo 0.99; relative L2 / power / peak): 2 mean free paths
    thick, gather 0.037 / 0.94 / 1.00, the deep field 0.040 / 1.03 / 1.02 (0.092 / 1.09 / 1.08
    with a deep field's exit angles at every distance); 4 thick, gather 0.084 / 1.02 / 1.09, deep
    field 0.053 / 1.03 / 0.97; 8 thick, gather 0.089 / 1.06 / 1.11 (too peaked), deep field
    0.049 / 1.02 / 0.96. On a front-lit sphere (lit points and those near its terminator: near
    the light) the gather is the better one: relative RMSE 0.082 against 0.12."""
    if distance_mfp is None:
        return np.ones(shape)
    lo, hi = GATHER_DISTANCE
    d = np.asarray(distance_mfp, dtype=np.float64)
    return np.broadcast_to(np.clip((hi - d) / (hi - lo), 0.0, 1.0), shape)


def collided_halfspace(beams_t: Sequence[tuple[ArrayLike, ArrayLike]], kappa: ArrayLike, mu: ArrayLike,
                       C: float) -> Array:
    """The collided fluence at the surface of a homogeneous half-space lit by ``beams_t``
    (transmitted irradiance ``E``, refracted cosine ``t``) by the first-collision diffusion with
    the Robin condition ``phi - 2 C kappa phi' = 0``: ``sum_k 2 C sigma_s E_k / ((t_k s +
    sigma_t) (1 + 2 C kappa s))``, ``s = sqrt(mu / kappa)`` (kappa mm, mu mm^-1, ``(N, 3)``)."""
    k = np.asarray(kappa, dtype=np.float64)
    m = np.asarray(mu, dtype=np.float64)
    st = 1.0 / (3.0 * k)
    ss = np.maximum(st - m, 0.0)
    s = np.sqrt(np.maximum(m / k, 0.0))
    out = np.zeros_like(k)
    for E, t in beams_t:
        tt = np.asarray(t, dtype=np.float64)[:, None]
        out += np.where(tt > 1e-6, 2.0 * C * ss * np.asarray(E, dtype=np.float64)
                        / ((tt * s + st) * (1.0 + 2.0 * C * k * s)), 0.0)
    return out
