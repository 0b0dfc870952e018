"""Irradiance from rectangular area lights, as beams (no GL; lengths in mm).

An :class:`~glsldiff.physics.lights.AreaLight` of radiance L is cut into ``samples`` x
``samples`` sub-rectangles k. At a point p with outward normal n, sub-rectangle k delivers the
irradiance ``L G_k`` with the form factor integral

    G_k = integral over k of cos_r cos_e / r^2 dA     (sr; pi for a hemisphere filled by it)

computed exactly by Lambert's polygon formula ``G = 1/2 sum_j theta_j (n . gamma_j)`` (theta_j
the angle the j-th edge subtends at p, gamma_j the unit normal of the plane through p and that
edge) for p on the emitting side, each sub-rectangle first clipped to the half-space above p's
tangent plane. Each sub-rectangle is one *beam*: transmitted irradiance ``E_k = L G_k
F_t(eta, cos_k)`` arriving at the refracted cosine ``t_k = sqrt(1 - (1 - cos_k^2) / eta^2)``,
``cos_k`` the cosine of the sub-rectangle's vector irradiance (``1/2 sum_j theta_j gamma_j``,
the cosine-weighted mean direction of arrival: normal incidence for a point just above a
sub-rectangle, where the direction of its centre would be grazing), which the first-collision volume source
(:mod:`glsldiff.physics.collision`) attenuates along. As the sub-rectangles shrink the sum
converges to the exact Fresnel-weighted integral; the form factors are exact at any size, so
the plain irradiance (``eta=None``) is exact for an unoccluded rectangle. A sub-rectangle that
fills a wide solid angle (a light touching the surface) takes ``F_t`` and ``t`` averaged over
the directions it fills instead (:func:`area_beams`).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core import checks
from glsldiff.physics.lights import AreaLight
from glsldiff.physics.optics import fresnel_transmittance, refracted_cosine

__all__ = ["sub_rectangles", "form_factors", "area_beams", "solid_angles"]

#: Sub-rectangles of a form factor above this (sr) at a point get their Fresnel factor averaged over
#: the directions they fill (:func:`area_beams`) ...
WIDE_FORM_FACTOR = 0.05
#: ... on this many cosine-weighted directions about the normal, where at least MIN_HITS of them
#: hit the sub-rectangle (the mean direction's factor is right for narrower ones).
FRESNEL_DIRECTIONS = 1024
MIN_HITS = 16
#: Beyond this many sub-rectangle diagonals, :func:`solid_angles` takes a sub-rectangle as a point.
FAR_DIAGONALS = 4.0
#: Points handled at once (memory: points x sub-rectangles x 4 corners x 3 floats).
_CHUNK = 4096


def sub_rectangles(light: AreaLight) -> NDArray[np.float64]:
    """``(K, 4, 3)`` corners of the ``samples^2`` sub-rectangles, mm."""
    m = light.samples
    right, up, _ = light.frame
    w, h = light.size
    c0 = np.asarray(light.position) - 0.5 * w * right - 0.5 * h * up
    i, j = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")
    i, j = i.ravel()[:, None], j.ravel()[:, None]
    du, dv = w / m * right, h / m * up
    return np.stack([c0 + i * du + j * dv, c0 + i * du + (j + 1) * dv,
                     c0 + (i + 1) * du + (j + 1) * dv, c0 + (i + 1) * du + j * dv], axis=1)


def _clipped_lambert(d: NDArray[np.float64], n: NDArray[np.float64]
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Lambert's formula for quads ``d`` (N, K, 4, 3) relative to the points, clipped to the
    half-space above each point's tangent plane (normal ``n`` (N, 3)) by Sutherland-Hodgman:
    edge c emits its start corner if above and the crossing point if it crosses, into 8 slots;
    an empty slot repeats the previous vertex (a zero-length edge adds nothing). Returns the
    form factor ``G`` (N, K) and the cosine to ``n`` of the vector irradiance (the
    cosine-weighted mean direction of arrival)."""
    h = np.einsum("nkcj,nj->nkc", d, n)
    h1, d1 = np.roll(h, -1, axis=2), np.roll(d, -1, axis=2)
    f = (h / np.where(h != h1, h - h1, 1.0))[..., None]
    slots = np.stack([d, d + f * (d1 - d)], axis=3).reshape(d.shape[:2] + (8, 3))
    valid = np.stack([h > 0.0, (h > 0.0) != (h1 > 0.0)], axis=3).reshape(d.shape[:2] + (8,))
    idx = np.where(valid, np.arange(8), -1)
    last = np.maximum.accumulate(idx, axis=2)
    last = np.where(last < 0, idx.max(axis=2, keepdims=True), last).clip(0)   # wrap: the last valid vertex
    v = np.take_along_axis(slots, last[..., None], axis=2)
    a = v / np.linalg.norm(v, axis=-1, keepdims=True).clip(1e-300)
    b = np.roll(a, -1, axis=2)
    cross = np.cross(a, b)
    norm = np.linalg.norm(cross, axis=-1)
    theta = np.arctan2(norm, np.einsum("nkcj,nkcj->nkc", a, b))
    gamma = cross / norm[..., None].clip(1e-300)
    vec = 0.5 * np.einsum("nkc,nkcj->nkj", theta, gamma)          # the vector irradiance per unit radiance
    g = np.abs(np.einsum("nkj,nj->nk", vec, n))
    lit = valid.any(axis=2)
    cos = np.where(lit, g / np.linalg.norm(vec, axis=-1).clip(1e-300), 0.0)
    return np.where(lit, g, 0.0), np.clip(cos, 0.0, 1.0)


