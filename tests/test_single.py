"""Tests for glsldiff.physics.single: the single-scattering term of the final shading pass.

References used here, all independent of the code under test: the closed form of the
single-scattering integral at normal incidence and view, a photon Monte Carlo simulation of
first-order scattering below a plane, scipy quadrature of the planar single-scattering integral
in a depth-graded medium, and reciprocity of the transport form.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate

from glsldiff.physics import single
from glsldiff.core.errors import InputError
from glsldiff.physics.optics import fresnel_reflectance
from glsldiff.physics.lights import DirectionalLight, EnvironmentLight, PointLight, SpotLight
from glsldiff.physics.single import henyey_greenstein, light_single_scattering, single_scattering

ETA = 1.3
UP = np.array([0.0, 0.0, 1.0])


def _rows(v, n):
    return np.tile(np.asarray(v, dtype=np.float64), (n, 1))


def _const(sa, ss):
    """A material callable that returns the same RGB coefficients everywhere."""
    sa, ss = np.asarray(sa, dtype=np.float64), np.asarray(ss, dtype=np.float64)
    return lambda x: (np.broadcast_to(sa, (len(x), 3)), np.broadcast_to(ss, (len(x), 3)))


def _normal_geometry(n=1):
    return np.zeros((n, 3)), _rows(UP, n), _rows(UP, n), _rows(UP, n)


def _ft_normal(eta):
    """Fresnel transmittance at normal incidence, 1 - ((eta - 1)/(eta + 1))^2 = 4 eta/(eta + 1)^2."""
    return 4.0 * eta / (eta + 1.0) ** 2


def _random_geometry(rng, n):
    def unit():
        d = rng.normal(size=(n, 3))
        return d / np.linalg.norm(d, axis=1, keepdims=True)
    return rng.normal(scale=5.0, size=(n, 3)), unit(), unit(), unit()


# ------------------------------------------------------------------ closed forms


@pytest.mark.parametrize("model", ["transport", "jensen2001"])
@pytest.mark.parametrize("eta", [1.0, 1.3, 1.5])
@pytest.mark.parametrize("kind", ["pair", "callable"])
def test_normal_incidence_closed_form(model, eta, kind):
    """Normal incidence and view: both refracted paths run along the normal, so
    int_0^inf sigma_s p exp(-(sigma_t_o + sigma_t_i) s) ds = sigma_s p / (sigma_t_o + sigma_t_i) and
    L = E F_t(1)^2 sigma_s p / (2 sigma_t), over eta^2 for the transport form (radiance leaving
    the denser medium), p = 1/(4 pi) backscattering for g = 0."""
    sa, ss = np.array([0.002, 0.05, 0.7]), np.array([2.2, 1.0, 0.3])
    E = np.array([[1.0, 2.0, 0.5]])
    mat = (sa, ss) if kind == "pair" else _const(sa, ss)
    L = single_scattering(*_normal_geometry(), E, mat, eta, model=model)
    st = sa + ss
    expected = E[0] * _ft_normal(eta) ** 2 * ss / (4.0 * np.pi) / (st + st)
    if model == "transport":
        expected /= eta**2
    np.testing.assert_allclose(L[0], expected, rtol=0.01)
    np.testing.assert_allclose(L[0], expected, rtol=1e-12)  # exact for a homogeneous medium


@pytest.mark.parametrize("g", [0.0, 0.7, -0.4])
def test_normal_incidence_anisotropic(g):
    """With g != 0 the reduced sigma_s' is scaled to sigma_s = sigma_s'/(1 - g) and the phase is
    Henyey-Greenstein at the backscatter angle, cos = -1: p = (1 - g^2)/(4 pi (1 + g)^3)."""
    sa, ssr = np.array([0.01, 0.1, 0.5]), np.array([1.0, 1.5, 0.8])
    L = single_scattering(*_normal_geometry(), np.ones((1, 3)), (sa, ssr), ETA, g=g)
    ss = ssr / (1.0 - g)
    p = (1.0 - g * g) / (4.0 * np.pi * (1.0 + g) ** 3)
    expected = _ft_normal(ETA) ** 2 * ss * p / (2.0 * (sa + ss)) / ETA**2
    np.testing.assert_allclose(L[0], expected, rtol=1e-12)


def test_henyey_greenstein_normalized():
    """int p dw = 1 and the mean cosine is g."""
    for g in (0.0, 0.5, -0.8):
        norm = integrate.quad(lambda c: 2 * np.pi * henyey_greenstein(c, g), -1, 1)[0]
        mean = integrate.quad(lambda c: 2 * np.pi * c * henyey_greenstein(c, g), -1, 1)[0]
        assert norm == pytest.approx(1.0, abs=1e-10)
        assert mean == pytest.approx(g, abs=1e-10)


# ------------------------------------------------------------------ Monte Carlo


def _mc_cone_radiance(sa, ss, eta, g, theta_max, n, seed):
    """Photon Monte Carlo of first-order scattering below a plane, normal incidence (E = 1).

    Photons enter with weight F_t(1), travel down to an interaction depth z ~ Exp(sigma_t),
    scatter with albedo sigma_s/sigma_t into an isotropically sampled direction weighted by
    4 pi p (restricted to upward cosines u whose refracted exit lies within theta_max of the
    normal, weight (1 - u_min)/2 for that restriction), survive exp(-sigma_t z / u) to the
    surface and leave with the inside-to-outside Fresnel transmittance at u. The exiting flux
    per unit area over the cone, divided by its projected solid angle pi sin^2(theta_max), is
    the cone-averaged radiance.
    """
    rng = np.random.default_rng(seed)
    st = sa + ss
    u_min = np.sqrt(1.0 - np.sin(theta_max) ** 2 / eta**2)
    z = rng.exponential(1.0 / st, size=n)
    u = rng.uniform(u_min, 1.0, size=n)
    w = (_ft_normal(eta) * (ss / st) * 4 * np.pi * henyey_greenstein(-u, g) * 0.5 * (1.0 - u_min)
         * np.exp(-st * z / u) * (1.0 - fresnel_reflectance(1.0 / eta, u)))
    cone = np.pi * np.sin(theta_max) ** 2
    return w.mean() / cone, w.std() / np.sqrt(n) / cone


@pytest.mark.parametrize("g", [0.0, 0.6])
def test_transport_matches_monte_carlo(g):
    """The transport form agrees with an independent photon simulation to < 1 % (cone of 40
    degrees around the normal: exit angles with mu_o from 0.77 to 1 are part of the check);
    the literal Jensen et al. form is brighter by about eta^2."""
    sa, ss = 0.05, 1.0 / (1.0 - g)   # physical sigma_s; the function takes sigma_s' = sigma_s (1 - g)
    theta = np.radians(40.0)
    mc, err = _mc_cone_radiance(sa, ss, ETA, g, theta, 400_000, seed=7)
    assert err < 0.002 * mc
    # cone average of L(mu) mu over the projected solid angle, Gauss-Legendre in mu
    x, wq = np.polynomial.legendre.leggauss(24)
    mu = np.cos(theta) + (1.0 - np.cos(theta)) * 0.5 * (x + 1.0)
    wq = wq * 0.5 * (1.0 - np.cos(theta))
    view = np.stack([np.sqrt(1.0 - mu**2), np.zeros_like(mu), mu], axis=1)
    pts, nrm, _, light = _normal_geometry(mu.size)
    mat = (np.full(3, sa), np.full(3, ss * (1.0 - g)))
    out = {}
    for model in ("transport", "jensen2001"):
        L = single_scattering(pts, nrm, view, light, np.ones((mu.size, 3)), mat, ETA, g=g, model=model)
        out[model] = 2 * np.pi * np.sum(wq * L[:, 0] * mu) / (np.pi * np.sin(theta) ** 2)
    assert out["transport"] == pytest.approx(mc, rel=0.01)
    assert out["jensen2001"] / mc == pytest.approx(ETA**2, rel=0.02)


def test_transport_is_reciprocal():
    """The transport BRDF L / (E mu_i) is symmetric in light and view; the Jensen form is not."""
    rng = np.random.default_rng(3)
    n = 64
    pts, nrm = np.zeros((n, 3)), _rows(UP, n)
    a, b = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    a[:, 2], b[:, 2] = np.abs(a[:, 2]) + 0.05, np.abs(b[:, 2]) + 0.05
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    mat, E = (np.array([0.01, 0.2, 0.9]), np.array([1.0, 0.4, 2.0])), np.ones((n, 3))
    for g in (0.0, 0.5):
        f_ab = single_scattering(pts, nrm, a, b, E, mat, ETA, g=g) / b[:, 2:]
        f_ba = single_scattering(pts, nrm, b, a, E, mat, ETA, g=g) / a[:, 2:]
        np.testing.assert_allclose(f_ab, f_ba, rtol=1e-12)
    j_ab = single_scattering(pts, nrm, a, b, E, mat, ETA, model="jensen2001") / b[:, 2:]
    j_ba = single_scattering(pts, nrm, b, a, E, mat, ETA, model="jensen2001") / a[:, 2:]
    assert np.abs(j_ab / j_ba - 1).max() > 0.05


# ------------------------------------------------------------------ heterogeneous media


def _graded():
    """A depth-graded medium below the plane z = 0: absorption rising, scattering falling with depth."""
    def coeffs(depth):
        d = np.maximum(depth, 0.0)[:, None]
        sa = np.array([0.02, 0.1, 0.4]) + np.array([0.6, 0.3, 0.2]) * (1.0 - np.exp(-d / 0.7))
        ss = np.array([1.5, 1.2, 0.9]) - np.array([0.8, 0.5, 0.3]) * (1.0 - np.exp(-d / 0.5))
        return sa, ss

    def material(x):
        return coeffs(-x[:, 2])
    return coeffs, material


def _graded_reference(coeffs, mu_o, mu_i, cos_phase, eta, g=0.0):
    """scipy quadrature of the planar single-scattering integral (transport form, E = 1).

    Along the refracted view ray s, depth z = s t_o; the light path from depth z has length
    z / t_i; with T(z) = int_0^z sigma_t dz' the optical depths are T/t_o (view) and T/t_i
    (light), and L = F_o F_i p mu_i / (eta^2 t_i) int_0^inf sigma_s(z) exp(-T/t_o - T/t_i) ds.
    """
    t_o = np.sqrt(1 - (1 - mu_o**2) / eta**2)
    t_i = np.sqrt(1 - (1 - mu_i**2) / eta**2)
    f_o = 1 - fresnel_reflectance(eta, mu_o)
    f_i = 1 - fresnel_reflectance(eta, mu_i)
    p = henyey_greenstein(cos_phase, g)
    out = []
    for c in range(3):
        def st(z, c=c):
            sa, ss = coeffs(np.array([z]))
            return float(sa[0, c] + ss[0, c] / (1 - g))

        def integrand(s, c=c):
            z = s * t_o
            T = integrate.quad(st, 0.0, z, epsabs=1e-13, epsrel=1e-11)[0]
            return coeffs(np.array([z]))[1][0, c] / (1 - g) * np.exp(-T / t_o - T / t_i)

        out.append(integrate.quad(integrand, 0.0, np.inf, epsabs=1e-12, epsrel=1e-10, limit=200)[0])
    return f_o * f_i * p * mu_i / (eta**2 * t_i) * np.array(out)


@pytest.mark.parametrize("angles", [(0.0, 0.0), (35.0, 60.0), (70.0, 20.0)])
def test_graded_medium_against_quadrature(angles):
    """Depth-graded medium: the default 16-node march is within 1 % of scipy quadrature of the
    planar integral, for normal and oblique light and view (azimuths 180 degrees apart)."""
    coeffs, material = _graded()
    th_o, th_i = np.radians(angles)
    v = np.array([[np.sin(th_o), 0.0, np.cos(th_o)]])
    l_dir = np.array([[-np.sin(th_i), 0.0, np.cos(th_i)]])
    L = single_scattering(np.zeros((1, 3)), UP[None], v, l_dir, np.ones((1, 3)), material, ETA)
    # the phase angle from the refracted directions, written out independently
    sin_o, sin_i = np.sin(th_o) / ETA, np.sin(th_i) / ETA
    prop_l = np.array([sin_i, 0.0, -np.sqrt(1 - sin_i**2)])    # refracted light, travelling down
    up_view = np.array([sin_o, 0.0, np.sqrt(1 - sin_o**2)])    # scattered light towards the viewer
    ref = _graded_reference(coeffs, np.cos(th_o), np.cos(th_i), prop_l @ up_view, ETA)
    np.testing.assert_allclose(L[0], ref, rtol=0.01)
    # and the graded medium differs from its surface value (the test is not trivially homogeneous)
    surf = single_scattering(np.zeros((1, 3)), UP[None], v, l_dir, np.ones((1, 3)),
                             tuple(a[0] for a in coeffs(np.zeros(1))), ETA)
    assert np.abs(surf[0] / ref - 1).max() > 0.1


def test_graded_medium_converges_with_samples():
    """More nodes along both paths: the error against quadrature does not grow and ends < 0.1 %."""
    coeffs, material = _graded()
    th = np.radians(30.0)
    v = np.array([[np.sin(th), 0.0, np.cos(th)]])
    ref = _graded_reference(coeffs, np.cos(th), np.cos(th), -(np.cos(2 * np.arcsin(np.sin(th) / ETA))),
                            ETA)
    errs = [np.abs(single_scattering(np.zeros((1, 3)), UP[None], v, v, np.ones((1, 3)), material, ETA,
                                     samples=s, light_samples=k)[0] / ref - 1).max()
            for s, k in ((4, 2), (16, 4), (48, 8))]
    assert errs[2] < 1e-3
    assert errs[2] <= errs[0]


# ------------------------------------------------------------------ behaviour


@pytest.mark.parametrize("kind", ["pair", "callable"])
def test_inverse_sigma_t(kind):
    """With sigma_s fixed, L is proportional to 1/sigma_t (homogeneous, any geometry)."""
    rng = np.random.default_rng(11)
    pts, nrm, v, l_dir = _random_geometry(rng, 32)
    v = np.where((np.einsum("ij,ij->i", v, nrm) < 0)[:, None], -v, v)
    l_dir = np.where((np.einsum("ij,ij->i", l_dir, nrm) < 0)[:, None], -l_dir, l_dir)
    ss = np.array([1.0, 0.5, 2.0])
    results = []
    for sa in (0.0, 0.5, 2.0, 10.0):
        sa3 = np.full(3, sa)
        mat = (sa3, ss) if kind == "pair" else _const(sa3, ss)
        L = single_scattering(pts, nrm, v, l_dir, np.ones((32, 3)), mat, ETA, samples=8)
        results.append(L * (sa3 + ss))
    for r in results[1:]:
        np.testing.assert_allclose(r, results[0], rtol=1e-10)
    assert (results[0] > 0).all()


def test_zero_for_back_facing_light_or_view():
    """n.l <= 0 or n.v <= 0 gives exactly zero; front-facing rows stay positive."""
    n = 6
    pts, nrm = np.zeros((n, 3)), _rows(UP, n)
    s = np.sqrt(0.5)
    light = np.array([[0, 0, 1], [s, 0, -s], [1, 0, 0], [0, 0, 1], [0, 0, 1], [0, s, s]], dtype=float)
    view = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, -s, -s], [0, 1, 0], [s, 0, s]], dtype=float)
    _, material = _graded()
    for mat in ((np.full(3, 0.1), np.full(3, 1.0)), material):
        L = single_scattering(pts, nrm, view, light, np.ones((n, 3)), mat, ETA)
        assert (L[1:5] == 0.0).all()
        assert (L[[0, 5]] > 0.0).all()


@pytest.mark.parametrize("kind", ["pair", "callable"])
def test_monotone_decrease_with_absorption(kind):
    """Adding absorption (everywhere) strictly lowers the radiance in every channel."""
    rng = np.random.default_rng(5)
    pts, nrm, v, l_dir = _random_geometry(rng, 16)
    v = np.where((np.einsum("ij,ij->i", v, nrm) < 0)[:, None], -v, v)
    l_dir = np.where((np.einsum("ij,ij->i", l_dir, nrm) < 0)[:, None], -l_dir, l_dir)
    coeffs, _ = _graded()
    prev = None
    for extra in (0.0, 0.01, 0.1, 1.0, 5.0):
        if kind == "pair":
            mat = (np.array([0.02, 0.1, 0.4]) + extra, np.array([1.5, 1.2, 0.9]))
        else:
            def mat(x, extra=extra):
                sa, ss = coeffs(np.abs(x[:, 0]))       # graded along x, any positions
                return sa + extra, ss
        L = single_scattering(pts, nrm, v, l_dir, np.ones((16, 3)), mat, ETA)
        if prev is not None:
            assert (L < prev).all()
        prev = L


@pytest.mark.parametrize("g", [0.0, 0.5, -0.3])
@pytest.mark.parametrize("model", ["transport", "jensen2001"])
def test_constant_callable_equals_pair(g, model):
    """A constant callable reproduces the homogeneous pair (random geometry, RGB coefficients
    with unequal extinction, any node counts)."""
    rng = np.random.default_rng(2)
    pts, nrm, v, l_dir = _random_geometry(rng, 200)
    E = rng.uniform(0.1, 3.0, size=(200, 3))
    sa, ss = np.array([0.01, 0.3, 1.0]), np.array([1.0, 0.5, 2.0])
    ref = single_scattering(pts, nrm, v, l_dir, E, (sa, ss), ETA, g=g, model=model)
    assert (ref > 0).any() and (ref == 0).any()
    for samples, k in ((1, 0), (3, 1), (16, 4)):
        L = single_scattering(pts, nrm, v, l_dir, E, _const(sa, ss), ETA, samples=samples, g=g,
                              model=model, light_samples=k)
        np.testing.assert_allclose(L, ref, rtol=1e-12, atol=0)


def test_deterministic_and_chunk_independent(monkeypatch):
    """No random numbers: repeated calls are bit-identical, point order does not matter, and
    splitting into chunks (small _CHUNK_POSITIONS) gives the same result."""
    rng = np.random.default_rng(9)
    pts, nrm, v, l_dir = _random_geometry(rng, 300)
    pts[:, 2] = -np.abs(pts[:, 2])
    _, material = _graded()
    E = np.ones((300, 3))
    a = single_scattering(pts, nrm, v, l_dir, E, material, ETA)
    b = single_scattering(pts, nrm, v, l_dir, E, material, ETA)
    assert np.array_equal(a, b)
    perm = rng.permutation(300)
    c = single_scattering(pts[perm], nrm[perm], v[perm], l_dir[perm], E[perm], material, ETA)
    np.testing.assert_allclose(c, a[perm], rtol=1e-13, atol=0)
    monkeypatch.setattr(single, "_CHUNK_POSITIONS", 200)
    d = single_scattering(pts, nrm, v, l_dir, E, material, ETA)
    np.testing.assert_allclose(d, a, rtol=1e-13, atol=0)


def test_directions_are_normalized_and_empty_input():
    """Non-unit normals and directions are normalized; N = 0 gives an empty (0, 3) result."""
    pts, nrm, v, l_dir = _normal_geometry(1)
    mat = (np.full(3, 0.1), np.full(3, 1.0))
    a = single_scattering(pts, nrm, v, l_dir, np.ones((1, 3)), mat, ETA)
    b = single_scattering(pts, 3 * nrm, 0.2 * v, 7 * l_dir, np.ones((1, 3)), mat, ETA)
    np.testing.assert_allclose(a, b, rtol=1e-14)
    e = single_scattering(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                          np.zeros((0, 3)), mat, ETA)
    assert e.shape == (0, 3)


# ------------------------------------------------------------------ bad input


def _good():
    pts, nrm, v, l_dir = _normal_geometry(4)
    return dict(points=pts, normals=nrm, view_dirs=v, light_dirs=l_dir, irradiance=np.ones((4, 3)),
                material=(np.full(3, 0.1), np.full(3, 1.0)), eta=ETA)


def _bad_callable_negative(x):
    return np.full((len(x), 3), 0.1), np.full((len(x), 3), -1.0)


@pytest.mark.parametrize("change, field", [
    ({"normals": np.ones((3, 3))}, "normals"),
    ({"points": np.zeros((4, 2))}, "points"),
    ({"view_dirs": np.ones((5, 3))}, "view_dirs"),
    ({"light_dirs": np.zeros((4, 3))}, "light_dirs"),
    ({"irradiance": np.ones((4, 2))}, "irradiance"),
    ({"irradiance": -np.ones((4, 3))}, "irradiance"),
    ({"irradiance": np.full((4, 3), np.nan)}, "irradiance"),
    ({"material": (np.full(3, -0.1), np.full(3, 1.0))}, "sigma_a"),
    ({"material": (np.full(3, 0.1), np.array([1.0, -1.0, 1.0]))}, "sigma_s"),
    ({"material": (np.full(3, 0.0), np.full(3, 0.0))}, "sigma_a + sigma_s"),
    ({"material": (np.full(4, 0.1), np.full(3, 1.0))}, "sigma_a"),
    ({"material": "marble"}, "material"),
    ({"material": _bad_callable_negative}, "sigma_s"),
    ({"material": lambda x: x}, "material"),
    ({"eta": 0.0}, "eta"),
    ({"eta": -1.3}, "eta"),
    ({"eta": float("nan")}, "eta"),
    ({"samples": 0}, "samples"),
    ({"samples": 2.5}, "samples"),
    ({"samples": True}, "samples"),
    ({"g": 1.0}, "g"),
    ({"g": -1.5}, "g"),
    ({"light_samples": -1}, "light_samples"),
    ({"model": "dipole"}, "model"),
])
def test_bad_input_names_field(change, field):
    kwargs = _good()
    kwargs.update(change)
    with pytest.raises(InputError, match=field.replace("+", r"\+")):
        single_scattering(**kwargs)


def test_light_single_scattering_takes_the_light_types():
    """A light of glsldiff.physics.lights: its direction and normal irradiance per point (sun:
    E0; point light: I / r^2; spot: times its cone factor) times the visibility."""
    rng = np.random.default_rng(7)
    pts = np.c_[rng.uniform(-5, 5, (6, 2)), np.zeros(6)]
    nrm, view = _rows(UP, 6), _rows([0.3, 0.0, 1.0], 6)
    mat, vis = (np.array([0.01, 0.1, 0.3]), np.array([1.0, 0.8, 0.5])), np.linspace(0.0, 1.0, 6)
    sun = DirectionalLight((0.2, -0.4, 1.0), (1.0, 2.0, 3.0))
    ref = single_scattering(pts, nrm, view, _rows(sun.direction, 6), vis[:, None] * np.array([1.0, 2.0, 3.0]),
                            mat, ETA)
    np.testing.assert_allclose(light_single_scattering(pts, nrm, view, sun, mat, ETA, vis), ref, rtol=1e-14)
    pos = np.array([1.0, 2.0, 30.0])
    d = pos - pts
    r2 = (d ** 2).sum(axis=1)
    ref = single_scattering(pts, nrm, view, d, (100.0 / r2)[:, None] * np.ones(3), mat, ETA, samples=4)
    np.testing.assert_allclose(light_single_scattering(pts, nrm, view, PointLight(pos, 100.0), mat, ETA,
                                                       samples=4), ref, rtol=1e-13)
    spot = SpotLight(pos, (0.0, 0.0, -1.0), 100.0, cone_deg=10.0, falloff_deg=5.0)
    out = light_single_scattering(pts, nrm, view, spot, mat, ETA)
    cos_axis = d[:, 2] / np.sqrt(r2)
    inside, outside = cos_axis > np.cos(np.radians(5.0)), cos_axis < np.cos(np.radians(10.0))
    assert inside.any() and outside.any()
    np.testing.assert_allclose(out[inside], ref[inside], rtol=1e-13)
    assert np.all(out[outside] == 0.0)
    with pytest.raises(InputError, match="environment"):
        light_single_scattering(pts, nrm, view, EnvironmentLight(np.ones((2, 4, 3))), mat, ETA)
    with pytest.raises(InputError, match="visibility"):
        light_single_scattering(pts, nrm, view, sun, mat, ETA, vis[:3])
