"""The ray casting kernel (glsldiff.mesh.raycast.first_hits) against brute-force Moller-Trumbore
over all faces (no tree): random rays from inside and outside a torus and a box, axis-parallel
directions (zero components of either sign), rays in the planes of faces, t_min / t_max bounds,
misses; and the interpreted path (GLSLDIFF_JIT=0)."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("trimesh")

from glsldiff.core.errors import InputError  # noqa: E402
from glsldiff.mesh import box_mesh, torus_mesh  # noqa: E402
from glsldiff.mesh.raycast import first_hits  # noqa: E402


def _all_hits(mesh, o, d, t_min, t_max):
    """``(R, F)`` ray parameter of every (ray, face) hit with ``t_min < t <= t_max``, inf
    elsewhere: Moller-Trumbore, both sides, the kernel's arithmetic."""
    tri = mesh.triangles
    a, e1, e2 = tri[None, :, 0], (tri[:, 1] - tri[:, 0])[None], (tri[:, 2] - tri[:, 0])[None]
    o, d = o[:, None], d[:, None]

    def cross(x, y):
        return np.stack([x[..., 1] * y[..., 2] - x[..., 2] * y[..., 1], x[..., 2] * y[..., 0] - x[..., 0] * y[..., 2],
                         x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]], axis=-1)

    def dot(x, y):
        return x[..., 0] * y[..., 0] + x[..., 1] * y[..., 1] + x[..., 2] * y[..., 2]

    with np.errstate(all="ignore"):
        p = cross(d, e2)
        det = dot(e1, p)
        good = np.abs(det) > 1e-300
        inv = 1.0 / np.where(good, det, 1.0)
        s = o - a
        q = cross(s, e1)
        u, v, t = dot(s, p) * inv, dot(d, q) * inv, dot(e2, q) * inv
    hit = good & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > np.asarray(t_min)[..., None]) \
        & (t <= np.asarray(t_max)[..., None])
    return np.where(hit, t, np.inf)


def _check(mesh, o, d, t_min=1e-6, t_max=np.inf):
    """first_hits agrees with brute force: the same misses, t to 1e-12, the same face but for
    faces hit at the same t. Returns ``(t, face)``."""
    t, f = first_hits(mesh, o, d, t_min=t_min, t_max=t_max)
    assert t.dtype == np.float64 and f.dtype == np.int64 and t.shape == f.shape == (len(o),)
    all_t = _all_hits(mesh, o, d, t_min, t_max)
    ref = all_t.min(axis=1)
    miss = np.isinf(ref)
    np.testing.assert_array_equal(np.isinf(t), miss)
    np.testing.assert_array_equal(f[miss], -1)
    np.testing.assert_allclose(t[~miss], ref[~miss], rtol=1e-12, atol=0)
    hit = np.flatnonzero(~miss)
    assert (f[hit] >= 0).all()
    # the kernel's face is one the ray hits first, up to rounding (through an edge or a vertex,
    # the faces there are hit at t a few ulps apart, and a box is skipped if entered beyond t)
    np.testing.assert_allclose(all_t[hit, f[hit]], ref[hit], rtol=1e-12, atol=0)
    two = np.sort(all_t[hit], axis=1)[:, :2]
    clear = two[:, 1] > two[:, 0] * (1 + 1e-9)   # no other face hit near the first
    np.testing.assert_array_equal(f[hit][clear], all_t[hit][clear].argmin(axis=1))
    return t, f


