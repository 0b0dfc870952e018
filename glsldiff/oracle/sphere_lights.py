"""The sphere series (:mod:`glsldiff.oracle.sphere_series`) for the renderer's lights:
directional, point, spot and projector lights on a homogeneous sphere, with the transmitted
irradiance pass 1 computes (:func:`glsldiff.physics.lights.incidence`) turned into the
boundary source by :func:`glsldiff.physics.exitance.source_from_irradiance`."""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize

from glsldiff.core import checks
from glsldiff.core.errors import InputError
from glsldiff.oracle.sphere_series import QOfCos, QOfDirs, SphereSeries, _frame
from glsldiff.physics.exitance import EXITANT, source_from_irradiance
from glsldiff.physics.lights import (DirectionalLight, PointLight, ProjectorLight, SpotLight, check_light,
                                     incidence, to_light)
from glsldiff.physics.optics import boundary_constant, transmitted_cosine

__all__ = ["sphere_directional", "sphere_point_light", "sphere_spot", "sphere_from_light", "light_source_function"]

def _medium(radius: float, kappa: float, mu: float, eta: float, C: float | None,
            centre: ArrayLike) -> SphereSeries:
    eta = checks.real(eta, "eta", 0.0, math.inf, lo_open=True, hi_open=True)
    return SphereSeries(radius, kappa, mu, float(boundary_constant(eta)) if C is None else C, centre)


def light_source_function(light: Any, radius: float, eta: float, centre: ArrayLike = (0.0, 0.0, 0.0),
                          channel: int = 0, convention: str = "p1") -> QOfDirs:
    """``q(n)`` on the sphere for a directional, point, spot or projector light (one RGB
    ``channel``): ``E_t = F_t(eta, cos_i) cos_i^+`` times the light's unshadowed irradiance
    (:func:`glsldiff.physics.lights.incidence`), as pass 1 computes it; ``cos_i`` between the
    normal and the direction to the light. Positional lights must lie outside the sphere."""
    check_light(light, "light")
    R = checks.real(radius, "radius", 0.0, math.inf, lo_open=True, hi_open=True)
    c = checks.vector3(centre, "centre")
    ch = checks.integer(channel, "channel", 0, 2)
    checks.choice(convention, "convention", EXITANT)
    if not isinstance(light, DirectionalLight):
        if not isinstance(light, (PointLight, SpotLight, ProjectorLight)):
            raise InputError("light must be a directional, point, spot or projector light")
        if np.linalg.norm(np.asarray(light.position) - c) <= R * (1.0 + 1e-12):
            raise InputError("the light must lie outside the sphere")

    def q(n: NDArray[np.float64]) -> NDArray[np.float64]:
        n = np.asarray(n, dtype=np.float64).reshape(-1, 3)
        p = c + R * n
        w = to_light(light, p)
        scale, colour = incidence(light, p, transmitted_cosine(eta, (n * w).sum(axis=1)))   # as pass 1
        col = colour[..., ch]
        return source_from_irradiance(scale * col, eta, convention)
    return q


def _axial(q_of_dirs: QOfDirs, axis: NDArray[np.float64]) -> QOfCos:
    e1, _ = _frame(axis)

    def q(x: NDArray[np.float64]) -> NDArray[np.float64]:
        x = np.asarray(x, dtype=np.float64)
        sn = np.sqrt(np.clip(1.0 - x * x, 0.0, None))
        return np.asarray(q_of_dirs(x.ravel()[:, None] * axis + sn.ravel()[:, None] * e1)).reshape(x.shape)
    return q


def _fresnel_breaks(eta: float) -> list[float]:
    """Critical-angle cosine on the outside (eta < 1: total reflection below it)."""
    return [math.sqrt(1.0 - eta * eta)] if eta < 1.0 else []


