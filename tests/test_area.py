"""Area lights: exact form factors, Fresnel beams, P1-averaged pass-1 source, scene parsing."""
from __future__ import annotations

import math

import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.mesh import box_mesh
from glsldiff.physics.area import area_beams, form_factors
from glsldiff.physics.lights import AreaLight
from glsldiff.physics.optics import fresnel_transmittance, refracted_cosine
from glsldiff.render.pass1 import _sub_barycentrics, incident_light

_x, _w = np.polynomial.legendre.leggauss(64)
MU, W = 0.5 * (_x + 1.0), 0.5 * _w              # Gauss nodes on [0, 1]


def corner_factor(a: float, b: float, c: float) -> float:
    """Form factor (x pi: the integral of cos cos / r^2) of an a x b rectangle to a parallel
    differential area at height c above one corner (the classical closed form)."""
    X, Y = a / c, b / c
    f = (X / math.sqrt(1 + X * X) * math.atan(Y / math.sqrt(1 + X * X))
         + Y / math.sqrt(1 + Y * Y) * math.atan(X / math.sqrt(1 + Y * Y))) / (2 * math.pi)
    return math.pi * f


@pytest.mark.parametrize("samples", [1, 3, 8])
@pytest.mark.parametrize("height", [1e-3, 0.5, 2.0, 50.0])
def test_form_factor_matches_the_closed_form_at_any_subdivision(samples, height):
    light = AreaLight((0, 0, 0), (0, 0, 1), (4.0, 6.0), (1, 1, 1), samples=samples)
    g, cos = form_factors(light, [[0.0, 0.0, height], [2.0, 3.0, height]], [[0, 0, -1.0]] * 2)
    assert g.shape == (2, samples ** 2)
    assert g[0].sum() == pytest.approx(4 * corner_factor(2.0, 3.0, height), rel=1e-9)
    assert g[1].sum() == pytest.approx(corner_factor(4.0, 6.0, height), rel=1e-9)   # above a corner
    assert np.all((cos >= 0) & (cos <= 1))


def test_clipped_form_factor_of_a_tilted_receiver_matches_quadrature():
    """A receiver whose tangent plane cuts the rectangle sees only the part above it."""
    n = np.array([1.0, 0.0, -1.0]) / math.sqrt(2.0)
    x = np.linspace(-2, 2, 1601)
    X, Y = np.meshgrid(x, x)
    R = np.stack([X, Y, -np.ones_like(X)], -1)           # from the point (0, 0, 1) to the rectangle
    r = np.linalg.norm(R, axis=-1)
    ref = np.trapezoid(np.trapezoid(np.clip(R @ n / r, 0, None) / r / r ** 2, x), x)
    for s in (1, 5, 16):
        g, _ = form_factors(AreaLight((0, 0, 0), (0, 0, 1), (4, 4), (1, 1, 1), samples=s), [[0, 0, 1.0]], [n])
        assert g.sum() == pytest.approx(ref, rel=2e-5)


def test_nothing_behind_the_emitter_or_facing_away():
    light = AreaLight((0, 0, 0), (0, 0, 1), (4, 4), (1, 1, 1))
    g, _ = form_factors(light, [[0, 0, -1.0], [0, 0, 1.0], [0, 0, 0.0]], [[0, 0, 1.0], [0, 0, 1.0], [0, 0, -1.0]])
    assert not g.any()


def test_fresnel_beams_converge_and_a_point_on_the_emitter_sees_normal_incidence():
    p, n = [[1.0, 0.5, 1.0]], [[0.0, 0.6, -0.8]]
    vals = [area_beams(AreaLight((0, 0, 0), (0, 0, 1), (4, 4), (1, 1, 1), samples=s), p, n, 1.4)[0].sum()
            for s in (4, 16, 32)]
    assert abs(vals[1] - vals[2]) < 1e-3 * vals[2] and abs(vals[0] - vals[2]) < 2e-3 * vals[2]
    # just above a large emitter: one sub-rectangle fills the hemisphere; its light arrives from every
    # direction, so it crosses with the cosine-weighted hemispherical mean of F_t (issue 41: it used to
    # take F_t at its mean direction, normal incidence: 1 - R(1) = 0.972 at eta 1.4, against 0.917)
    g, t = area_beams(AreaLight((0, 0, -0.02), (0, 0, 1), (40, 40), (1, 1, 1)), [[-2.7, -2.76, 0.0]],
                      [[0, 0, -1.0]], 1.4)
    gg, _ = form_factors(AreaLight((0, 0, -0.02), (0, 0, 1), (40, 40), (1, 1, 1)), [[-2.7, -2.76, 0.0]],
                         [[0, 0, -1.0]])
    k = int(np.argmax(g[0]))
    hemi = 2.0 * float((MU * W * fresnel_transmittance(1.4, MU)).sum())
    assert g[0, k] / gg[0, k] == pytest.approx(hemi, rel=2e-3)
    assert g[0].sum() / gg[0].sum() == pytest.approx(hemi, rel=3e-3)
    assert 0.7 < t[0, k] < 0.95                     # refracted cosines spread over [sqrt(1 - 1/1.4^2), 1]


