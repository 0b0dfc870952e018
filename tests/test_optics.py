"""Tests for glsldiff.physics.optics: Fresnel terms, F_dr, C(eta) and the dipole model."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate

from glsldiff.physics import optics
from glsldiff.core.errors import InputError
from glsldiff.physics.optics import (
    PAPER_C, boundary_constant, dipole_constants, dipole_rd, dipole_total_reflectance, fdr,
    fdr_integral, eta_for_boundary_constant, fresnel_reflectance, fresnel_transmittance,
)


def _fresnel_hecht(eta: float, theta_i: float) -> tuple[float, float]:
    """Independent (R_s, R_p) from Snell's law and Hecht's sine/tangent forms."""
    theta_t = np.arcsin(np.sin(theta_i) / eta)
    r_s = -np.sin(theta_i - theta_t) / np.sin(theta_i + theta_t)
    r_p = np.tan(theta_i - theta_t) / np.tan(theta_i + theta_t)
    return r_s**2, r_p**2


# ---------------------------------------------------------------- Fresnel


@pytest.mark.parametrize("eta", [1.0, 1.1, 1.3, 1.5, 2.4, 1 / 1.5, 0.5])
def test_fresnel_normal_incidence(eta):
    """Normal incidence: F_r = ((eta - 1)/(eta + 1))^2 (Hecht, Optics, eq. 4.47)."""
    assert fresnel_reflectance(eta, 1.0) == pytest.approx(((eta - 1) / (eta + 1)) ** 2, rel=1e-14, abs=1e-16)


@pytest.mark.parametrize("eta", [1.1, 1.3, 1.5, 0.8])
def test_fresnel_grazing_is_one(eta):
    """Grazing incidence (cos_i -> 0): F_r -> 1 for any mismatched interface."""
    assert fresnel_reflectance(eta, 0.0) == pytest.approx(1.0, abs=1e-15)
    assert fresnel_reflectance(eta, 1e-7) == pytest.approx(1.0, abs=1e-5)
    assert fresnel_reflectance(eta, 1e-7) < 1.0 or eta < 1.0


def test_fresnel_energy_and_range():
    """Energy conservation F_r + F_t = 1 and 0 <= F_r <= 1 over a grid of eta and angles."""
    eta = np.array([0.6, 0.9, 1.0, 1.3, 1.5, 2.0])[:, None]
    cos_i = np.linspace(0.0, 1.0, 101)[None, :]
    fr, ft = fresnel_reflectance(eta, cos_i), fresnel_transmittance(eta, cos_i)
    assert fr.shape == (6, 101)
    np.testing.assert_allclose(fr + ft, 1.0, rtol=0, atol=1e-15)
    assert (fr >= 0).all() and (fr <= 1).all()
    np.testing.assert_array_equal(fr[2], 0.0)  # eta = 1: no interface


def test_fresnel_total_internal_reflection():
    """eta < 1: F_r = 1 beyond the critical angle sin(theta_c) = eta, < 1 just inside it."""
    eta = 1 / 1.5
    cos_c = np.sqrt(1 - eta**2)  # cosine of the critical angle, 41.81 deg
    beyond = np.linspace(0.0, cos_c * (1 - 1e-9), 50)
    np.testing.assert_array_equal(fresnel_reflectance(eta, beyond), 1.0)
    assert fresnel_reflectance(eta, cos_c + 1e-3) < 0.9
    assert fresnel_reflectance(eta, np.cos(np.radians(30.0))) < 0.1


def test_fresnel_45_degrees_eta_1_5():
    """eta = 1.5 at 45 deg: R = (R_s + R_p)/2 from Hecht's formulas (R_s = 0.0920, R_p = 0.0085)."""
    r_s, r_p = _fresnel_hecht(1.5, np.radians(45.0))
    assert r_s == pytest.approx(0.0920, abs=1e-4) and r_p == pytest.approx(0.0085, abs=1e-4)
    assert fresnel_reflectance(1.5, np.cos(np.radians(45.0))) == pytest.approx(0.5 * (r_s + r_p), rel=1e-13)
    # other angles, and the reverse direction through Stokes reciprocity (same R both ways)
    for deg in (10.0, 30.0, 60.0, 80.0):
        r_s, r_p = _fresnel_hecht(1.5, np.radians(deg))
        expected = 0.5 * (r_s + r_p)
        assert fresnel_reflectance(1.5, np.cos(np.radians(deg))) == pytest.approx(expected, rel=1e-12)
        theta_t = np.arcsin(np.sin(np.radians(deg)) / 1.5)
        assert fresnel_reflectance(1 / 1.5, np.cos(theta_t)) == pytest.approx(expected, rel=1e-12)