def sphere_from_light(light: Any, radius: float, kappa: float, mu: float, eta: float, *,
                      centre: ArrayLike = (0.0, 0.0, 0.0), channel: int = 0, convention: str = "p1",
                      C: float | None = None, general_l_max: int = 64, **kw: Any) -> SphereSeries:
    """Series for a :mod:`glsldiff.physics.lights` light on the sphere (one RGB ``channel``).

    Directional lights, point lights and spots aimed at the centre use the axisymmetric path
    (keywords ``tol``, ``l_max``, ``max_l_max`` of :meth:`SphereSeries.with_axisymmetric_source`);
    other spots and projectors the general one (``general_l_max``, ``oversample``).
    ``C`` defaults to ``boundary_constant(eta)``.
    """
    sph = _medium(radius, kappa, mu, eta, C, centre)
    R, c = sph.radius, sph.centre
    q_dirs = light_source_function(light, R, eta, c, channel, convention)
    breaks = _fresnel_breaks(eta)
    axis: NDArray[np.float64] | None = None
    if isinstance(light, DirectionalLight):
        axis = np.asarray(light.direction)
        breaks.append(0.0)
    elif isinstance(light, (PointLight, SpotLight)):
        v = np.asarray(light.position) - c
        d = float(np.linalg.norm(v))
        a = v / d
        aimed = isinstance(light, SpotLight) and float(a @ np.asarray(light.direction)) < 0.0 \
            and float(np.linalg.norm(np.cross(a, np.asarray(light.direction)))) < 1e-12
        if isinstance(light, PointLight) or aimed:
            axis = a
            breaks += _point_breaks(light, R, d, eta)
    if axis is None:
        oversample = kw.pop("oversample", 4)
        out = sph.with_source_function(q_dirs, l_max=general_l_max, oversample=oversample)
    else:
        out = sph.with_axisymmetric_source(_axial(q_dirs, axis), axis, breakpoints=breaks, **kw)
    out.eta, out.convention = float(eta), convention
    return out


def _point_breaks(light: Any, R: float, d: float, eta: float) -> list[float]:
    """cos(theta) of the horizon, the critical angle (eta < 1) and the spot's cone edges for a
    positional light at distance d from the centre on the axis."""
    def cos_incidence(x: float) -> float:
        return (d * x - R) / math.sqrt(d * d + R * R - 2.0 * d * R * x)

    def cos_axis(x: float) -> float:                 # angle at the light from the centre line
        return (d - R * x) / math.sqrt(d * d + R * R - 2.0 * d * R * x)

    lo = R / d
    out = [lo]
    for ci in _fresnel_breaks(eta):
        out.append(optimize.brentq(lambda x: cos_incidence(x) - ci, lo, 1.0, xtol=1e-15, rtol=1e-15))
    if isinstance(light, SpotLight):
        for deg in {light.cone_deg, light.falloff_deg}:
            target = math.cos(math.radians(deg))
            if cos_axis(lo) < target < 1.0:
                out.append(optimize.brentq(lambda x: cos_axis(x) - target, lo, 1.0, xtol=1e-15, rtol=1e-15))
    return out


def sphere_directional(radius: float, kappa: float, mu: float, eta: float, direction: ArrayLike,
                       irradiance: float = 1.0, **kw: Any) -> SphereSeries:
    """Sphere lit by a distant light from unit ``direction`` (towards the light) with normal
    ``irradiance`` E: ``E_t = E F_t(eta, cos) cos^+``. Keywords of :func:`sphere_from_light`."""
    E = checks.real(irradiance, "irradiance", 0.0)
    return sphere_from_light(DirectionalLight(direction, (E, E, E), shadows=False), radius, kappa, mu, eta, **kw)


def sphere_point_light(radius: float, kappa: float, mu: float, eta: float, position: ArrayLike,
                       intensity: float = 1.0, **kw: Any) -> SphereSeries:
    """Sphere lit by an isotropic point light of ``intensity`` I (W/sr) at ``position`` (mm,
    outside the sphere): ``E_t = I F_t(cos_i) cos_i^+ / dist^2``. Keywords of
    :func:`sphere_from_light`."""
    I = checks.real(intensity, "intensity", 0.0)
    return sphere_from_light(PointLight(position, (I, I, I), shadows=False), radius, kappa, mu, eta, **kw)


def sphere_spot(radius: float, kappa: float, mu: float, eta: float, position: ArrayLike,
                intensity: float = 1.0, cone_deg: float = 10.0, falloff_deg: float | None = None,
                direction: ArrayLike | None = None, **kw: Any) -> SphereSeries:
    """Sphere lit by a spot light (:class:`glsldiff.physics.lights.SpotLight` cone and falloff;
    ``falloff_deg`` defaults to ``cone_deg``: a hard edge). ``direction`` (from the light into
    the scene) defaults to the sphere's centre, which keeps the problem axisymmetric."""
    I = checks.real(intensity, "intensity", 0.0)
    centre = checks.vector3(kw.get("centre", (0.0, 0.0, 0.0)), "centre")
    pos = checks.vector3(position, "position")
    dirn = centre - pos if direction is None else direction
    light = SpotLight(pos, dirn, (I, I, I), cone_deg=cone_deg,
                      falloff_deg=cone_deg if falloff_deg is None else falloff_deg, shadows=False)
    return sphere_from_light(light, radius, kappa, mu, eta, **kw)