def test_a_lambertian_light_touching_the_surface_crosses_with_the_hemispherical_fresnel_mean():
    """Issue 41's defect: a 5 x 5 mm patch 0.02 mm below a slab (eta 1.3) put 0.983 of its light
    through the boundary at each point above it (F_t at normal incidence, whatever the number of
    samples); the cosine-weighted mean over the hemisphere is 0.939."""
    light = AreaLight((0, 0, -0.02), (0, 0, 1), (5, 5), (1, 1, 1), samples=4)
    p = np.stack([np.linspace(-1.5, 1.5, 7), np.linspace(-1.0, 1.2, 7), np.zeros(7)], axis=1)
    n = np.tile([0.0, 0.0, -1.0], (7, 1))
    g, _ = area_beams(light, p, n, 1.3)
    gg, _ = form_factors(light, p, n)
    hemi = 2.0 * float((MU * W * fresnel_transmittance(1.3, MU)).sum())
    assert hemi == pytest.approx(0.939, abs=1e-3)
    np.testing.assert_allclose(g.sum(axis=1) / gg.sum(axis=1), hemi, rtol=0.01)
    assert refracted_cosine(1.4, 0.0) == 0.0 and refracted_cosine(None, 0.3) == pytest.approx(0.3)


def test_area_light_checks():
    with pytest.raises(InputError, match="parallel"):
        AreaLight((0, 0, 0), (0, 0, 1), (1, 1), (1, 1, 1), up=(0, 0, 2))
    with pytest.raises(InputError, match="size"):
        AreaLight((0, 0, 0), (0, 0, 1), (1, -1), (1, 1, 1))
    with pytest.raises(InputError, match="shadows"):
        AreaLight((0, 0, 0), (0, 0, 1), (1, 1), (1, 1, 1), shadows=True)
    right, up, fwd = AreaLight((0, 0, 0), (0, 0, 2), (2, 1), (1, 1, 1)).frame
    np.testing.assert_allclose(fwd, [0, 0, 1])
    assert abs(right @ up) < 1e-12


def test_sub_barycentrics_tile_the_triangle():
    b = _sub_barycentrics(4)
    assert b.shape == (16, 3) and np.allclose(b.sum(axis=1), 1.0) and b.min() > 0
    np.testing.assert_allclose(b.mean(axis=0), 1 / 3)


def test_pass1_averages_an_area_light_over_the_node_cells(ctx):
    """A sharp-edged patch on a coarse grid: sampled at the nodes its lit area snaps to whole
    cells; averaged over the nodes' P1 cells the integrated irradiance is the patch's own."""
    h = 0.5
    xs = np.arange(-6.0, 6.0 + h / 2, h)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    p = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    m = len(xs)
    idx = np.arange(X.size).reshape(m, m)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tri = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    n = np.tile([0, 0, -1.0], (len(p), 1))
    light = AreaLight((0.0, 0.0, -0.01), (0, 0, 1), (4.25, 4.25), (1, 1, 1))   # 9 x 9 nodes inside
    mesh = box_mesh((12, 12, 2), origin=(-6, -6, 0))
    sampled, _ = incident_light(mesh, p, n, [light], None, ctx=ctx)
    averaged, info = incident_light(mesh, p, n, [light], None, ctx=ctx, triangles=tri)
    area = np.bincount(tri.ravel(), np.full(tri.size, h * h / 2 / 3), minlength=len(p))
    exact = 4.25 * 4.25 * math.pi        # nearly all of pi per unit area under the patch (gap 0.01 mm)
    assert info[0]["refined_triangles"] > 0
    assert abs((area * averaged[:, 0]).sum() / exact - 1) < 0.01
    assert (area * sampled[:, 0]).sum() / exact - 1 > 0.08        # sampled: 9 x 9 whole cells lit (+12 %)


def test_solid_angles_of_sub_rectangles_near_and_far():
    """On the axis of a square of side a at height h: 4 arcsin(a^2 / (a^2 + 4 h^2)); 2 pi as h -> 0;
    0 behind the emitting side; the far (point) form within 1.1 %."""
    from glsldiff.physics.area import solid_angles

    light = AreaLight((0, 0, 0), (0, 0, 1), (3.0, 3.0), (1, 1, 1), samples=3)   # 1 mm squares
    h = np.array([1e-4, 0.1, 0.5, 2.0, 5.0, 50.0])
    p = np.stack([np.zeros_like(h), np.zeros_like(h), h], 1)
    omega = solid_angles(light, np.full(len(h), 4), p)                           # the centre square
    np.testing.assert_allclose(omega, 4 * np.arcsin(1.0 / (1.0 + 4 * h * h)), rtol=1.1e-2)
    np.testing.assert_allclose(omega[:4], 4 * np.arcsin(1.0 / (1.0 + 4 * h[:4] ** 2)), rtol=1e-9)
    assert omega[0] == pytest.approx(2 * math.pi, rel=1e-3)
    assert solid_angles(light, [4], [[0.0, 0.0, -1.0]])[0] == 0.0