def test_fresnel_brewster_angle():
    """At Brewster's angle tan(theta_B) = eta the p-reflectance vanishes, so F_r = R_s/2."""
    theta_b = np.arctan(1.5)
    r_s, r_p = _fresnel_hecht(1.5, theta_b)
    assert r_p < 1e-28
    assert fresnel_reflectance(1.5, np.cos(theta_b)) == pytest.approx(r_s / 2, rel=1e-12)


def test_fresnel_scalar_and_bad_input():
    """Scalar in gives a scalar out; NaN, eta <= 0 and cos_i outside [0, 1] raise InputError."""
    assert np.ndim(fresnel_reflectance(1.3, 0.5)) == 0
    for eta, c in [(np.nan, 0.5), (0.0, 0.5), (-1.3, 0.5), (1.3, 1.5), (1.3, -0.1), (1.3, np.inf)]:
        with pytest.raises(InputError):
            fresnel_reflectance(eta, c)
    with pytest.raises(InputError, match="eta"):
        fresnel_transmittance(np.array([1.3, np.nan]), 1.0)
    with pytest.raises(ValueError):  # InputError is a ValueError
        fresnel_reflectance(1.3, 2.0)


# ---------------------------------------------------------------- F_dr and C(eta)


def test_fdr_polynomial_values():
    """Groenhuis F_dr at eta itself: 0.44476 (1.3), 0.59673 (1.5) (mertens.md 1.2 and 6.2)."""
    assert fdr(1.3) == pytest.approx(0.44476, abs=5e-6)
    assert fdr(1.5) == pytest.approx(0.59673, abs=5e-6)
    np.testing.assert_allclose(fdr(np.array([1.3, 1.5])), [0.444763, 0.596733], atol=1e-6)


def test_boundary_constant_values():
    """C = (1 + F_dr)/(1 - F_dr): 2.60206 (eta 1.3), 3.95950 (eta 1.5) (mertens.md 6.2)."""
    assert boundary_constant(1.3) == pytest.approx(2.60206, abs=5e-6)
    assert boundary_constant(1.5) == pytest.approx(3.95950, abs=5e-6)
    assert boundary_constant([1.3, 1.5]).shape == (2,)
    with pytest.raises(InputError):
        boundary_constant(5.0)  # F_dr > 1 there


def test_fdr_integral_measured_values():
    """Quadrature F_dr: measured 0.444457 (eta 1.3), 0.596346 (eta 1.5); 0 at eta = 1."""
    assert fdr_integral(1.3) == pytest.approx(0.444457, abs=1e-6)
    assert fdr_integral(1.5) == pytest.approx(0.596346, abs=1e-6)
    assert fdr_integral(1.0) == pytest.approx(0.0, abs=1e-14)
    np.testing.assert_allclose(fdr_integral(np.array([1.3, 1.5])), [0.444457, 0.596346], atol=1e-6)


