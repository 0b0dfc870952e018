"""glsldiff.render.pass1 (and its shadow maps, glsldiff.render.shadows): transmitted irradiance
at boundary nodes (Wang et al. 2008 sec. 5).

Expected values are computed here independently: Fresnel from its own s/p formula, shadow
regions from box geometry, hemispherical integrals by trapezoid quadrature, visibility by
Moller-Trumbore ray casting against the mesh triangles.
"""
from __future__ import annotations

import math

import moderngl
import numpy as np
import pytest

from glsldiff import mesh as M
from glsldiff.core.errors import InputError
from glsldiff.physics.lights import (DirectionalLight, EnvironmentLight, PointLight, ProjectorLight, SpotLight,
                                     casts_shadows, projector_factor)
from glsldiff.physics.sh import fibonacci_directions, sh_irradiance, sh_project
from glsldiff.render.pass1 import incident_light, visibility

pytest.importorskip("trimesh")
pytest.importorskip("pymeshlab")

ETA = 1.3


# ---- independent references ---------------------------------------------------------------
def fresnel_t(eta, cos_i):
    """1 - unpolarised Fresnel reflectance, written out here (not glsldiff.physics.optics)."""
    c = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0)
    sin_t2 = (1.0 - c * c) / eta**2
    ct = np.sqrt(np.clip(1.0 - sin_t2, 0.0, 1.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = ((c - eta * ct) / (c + eta * ct)) ** 2
        rp = ((eta * c - ct) / (eta * c + ct)) ** 2
    r = np.where(sin_t2 >= 1.0, 1.0, 0.5 * (rs + rp))
    return 1.0 - np.nan_to_num(r, nan=1.0)


def hemispherical(eta, f=lambda t: 1.0):
    """2 pi int_0^1 f(t) t F_t(eta, t) dt by the trapezoid rule on 400k intervals."""
    t = np.linspace(0.0, 1.0, 400_001)
    return 2.0 * math.pi * np.trapezoid(f(t) * t * fresnel_t(eta, t), t)


def ray_hits(mesh, origins, direction):
    """Whether rays origins + s direction (s > 0) hit any triangle (Moller-Trumbore)."""
    tri = mesh.triangles
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d = np.asarray(direction, dtype=np.float64)
    pvec = np.cross(d, e2)                                   # (F, 3)
    det = np.einsum("fj,fj->f", e1, pvec)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    out = np.zeros(len(origins), dtype=bool)
    for i, o in enumerate(origins):
        tvec = o - a
        u = np.einsum("fj,fj->f", tvec, pvec) * inv
        q = np.cross(tvec, e1)
        v = (q @ d) * inv
        s = np.einsum("fj,fj->f", e2, q) * inv
        out[i] = np.any(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (s > 1e-9))
    return out


def latlong(height, width, fn):
    """A lat-long map from fn(x, y, z) with the documented convention (row 0 = +z, u = 0 at
    azimuth -pi, azimuth increasing with u)."""
    theta = (np.arange(height) + 0.5) * math.pi / height
    phi = -math.pi + (np.arange(width) + 0.5) * 2.0 * math.pi / width
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    x, y, z = np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)
    img = fn(x, y, z)
    return np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img


# ---- meshes ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def offset_sphere():
    return M.sphere_mesh(10.0, 4, center=(3.0, -2.0, 5.0))


@pytest.fixture(scope="module")
def torus():
    return M.torus_mesh(10.0, 4.0, 48, 24)


@pytest.fixture(scope="module")
def two_boxes():
    """A 20 x 20 x 10 mm slab and a 4 x 4 x 2 mm box floating above it (z 15..17)."""
    big = M.box_mesh((20.0, 20.0, 10.0))
    small = M.box_mesh((4.0, 4.0, 2.0), origin=(8.0, 8.0, 15.0))
    return M.Mesh(np.vstack([big.vertices, small.vertices]),
                  np.vstack([big.faces, small.faces + len(big.vertices)]), name="two boxes")


@pytest.fixture(scope="module")
def slab_top():
    xs = np.linspace(0.25, 19.75, 40)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    pts = np.c_[X.ravel(), Y.ravel(), np.full(X.size, 10.0)]
    return pts, np.tile([0.0, 0.0, 1.0], (len(pts), 1))


# ---- directional light -------------------------------------------------------------------------
def test_directional_sphere_closed_form_and_far_side(ctx, offset_sphere):
    p, n = offset_sphere.vertices, offset_sphere.vertex_normals
    w = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
    irr = np.array([1.0, 2.0, 3.0])
    light = DirectionalLight(direction=(2.0, 4.0, 6.0), irradiance=irr)  # normalised inside
    assert np.allclose(light.direction, w)
    E, info = incident_light(offset_sphere, p, n, [light], eta=ETA, ctx=ctx)
    assert E.shape == (len(p), 3) and E.dtype == np.float64
    cos = n @ w
    ref = (np.clip(cos, 0, None) * fresnel_t(ETA, cos))[:, None] * irr
    lit = cos > 0.1
    np.testing.assert_allclose(E[lit], ref[lit], rtol=1e-9)
    assert np.all(E[cos <= 0] == 0.0)
    assert info[0]["light"] == "directional" and info[0]["shadow_map"] == "1024x1024"
    assert info[0]["seconds"] >= 0 and info[0]["facing"] == int((cos > 0).sum())
    assert info[0]["shadowed"] < 0.02 * info[0]["facing"]  # only at the terminator

    # the shadow map itself: nodes on the surface and 0.3 mm inside, with and without normals
    for pts in (p, p - 0.3 * n):
        for nn in (None, n):
            v = visibility(offset_sphere, pts, light, ctx=ctx, normals=nn)
            assert v.shape == (len(p),) and v.min() >= 0 and v.max() <= 1
            assert np.all(v[cos > 0.15] == 1.0), "lit side must be lit (no shadow acne)"
            assert np.all(v[cos < -0.15] == 0.0), "far side must be in shadow"


@pytest.mark.parametrize("kind", ["directional", "point", "spot_cube", "spot", "projector"])
def test_box_casts_shadow(ctx, two_boxes, slab_top, kind):
    pts, nrm = slab_top
    x, y = pts[:, 0], pts[:, 1]
    I = np.array([3.0, 2.0, 1.0])
    if kind == "directional":
        w = np.array([0.3, 0.0, 1.0]) / math.hypot(0.3, 1.0)
        light = DirectionalLight(w, I)
        # shadow of the box 8..12 x 8..12 at heights 15..17 shifted by -0.3 (z - 10) in x
        lo_x, hi_x, lo_y, hi_y = 8.0 - 2.1, 12.0 - 1.5, 8.0, 12.0
        cos = np.full(len(pts), w[2])
        expected = (cos * fresnel_t(ETA, cos))[:, None] * I
    else:
        pos = np.array([10.0, 10.0, 40.0])
        if kind == "point":
            light = PointLight(pos, I)
        elif kind == "spot_cube":  # wide cone: six cube views
            light = SpotLight(pos, (0.0, 0.0, -1.0), I, cone_deg=80.0, falloff_deg=70.0)
        elif kind == "projector":  # a white image whose frustum covers the slab (half width 17 mm)
            light = ProjectorLight(pos, (0.0, 0.0, -1.0), np.ones((3, 4, 3)), I, fov_deg=60.0)
        else:
            light = SpotLight(pos, (0.0, 0.0, -1.0), I, cone_deg=40.0, falloff_deg=35.0)
        # central projection from 30 mm above the slab: the box top (z = 17) casts the widest
        half = 2.0 * 30.0 / 23.0
        lo_x = lo_y = 10.0 - half
        hi_x = hi_y = 10.0 + half
        d = pos - pts
        r2 = (d**2).sum(axis=1)
        cos = d[:, 2] / np.sqrt(r2)
        expected = (cos * fresnel_t(ETA, cos) / r2)[:, None] * I  # all inside the falloff angle
    E, info = incident_light(two_boxes, pts, nrm, [light], eta=ETA, ctx=ctx, shadow_map_size=512)
    m = 0.35  # mm from the shadow edge
    inside = (x > lo_x + m) & (x < hi_x - m) & (y > lo_y + m) & (y < hi_y - m)
    outside = (x < lo_x - m) | (x > hi_x + m) | (y < lo_y - m) | (y > hi_y + m)
    assert inside.sum() > 40 and outside.sum() > 1000
    assert np.all(E[inside] == 0.0), "points in the cast shadow must get no light"
    np.testing.assert_allclose(E[outside], expected[outside], rtol=1e-9)
    label = "6 x 512x512 (cube)" if kind in ("point", "spot_cube") else "512x512"
    assert info[0]["shadow_map"] == label
    assert inside.sum() <= info[0]["shadowed"] <= len(pts) - outside.sum()


def test_visibility_matches_ray_casting(ctx, torus):
    """Torus (self-shadowing): shadow-map visibility vs exact ray casting, directional and point."""
    rng = np.random.default_rng(3)
    idx = rng.choice(len(torus.vertices), 400, replace=False)
    p, n = torus.vertices[idx], torus.vertex_normals[idx]
    cases = [DirectionalLight((1.0, 0.2, 0.25), 1.0), DirectionalLight((1.0, 0.2, 0.1), 1.0),
             PointLight((25.0, 3.0, 6.0), 1.0), PointLight((0.0, 0.0, 1.0), 1.0)]  # last: in the hole
    lit = shadowed = 0
    for light in cases:
        v = visibility(torus, p, light, ctx=ctx, shadow_map_size=512, normals=n)
        if isinstance(light, DirectionalLight):
            w = np.broadcast_to(np.asarray(light.direction), p.shape)
        else:
            d = np.asarray(light.position) - p
            w = d / np.linalg.norm(d, axis=1, keepdims=True)
        cos = np.einsum("ij,ij->i", n, w)
        sel = np.flatnonzero(cos > 0.25)
        truth = np.ones(len(sel), dtype=bool)
        for k, i in enumerate(sel):
            o = p[i] + 1e-4 * n[i]
            if isinstance(light, DirectionalLight):
                truth[k] = not ray_hits(torus, o[None], w[i])[0]
            else:  # only hits before the light count
                dist = np.linalg.norm(np.asarray(light.position) - o)
                truth[k] = not _hit_before(torus, o, w[i], dist)
        agree = np.mean((v[sel] > 0.5) == truth)
        assert agree >= 0.97, f"{light}: shadow map agrees with ray casting on {agree:.1%} only"
        lit, shadowed = lit + truth.sum(), shadowed + (~truth).sum()
        assert np.all(v[cos < -0.3] < 0.5), "points facing away from the light are shadowed"
    assert lit > 300 and shadowed > 100, "the cases must exercise both outcomes"


def _hit_before(mesh, origin, direction, dist):
    tri = mesh.triangles
    a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    pvec = np.cross(direction, e2)
    det = np.einsum("fj,fj->f", e1, pvec)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = origin - a
    u = np.einsum("fj,fj->f", tvec, pvec) * inv
    q = np.cross(tvec, e1)
    v = (q @ direction) * inv
    s = np.einsum("fj,fj->f", e2, q) * inv
    return bool(np.any(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (s > 1e-9) & (s < dist)))


# ---- point and spot lights -------------------------------------------------------------------
def test_point_light_inverse_square(ctx, two_boxes):
    """E = I cos F_t / r^2: doubling the height above a slab point quarters E (F_t, cos = 1)."""
    p = np.array([[3.0, 4.0, 10.0], [3.0, 4.0, 10.0], [3.0, 4.0, 10.0]])
    n = np.tile([0.0, 0.0, 1.0], (3, 1))
    I = np.array([1.0, 10.0, 100.0])
    vals = []
    for h in (5.0, 10.0, 20.0):
        E, info = incident_light(two_boxes, p[:1], n[:1], [PointLight((3.0, 4.0, 10.0 + h), I)],
                                   eta=ETA, ctx=ctx, shadow_map_size=256)
        vals.append(E[0])
        np.testing.assert_allclose(E[0], I * fresnel_t(ETA, 1.0) / h**2, rtol=1e-12)
    np.testing.assert_allclose(vals[0] / vals[1], 4.0, rtol=1e-12)
    np.testing.assert_allclose(vals[1] / vals[2], 4.0, rtol=1e-12)
    # oblique: cos and 1/r^2 together, shadows off
    pos = np.array([13.0, -2.0, 18.0])
    q = np.array([[5.0, 6.0, 10.0], [15.0, 15.0, 10.0]])
    E, info = incident_light(two_boxes, q, n[:2], [PointLight(pos, I, shadows=False)], eta=ETA)
    d = pos - q
    r = np.linalg.norm(d, axis=1)
    cos = d[:, 2] / r
    np.testing.assert_allclose(E, (cos * fresnel_t(ETA, cos) / r**2)[:, None] * I, rtol=1e-12)
    assert info[0]["shadow_map"] == "none (shadows off)"


def test_spot_cutoff_and_falloff(ctx, two_boxes):
    pos = np.array([3.0, 3.0, 24.0])  # 14 mm above the slab; the small box's shadow lies at y > 10
    x = np.linspace(3.0, 19.9, 200)
    p = np.c_[x, np.full_like(x, 3.0), np.full_like(x, 10.0)]
    n = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    spot = SpotLight(pos, (0.0, 0.0, -1.0), (1.0, 1.0, 1.0), cone_deg=38.0, falloff_deg=28.0)
    point = PointLight(pos, (1.0, 1.0, 1.0))
    Es, _ = incident_light(two_boxes, p, n, [spot], eta=ETA, ctx=ctx, shadow_map_size=256)
    Ep, _ = incident_light(two_boxes, p, n, [point], eta=ETA, ctx=ctx, shadow_map_size=256)
    d = p - pos
    ang = np.degrees(np.arccos(-d[:, 2] / np.linalg.norm(d, axis=1)))
    assert ang.min() < 27.0 and ang.max() > 39.0
    full, off, mid = ang < 28.0, ang > 38.0, (ang > 28.5) & (ang < 37.5)
    np.testing.assert_allclose(Es[full], Ep[full], rtol=1e-12)
    assert np.all(Es[off] == 0.0) and np.all(Ep[off] > 0)
    ratio = Es[mid, 0] / Ep[mid, 0]
    assert np.all((ratio > 0) & (ratio < 1)) and np.all(np.diff(ratio) <= 1e-12)
    c = np.cos(np.radians(ang[mid]))
    t = (c - math.cos(math.radians(38.0))) / (math.cos(math.radians(28.0)) - math.cos(math.radians(38.0)))
    np.testing.assert_allclose(ratio, t * t * (3 - 2 * t), rtol=1e-9)


# ---- projector ------------------------------------------------------------------------------------
def _pixel_points(light, depth):
    """Points at ``depth`` mm along the axis that project onto every pixel centre, (H, W, 3);
    built from the documented convention (row 0 towards up, column 0 on the left)."""
    H, W, _ = light.image.shape
    t = math.tan(math.radians(light.fov_deg) / 2.0)
    fwd = np.asarray(light.direction)
    up = np.asarray(light.up) - (np.asarray(light.up) @ fwd) * fwd
    up /= np.linalg.norm(up)
    right = np.cross(fwd, up)
    nx = (np.arange(W) + 0.5) / W * 2.0 - 1.0
    ny = 1.0 - (np.arange(H) + 0.5) / H * 2.0
    NY, NX = np.meshgrid(ny, nx, indexing="ij")
    return (np.asarray(light.position) + depth * (fwd + (NX * t * W / H)[..., None] * right
                                                  + (NY * t)[..., None] * up))


def test_projector_pixel_irradiance_on_a_plane(ctx):
    """E_t = I img(pixel) cos F_t / r^2 at the points each pixel centre lands on; bilinear between."""
    rng = np.random.default_rng(3)
    img = rng.uniform(0.0, 2.0, (5, 7, 3))
    I = np.array([300.0, 200.0, 100.0])
    pos = np.array([2.0, -3.0, 40.0])
    light = ProjectorLight(pos, (0.1, 0.2, -1.0), img, I, up=(0.0, 1.0, 0.3), fov_deg=35.0, shadows=False)
    # the plane z = 0, tilted against the axis: project the pixel rays onto it
    centres = _pixel_points(light, 1.0) - pos                   # ray directions (H, W, 3)
    p = (pos + centres * (-pos[2] / centres[..., 2])[..., None]).reshape(-1, 3)
    n = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    E, info = incident_light(M.box_mesh((1.0, 1.0, 1.0)), p, n, [light], eta=ETA)   # no shadow map
    d = pos - p
    r2 = (d**2).sum(axis=1)
    cos = d[:, 2] / np.sqrt(r2)
    expected = (cos * fresnel_t(ETA, cos) / r2)[:, None] * I * img.reshape(-1, 3)
    np.testing.assert_allclose(E, expected, rtol=1e-9)
    assert info[0]["light"] == "projector" and info[0]["shadow_map"] == "none (shadows off)"
    np.testing.assert_allclose(projector_factor(light, p), img.reshape(-1, 3), rtol=1e-9)
    # half way between two pixel centres (same row): the mean of the two pixels
    mid = 0.5 * (_pixel_points(light, 25.0)[2, 3] + _pixel_points(light, 25.0)[2, 4])
    np.testing.assert_allclose(projector_factor(light, mid[None])[0], 0.5 * (img[2, 3] + img[2, 4]), rtol=1e-9)


def test_projector_is_dark_outside_its_frustum_and_behind_it(ctx):
    light = ProjectorLight((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), np.ones((4, 8, 3)), 1.0, fov_deg=40.0,
                             shadows=False)
    t = math.tan(math.radians(20.0))
    # on the axis, just inside / outside the top edge and the (2x wider) side edge, and behind
    p = np.array([[0.0, 0.0, 10.0], [0.0, 0.99 * 10 * t, 10.0], [0.0, 1.01 * 10 * t, 10.0],
                  [0.99 * 20 * t, 0.0, 10.0], [1.01 * 20 * t, 0.0, 10.0], [0.0, 0.0, -10.0],
                  [0.0, 0.0, 0.0]])
    n = np.tile([0.0, 0.0, -1.0], (len(p), 1))
    n[5] = (0.0, 0.0, 1.0)                                   # the point behind faces the projector
    E, info = incident_light(M.box_mesh((1.0, 1.0, 1.0)), p, n, [light], eta=ETA)
    lit = np.array([True, True, False, True, False, False, False])
    assert np.all(E[lit] > 0) and np.all(E[~lit] == 0.0), E
    assert info[0]["facing"] == int(lit.sum())
    np.testing.assert_array_equal(projector_factor(light, p)[:, 0] > 0, lit)


def test_projector_image_orientation(ctx):
    """Column 0 is the projector's left, row 0 its top (up), also for an oblique frame."""
    left = np.zeros((4, 6, 3))
    left[:, :3] = 1.0
    top = np.zeros((4, 6, 3))
    top[:2] = 1.0
    # looking along +x with up +z: the projector's left is +y
    kw = dict(position=(0.0, 0.0, 0.0), direction=(1.0, 0.0, 0.0), intensity=1.0, up=(0.0, 0.3, 1.0),
              fov_deg=30.0, shadows=False)
    p = np.array([[30.0, 3.0, 0.0], [30.0, -3.0, 0.0], [30.0, 0.0, 3.0], [30.0, 0.0, -3.0]])
    n = np.tile([-1.0, 0.0, 0.0], (4, 1))
    mesh = M.box_mesh((1.0, 1.0, 1.0))
    E_left, _ = incident_light(mesh, p, n, [ProjectorLight(image=left, **kw)], eta=ETA)
    E_top, _ = incident_light(mesh, p, n, [ProjectorLight(image=top, **kw)], eta=ETA)
    assert E_left[0, 0] > 0 and E_left[1, 0] == 0.0        # +y (left) lit, -y dark
    assert E_top[2, 0] > 0 and E_top[3, 0] == 0.0          # +z (up) lit, -z dark


def test_projector_shadow_uses_the_spot_machinery(ctx, two_boxes, slab_top):
    """The frustum-covering spot: same shadow map, so the same visibility as that spot light."""
    light = ProjectorLight((10.0, 10.0, 40.0), (0.0, 0.0, -1.0), np.ones((2, 4, 3)), 1.0, fov_deg=40.0)
    spot = light.spot
    assert isinstance(spot, SpotLight) and spot.cone_deg == spot.falloff_deg
    t = math.tan(math.radians(20.0))
    assert math.isclose(math.tan(math.radians(spot.cone_deg)), t * math.hypot(1.0, 2.0))
    pts, nrm = slab_top
    v = visibility(two_boxes, pts, light, ctx=ctx, normals=nrm, shadow_map_size=256)
    np.testing.assert_array_equal(v, visibility(two_boxes, pts, spot, ctx=ctx, normals=nrm,
                                                  shadow_map_size=256))
    assert (v == 0).sum() > 40 and (v == 1).sum() > 1000
    assert casts_shadows(light) and not casts_shadows(ProjectorLight((0, 0, 1), (0, 0, -1),
                                                                           np.ones((1, 1, 3)), 1.0,
                                                                           shadows=False))


# ---- environment light ---------------------------------------------------------------------------
@pytest.mark.parametrize("vis", [False, True])
@pytest.mark.parametrize("eta", [1.0, ETA])
def test_environment_constant_on_sphere(ctx, offset_sphere, vis, eta):
    Lrad = np.array([0.5, 1.0, 2.0])
    img = np.ones((24, 48, 3)) * Lrad
    light = EnvironmentLight(img, scale=2.0, visibility=vis, directions=32)
    E, info = incident_light(offset_sphere, offset_sphere.vertices, offset_sphere.vertex_normals, [light], eta=eta, ctx=ctx,
                               shadow_map_size=256)
    expected = 2.0 * Lrad * hemispherical(eta)  # pi L (1 - external hemispherical Fresnel)
    if eta == 1.0:
        np.testing.assert_allclose(expected, 2.0 * math.pi * Lrad, rtol=1e-9)
    np.testing.assert_allclose(E, np.broadcast_to(expected, E.shape), rtol=0.01)
    assert info[0]["light"] == "environment" and info[0]["sh_order"] == 2
    assert info[0]["shadow_map"] == ("32 x 256x256" if vis else "none (visibility off)")


def test_incident_irradiance_without_interface(ctx, offset_sphere):
    """``eta=None``: the irradiance arriving at the surface (no Fresnel factor), as a diffuse
    surface reflectance needs: E0 cos for a directional light, pi L for a constant sky."""
    p, n = offset_sphere.vertices, offset_sphere.vertex_normals
    light = DirectionalLight(direction=(0.0, 0.0, 1.0), irradiance=(1.0, 2.0, 3.0))
    E, _ = incident_light(offset_sphere, p, n, [light], eta=None, ctx=ctx)
    cos = n[:, 2]
    lit = cos > 0.1
    np.testing.assert_allclose(E[lit], cos[lit, None] * np.array([1.0, 2.0, 3.0]), rtol=1e-12)
    env = EnvironmentLight(np.full((24, 48, 3), 0.5), visibility=False)
    E, _ = incident_light(offset_sphere, p, n, [env], eta=None, ctx=ctx)
    np.testing.assert_allclose(E, math.pi * 0.5, rtol=0.01)


def test_environment_linear_map_convention(ctx, offset_sphere):
    """L = 1 + 0.5 x + 0.3 y + 0.2 z: E(n) = pi + 2 pi / 3 (0.5 n_x + 0.3 n_y + 0.2 n_z) at eta 1,
    and on +z with Fresnel: 2 pi int (1 + 0.2 t) t F_t dt."""
    img = latlong(48, 96, lambda x, y, z: 1.0 + 0.5 * x + 0.3 * y + 0.2 * z)
    n = offset_sphere.vertex_normals
    E, _ = incident_light(offset_sphere, offset_sphere.vertices, n, [EnvironmentLight(img, visibility=False)],
                            eta=1.0, ctx=ctx)
    ref = math.pi + 2.0 * math.pi / 3.0 * (n @ np.array([0.5, 0.3, 0.2]))
    np.testing.assert_allclose(E[:, 1], ref, rtol=2e-3)
    c = sh_project(img)
    up = sh_irradiance(c, [[0.0, 0.0, 1.0]], eta=ETA)
    np.testing.assert_allclose(up[0], hemispherical(ETA, lambda t: 1.0 + 0.2 * t), rtol=2e-3)
    # order 0 keeps only the mean
    E0, _ = incident_light(offset_sphere, offset_sphere.vertices, n,
                             [EnvironmentLight(img, order=0, visibility=False)], eta=1.0)
    np.testing.assert_allclose(E0, math.pi, rtol=2e-3)


def test_environment_visibility_on_torus(ctx, torus):
    """Ambient occlusion lowers the inner ring; compare with ray-cast visibility."""
    img = np.ones((16, 32, 3))
    p, n = torus.vertices, torus.vertex_normals
    K = 48
    E0, _ = incident_light(torus, p, n, [EnvironmentLight(img, visibility=False)], eta=ETA, ctx=ctx)
    E1, info = incident_light(torus, p, n, [EnvironmentLight(img, directions=K)], eta=ETA, ctx=ctx,
                                shadow_map_size=256)
    rho = np.hypot(p[:, 0], p[:, 1])
    inner = np.flatnonzero(rho < 6.1)
    outer = np.flatnonzero(rho > 13.9)
    assert len(inner) >= 24 and len(outer) >= 24
    np.testing.assert_allclose(E1[outer], E0[outer], rtol=1e-9)  # nothing blocks the outer equator
    ratio = E1[inner, 0] / E0[inner, 0]
    assert ratio.max() < 0.8, "the inner ring sees the opposite side of the torus"
    assert 0.0 < info[0]["mean_visibility"] < 1.0
    ao = visibility(torus, p, EnvironmentLight(img, directions=K), ctx=ctx, shadow_map_size=256,
                      normals=n)
    assert np.all(ao[outer] == 1.0) and ao[inner].max() < 0.8
    # independent: the same K Fibonacci directions, visibility by ray casting
    dirs = fibonacci_directions(K)
    assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0) and abs(dirs.mean(axis=0)).max() < 0.05
    for i in inner[::6]:
        cos = dirs @ n[i]
        wk = np.clip(cos, 0, None) * fresnel_t(ETA, cos)
        vis = np.array([not ray_hits(torus, (p[i] + 1e-4 * n[i])[None], w)[0] if c > 0 else False
                        for w, c in zip(dirs, cos)])
        expected = (wk * vis).sum() / wk.sum()
        assert abs(E1[i, 0] / E0[i, 0] - expected) < 0.06


