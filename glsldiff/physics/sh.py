"""Spherical harmonics of environment light, and directions on the sphere.

Real orthonormal spherical harmonics up to band ``order`` (``(order + 1)^2`` coefficients, 9
for order 2), indexed ``k = l (l + 1) + m``. A lat-long radiance map is projected with each
pixel taken as constant radiance over its exact solid angle (:func:`sh_project`; map convention
in :func:`latlong_directions`).

Irradiance (Funk-Hecke): the kernel h(t) = t^+ F_t(eta, t) depends only on t = n . w, so

    E_sh(n) = sum_lm lambda_l c_lm Y_lm(n),   lambda_l = 2 pi int_0^1 t F_t(eta, t) P_l(t) dt,

with lambda_l computed by adaptive quadrature (:func:`transfer_coefficients`) and F_t = 1 -
Fresnel reflectance (:func:`glsldiff.physics.optics.fresnel_transmittance`, eta = n_inside /
n_outside). The Fresnel factor is therefore included *exactly* in the kernel; the only
approximation is the band limit of the radiance (the classic irradiance-map error, a few
percent for order 2 on natural maps, more for a small bright sun in the map, which belongs in
a directional light; exact for maps that are themselves band limited; negative ringing is
clipped to 0). With eta = 1 the lambdas are pi, 2 pi / 3, pi / 4 (Ramamoorthi and Hanrahan
2001).

Units: directions are unit vectors; radiance in the caller's units, irradiance in radiance
times sr.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.polynomial import legendre
from numpy.typing import ArrayLike, NDArray
from scipy import integrate

from glsldiff.core.checks import integer, radiance_map, real
from glsldiff.core.errors import InputError
from glsldiff.physics.optics import fresnel_transmittance

__all__ = ["sh_basis", "sh_project", "sh_evaluate", "sh_irradiance", "transfer_coefficients",
           "latlong_directions", "fibonacci_directions", "MAX_SH_ORDER", "MAX_DIRECTIONS"]

MAX_SH_ORDER = 8
MAX_DIRECTIONS = 4096


def _sh_norm(order: int) -> NDArray[np.float64]:
    """Normalisation sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!) indexed [l, m], m >= 0."""
    out = np.zeros((order + 1, order + 1))
    for l in range(order + 1):
        for m in range(l + 1):
            out[l, m] = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - m) / math.factorial(l + m))
    return out


def _legendre(order: int, z: NDArray[np.float64]) -> NDArray[np.float64]:
    """Associated Legendre P_l^m(z), m >= 0, without the Condon-Shortley phase: ``[l, m, ...]``."""
    z = np.asarray(z, dtype=np.float64)
    s = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    P = np.zeros((order + 1, order + 1) + z.shape)
    P[0, 0] = 1.0
    for m in range(order + 1):
        if m > 0:
            P[m, m] = (2 * m - 1) * s * P[m - 1, m - 1]
        if m + 1 <= order:
            P[m + 1, m] = (2 * m + 1) * z * P[m, m]
        for l in range(m + 2, order + 1):
            P[l, m] = ((2 * l - 1) * z * P[l - 1, m] - (l + m - 1) * P[l - 2, m]) / (l - m)
    return P


def _azimuthal(order: int, phi: NDArray[np.float64]) -> NDArray[np.float64]:
    """``[order + m, ...]``: sqrt2 cos(m phi) for m > 0, 1 for m = 0, sqrt2 sin(|m| phi) for m < 0."""
    phi = np.asarray(phi, dtype=np.float64)
    T = np.empty((2 * order + 1,) + phi.shape)
    for m in range(-order, order + 1):
        if m > 0:
            T[order + m] = math.sqrt(2.0) * np.cos(m * phi)
        elif m < 0:
            T[order + m] = math.sqrt(2.0) * np.sin(-m * phi)
        else:
            T[order] = 1.0
    return T


def _check_order(order: Any) -> int:
    return integer(order, "order", 0, MAX_SH_ORDER)


def sh_basis(directions: ArrayLike, order: int = 2) -> NDArray[np.float64]:
    """Real orthonormal SH ``(N, (order + 1)^2)`` at unit ``directions`` (N, 3).

    Index ``k = l (l + 1) + m``; ``Y_1,-1, Y_10, Y_11`` are ``sqrt(3 / 4 pi) (y, z, x)``.
    """
    order = _check_order(order)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    P = _legendre(order, d[:, 2])
    T = _azimuthal(order, np.arctan2(d[:, 1], d[:, 0]))
    K = _sh_norm(order)
    out = np.empty((len(d), (order + 1) ** 2))
    for l in range(order + 1):
        for m in range(-l, l + 1):
            out[:, l * (l + 1) + m] = K[l, abs(m)] * P[l, abs(m)] * T[order + m]
    return out


def latlong_directions(height: int, width: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit directions ``(H, W, 3)`` of lat-long pixel centres and their solid angles ``(H, W)``
    (exact per pixel: ``(cos theta_top - cos theta_bottom) * 2 pi / W``; they sum to 4 pi).

    Map convention: row 0 is the zenith (+z), row H - 1 the nadir; column u = 0 is azimuth
    -pi and azimuth grows with u (u = 0.5 is +x, u = 0.75 is +y).
    """
    theta_edges = np.linspace(0.0, math.pi, height + 1)
    theta = 0.5 * (theta_edges[:-1] + theta_edges[1:])
    phi = -math.pi + (np.arange(width) + 0.5) * (2.0 * math.pi / width)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    d = np.stack([st * np.cos(phi)[None], st * np.sin(phi)[None], np.broadcast_to(ct, (height, width))], -1)
    band = np.cos(theta_edges[:-1]) - np.cos(theta_edges[1:])
    return d, np.repeat(band[:, None] * (2.0 * math.pi / width), width, axis=1)