def test_fdr_integral_against_polynomial():
    """Groenhuis fit vs exact: measured |diff| 3.1e-4 (1.3), 3.9e-4 (1.5), max 5.0e-4 on [1.2, 2],
    max 1.6e-3 on [1, 2] (at eta = 1, where the polynomial gives 0.0016 instead of 0)."""
    assert abs(fdr_integral(1.3) - fdr(1.3)) == pytest.approx(3.06e-4, abs=1e-6)
    assert abs(fdr_integral(1.5) - fdr(1.5)) == pytest.approx(3.88e-4, abs=1e-6)
    eta = np.linspace(1.2, 2.0, 33)
    assert np.abs(fdr_integral(eta) - fdr(eta)).max() < 5.1e-4
    eta = np.linspace(1.0, 2.0, 21)
    assert np.abs(fdr_integral(eta) - fdr(eta)).max() < 1.7e-3


@pytest.mark.parametrize("eta", [1.2, 1.3, 1.5, 2.0])
def test_fdr_integral_reciprocity(eta):
    """Internal and external diffuse reflectance obey 1 - F_int = (1 - F_ext)/eta^2; for eta 1.5
    F_ext = 0.0918 (mertens.md 1.2), computed here by an independent quadrature."""
    f_ext = integrate.quad(lambda t: 2 * fresnel_reflectance(eta, np.cos(t)) * np.cos(t) * np.sin(t),
                           0, np.pi / 2, epsabs=1e-14, epsrel=1e-12)[0]
    if eta == 1.5:
        assert f_ext == pytest.approx(0.0918, abs=5e-5)
    assert fdr_integral(eta) == pytest.approx(1 - (1 - f_ext) / eta**2, abs=1e-10)


def test_paper_c_and_inverse():
    """Wang 2008 quotes C = 2.1489 for eta 1.3; inverting the polynomial gives eta = 1.22410."""
    assert PAPER_C == 2.1489
    eta = eta_for_boundary_constant(PAPER_C)
    assert eta == pytest.approx(1.22410, abs=1e-5)
    assert boundary_constant(eta) == pytest.approx(PAPER_C, rel=1e-12)
    assert eta_for_boundary_constant(boundary_constant(1.3)) == pytest.approx(1.3, rel=1e-12)
    cs = np.array([1.5, 2.6, 3.9595])
    np.testing.assert_allclose(boundary_constant(eta_for_boundary_constant(cs)), cs, rtol=1e-12)
    for bad in (0.0, -2.0, np.nan):
        with pytest.raises(InputError, match="C"):
            eta_for_boundary_constant(bad)


# ---------------------------------------------------------------- dipole

# mertens.md 6.2, derived dipole constants (R/G/B): sigma_a, sigma_s', sigma_tr, z_r,
# z_v(1.3), rho(1.3), z_v(1.5), rho(1.5)
DIPOLE_TABLE = {
    "marble": ([0.0021, 0.0041, 0.0071], [2.19, 2.62, 3.00], [0.1175, 0.1797, 0.2531],
               [0.4562, 0.3811, 0.3325], [2.0389, 1.7032, 1.4863], [0.867, 0.834, 0.801],
               [2.8645, 2.3929, 2.0882], [0.830, 0.791, 0.753]),
    "skin1": ([0.032, 0.17, 0.48], [0.74, 0.88, 1.01], [0.2722, 0.7318, 1.4648],
              [1.2953, 0.9524, 0.6711], [5.7894, 4.2566, 2.9996], [0.436, 0.227, 0.131],
              [8.1338, 5.9803, 4.2143], [0.389, 0.214, 0.128]),
    "ketchup": ([0.061, 0.97, 1.45], [0.18, 0.07, 0.03], [0.2100, 1.7397, 2.5373],
                [4.1494, 0.9615, 0.6757], [18.5453, 4.2975, 3.0199], [0.164, 0.006, 0.002],
                [26.0553, 6.0378, 4.2428], [0.158, 0.006, 0.002]),
    "wholemilk": ([0.0011, 0.0024, 0.014], [2.55, 3.21, 3.77], [0.0918, 0.1521, 0.3987],
                  [0.3920, 0.3113, 0.2643], [1.7520, 1.3913, 1.1811], [0.908, 0.881, 0.759],
                  [2.4614, 1.9547, 1.6594], [0.881, 0.848, 0.705]),
}


