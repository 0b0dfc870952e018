"""Unscattered light: a light source seen straight through the object (thin parts, back-lit slabs).

Per shaded vertex x (outward normal n) seen from the eye along w_o: the view ray refracts into
the medium, runs straight to its exit point y (:func:`glsldiff.mesh.raycast.first_hits`),
refracts out along w_e (total internal reflection: no contribution), and, unless it hits the
mesh again, reaches what lies behind: an :class:`~glsldiff.physics.lights.AreaLight` whose
emitting side faces it, or an :class:`~glsldiff.physics.lights.EnvironmentLight` (its map in
direction w_e). The radiance reaching the eye is

    L_u = F_t(eta, n . w_o) F_t(eta, n_y . w_e) exp(-integral_x^y sigma_t') L_light(w_e)

(radiance over eta^2 is invariant along a ray: the eta^2 of entering and of leaving cancel).
``sigma_t' = sigma_a + sigma_s'``: the similarity relation's reduced coefficient, which is the
true extinction for the isotropic phase function of the Monte Carlo reference. Directional,
point, spot and projector lights are points in direction space: they are never seen through
the object (measure zero), so they add nothing here.

The path is followed at most ``REACH`` mean free paths of the least extinguishing channel
(exp(-REACH) of the light's radiance beyond). Heterogeneous media are sampled at ``STEPS``
midpoints along the path. Exit normals are the hit faces' geometric normals.
"""
from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff.mesh.raycast import first_hits
from glsldiff.physics.lights import AreaLight, EnvironmentLight, Light
from glsldiff.physics.optics import fresnel_transmittance, refract
from glsldiff.physics.sh import latlong_lookup

__all__ = ["unscattered", "sees_through", "REACH", "STEPS"]

REACH = 16.0
STEPS = 16


def sees_through(lights: Sequence[Light]) -> bool:
    """Whether any of ``lights`` can be seen through an object (area and environment lights)."""
    return any(isinstance(lt, (AreaLight, EnvironmentLight)) for lt in lights)


def _behind(lights: Sequence[Light], y: NDArray, w: NDArray) -> NDArray[np.float64]:
    """Radiance ``(N, 3)`` arriving at points ``y`` from direction ``w`` (rays ``y + s w``)."""
    out = np.zeros((len(y), 3))
    for lt in lights:
        if isinstance(lt, AreaLight):
            right, up, fwd = lt.frame
            den = w @ fwd
            facing = den < 0.0                                         # the ray meets the emitting side
            s = np.where(facing, ((np.asarray(lt.position) - y) @ fwd) / np.where(facing, den, 1.0), -1.0)
            p = y + s[:, None] * w - np.asarray(lt.position)
            inside = (s > 0) & (np.abs(p @ right) <= lt.size[0] / 2) & (np.abs(p @ up) <= lt.size[1] / 2)
            out += inside[:, None] * np.asarray(lt.radiance)
        elif isinstance(lt, EnvironmentLight):
            out += lt.scale * latlong_lookup(lt.image, w)
    return out


def unscattered(mesh: Any, vertices: NDArray, normals: NDArray, eye: NDArray, eta: float,
                lights: Sequence[Light], sigma_t: NDArray | Callable[[NDArray], NDArray],
                sigma_t_min: float | None = None) -> NDArray[np.float64]:
    """``(V, 3)`` unscattered radiance towards ``eye`` at ``vertices`` (module docstring).

    ``sigma_t``: ``(3,)`` homogeneous sigma_t' (mm^-1), or a function of points ``(M, 3)``
    returning ``(M, 3)``; ``sigma_t_min``: its smallest value anywhere in the object (bounds the
    path followed; default: that of the homogeneous ``sigma_t``, no bound for a function)."""
    v = np.asarray(vertices, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    out = np.zeros((len(v), 3))
    seen = [lt for lt in lights if isinstance(lt, (AreaLight, EnvironmentLight))]
    if not seen or len(v) == 0:
        return out
    w_o = np.asarray(eye, dtype=np.float64) - v
    w_o /= np.linalg.norm(w_o, axis=1, keepdims=True).clip(1e-300)
    mu = np.einsum("ij,ij->i", n, w_o)
    idx = np.flatnonzero(mu > 0.0)
    d, _ = refract(-w_o[idx], n[idx], 1.0 / eta)
    homogeneous = not callable(sigma_t)
    if sigma_t_min is None:
        sigma_t_min = float(np.min(sigma_t)) if homogeneous else 0.0
    reach = REACH / sigma_t_min if sigma_t_min > 0 else np.inf
    h = 1e-6 * float(np.ptp(v, axis=0).max())
    s, face = first_hits(mesh, v[idx] + h * d, d, t_max=reach)
    hit = face >= 0
    idx, d, s, face = idx[hit], d[hit], s[hit] + h, face[hit]
    y = v[idx] + s[:, None] * d
    n_y = mesh.face_normals[face]
    w_e, ok = refract(d, -n_y, eta)
    idx, d, s, y, n_y, w_e = idx[ok], d[ok], s[ok], y[ok], n_y[ok], w_e[ok]
    again, _ = first_hits(mesh, y + h * w_e, w_e)
    free = ~np.isfinite(again)                                       # the escaped ray leaves the object
    idx, d, s, y, n_y, w_e = idx[free], d[free], s[free], y[free], n_y[free], w_e[free]
    L = _behind(seen, y, w_e)
    if homogeneous:
        tau = s[:, None] * np.asarray(sigma_t, dtype=np.float64)[None]
    else:
        mids = (np.arange(STEPS) + 0.5) / STEPS
        pts = v[idx][:, None] + (s[:, None, None] * mids[None, :, None]) * d[:, None]
        tau = sigma_t(pts.reshape(-1, 3)).reshape(len(idx), STEPS, 3).mean(axis=1) * s[:, None]
    f = (np.asarray(fresnel_transmittance(eta, mu[idx])) *
         np.asarray(fresnel_transmittance(eta, np.clip(np.einsum("ij,ij->i", n_y, w_e), 0.0, 1.0))))
    out[idx] = f[:, None] * np.exp(-tau) * L
    return out