def _rays(rng, n, centre, spread, zero_frac=0.4):
    o = centre + rng.uniform(-spread, spread, size=(n, 3))
    d = rng.normal(size=(n, 3)) * rng.uniform(0.1, 10.0, size=(n, 1))   # not unit
    k = int(zero_frac * n)
    d[:k // 2, rng.integers(0, 3)] = 0.0                                  # one zero component
    axis = rng.integers(0, 3, size=k - k // 2)                            # axis-parallel
    d[k // 2:k] = np.eye(3)[axis] * rng.choice([-2.0, 0.5], size=(len(axis), 1))
    d[rng.random(n) < 0.5] *= -1.0                                        # zeros of both signs
    return o, d


@pytest.fixture(scope="module")
def torus():
    return torus_mesh(20.0, 6.0, major_sections=24, minor_sections=12)


def test_random_rays_inside_and_outside_a_torus(torus):
    rng = np.random.default_rng(7)
    o, d = _rays(rng, 1500, np.zeros(3), 40.0)       # mostly outside, many misses
    t, f = _check(torus, o, d)
    assert 0.05 < np.isfinite(t).mean() < 0.9
    o, d = _rays(rng, 1500, np.zeros(3), 1.0)        # in the hole
    _check(torus, o, d)
    ang = rng.uniform(0, 2 * np.pi, 1500)            # inside the tube: every ray hits
    o = np.c_[20 * np.cos(ang), 20 * np.sin(ang), np.zeros(1500)] + rng.uniform(-3, 3, size=(1500, 3))
    _, d = _rays(rng, 1500, np.zeros(3), 1.0)
    t, f = _check(torus, o, d)
    assert np.isfinite(t).all()


def test_rays_from_the_vertices_skip_their_own_faces(torus):
    v, n = torus.vertices, torus.vertex_normals
    for t_min in (1e-9, 1e-3, 0.5, 5.0):
        t, _ = _check(torus, v, -n, t_min=t_min)
        assert (t[np.isfinite(t)] > t_min).all()
    _check(torus, v, n)                               # outwards: across the hole or nothing


def test_t_min_and_t_max_bounds(torus):
    rng = np.random.default_rng(11)
    o, d = _rays(rng, 1000, np.zeros(3), 30.0)
    t_max = rng.uniform(0.0, 40.0, size=len(o))
    t_min = rng.uniform(0.0, 10.0, size=len(o))
    for lo, hi in ((0.0, 5.0), (3.0, 25.0), (2.0, 1.0), (0.0, 0.0)):
        _check(torus, o, d, t_min=lo, t_max=hi)
    # per-ray bounds are not part of the API: check ray by ray on a few
    for i in range(0, len(o), 97):
        _check(torus, o[i:i + 1], d[i:i + 1], t_min=float(t_min[i]), t_max=float(t_max[i]))
    # t_max is inclusive, t_min exclusive, to the last bit
    t, f = first_hits(torus, o, d)
    hit = np.flatnonzero(np.isfinite(t))[:100]
    for i in hit:
        t1, f1 = first_hits(torus, o[i:i + 1], d[i:i + 1], t_max=float(t[i]))
        assert t1[0] == t[i] and f1[0] == f[i]
        t2, _ = first_hits(torus, o[i:i + 1], d[i:i + 1], t_max=float(np.nextafter(t[i], 0.0)))
        assert t2[0] == np.inf
        t3, _ = _check(torus, o[i:i + 1], d[i:i + 1], t_min=float(t[i]))
        assert t3[0] > t[i]


def test_axis_parallel_rays_on_a_box():
    """Rays along the axes through the box's planes, edges and corners: inside a slab plane
    the ray is in the slab (for +0 and -0 alike); faces in the ray's plane are not hit."""
    m = box_mesh((10.0, 20.0, 30.0), origin=(-5.0, -10.0, 0.0))
    rng = np.random.default_rng(5)
    grid = np.array([-7.0, -5.0, -2.5, 0.0, 5.0, 7.0])
    o = np.stack(np.meshgrid(grid, 2 * grid, 3 * grid + 15, indexing="ij"), axis=-1).reshape(-1, 3)
    for axis in range(3):
        for sign in (1.0, -1.0):
            for zero in (0.0, -0.0):
                d = np.full((len(o), 3), zero)
                d[:, axis] = sign * rng.uniform(0.5, 2.0)
                t, _ = _check(m, o, d)
                assert np.isfinite(t).any()
    # in the top face's plane, +x: the side face x = 5 at t = 5 whatever the sign of the zeros
    for zero in (0.0, -0.0):
        t, f = first_hits(m, [[0.0, 0.0, 30.0], [0.0, 10.0, 15.0]], [[1.0, zero, zero], [1.0, zero, zero]])
        np.testing.assert_array_equal(t, [5.0, 5.0])


def test_big_mesh_many_rays_and_no_rays():
    m = torus_mesh(20.0, 6.0, major_sections=96, minor_sections=48)   # 9216 faces
    rng = np.random.default_rng(3)
    o, d = _rays(rng, 400, np.zeros(3), 30.0)
    _check(m, o, d)
    t, f = first_hits(m, np.zeros((0, 3)), np.zeros((0, 3)))
    assert t.shape == f.shape == (0,) and t.dtype == np.float64 and f.dtype == np.int64
    t, f = first_hits(m, [], [])
    assert t.shape == (0,)


def test_bad_input(torus):
    with pytest.raises(ValueError, match="2 origins but 1 directions"):
        first_hits(torus, np.zeros((2, 3)), np.ones((1, 3)))
    with pytest.raises(InputError, match="directions"):
        first_hits(torus, np.zeros((1, 3)), [[np.nan, 0.0, 1.0]])
    with pytest.raises(InputError, match="origins"):
        first_hits(torus, np.zeros((1, 2)), np.ones((1, 3)))


_INTERPRETED = """
import sys
import numpy as np
from glsldiff.mesh import torus_mesh
from glsldiff.mesh.raycast import first_hits
m = torus_mesh(20.0, 6.0, major_sections=8, minor_sections=6)
z = np.load(sys.argv[1])
t, f = first_hits(m, z["o"], z["d"], t_min=0.1, t_max=35.0)
assert "numba" not in sys.modules
np.savez(sys.argv[2], t=t, f=f)
"""


def test_interpreted_kernel_gives_the_same(tmp_path):
    """GLSLDIFF_JIT=0 (a fresh process: the switch is read at the first call) runs the same
    functions as plain Python."""
    m = torus_mesh(20.0, 6.0, major_sections=8, minor_sections=6)
    rng = np.random.default_rng(1)
    o, d = _rays(rng, 40, np.zeros(3), 30.0)
    np.savez(tmp_path / "in.npz", o=o, d=d)
    env = dict(os.environ, GLSLDIFF_JIT="0")
    run = subprocess.run([sys.executable, "-c", _INTERPRETED, str(tmp_path / "in.npz"), str(tmp_path / "out.npz")],
                         env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    z = np.load(tmp_path / "out.npz")
    t, f = _check(m, o, d, t_min=0.1, t_max=35.0)
    np.testing.assert_array_equal(z["t"], t)
    np.testing.assert_array_equal(z["f"], f)
