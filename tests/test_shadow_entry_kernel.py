"""The compiled ShadowMap.entry / entry_normals (glsldiff.render.shadows) against the numpy code
they replaced (kept here as the reference), on real shadow maps of a torus and a box: a
directional light (one orthographic view), a point light (six cube views), a narrow spot light
(one perspective view, its cone cutting the mesh) and a wide one (a cube); points inside and
around the mesh, far outside every view and behind the spot light; and the kernel's closest
point on a triangle against glsldiff.mesh.closest.closest_on_triangles, degenerate triangles
included."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.mesh import box_mesh, torus_mesh
from glsldiff.mesh.closest import closest_on_triangle, closest_on_triangles
from glsldiff.mesh.types import normalize
from glsldiff.physics.lights import DirectionalLight, PointLight, SpotLight, to_light
from glsldiff.render.shadows import ON_FACE_TEXELS, DepthRenderer, ShadowMap

SIZE = 256
FAR = 1.0e30                        # the maps' clear value (no surface)
TOL = 1e-12


# ---- the numpy code the kernels replaced ----------------------------------------------------
def _taps(sm: ShadowMap, p: np.ndarray, table: np.ndarray):
    """Depth, the atlas ``table``'s values at the 2 x 2 texels, bilinear weights, the
    inside-the-view mask and the texel's width at each point."""
    n = len(p)
    depth, ok, texel = np.zeros(n), np.zeros(n, dtype=bool), np.zeros(n)
    vals = np.zeros((4, n) + table.shape[2:], dtype=table.dtype)
    wts = np.zeros((4, n))
    flat, cols = table.reshape((-1,) + table.shape[2:]), table.shape[1]
    which = sm._views_of(p)
    for k, v in enumerate(sm.views):
        sel = np.flatnonzero(which == k)
        if sel.size == 0:
            continue
        if sel.size == n:
            sel = slice(None)
        depth[sel], fx, fy, ok[sel], scale = sm._project(v, p[sel], sm.size)
        texel[sel] = 2.0 * scale / sm.size
        for j, (iy, ix, w) in enumerate(sm._texels(v, fx, fy)):
            vals[j, sel], wts[j, sel] = np.take(flat, iy * cols + ix, axis=0), w
    return depth, vals, wts, ok, texel


def entry_reference(sm: ShadowMap, p: np.ndarray) -> np.ndarray:
    depth, vals, wts, ok, _ = _taps(sm, p, sm.front)
    have = vals < 0.5 * FAR
    bil = (np.where(have, vals, 0.0) * wts).sum(axis=0)
    near = vals[np.argmax(wts, axis=0), np.arange(len(p))]
    front = np.where(have.all(axis=0), bil, np.where(near < 0.5 * FAR, near, np.nan))
    return np.where(ok, np.maximum(depth - front, 0.0), np.nan)


def entry_normals_reference(sm: ShadowMap, y: np.ndarray) -> np.ndarray:
    tri, cn = sm.surface
    n = len(y)
    out = np.full((n, 3), np.nan)
    _, faces, wts, _, texel = _taps(sm, y, sm.face)
    f0 = faces[np.argmax(wts, axis=0), np.arange(n)].astype(np.int64)
    f = f0.copy()
    d2 = np.full(n, np.inf)
    bary = np.zeros((n, 3))
    off = np.flatnonzero(f >= 0)
    for j in range(-1, 4):
        if j < 0:
            at, fj = off, f[off]
        else:
            fj = faces[j, off].astype(np.int64)
            new = (fj >= 0) & (fj != f0[off]) & (faces[:j, off] != fj).all(axis=0)
            at, fj = off[new], fj[new]
        if at.size == 0:
            continue
        t = tri[fj]
        bj = closest_on_triangles(y[at], t[:, 0], t[:, 1], t[:, 2])
        dj = ((np.einsum("ij,ijk->ik", bj, t) - y[at]) ** 2).sum(axis=1)
        better = dj < d2[at]
        k = at[better]
        d2[k], bary[k], f[k] = dj[better], bj[better], fj[better]
        if j < 0:
            inside = (bj > 0.0).all(axis=1) & (dj <= (ON_FACE_TEXELS * texel[off]) ** 2)
            off = off[~inside & ((faces[:, off] != fj) & (faces[:, off] >= 0)).any(axis=0)]
    have = np.flatnonzero(f >= 0)
    out[have] = normalize(np.einsum("ij,ijk->ik", bary[have], cn[f[have]]))
    return out


# ---- set-up ----------------------------------------------------------------------------------
MESHES = {"torus": lambda: torus_mesh(30.0, 10.0),
          "box": lambda: box_mesh((60.0, 40.0, 30.0), origin=(-30.0, -20.0, -15.0))}
SUN = np.array([-0.4, 0.7, 0.6]) / np.linalg.norm([-0.4, 0.7, 0.6])
LIGHTS = {
    "directional": DirectionalLight(tuple(SUN), (1.0, 1.0, 1.0)),
    "point": PointLight((70.0, -40.0, 90.0), (1.0, 1.0, 1.0)),
    # aimed past the centre, a 12-degree cone cuts the mesh: texels at the tile's edges hold faces
    "spot": SpotLight((20.0, 90.0, 60.0), tuple(-np.array([2.0, 8.0, 6.0]) / np.linalg.norm([2.0, 8.0, 6.0])),
                      (1.0, 1.0, 1.0), cone_deg=12.0, falloff_deg=0.0),
    "wide spot": SpotLight((0.0, -10.0, 80.0), (0.0, 0.0, -1.0), (1.0, 1.0, 1.0), cone_deg=75.0,
                           falloff_deg=0.0),
}