# ---- mixed, info, GL hygiene ------------------------------------------------------------------------
def test_lights_add_up_and_release_gl_objects(ctx, offset_sphere, monkeypatch):
    created = []
    for name in ("texture", "framebuffer", "buffer", "program", "vertex_array"):
        orig = getattr(moderngl.Context, name)

        def wrap(self, *a, _orig=orig, **k):
            obj = _orig(self, *a, **k)
            created.append(obj)
            return obj
        monkeypatch.setattr(moderngl.Context, name, wrap)
    p, n = offset_sphere.vertices, offset_sphere.vertex_normals
    lights = [DirectionalLight((0, 0, 1), 1.0), PointLight((0, 30, 0), 50.0),
              SpotLight((30, 0, 0), (-1, 0, 0), 80.0, cone_deg=20, falloff_deg=10),
              ProjectorLight((0, -30, 0), (0, 1, 0), np.full((4, 6, 3), 0.5), 80.0, up=(0, 0, 1)),
              EnvironmentLight(np.full((8, 16, 3), 0.1), directions=8)]
    E, info = incident_light(offset_sphere, p, n, lights, eta=ETA, ctx=ctx, shadow_map_size=128)
    assert [i["light"] for i in info] == ["directional", "point", "spot", "projector", "environment"]
    assert created and all(isinstance(o.mglo, moderngl.InvalidObject) for o in created), \
        "every GL object created by incident_light must be released"
    monkeypatch.undo()
    parts = [incident_light(offset_sphere, p, n, [li], eta=ETA, ctx=ctx, shadow_map_size=128)[0] for li in lights]
    np.testing.assert_allclose(E, sum(parts), rtol=1e-12, atol=0)
    assert all(casts_shadows(li) for li in lights)
    assert not casts_shadows(PointLight((0, 0, 0), 1.0, shadows=False))
    assert not casts_shadows(EnvironmentLight(np.ones((2, 4, 3)), visibility=False))
    empty, info = incident_light(offset_sphere, np.zeros((0, 3)), np.zeros((0, 3)), lights, eta=ETA, ctx=ctx)
    assert empty.shape == (0, 3) and len(info) == 5


