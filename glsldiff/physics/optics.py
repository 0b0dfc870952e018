"""Interface optics and the dipole diffusion model (validation reference).

Fresnel terms of a smooth dielectric interface, the diffuse Fresnel reflectance F_dr
(Groenhuis polynomial and exact quadrature), the boundary constant C(eta) of the
diffusion boundary condition (Wang et al. 2008 eq. 2), and the Jensen et al. 2001
dipole (Mertens 2005 Table 3.1, eq. 3.24). Units: lengths in mm, coefficients in mm^-1.
All functions broadcast over scalars and arrays (e.g. RGB coefficients of shape (3,)).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import integrate, optimize

from glsldiff.core.checks import finite_values, require
from glsldiff.core.errors import InputError
from glsldiff.core.jit import kernel

__all__ = [
    "PAPER_C", "optical_pair", "fresnel_reflectance", "fresnel_transmittance", "fresnel_transmittance_at",
    "transmitted_cosine", "refracted_cosine",
    "refract",
    "fdr", "fdr_integral", "fresnel_moments", "moment_boundary_constant",
    "boundary_constant", "eta_for_boundary_constant", "DipoleConstants",
    "dipole_constants", "dipole_rd", "dipole_total_reflectance",
]

# The boundary constant Wang et al. 2008 quote for eta = 1.3. It is inconsistent with the
# Groenhuis polynomial they cite, which gives C(1.3) = 2.6021 (2.1489 is C at eta = 1.2241).
# glsldiff defaults to the polynomial, boundary_constant(eta); PAPER_C is kept for
# faithful comparisons with the paper.
PAPER_C = 2.1489


def _eta(eta: ArrayLike) -> NDArray[np.float64]:
    a = finite_values(eta, "eta")
    require(a, a <= 0.0, "eta", "> 0", "eta is the relative index n_inside / n_outside (e.g. 1.3)")
    return a


def optical_pair(sigma_a: ArrayLike, sigma_s_prime: ArrayLike) -> tuple[NDArray[np.float64], ...]:
    """Checked ``(sigma_a, sigma_s', sigma_t' = sigma_a + sigma_s')`` [mm^-1], broadcast together:
    finite, sigma_a >= 0, sigma_s' >= 0 and sigma_t' > 0."""
    sa, ss = np.broadcast_arrays(finite_values(sigma_a, "sigma_a"), finite_values(sigma_s_prime, "sigma_s_prime"))
    require(sa, sa < 0.0, "sigma_a", ">= 0", "absorption coefficients are non-negative, in mm^-1")
    require(ss, ss < 0.0, "sigma_s_prime", ">= 0", "reduced scattering is non-negative, in mm^-1")
    st = sa + ss
    require(st, st <= 0.0, "sigma_a + sigma_s_prime", "> 0", "make sigma_a or sigma_s_prime positive")
    return sa, ss, st


def _out(a: NDArray[np.float64]) -> NDArray[np.float64] | np.float64:
    """0-d arrays become numpy scalars so scalar input gives scalar output."""
    return a[()] if a.ndim == 0 else a


def fresnel_reflectance(eta: ArrayLike, cos_i: ArrayLike) -> NDArray[np.float64] | np.float64:
    """Unpolarized Fresnel reflectance of a smooth dielectric interface.

    Parameters
    ----------
    eta
        Relative index n2/n1 (light arrives in medium n1, refracts into n2); > 0.
    cos_i
        Cosine of the angle of incidence, in [0, 1].

    Returns
    -------
    F_r in [0, 1] (dimensionless); 1 under total internal reflection (eta < 1).
    """
    eta, c = np.broadcast_arrays(_eta(eta), finite_values(cos_i, "cos_i"))
    require(c, (c < 0.0) | (c > 1.0), "cos_i", "in [0, 1]", "pass the cosine of the incidence angle")
    return _out(_fresnel_r(eta, c))


def _fresnel_r(eta: NDArray[np.float64], c: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unchecked Fresnel reflectance (s and p amplitudes, Mertens 2005 section 2.1)."""
    sin_t2 = (1.0 - c * c) / (eta * eta)
    cos_t = np.sqrt(np.clip(1.0 - sin_t2, 0.0, 1.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        r_s = (c - eta * cos_t) / (c + eta * cos_t)
        r_p = (eta * c - cos_t) / (eta * c + cos_t)
        fr = 0.5 * (r_s * r_s + r_p * r_p)
    fr = np.where(sin_t2 >= 1.0, 1.0, fr)  # total internal reflection
    # matched index: no interface (also avoids 0/0 at grazing incidence)
    return np.asarray(np.where(eta == 1.0, 0.0, fr), dtype=np.float64)


def fresnel_transmittance(eta: ArrayLike, cos_i: ArrayLike) -> NDArray[np.float64] | np.float64:
    """Fresnel transmittance F_t = 1 - F_r (dimensionless); arguments as `fresnel_reflectance`."""
    return _out(1.0 - np.asarray(fresnel_reflectance(eta, cos_i)))


@kernel
def fresnel_transmittance_at(eta: float, c: float) -> float:
    """:func:`fresnel_transmittance` of one cosine ``c`` in [0, 1] (unchecked; :func:`_fresnel_r`'s
    formula), a kernel helper for compiled loops."""
    if eta == 1.0:
        return 1.0
    sin_t2 = (1.0 - c * c) / (eta * eta)
    if sin_t2 >= 1.0:
        return 0.0
    cos_t = np.sqrt(min(max(1.0 - sin_t2, 0.0), 1.0))
    r_s = (c - eta * cos_t) / (c + eta * cos_t)
    r_p = (eta * c - cos_t) / (eta * c + cos_t)
    return 1.0 - 0.5 * (r_s * r_s + r_p * r_p)


def transmitted_cosine(eta: float | None, cos: ArrayLike) -> NDArray[np.float64]:
    """``max(cos, 0) F_t(eta, cos)``: the share of a light's irradiance that crosses the
    boundary at incidence cosine ``cos`` (0 where ``cos <= 0``); ``max(cos, 0)`` for
    ``eta=None`` (the incident irradiance, no interface)."""
    cos = np.asarray(cos, dtype=np.float64)
    if eta is None:
        return np.where(cos > 0.0, 1.0, 0.0) * cos.clip(0.0)
    c = np.clip(cos, 0.0, 1.0)
    return cos.clip(0.0) * np.where(cos > 0.0, np.asarray(fresnel_transmittance(eta, c)), 0.0)


def refracted_cosine(eta: float | None, cos: ArrayLike) -> NDArray[np.float64]:
    """Cosine to the normal of a direction of incidence cosine ``cos`` after refraction into
    the medium of relative index ``eta`` (``cos`` itself for ``eta=None``); 0 where ``cos <= 0``."""
    c = np.clip(np.asarray(cos, dtype=np.float64), 0.0, 1.0)
    if eta is None:
        return c
    return np.where(c > 0.0, np.sqrt(np.clip(1.0 - (1.0 - c * c) / (eta * eta), 0.0, 1.0)), 0.0)


def refract(d: NDArray[np.float64], n: NDArray[np.float64], eta_r: float
            ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Snell: unit propagation directions ``d`` (N, 3) crossing surfaces with unit normals ``n``
    facing against them (``n . d < 0``), ``eta_r = n_from / n_to``; returns the refracted unit
    directions and a mask of rays not totally internally reflected (where it is False the
    direction is the grazing limit)."""
    cos_i = -np.einsum("ij,ij->i", n, d)
    sin2 = eta_r * eta_r * (1.0 - cos_i * cos_i)
    ok = sin2 <= 1.0
    cos_t = np.sqrt(np.clip(1.0 - sin2, 0.0, 1.0))
    t = eta_r * d + (eta_r * cos_i - cos_t)[:, None] * n
    return t / np.linalg.norm(t, axis=1, keepdims=True).clip(1e-300), ok


def fdr(eta: ArrayLike) -> NDArray[np.float64] | np.float64:
    """Internal diffuse Fresnel reflectance, Groenhuis et al. 1983 polynomial.

    F_dr = -1.440/eta^2 + 0.710/eta + 0.668 + 0.0636 eta, evaluated at the relative index
    eta = n_inside/n_outside itself (dimensionless). A fit for eta in about [1, 2]: within
    1.6e-3 of `fdr_integral` there (5e-4 for eta >= 1.2); it turns negative for eta < 1.
    """
    e = _eta(eta)
    return _out(-1.440 / e**2 + 0.710 / e + 0.668 + 0.0636 * e)


def fdr_integral(eta: ArrayLike) -> NDArray[np.float64] | np.float64:
    """Exact internal diffuse Fresnel reflectance by adaptive quadrature.

    F_dr = 2 int_0^{pi/2} F_r(1/eta, cos t) cos t sin t dt: diffuse light inside a medium of
    relative index eta hitting the boundary (dimensionless). Loops over array entries.
    """
    e = _eta(eta)
    out = np.empty_like(e)
    for idx, ev in np.ndenumerate(e):
        inv = np.float64(1.0 / ev)
        f = lambda t, inv=inv: 2.0 * float(_fresnel_r(inv, np.cos(t))) * np.cos(t) * np.sin(t)
        pts = [float(np.arcsin(1.0 / ev))] if ev > 1.0 else None  # kink at the critical angle
        out[idx] = integrate.quad(f, 0.0, 0.5 * np.pi, points=pts, epsabs=1e-14, epsrel=1e-12,
                                  limit=200)[0]
    return _out(out)


def boundary_constant(eta: ArrayLike) -> NDArray[np.float64] | np.float64:
    """Boundary constant C = A = (1 + F_dr)/(1 - F_dr) with the Groenhuis F_dr (dimensionless)."""
    f = np.asarray(fdr(eta))
    if ((f >= 1.0) | (f <= -1.0)).any():
        raise InputError("eta is outside the range (about 0.73 to 3.85) where the Groenhuis F_dr lies in "
                         "(-1, 1) and C is positive and finite; use a relative index near 1.3-1.5")
    return _out((1.0 + f) / (1.0 - f))


def fresnel_moments(eta: float) -> tuple[float, float]:
    """Fresnel moments ``(C1, C2) = (int_0^1 F_r mu dmu, int_0^1 F_r mu^2 dmu)`` of light inside a
    medium of relative index ``eta`` reaching its boundary (``F_r(1/eta, mu)``, 1 beyond the
    critical angle); ``2 C1`` is the internal diffuse reflectance :func:`fdr_integral`."""
    e = float(finite_values(eta, "eta"))
    require(np.asarray(e), np.asarray(e) <= 0.0, "eta", "> 0", "a relative refractive index is positive")
    mu_c = math.sqrt(max(0.0, 1.0 - 1.0 / (e * e))) if e > 1.0 else 0.0     # TIR below mu_c
    x, w = np.polynomial.legendre.leggauss(64)
    u = 0.5 * (x + 1.0)                      # mu = mu_c + (1 - mu_c) u^2: smooth at the critical angle
    mu = mu_c + (1.0 - mu_c) * u * u
    wt = (1.0 - mu_c) * u * w
    F = np.asarray(_fresnel_r(np.float64(1.0 / e), mu))
    return (float(np.sum(wt * F * mu)) + mu_c ** 2 / 2.0, float(np.sum(wt * F * mu * mu)) + mu_c ** 3 / 3.0)


def moment_boundary_constant(eta: float) -> float:
    """``A = (1 + 3 C2) / (1 - 2 C1)`` of the P1 Marshak boundary condition with the exact
    Fresnel moments (:func:`fresnel_moments`; d'Eon 2012, "A Better Dipole"): 2.340 for eta
    1.3, 2.948 for 1.4, 1 for eta = 1 (the classic ``(1 + F_dr) / (1 - F_dr)``: 2.602, 3.251).
    The renderer's first-collision (``volume``) source solves with it: against transport
    through a 5 mm slab (:mod:`glsldiff.oracle.slab_transport`) its transmitted radiance goes
    from 1.06-1.08x to 0.99-1.01x at eta 1.3-1.4."""
    c1, c2 = fresnel_moments(eta)
    return (1.0 + 3.0 * c2) / (1.0 - 2.0 * c1)


def eta_for_boundary_constant(C: ArrayLike) -> NDArray[np.float64] | np.float64:
    """Relative index eta with boundary_constant(eta) == C, by Brent's method (C > 0)."""
    c = finite_values(C, "C")
    require(c, c <= 0.0, "C", "> 0", "C = (1 + F_dr)/(1 - F_dr) is positive (2.6021 for eta 1.3)")
    out = np.empty_like(c)
    for idx, cv in np.ndenumerate(c):
        target = (cv - 1.0) / (cv + 1.0)  # F_dr; fdr(eta) is increasing for eta > 0
        out[idx] = optimize.brentq(lambda e: float(fdr(e)) - target, 0.1, 20.0, xtol=1e-14, rtol=1e-14)
    return _out(out)


@dataclass(frozen=True, eq=False)
class DipoleConstants:
    """Derived dipole quantities (Mertens 2005 Table 3.1); arrays broadcast like the inputs.

    sigma_t_prime, sigma_tr [mm^-1]; alpha_prime, A [-]; D, z_r, z_v [mm].
    """

    sigma_t_prime: NDArray[np.float64]
    alpha_prime: NDArray[np.float64]
    sigma_tr: NDArray[np.float64]
    D: NDArray[np.float64]
    A: NDArray[np.float64]
    z_r: NDArray[np.float64]
    z_v: NDArray[np.float64]


def dipole_constants(sigma_a: ArrayLike, sigma_s_prime: ArrayLike, eta: ArrayLike) -> DipoleConstants:
    """Dipole constants from absorption and reduced scattering [mm^-1] and relative index eta."""
    sa, ss, st = optical_pair(sigma_a, sigma_s_prime)
    sa, ss, st, A = np.broadcast_arrays(sa, ss, st, np.asarray(boundary_constant(eta)))
    D = 1.0 / (3.0 * st)
    z_r = 1.0 / st
    return DipoleConstants(sigma_t_prime=st.copy(), alpha_prime=ss / st, sigma_tr=np.sqrt(3.0 * sa * st),
                           D=D, A=A.copy(), z_r=z_r, z_v=z_r + 4.0 * A * D)


def dipole_rd(r: ArrayLike, sigma_a: ArrayLike, sigma_s_prime: ArrayLike,
              eta: ArrayLike) -> NDArray[np.float64] | np.float64:
    """Dipole diffuse reflectance profile R_d(r) [mm^-2] (Jensen et al. 2001).

    Parameters
    ----------
    r
        Distance between entry and exit points [mm], >= 0. For RGB coefficients of shape (3,)
        pass ``r[..., None]`` to get shape (..., 3) (plain numpy broadcasting).
    sigma_a, sigma_s_prime
        Absorption and reduced scattering coefficients [mm^-1].
    eta
        Relative refractive index (boundary constant from the Groenhuis F_dr).
    """
    rr = finite_values(r, "r")
    require(rr, rr < 0.0, "r", ">= 0", "r is a distance in mm")
    k = dipole_constants(sigma_a, sigma_s_prime, eta)
    d_r = np.sqrt(rr**2 + k.z_r**2)
    d_v = np.sqrt(rr**2 + k.z_v**2)
    term_r = k.z_r * (1.0 + k.sigma_tr * d_r) * np.exp(-k.sigma_tr * d_r) / d_r**3
    term_v = k.z_v * (1.0 + k.sigma_tr * d_v) * np.exp(-k.sigma_tr * d_v) / d_v**3
    return _out(k.alpha_prime / (4.0 * np.pi) * (term_r + term_v))


def dipole_total_reflectance(sigma_a: ArrayLike, sigma_s_prime: ArrayLike,
                             eta: ArrayLike) -> NDArray[np.float64] | np.float64:
    """Total diffuse reflectance rho = 2 pi int_0^inf R_d(r) r dr (Mertens eq. 3.24), dimensionless.

    rho = (alpha'/2) (exp(-sigma_tr z_r) + exp(-sigma_tr z_v)).
    """
    k = dipole_constants(sigma_a, sigma_s_prime, eta)
    return _out(0.5 * k.alpha_prime * (np.exp(-k.sigma_tr * k.z_r) + np.exp(-k.sigma_tr * k.z_v)))