def _points(mesh, rng) -> np.ndarray:
    """Inside (below the surface), around the mesh, far outside every view, and near the spot
    lights (behind and beside them). The points below the surface are moved off the vertex
    normals: a point on the line of a vertex normal of a symmetric mesh is as far from two
    faces, and which one is the closer is then a matter of rounding."""
    v, nrm = mesh.vertices, mesh.vertex_normals
    i = rng.integers(0, len(v), 3000)
    inside = v[i] - rng.uniform(0.05, 4.0, (len(i), 1)) * nrm[i] + rng.normal(scale=0.3, size=(len(i), 3))
    lo, hi = v.min(axis=0), v.max(axis=0)
    c, r = 0.5 * (lo + hi), 0.5 * (hi - lo)
    around = c + rng.uniform(-1.5, 1.5, (3000, 3)) * r
    far = c + rng.normal(size=(500, 3)) * 20.0 * r.max()
    near_lights = np.concatenate([np.asarray(lt.position) + rng.normal(size=(200, 3)) * 15.0
                                  for lt in LIGHTS.values() if hasattr(lt, "position")])
    return np.concatenate([inside, around, far, near_lights])


def _same(a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    ok = ~np.isnan(a)
    np.testing.assert_allclose(a[ok], b[ok], rtol=0.0, atol=TOL)


@pytest.mark.parametrize("light", list(LIGHTS), ids=list(LIGHTS))
@pytest.mark.parametrize("name", list(MESHES))
def test_kernels_equal_the_numpy_code(ctx, name, light):
    mesh = MESHES[name]()
    lt = LIGHTS[light]
    rng = np.random.default_rng(7)
    x = _points(mesh, rng)
    with DepthRenderer(ctx, mesh) as r:
        sm = r.shadow_map(lt, SIZE, normals=True)
        assert len(sm.views) == (1 if light in ("directional", "spot") else 6)
        p = x - r.centre
        ell = sm.entry(p)
        ref = entry_reference(sm, p)
        _same(ell, ref)
        ok = np.isfinite(ref)
        assert 0.2 < ok.mean() < 0.95            # hits and misses, both
        # entry points (as single scattering takes them) and the raw points (mostly off any face)
        y = np.concatenate([x[ok] + ell[ok, None] * to_light(lt, x[ok]), x]) - r.centre
        n = sm.entry_normals(y)
        n_ref = entry_normals_reference(sm, y)
        _same(n, n_ref)
        have = np.isfinite(n_ref[:, 0])
        assert have[:ok.sum()].mean() > 0.9 and not have.all()
        np.testing.assert_allclose(np.linalg.norm(n[have], axis=1), 1.0, atol=1e-12)
        if light == "spot":                     # points off the view read the clipped edge texels
            _, _, _, inside_view, _ = _taps(sm, y, sm.face)
            assert (~inside_view & have).any()


def test_entry_of_no_points_and_repeated_calls(ctx):
    """An empty input gives an empty output; the views' packing is made once per map."""
    mesh = MESHES["torus"]()
    with DepthRenderer(ctx, mesh) as r:
        sm = r.shadow_map(LIGHTS["point"], 64, normals=True)
        assert sm.entry(np.zeros((0, 3))).shape == (0,)
        assert sm.entry_normals(np.zeros((0, 3))).shape == (0, 3)
        assert sm.views_packed is sm.views_packed and len(sm.views_packed) == 6


def _kernel_bary(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.array([closest_on_triangle(*map(float, q), tuple(map(float, (*ta, *tb, *tc))))
                     for q, ta, tb, tc in zip(p, a, b, c)])


def test_closest_on_triangle_equals_closest_on_triangles():
    """Every region (corners, edges, interior) of random triangles, and degenerate ones
    (coincident corners, collinear corners, all three the same): the same barycentrics.
    Coordinates are small integers and halves, so both compute exactly."""
    rng = np.random.default_rng(3)
    n = 3000
    a, b, c = (rng.integers(-6, 7, (n, 3)) / 2.0 for _ in range(3))
    p = rng.integers(-12, 13, (n, 3)) / 2.0
    k = n // 6                                    # degenerate triangles
    b[:k] = a[:k]                                 # a = b
    c[k:2 * k] = b[k:2 * k]                       # b = c
    c[2 * k:3 * k] = a[2 * k:3 * k] + 2.0 * (b[2 * k:3 * k] - a[2 * k:3 * k])   # collinear
    b[3 * k:4 * k] = c[3 * k:4 * k] = a[3 * k:4 * k]                            # a point
    ref = closest_on_triangles(p, a, b, c)
    got = _kernel_bary(p, a, b, c)
    np.testing.assert_allclose(got, ref, rtol=0.0, atol=1e-15)
    assert np.isfinite(got).all()
    # the degenerate ones hit the (1, 0, 0) fallback somewhere, and every region is exercised
    assert (got[:4 * k] == (1.0, 0.0, 0.0)).all(axis=1).any()
    assert ((got > 0).all(axis=1)).any() and ((got == 0).sum(axis=1) == 1).any()
    assert ((got == 1.0).any(axis=1)).any()


def test_closest_on_triangle_random_floats():
    """Random float triangles and points: equal up to the order of numpy's sums."""
    rng = np.random.default_rng(4)
    n = 3000
    a, b, c = (rng.normal(size=(n, 3)) for _ in range(3))
    p = rng.normal(size=(n, 3)) * 1.5
    np.testing.assert_allclose(_kernel_bary(p, a, b, c), closest_on_triangles(p, a, b, c),
                               rtol=0.0, atol=1e-12)
