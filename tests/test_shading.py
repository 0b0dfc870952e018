"""Pass 3 (shaders/shade.frag) against a numpy evaluation of the same formulas, pixel by pixel.

A flat patch at z = 0 fills an orthographic top view of 1 mm pixels; every vertex carries the
same normal, multiple-scattering bracket, per-light visibility and extra radiance, so each
fragment sees exactly those values at its own position. The shading eye is elsewhere, so the
view direction, and with it ``F_t(eta, n.w_o)`` and the Ward lobe, changes across the image.
The oracle: ``F_t`` from :func:`glsldiff.physics.optics.fresnel_transmittance`, the bracket from
:func:`glsldiff.physics.exitance.exitant_bracket`, each light's direction and unshadowed
irradiance (1 / r^2, spot cone) from :mod:`glsldiff.physics.lights`, and the isotropic Ward lobe.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from glsldiff.core.camera import look_at, projection
from glsldiff.physics.exitance import exitant_bracket
from glsldiff.physics.lights import DirectionalLight, PointLight, SpotLight, incidence, spot_factor, to_light
from glsldiff.physics.optics import fresnel_transmittance
from glsldiff.render.shading import MAX_SHADER_LIGHTS, shade

pytestmark = pytest.mark.usefixtures("ctx")

W, H = 24, 20                    # pixels, 1 mm each: the view spans x in [-12, 12], y in [-10, 10]
MVP = (projection(1.0 / 12.0, 1.0 / 10.0, 1.0, 100.0, orthographic=True)
       @ look_at((0.0, 0.0, 50.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0)))
PATCH = np.array([[-20.0, -20.0, 0.0], [20.0, -20.0, 0.0], [20.0, 20.0, 0.0], [-20.0, 20.0, 0.0]])
FACES = np.array([[0, 1, 2], [0, 2, 3]])
EYE = np.array([7.0, -4.0, 30.0])           # the shading eye (mm), off axis
VIS = np.array([1.0, 0.6, 0.8, 0.5])        # per-light shadow visibility

# directional, point, smooth spot, hard-edged spot
LIGHTS = [DirectionalLight((0.3, 0.2, 1.0), (1.0, 0.8, 0.6)),
          PointLight((-6.0, 5.0, 15.0), (300.0, 200.0, 100.0)),
          SpotLight((4.0, 2.0, 20.0), (0.0, 0.1, -1.0), (400.0,) * 3, cone_deg=20.0, falloff_deg=10.0),
          SpotLight((-5.0, -4.0, 25.0), (0.0, 0.0, -1.0), (500.0,) * 3, cone_deg=12.0, falloff_deg=12.0)]


def _pixel_positions() -> np.ndarray:
    """World positions (mm) of the pixel centres, ``(H, W, 3)``, row 0 = top (+y)."""
    x = -12.0 + np.arange(W) + 0.5
    y = 10.0 - np.arange(H) - 0.5
    X, Y = np.meshgrid(x, y)
    return np.stack([X, Y, np.zeros_like(X)], axis=2)


def _ward(n, wi, wo, ci, co, rho_s, alpha):
    """Isotropic Ward lobe rho_s exp(-tan^2 theta_h / alpha^2) / (4 pi alpha^2 sqrt(cos_i cos_o))."""
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    ch = np.maximum(np.sum(n * h, axis=1), 1e-4)
    t2 = (1.0 - ch * ch) / (ch * ch)
    return rho_s * np.exp(-t2 / alpha**2) / (4.0 * math.pi * alpha**2 * np.sqrt(ci * co))


def _oracle(normal, ms, ss, eta, rho_s, alpha, lights):
    """Per-pixel radiance ``(H, W, 3)`` by the shader's formulas in float64."""
    p = _pixel_positions().reshape(-1, 3)
    n = np.broadcast_to(normal / np.linalg.norm(normal), p.shape).copy()
    wo = EYE - p
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    co = np.sum(n * wo, axis=1)
    back = co <= 0.0                        # seen from behind: the shader flips the normal
    n[back], co[back] = -n[back], -co[back]
    L = np.asarray(fresnel_transmittance(eta, np.clip(co, 0.0, 1.0)))[:, None] * ms + ss
    for light, vis in zip(lights, VIS):
        wi = to_light(light, p)
        scale, colour = incidence(light, p)
        ci = np.sum(n * wi, axis=1)
        lit = ci > 0.0
        f = np.where(lit, _ward(n, wi, wo, np.where(lit, ci, 1.0), co, rho_s, alpha), 0.0)
        L = L + (f * np.where(lit, ci, 0.0) * scale * vis)[:, None] * colour
    return L.reshape(H, W, 3)