def latlong_lookup(image: ArrayLike, directions: ArrayLike) -> NDArray[np.float64]:
    """The pixels ``(N, C)`` of a lat-long map ``(H, W, C)`` (convention of
    :func:`latlong_directions`) that unit ``directions`` (N, 3) fall in (nearest pixel)."""
    img = np.asarray(image, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    h, w = img.shape[:2]
    theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    phi = np.arctan2(d[:, 1], d[:, 0])
    row = np.clip((theta / math.pi * h).astype(np.int64), 0, h - 1)
    col = np.floor((phi + math.pi) / (2.0 * math.pi) * w).astype(np.int64) % w
    return img[row, col]


def sh_project(image: ArrayLike, order: int = 2) -> NDArray[np.float64]:
    """SH coefficients ``((order + 1)^2, 3)`` of a lat-long radiance map ``(H, W, 3)``.

    Each pixel is taken as constant radiance over its solid angle and the basis is integrated
    over the pixel (exactly in azimuth, 8-point Gauss-Legendre in polar angle), so a constant
    map projects onto band 0 alone to rounding (see :func:`latlong_directions` for the map
    convention). Separable in rows and columns: memory stays O(H W) for large maps.
    """
    order = _check_order(order)
    img = radiance_map(image, "image")
    H, W, _ = img.shape
    # pixels are taken as constant over their area; the basis is integrated over each pixel:
    # exactly in azimuth, by 8-point Gauss-Legendre in polar angle (weight sin theta) per row
    phi_edges = -math.pi + np.arange(W + 1) * (2.0 * math.pi / W)
    T = np.empty((2 * order + 1, W))
    T[order] = np.diff(phi_edges)
    for m in range(1, order + 1):
        T[order + m] = math.sqrt(2.0) * np.diff(np.sin(m * phi_edges)) / m
        T[order - m] = -math.sqrt(2.0) * np.diff(np.cos(m * phi_edges)) / m
    F = np.einsum("hwc,mw->hmc", img, T)                                  # (H, 2o+1, 3)
    gx, gw = np.polynomial.legendre.leggauss(8)
    edges = np.linspace(0.0, math.pi, H + 1)
    half = 0.5 * np.diff(edges)
    theta = (edges[:-1] + half)[:, None] + half[:, None] * gx[None, :]   # (H, 8)
    wt = half[:, None] * gw[None, :] * np.sin(theta)                     # (H, 8)
    P = _legendre(order, np.cos(theta))                                   # (o+1, o+1, H, 8)
    K = _sh_norm(order)
    out = np.empty(((order + 1) ** 2, 3))
    for l in range(order + 1):
        for m in range(-l, l + 1):
            w = K[l, abs(m)] * (P[l, abs(m)] * wt).sum(axis=1)            # (H,)
            out[l * (l + 1) + m] = w @ F[:, order + m]
    return out


def _order_of(coeffs: NDArray[np.float64]) -> int:
    k = coeffs.shape[0]
    order = int(round(math.sqrt(k))) - 1
    if (order + 1) ** 2 != k or order > MAX_SH_ORDER:
        raise InputError(f"coeffs must have (order + 1)^2 rows (1, 4, 9, ...), got {k}")
    return order


def _coeffs(coeffs: ArrayLike) -> NDArray[np.float64]:
    c = np.asarray(coeffs, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3 or not np.isfinite(c).all():
        raise InputError(f"coeffs must be a finite ((order + 1)^2, 3) array, got shape {c.shape}")
    return c


def sh_evaluate(coeffs: ArrayLike, directions: ArrayLike) -> NDArray[np.float64]:
    """Band-limited radiance ``(N, 3)`` of SH ``coeffs`` in unit ``directions`` (N, 3)."""
    c = _coeffs(coeffs)
    return sh_basis(directions, _order_of(c)) @ c


@lru_cache(maxsize=64)
def _transfer(order: int, eta: float | None) -> tuple[float, ...]:
    out = []
    for l in range(order + 1):
        Pl = legendre.Legendre.basis(l)
        if eta is None or eta == 1.0:
            f = lambda t, Pl=Pl: t * Pl(t)  # noqa: E731
        else:
            f = lambda t, Pl=Pl: t * float(fresnel_transmittance(eta, min(max(t, 0.0), 1.0))) * Pl(t)  # noqa: E731
        pts = None
        if eta is not None and eta < 1.0:  # total internal reflection beyond the critical angle
            pts = [math.sqrt(max(0.0, 1.0 - eta * eta))]
        val = integrate.quad(f, 0.0, 1.0, points=pts, epsabs=1e-13, epsrel=1e-11, limit=200)[0]
        out.append(2.0 * math.pi * val)
    return tuple(out)


def transfer_coefficients(order: int = 2, eta: float | None = None) -> NDArray[np.float64]:
    """Funk-Hecke eigenvalues ``lambda_l = 2 pi int_0^1 t F_t(eta, t) P_l(t) dt``, l = 0..order.

    ``eta=None`` (or 1) drops the Fresnel factor: pi, 2 pi / 3, pi / 4, 0, -pi / 24, ...
    """
    order = _check_order(order)
    if eta is not None:
        eta = real(eta, "eta", 0.0, math.inf, lo_open=True, hi_open=True)
    return np.asarray(_transfer(order, eta))


def sh_irradiance(coeffs: ArrayLike, normals: ArrayLike, eta: float | None = None) -> NDArray[np.float64]:
    """Unshadowed irradiance ``(N, 3)`` on surfaces with unit ``normals`` (N, 3) under SH radiance.

    ``eta=None``: plain irradiance int L (n.w)^+ dw; with ``eta``: the transmitted irradiance
    int L (n.w)^+ F_t(eta, n.w) dw (Fresnel factor folded exactly into the zonal kernel).
    Negative values from SH ringing are clipped to 0.
    """
    c = _coeffs(coeffs)
    order = _order_of(c)
    lam = transfer_coefficients(order, eta)
    lam_k = np.concatenate([np.full(2 * l + 1, lam[l]) for l in range(order + 1)])
    return np.maximum(sh_basis(normals, order) @ (lam_k[:, None] * c), 0.0)


def fibonacci_directions(n: int) -> NDArray[np.float64]:
    """``n`` nearly uniformly spread unit directions ``(n, 3)`` (Fibonacci sphere), 1 to
    ``MAX_DIRECTIONS``."""
    n = integer(n, "directions", 1, MAX_DIRECTIONS)
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    s = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)
