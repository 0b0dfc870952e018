"""Single scattering through the object (glsldiff.render.single): every light kind, reflection
and transmission, against closed forms below a plane and through a slab."""
from __future__ import annotations

import math

import numpy as np
import pytest

from glsldiff.mesh import box_mesh
from glsldiff.physics.lights import AreaLight, DirectionalLight, EnvironmentLight
from glsldiff.physics.optics import fresnel_transmittance, refracted_cosine
from glsldiff.physics.sh import fibonacci_directions
from glsldiff.physics.single import single_scattering
from glsldiff.render.shadows import DepthRenderer
from glsldiff.render.single import ENV_DIRECTIONS, single_scattering_frame

SA, SS = np.array([0.01, 0.05, 0.2]), np.array([1.0, 0.8, 0.5])
EYE = np.array([0.0, 60.0, 200.0])


def _face(n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Points on the slab's top face (z = 0) near its centre, normals +z."""
    x = np.linspace(-4.0, 4.0, n)
    return np.stack([x, 0.3 * x, 0 * x], 1), np.tile([0.0, 0.0, 1.0], (n, 1))


def _frame(ctx, thickness: float, lights, eta: float, medium=(SA, SS), size: int = 1024) -> np.ndarray:
    mesh = box_mesh((60.0, 60.0, thickness), origin=(-30.0, -30.0, -thickness))
    P, N = _face()
    with DepthRenderer(ctx, mesh) as r:
        return single_scattering_frame(mesh, P, N, EYE, eta, lights, medium, r, shadow_map_size=size)


def _view() -> tuple[np.ndarray, np.ndarray]:
    P, _ = _face()
    v = EYE - P
    return v / np.linalg.norm(v, axis=1, keepdims=True), P


@pytest.mark.parametrize("eta", [1.0, 1.4])
def test_front_lit_thick_slab_is_the_planar_closed_form(ctx, eta):
    """Light and view on one face of a slab 40 mm deep (200 mean free paths): Jensen's planar
    transport model, exactly (physics.single's closed form)."""
    w = np.array([0.5, -0.2, 1.0]) / np.linalg.norm([0.5, -0.2, 1.0])
    ours = _frame(ctx, 40.0, [DirectionalLight(tuple(w), (1.0, 1.0, 1.0))], eta)
    view, P = _view()
    ref = single_scattering(P, np.tile([0, 0, 1.0], (len(P), 1)), view, np.tile(w, (len(P), 1)),
                            np.ones((len(P), 3)), (SA, SS), eta)
    np.testing.assert_allclose(ours, ref, rtol=2e-3)


@pytest.mark.parametrize("eta", [1.0, 1.4])
def test_thin_slab_reflection_and_transmission_match_their_closed_forms(ctx, eta):
    """A 2 mm slab: reflection is the planar form cut at the back face, and light from behind
    (normal incidence) scattered once towards the viewer is
    ``F_t F_t / eta^2 sigma_s / 4 pi  e^{-sigma_t T} (1 - e^{-k S}) / k``, k = sigma_t (1 - t_o), S = T / t_o."""
    T = 2.0
    view, P = _view()
    mu_o = view[:, 2]
    t_o = refracted_cosine(eta, mu_o)
    st = SA + SS
    f_o = np.asarray(fresnel_transmittance(eta, mu_o))[:, None]
    # transmission
    back = _frame(ctx, T, [DirectionalLight((0.0, 0.0, -1.0), (1.0, 1.0, 1.0))], eta)
    k = st[None] * (1.0 - t_o[:, None])
    S = (T / t_o)[:, None]
    integral = np.exp(-st * T)[None] * np.where(k > 1e-12, -np.expm1(-k * S) / np.maximum(k, 1e-300), S)
    ref_t = f_o * float(fresnel_transmittance(eta, 1.0)) / eta**2 * SS / (4 * math.pi) * integral
    np.testing.assert_allclose(back, ref_t, rtol=2e-3)
    # reflection at normal incidence, cut at depth T: the half-space form times (1 - e^{-sigma_t (1 + t_o) S})
    front = _frame(ctx, T, [DirectionalLight((0.0, 0.0, 1.0), (1.0, 1.0, 1.0))], eta)
    half = single_scattering(P, np.tile([0, 0, 1.0], (len(P), 1)), view, np.tile([0, 0, 1.0], (len(P), 1)),
                             np.ones((len(P), 3)), (SA, SS), eta)
    cut = -np.expm1(-st[None] * (1.0 + t_o[:, None]) * S)
    np.testing.assert_allclose(front, half * cut, rtol=2e-3)


def test_heterogeneous_medium_linear_in_depth_through_a_slab(ctx):
    """Absorption rising linearly with depth, light from behind and view along the normal: every
    sample sees the same total optical depth, L = F_t^2 / eta^2 sigma_s / 4 pi T e^{-tau}.
    A constant callable reproduces the homogeneous pair."""
    T, eta = 2.0, 1.3
    mesh = box_mesh((60.0, 60.0, T), origin=(-30.0, -30.0, -T))

    def medium(p):
        z = -p[:, 2:3]                                           # depth below the top face
        return 0.05 + 0.4 * z * np.ones((1, 3)), np.ones((len(p), 3)) * SS

    P, N = np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 1.0]])
    eye = np.array([0.0, 0.0, 300.0])
    light = [DirectionalLight((0.0, 0.0, -1.0), (1.0, 1.0, 1.0))]
    with DepthRenderer(ctx, mesh) as r:
        het = single_scattering_frame(mesh, P, N, eye, eta, light, medium, r)
        const = single_scattering_frame(mesh, P, N, eye, eta, light, lambda p: (np.broadcast_to(SA, p.shape),
                                                                                 np.broadcast_to(SS, p.shape)), r)
        homog = single_scattering_frame(mesh, P, N, eye, eta, light, (SA, SS), r)
    tau = (0.05 * T + 0.2 * T * T) + SS * T
    f = float(fresnel_transmittance(eta, 1.0))
    np.testing.assert_allclose(het[0], f * f / eta**2 * SS / (4 * math.pi) * T * np.exp(-tau), rtol=5e-3)
    np.testing.assert_allclose(const, homog, rtol=1e-9)