def _render(normal, ms, ss, eta, rho_s, alpha, lights, ctx):
    v = len(PATCH)
    return shade(ctx, PATCH, FACES, np.tile(normal, (v, 1)), np.tile(ms, (v, 1)),
                 np.tile(VIS, (v, 1)), np.tile(ss, (v, 1)), lights, EYE, MVP,
                 eta, rho_s, alpha, (W, H))


@pytest.mark.parametrize("eta, convention, normal", [
    (1.3, "p1", (0.2, -0.1, 1.0)),
    (1.5, "arbree", (0.0, 0.0, 1.0)),
    (1.0, "paper", (-0.1, 0.3, 1.0)),
    (1.4, "p1", (0.0, 0.0, -1.0)),           # faces away from the eye: flipped, as at silhouettes
])
def test_shader_matches_the_numpy_formulas(ctx, eta, convention, normal):
    normal = np.asarray(normal, float)
    phi, q = np.array([2.0, 1.2, 0.6]), np.array([0.5, 0.3, 0.1])
    ms = exitant_bracket(phi, q, eta, convention)
    assert np.all(ms > 0.0)
    ss = np.array([0.01, 0.02, 0.03])
    rho_s, alpha = 0.08, 0.3
    assert len(LIGHTS) == MAX_SHADER_LIGHTS == len(VIS)     # every shader light slot in use
    img = _render(normal, ms, ss, eta, rho_s, alpha, LIGHTS, ctx)
    ref = _oracle(normal, ms, ss, eta, rho_s, alpha, LIGHTS)
    # the hard-edged spot: pixels within float32 reach of its edge may fall either side
    spot = LIGHTS[3]
    c = -(to_light(spot, _pixel_positions().reshape(-1, 3)) @ np.asarray(spot.direction))
    edge = (np.abs(c - math.cos(math.radians(spot.cone_deg))) < 1e-5).reshape(H, W)
    assert edge.sum() <= 2
    np.testing.assert_allclose(img[~edge], ref[~edge], rtol=2e-4, atol=1e-6 * ref.max())
    # the image covers every case: each spot's inside and outside (and the smooth one's ramp),
    # and highlights that matter
    p = _pixel_positions().reshape(-1, 3)
    smooth, hard = (spot_factor(light, -(to_light(light, p) @ np.asarray(light.direction)))
                    for light in LIGHTS[2:])
    assert smooth.min() == hard.min() == 0.0 and smooth.max() == hard.max() == 1.0
    assert np.any((smooth > 0.0) & (smooth < 1.0))
    specular = ref - _oracle(normal, ms, ss, eta, 0.0, alpha, LIGHTS)
    assert specular.max() > 0.1 * ref.max()


def test_fresnel_and_bracket_alone(ctx):
    """No specular: L = F_t(eta, n.w_o) B + ss exactly, from normal to grazing view."""
    eta, normal = 1.5, np.array([0.0, 0.0, 1.0])
    ms, ss = np.array([1.0, 0.5, 0.25]), np.zeros(3)
    img = _render(normal, ms, ss, eta, 0.0, 0.3, LIGHTS[:1], ctx)
    p = _pixel_positions().reshape(-1, 3)
    wo = EYE - p
    co = wo[:, 2] / np.linalg.norm(wo, axis=1)
    ref = np.asarray(fresnel_transmittance(eta, co))[:, None] * ms
    np.testing.assert_allclose(img.reshape(-1, 3), ref, rtol=1e-5, atol=1e-7)


def test_kept_shader_gives_the_fresh_image(ctx):
    """A :class:`Shader` kept across frames (new values, a new mesh, a new size) shades what a
    fresh one does."""
    from glsldiff.core.camera import look_at, projection
    from glsldiff.mesh.primitives import box_mesh, sphere_mesh
    from glsldiff.render.shading import Shader

    def args(mesh, eye, size, seed):
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        rng = np.random.default_rng(seed)
        mvp = projection(3.0 * size[1] / size[0], 3.0, 1.0, 100.0) @ look_at(eye, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
        return (v, f, mesh.vertex_normals, rng.uniform(0.1, 1.0, (len(v), 3)), np.ones((len(v), MAX_SHADER_LIGHTS)),
                rng.uniform(0.0, 0.1, (len(v), 3)), LIGHTS[:1], np.asarray(eye), mvp, 1.3, 0.05, 0.3, size)

    frames = [args(sphere_mesh(5.0, 3), (3.0, 4.0, 30.0), (40, 32), 0),
              args(sphere_mesh(5.0, 3), (-8.0, 2.0, 25.0), (40, 32), 1),
              args(box_mesh((6.0, 4.0, 5.0), (-3.0, -2.0, -2.5)), (9.0, 7.0, 20.0), (36, 30), 2)]
    with Shader(ctx) as kept:
        for a in frames:
            fresh = shade(ctx, *a)
            assert np.count_nonzero(fresh.sum(axis=2)) > 100
            np.testing.assert_array_equal(kept.shade(*a), fresh)
