"""A laterally uniform slab, exactly and by diffusion: the 1-D oracle of the exitance conventions.

:func:`slab_monte_carlo` transports photons through a slab (thickness in mm, sigma_a and
sigma_s' in mm^-1, isotropic scattering) with smooth Fresnel boundaries of relative index
``eta`` on both faces (reflection, total internal reflection and refraction, as Mitsuba's
dielectric boundary), lit uniformly on its face ``z = 0`` by a diffuse (Lambertian) or a
collimated light of unit irradiance. It returns the radiance leaving either face per bin of
the exit cosine, split into unscattered and scattered light, with the standard error of
independent batches.

:func:`slab_diffusion` solves the same slab by the renderer's diffusion model: the
first-collision (``"volume"``) or the Marshak boundary (``"surface"``) source
(:mod:`glsldiff.physics.collision`, :func:`glsldiff.physics.exitance.source_from_irradiance`),
``-kappa phi'' + mu phi = Q`` with the Robin condition ``phi + 2 C kappa dphi/dn = q`` on both
faces (second-order finite differences, fine grid), and the exitant radiance
``F_t(eta, cos_o) B`` of :func:`glsldiff.physics.exitance.exitant_bracket`.

They isolate the model's error from the 3-D discretisation's: measured with 1-2 M photons, a
5 mm slab, sigma_s' = 1.2, sigma_a = 0.02 /mm, diffuse light behind (issue 18's patch case):
the ``p1`` radiance along the normal of the unlit face with the volume source is 1.034x Monte
Carlo's at eta = 1 (exit cosines 0.9-1, standard error 0.1 %); at eta = 1.4 1.062x with the
classic Robin constant and 0.988x with the Fresnel-moment one the renderer now uses
(:func:`glsldiff.physics.optics.moment_boundary_constant`; 1.074x -> 0.994x at eta = 1.3).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from numpy.typing import NDArray

from glsldiff.core.errors import InputError
from glsldiff.physics.exitance import exitant_bracket, source_from_irradiance
from glsldiff.physics.optics import (boundary_constant, fresnel_reflectance, fresnel_transmittance,
                                     moment_boundary_constant)

__all__ = ["SlabTransport", "slab_monte_carlo", "slab_diffusion", "INCIDENCE"]

#: Lights of the slab: diffuse (Lambertian, unit irradiance) or collimated along the normal.
INCIDENCE = ("diffuse", "normal")
_ROULETTE = 1e-3


@dataclass(frozen=True)
class SlabTransport:
    """Monte Carlo answer per unit incident irradiance. Radiances ``(2, bins)``: row 0 leaves
    the lit face (reflection), row 1 the far face (transmission), per bin of the outside exit
    cosine ``edges``; ``*_err`` their standard errors. ``absorbed`` and ``specular`` (reflected
    at the lit face without entering) complete the energy balance."""

    edges: NDArray[np.float64]
    scattered: NDArray[np.float64]
    scattered_err: NDArray[np.float64]
    unscattered: NDArray[np.float64]
    flux: NDArray[np.float64]            # (2,) scattered light leaving each face
    unscattered_flux: NDArray[np.float64]   # (2,) light leaving each face without scattering
    absorbed: float
    specular: float
    photons: int


def _check(sigma_a: float, sigma_s: float, thickness: float, eta: float, incidence: str) -> None:
    if not (sigma_a >= 0 and sigma_s >= 0 and sigma_a + sigma_s > 0 and thickness > 0 and eta > 0):
        raise InputError(f"slab: sigma_a {sigma_a}, sigma_s' {sigma_s} (>= 0, sum > 0), thickness {thickness} "
                         f"mm and eta {eta} (> 0) out of range")
    if incidence not in INCIDENCE:
        raise InputError(f"slab: incidence {incidence!r}; choose one of {', '.join(INCIDENCE)}")


def _batch(rng: np.random.Generator, n: int, st: float, albedo: float, L: float, eta: float, incidence: str,
           edges: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray, float, float]:
    """One batch of ``n`` photons: (scattered radiance (2, bins), unscattered (2, bins),
    scattered and unscattered flux (2,), absorbed, specular), per unit incident irradiance."""
    mu_out = np.ones(n) if incidence == "normal" else np.sqrt(rng.random(n))      # cosine-weighted
    enter = rng.random(n) >= np.asarray(fresnel_reflectance(eta, mu_out))
    specular = float(np.count_nonzero(~enter)) / n
    mu = np.sqrt(1.0 - (1.0 - mu_out[enter] ** 2) / eta ** 2)
    m = len(mu)
    z, wt = np.zeros(m), np.ones(m)
    first = np.ones(m, dtype=bool)
    alive = np.ones(m, dtype=bool)
    bins = len(edges) - 1
    rad, unsc, flux, flux_u = np.zeros((2, bins)), np.zeros((2, bins)), np.zeros(2), np.zeros(2)
    absorbed = 0.0
    while alive.any():
        idx = np.flatnonzero(alive)
        zn = z[idx] + mu[idx] * (-np.log(rng.random(len(idx))) / st)
        far, near = zn >= L, zn <= 0.0
        hit = far | near
        k, f_hit = idx[hit], far[hit]
        mk = np.abs(mu[k])
        refl = rng.random(len(k)) < np.asarray(fresnel_reflectance(1.0 / eta, mk))   # inside -> out (TIR: 1)
        out = ~refl
        cos_o = np.sqrt(np.clip(1.0 - eta ** 2 * (1.0 - mk[out] ** 2), 0.0, 1.0))
        side = f_hit[out].astype(int)
        w_o, first_o = wt[k[out]], first[k[out]]
        b = np.clip(np.digitize(cos_o, edges) - 1, 0, bins - 1)
        np.add.at(rad, (side[~first_o], b[~first_o]), w_o[~first_o])
        np.add.at(unsc, (side[first_o], b[first_o]), w_o[first_o])
        np.add.at(flux, side[~first_o], w_o[~first_o])
        np.add.at(flux_u, side[first_o], w_o[first_o])
        alive[k[out]] = False
        kr = k[refl]                                        # mirrored at the face it reached
        z[kr] = np.where(f_hit[refl], L, 0.0)
        mu[kr] = -mu[kr]
        kc = idx[~hit]                                      # collisions inside
        z[kc] = zn[~hit]
        absorbed += float(wt[kc].sum()) * (1.0 - albedo)
        wt[kc] *= albedo
        mu[kc] = 2.0 * rng.random(len(kc)) - 1.0
        first[kc] = False
        low = np.flatnonzero(alive & (wt < _ROULETTE))
        if len(low):
            survive = rng.random(len(low)) < 0.1
            wt[low[survive]] *= 10.0
            alive[low[~survive]] = False
    mid = 0.5 * (edges[1:] + edges[:-1])
    to_radiance = 1.0 / (n * 2.0 * math.pi * np.diff(edges) * mid)           # dP / (dOmega cos)
    return rad * to_radiance, unsc * to_radiance, flux / n, flux_u / n, absorbed / n, specular


def slab_monte_carlo(sigma_a: float, sigma_s: float, thickness: float, eta: float = 1.0,
                     incidence: str = "diffuse", photons: int = 2_000_000, batches: int = 4, bins: int = 10,
                     seed: int = 0) -> SlabTransport:
    """Exact transport through the slab (module docstring); ``photons`` in ``batches``
    independent batches (their spread is the standard error)."""
    _check(sigma_a, sigma_s, thickness, eta, incidence)
    if photons < batches or batches < 2:
        raise InputError(f"slab: {photons} photons in {batches} batches (at least 2 batches of 1)")
    st = sigma_a + sigma_s
    edges = np.linspace(0.0, 1.0, bins + 1)
    rng = np.random.default_rng(seed)
    parts = [_batch(rng, photons // batches, st, sigma_s / st, thickness, eta, incidence, edges)
             for _ in range(batches)]
    rad = np.stack([p[0] for p in parts])
    return SlabTransport(edges, rad.mean(axis=0), rad.std(axis=0, ddof=1) / math.sqrt(batches),
                         np.mean([p[1] for p in parts], axis=0), np.mean([p[2] for p in parts], axis=0),
                         np.mean([p[3] for p in parts], axis=0), float(np.mean([p[4] for p in parts])),
                         float(np.mean([p[5] for p in parts])),
                         batches * (photons // batches))


def slab_diffusion(sigma_a: float, sigma_s: float, thickness: float, eta: float = 1.0,
                   incidence: str = "diffuse", source: str = "volume", convention: str = "p1",
                   cos_o: float = 1.0, C: float | None = None, n: int = 4000) -> NDArray[np.float64]:
    """``(2,)`` exitant radiance leaving the lit face and the far face at outside cosine
    ``cos_o`` by the renderer's diffusion model (module docstring), per unit incident irradiance.
    ``C``: the Robin constant, by default the renderer's (the Fresnel-moment one with the volume
    source, the classic one with the surface source)."""
    _check(sigma_a, sigma_s, thickness, eta, incidence)
    if source not in ("volume", "surface"):
        raise InputError(f"slab: source {source!r}; choose volume or surface")
    st = sigma_a + sigma_s
    kappa = 1.0 / (3.0 * st)
    if C is None:
        C = moment_boundary_constant(eta) if source == "volume" else float(boundary_constant(eta))
    z = np.linspace(0.0, thickness, n + 1)
    h = z[1] - z[0]
    if incidence == "normal":
        mu, share = np.ones(1), np.ones(1)
    else:
        x, g = np.polynomial.legendre.leggauss(64)
        mu, share = 0.5 * (x + 1.0), g * 0.5 * (x + 1.0)            # 2 mu dmu of a Lambertian light
    E_t = share * np.asarray(fresnel_transmittance(eta, mu))          # transmitted irradiance per beam
    t = np.sqrt(1.0 - (1.0 - mu ** 2) / eta ** 2)
    Q = np.zeros(n + 1)
    q = np.zeros(2)
    if source == "volume":
        Q = sigma_s * (E_t[None, :] / t[None, :] * np.exp(-st * z[:, None] / t[None, :])).sum(axis=1)
    else:
        q[0] = float(source_from_irradiance(E_t.sum(), eta, convention))
    # -kappa phi'' + sigma_a phi = Q; Robin phi -/+ 2 C kappa phi' = q via ghost nodes
    main = np.full(n + 1, 2.0 * kappa / h ** 2 + sigma_a)
    off = np.full(n, -kappa / h ** 2)
    A = sp.diags([main, off, off], [0, 1, -1], format="lil")
    b = Q.copy()
    for end, nb in ((0, 1), (n, n - 1)):
        A[end, nb] = -2.0 * kappa / h ** 2
        A[end, end] = 2.0 * kappa / h ** 2 + sigma_a + 1.0 / (C * h)
    b[0] += q[0] / (C * h)
    phi = spl.spsolve(A.tocsr(), b)
    B = exitant_bracket(np.array([phi[0], phi[-1]]), q, eta, convention, C)
    return float(fresnel_transmittance(eta, cos_o)) * B