def test_dipole_marble_red_eta_1_5():
    """Marble R channel, eta 1.5 (mertens.md 6.1): sigma_tr 0.11752, z_r 0.45618, z_v 2.86453,
    D 0.15206, alpha' 0.99904, A 3.95950, rho 0.83019."""
    k = dipole_constants(0.0021, 2.19, 1.5)
    assert k.sigma_t_prime == pytest.approx(2.1921, abs=1e-12)
    assert k.sigma_tr == pytest.approx(0.11752, abs=5e-6)
    assert k.z_r == pytest.approx(0.45618, abs=5e-6)
    assert k.z_v == pytest.approx(2.86453, abs=5e-6)
    assert k.D == pytest.approx(0.15206, abs=5e-6)
    assert k.alpha_prime == pytest.approx(0.99904, abs=5e-6)
    assert k.A == pytest.approx(3.95950, abs=5e-6)
    assert dipole_total_reflectance(0.0021, 2.19, 1.5) == pytest.approx(0.83019, abs=5e-6)


@pytest.mark.parametrize("name", sorted(DIPOLE_TABLE))
def test_dipole_constants_table(name):
    """RGB rows of the derived-constants table in mertens.md 6.2 at eta 1.3 and 1.5 (4 and 3 decimals)."""
    sa, ss, s_tr, z_r, z_v13, rho13, z_v15, rho15 = (np.array(v) for v in DIPOLE_TABLE[name])
    for eta, z_v, rho in ((1.3, z_v13, rho13), (1.5, z_v15, rho15)):
        k = dipole_constants(sa, ss, eta)
        assert k.z_v.shape == (3,)
        np.testing.assert_allclose(k.sigma_tr, s_tr, atol=5.1e-5)
        np.testing.assert_allclose(k.z_r, z_r, atol=5.1e-5)
        np.testing.assert_allclose(k.z_v, z_v, atol=5.1e-5)
        np.testing.assert_allclose(dipole_total_reflectance(sa, ss, eta), rho, atol=5.1e-4)


@pytest.mark.parametrize("sa, ss, eta", [(0.0021, 2.19, 1.5), (0.0014, 0.70, 1.3), (0.48, 1.01, 1.3),
                                         (1.45, 0.03, 1.5), (0.0, 1.0, 1.3), (0.0002, 7.38, 1.0)])
def test_dipole_rd_integrates_to_total_reflectance(sa, ss, eta):
    """2 pi int_0^inf R_d(r) r dr equals the closed form (3.24) to 1e-8 relative (mertens.md 1.4)."""
    q = integrate.quad(lambda r: 2 * np.pi * dipole_rd(r, sa, ss, eta) * r, 0, np.inf,
                       epsabs=0, epsrel=1e-12, limit=500)[0]
    assert q == pytest.approx(dipole_total_reflectance(sa, ss, eta), rel=1e-8)


def test_dipole_rd_broadcast_and_values():
    """R_d is positive, decreasing in r, broadcasts RGB via r[:, None]; R_d(0) matches Table 3.1."""
    sa, ss = np.array(DIPOLE_TABLE["marble"][0]), np.array(DIPOLE_TABLE["marble"][1])
    r = np.linspace(0.0, 20.0, 201)
    rd = dipole_rd(r[:, None], sa, ss, 1.3)
    assert rd.shape == (201, 3)
    assert (rd > 0).all() and (np.diff(rd, axis=0) < 0).all()
    k = dipole_constants(sa, ss, 1.3)
    at0 = k.alpha_prime / (4 * np.pi) * sum((1 + k.sigma_tr * z) * np.exp(-k.sigma_tr * z) / z**2
                                            for z in (k.z_r, k.z_v))
    np.testing.assert_allclose(rd[0], at0, rtol=1e-14)
    assert np.ndim(dipole_rd(1.0, 0.0021, 2.19, 1.3)) == 0