def form_factors(light: AreaLight, points: ArrayLike, normals: ArrayLike
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(N, K)`` form-factor integrals ``G_k`` (sr) of the sub-rectangles at ``points`` (N, 3)
    with unit ``normals`` (module docstring; 0 behind the light, exact for any size) and the
    cosines ``(N, K)`` of their mean directions of arrival."""
    p = checks.points(points)
    n = checks.unit_rows(normals, "normals", len(p))
    corners = sub_rectangles(light)
    fwd = np.asarray(light.direction)
    out, cos = np.zeros((2, len(p), len(corners)))
    for s in range(0, len(p), _CHUNK):
        pp, nn = p[s:s + _CHUNK], n[s:s + _CHUNK]
        front = ((pp - np.asarray(light.position)) @ fwd) > 0.0
        g, c = _clipped_lambert(corners[None] - pp[:, None, None, :], nn)
        out[s:s + _CHUNK] = np.where(front[:, None], g, 0.0)
        cos[s:s + _CHUNK] = np.where(front[:, None], c, 0.0)
    return out, cos


def _disk_directions(count: int) -> NDArray[np.float64]:
    """``(count, 3)`` directions about +z, cosine-weighted (a Fibonacci spiral on the unit disk
    lifted to the hemisphere): each stands for the same share of a Lambertian irradiance."""
    k = np.arange(count) + 0.5
    r = np.sqrt(k / count)
    phi = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.clip(1.0 - r * r, 0.0, 1.0))], axis=1)


def _fresnel_over_rectangle(corners: NDArray[np.float64], p: NDArray[np.float64], n: NDArray[np.float64],
                            eta: float) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Over the directions of :func:`_disk_directions` about each point's normal that hit its
    sub-rectangle (``corners`` (M, 4, 3), points ``p``, normals ``n`` (M, 3)): the mean of
    ``F_t(eta, cos)`` and of the refracted cosine weighted by it, and the number of hits."""
    D = _disk_directions(FRESNEL_DIRECTIONS)
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    u = np.cross(n, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(n, u)
    w = D[None, :, 0:1] * u[:, None] + D[None, :, 1:2] * v[:, None] + D[None, :, 2:3] * n[:, None]   # (M, D, 3)
    c0 = corners[:, 0]
    e1, e2 = corners[:, 1] - c0, corners[:, 3] - c0
    plane = np.cross(e1, e2)
    denom = np.einsum("mdj,mj->md", w, plane)
    s = np.einsum("mj,mj->m", c0 - p, plane)[:, None] / np.where(np.abs(denom) > 1e-300, denom, np.inf)
    x = p[:, None] + s[..., None] * w - c0[:, None]                                                    # on the plane
    g11, g12, g22 = (np.einsum("mj,mj->m", a, b)[:, None] for a, b in ((e1, e1), (e1, e2), (e2, e2)))
    b1, b2 = np.einsum("mdj,mj->md", x, e1), np.einsum("mdj,mj->md", x, e2)
    det = g11 * g22 - g12 * g12
    a_, b_ = (g22 * b1 - g12 * b2) / det, (g11 * b2 - g12 * b1) / det
    hit = (s > 0) & (a_ >= 0) & (a_ <= 1) & (b_ >= 0) & (b_ <= 1)
    cos = D[:, 2][None, :]
    ft = np.asarray(fresnel_transmittance(eta, np.broadcast_to(cos, hit.shape)))
    count = hit.sum(axis=1)
    f_sum = np.where(hit, ft, 0.0).sum(axis=1)
    t_sum = np.where(hit, ft * refracted_cosine(eta, cos), 0.0).sum(axis=1)
    mean_f = np.where(count > 0, f_sum / np.maximum(count, 1), 0.0)
    mean_t = np.where(f_sum > 0, t_sum / np.maximum(f_sum, 1e-300), 0.0)
    return mean_f, mean_t, count


def area_beams(light: AreaLight, points: ArrayLike, normals: ArrayLike, eta: float | None
               ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(scale (N, K), t (N, K))``: beam k's transmitted irradiance is ``scale[:, k] *
    light.radiance`` (``F_t`` folded in unless ``eta`` is None) and ``t`` its refracted cosine.

    ``F_t`` is taken at each sub-rectangle's mean direction of arrival, except where the
    sub-rectangle fills a wide solid angle (form factor above :data:`WIDE_FORM_FACTOR`: a light
    close to or touching the surface): there it is averaged over the directions it fills, each
    weighted by its cosine (:data:`FRESNEL_DIRECTIONS` directions; a Lambertian light touching
    the surface then crosses with the hemispherical average of ``F_t``, 0.939 at eta = 1.3, not
    with ``F_t`` at normal incidence, 0.983), and ``t`` is the ``F_t``-weighted mean refracted
    cosine of those directions."""
    p = checks.points(points)
    n = checks.unit_rows(normals, "normals", len(p))
    g, c = form_factors(light, p, n)
    if eta is None:
        return g, refracted_cosine(eta, c)
    ft = np.where(c > 0.0, np.asarray(fresnel_transmittance(eta, c)), 0.0)
    t = refracted_cosine(eta, c)
    wide_p, wide_k = np.nonzero(g > WIDE_FORM_FACTOR)
    if wide_p.size:
        corners = sub_rectangles(light)
        for s in range(0, wide_p.size, _CHUNK // 8):
            ip, ik = wide_p[s:s + _CHUNK // 8], wide_k[s:s + _CHUNK // 8]
            mf, mt, count = _fresnel_over_rectangle(corners[ik], p[ip], n[ip], float(eta))
            ok = count >= MIN_HITS
            ft[ip[ok], ik[ok]], t[ip[ok], ik[ok]] = mf[ok], mt[ok]
    return g * ft, t


def solid_angles(light: AreaLight, index: ArrayLike, points: ArrayLike) -> NDArray[np.float64]:
    """Solid angle (sr, (N,)) that sub-rectangle ``index[i]`` (of :func:`sub_rectangles`)
    subtends at ``points[i]``, 0 behind the light's emitting side: exact (Van Oosterom and
    Strackee's formula on its two triangles) nearer than ``FAR_DIAGONALS`` diagonals, else
    the point-source form ``A cos_e / r^2`` (within 1.1 % there). A Lambertian rectangle of
    radiance L delivers the normal irradiance ``L Omega`` along a narrow beam."""
    p = checks.points(points)
    k = np.asarray(index, dtype=np.int64)
    corners = sub_rectangles(light)
    fwd = np.asarray(light.direction)
    area = light.size[0] * light.size[1] / light.samples**2
    diag = float(np.hypot(*light.size)) / light.samples
    d = corners[k].mean(axis=1) - p
    r = np.linalg.norm(d, axis=1).clip(1e-300)
    cos_e = -(d @ fwd) / r
    out = np.where(cos_e > 0, area * cos_e / r**2, 0.0)
    near = np.flatnonzero((r < FAR_DIAGONALS * diag) & (cos_e > 0))
    if near.size:
        q = corners[k[near]] - p[near, None, :]                                 # (M, 4, 3)
        total = np.zeros(near.size)
        for a, b, c in ((0, 1, 2), (0, 2, 3)):
            A, B, C = q[:, a], q[:, b], q[:, c]
            la, lb, lc = (np.linalg.norm(v, axis=1) for v in (A, B, C))
            num = np.abs(np.einsum("ij,ij->i", A, np.cross(B, C)))
            den = (la * lb * lc + np.einsum("ij,ij->i", A, B) * lc + np.einsum("ij,ij->i", A, C) * lb
                   + np.einsum("ij,ij->i", B, C) * la)
            total += 2.0 * np.arctan2(num, den)
        out[near] = total
    return out