def test_small_distant_area_light_is_the_directional_light_of_its_irradiance(ctx):
    """A 1 mm square 500 mm behind the slab (radiance L) delivers L A / d^2 along its axis:
    the same single scattering, through and in front, as that directional light."""
    d, side, eta = 500.0, 1.0, 1.4
    for z, sign in ((-2.0 - d, 1.0), (d, -1.0)):                # behind (transmission), in front (reflection)
        area = AreaLight((0.0, 0.0, z), (0.0, 0.0, sign), (side, side), (1.0, 1.0, 1.0), samples=1)
        dist = abs(z) - (2.0 if sign > 0 else 0.0)
        e = side * side / dist**2
        a = _frame(ctx, 2.0, [area], eta)
        b = _frame(ctx, 2.0, [DirectionalLight((0.0, 0.0, -sign), (e, e, e))], eta)
        np.testing.assert_allclose(a, b, rtol=2e-2)


def test_environment_light_is_the_sum_of_its_direction_beams(ctx):
    """A uniform environment over a thick slab: the sum over the Fibonacci beams of the planar
    closed form, each of irradiance L 4 pi / K (the beams from below meet no surface facing them
    on the lit side... they enter the back face 40 mm away: nothing comes through)."""
    eta = 1.3
    env = EnvironmentLight(np.ones((16, 32, 3)))
    ours = _frame(ctx, 40.0, [env], eta)
    view, P = _view()
    ref = np.zeros_like(ours)
    dirs = fibonacci_directions(ENV_DIRECTIONS)
    for w in dirs[dirs[:, 2] > 0]:
        ref += single_scattering(P, np.tile([0, 0, 1.0], (len(P), 1)), view, np.tile(w, (len(P), 1)),
                                 np.full((len(P), 3), 4 * math.pi / len(dirs)), (SA, SS), eta)
    np.testing.assert_allclose(ours, ref, rtol=2e-2)


def test_stiff_media_stay_finite_and_non_negative(ctx):
    """Pure absorber (no single scattering), huge absorption, albedo 1, eta 1."""
    light = [DirectionalLight((0.3, 0.0, 1.0), (1.0, 1.0, 1.0)), DirectionalLight((0.0, 0.0, -1.0), (1.0, 1.0, 1.0))]
    for sa, ss, eta in ((np.full(3, 0.5), np.zeros(3), 1.3), (np.full(3, 1e4), np.full(3, 1.0), 1.3),
                        (np.zeros(3), np.full(3, 2.0), 1.0)):
        out = _frame(ctx, 2.0, light, eta, medium=(sa, ss))
        assert np.all(np.isfinite(out)) and out.min() >= 0.0
        if not ss.any():
            assert not out.any()
    far = _frame(ctx, 2.0, [DirectionalLight((0.0, 0.0, -1.0), (1.0, 1.0, 1.0))], 1.3,
                 medium=(np.full(3, 1e4), np.ones(3)))
    assert far.max() < 1e-300                                        # nothing crosses 2 mm of sigma_t 1e4