def test_dipole_total_reflectance_limits():
    """No absorption gives rho = 1 (all light returns); pure absorber gives rho = 0."""
    assert dipole_total_reflectance(0.0, 1.0, 1.3) == pytest.approx(1.0, abs=1e-15)
    assert dipole_total_reflectance(1.0, 0.0, 1.3) == 0.0
    rho = dipole_total_reflectance(np.array([0.001, 0.01, 0.1]), 1.0, 1.3)
    assert (np.diff(rho) < 0).all()


def test_dipole_bad_input():
    """Negative r or coefficients, both coefficients zero, NaN or eta <= 0 raise InputError."""
    for args in [(-1.0, 0.1, 1.0, 1.3), (1.0, -0.1, 1.0, 1.3), (1.0, 0.1, -1.0, 1.3),
                 (1.0, 0.0, 0.0, 1.3), (1.0, np.nan, 1.0, 1.3), (1.0, 0.1, 1.0, 0.0)]:
        with pytest.raises(InputError):
            dipole_rd(*args)
    with pytest.raises(InputError, match=r"sigma_a has 1 NaN value\(s\) at e.g. index \(1,\)"):
        dipole_total_reflectance([0.1, np.nan, 0.2], 1.0, 1.3)


def test_public_api_listed():
    """Every name in optics.__all__ exists."""
    assert all(hasattr(optics, n) for n in optics.__all__)


def test_refract_obeys_snell_and_flags_total_internal_reflection():
    from glsldiff.physics.optics import refract

    theta = np.radians([0.0, 20.0, 45.0, 80.0])
    d = np.stack([np.sin(theta), np.zeros(4), -np.cos(theta)], 1)        # going down onto z = 0
    n = np.tile([0.0, 0.0, 1.0], (4, 1))
    t, ok = refract(d, n, 1.0 / 1.4)                                      # into the denser medium
    assert ok.all() and np.allclose(np.linalg.norm(t, axis=1), 1.0)
    np.testing.assert_allclose(t[:, 0], np.sin(theta) / 1.4, atol=1e-15)  # sin_t = sin_i / eta
    assert np.all(t[:, 2] < 0)                                            # still going down
    up = t * [1.0, 1.0, -1.0]                                             # the same ray inside, going up
    back, ok = refract(up, -n, 1.4)                                       # leaving: the incident angle again
    assert ok.all()
    np.testing.assert_allclose(back[:, 0], np.sin(theta), atol=1e-12)
    _, ok = refract(np.array([[np.sin(1.2), 0.0, np.cos(1.2)]]), np.array([[0.0, 0.0, -1.0]]), 1.4)
    assert not ok[0]                                                      # 69 deg inside eta 1.4: totally reflected


@pytest.mark.parametrize("eta", [0.8, 1.0, 1.3, 1.4, 1.5])
def test_fresnel_moments_against_quadrature(eta):
    """C1 = F_dr / 2 (fdr_integral), C2 by adaptive quadrature; A = (1 + 3 C2) / (1 - 2 C1)."""
    from scipy.integrate import quad
    from glsldiff.physics.optics import fdr_integral, fresnel_moments, moment_boundary_constant
    c1, c2 = fresnel_moments(eta)
    kink = [float(np.sqrt(1 - 1 / eta**2))] if eta > 1 else None
    ref2 = quad(lambda m: float(fresnel_reflectance(1 / eta, m)) * m * m, 0, 1, points=kink, epsabs=1e-13)[0]
    assert 2 * c1 == pytest.approx(float(fdr_integral(eta)), abs=1e-6)
    assert c2 == pytest.approx(ref2, abs=1e-6)
    assert moment_boundary_constant(eta) == pytest.approx((1 + 3 * c2) / (1 - 2 * c1), rel=1e-12)
    if eta == 1.0:
        assert (c1, c2) == (0.0, 0.0) and moment_boundary_constant(eta) == 1.0