def test_bad_incident_light_arguments(ctx, offset_sphere):
    p, n = offset_sphere.vertices[:10], offset_sphere.vertex_normals[:10]
    sun = [DirectionalLight((0, 0, 1), 1.0)]
    cases = [
        (dict(eta=0.0), "eta"), (dict(eta=-1.3), "eta"), (dict(eta=np.nan), "eta"),
        (dict(normals=n[:9]), "normals"), (dict(normals=np.zeros((10, 3))), "normals"),
        (dict(points=p[:, :2]), "points"), (dict(points=np.where(p > 0, np.nan, p)), "points"),
        (dict(lights=["sun"]), r"lights\[0\]"), (dict(shadow_map_size=0), "shadow_map_size"),
        (dict(shadow_map_size=100.5), "shadow_map_size"), (dict(mesh="bunny"), "mesh"),
    ]
    for change, field in cases:
        args = dict(mesh=offset_sphere, points=p, normals=n, lights=sun, eta=ETA, ctx=ctx) | change
        with pytest.raises(InputError, match=field):
            incident_light(**args)
    with pytest.raises(InputError, match="normals"):
        visibility(offset_sphere, p, sun[0], ctx=ctx, normals=n[:3])
    with pytest.raises(InputError, match="light"):
        visibility(offset_sphere, p, "sun", ctx=ctx)
