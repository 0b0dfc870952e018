"""Screened smoothing along a surface (glsldiff.mesh.smoothing) and the renderer's smoothed
exitant flux ([options].flux = "smoothed")."""
import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.mesh import box_mesh, screened_smoothing, sphere_mesh, subdivide
from glsldiff.mesh.types import vertex_areas


def _plane(nx: int = 241, ny: int = 9, h: float = 0.05):
    """A flat strip of right triangles, x in [-6, 6] mm, spacing ``h``."""
    x, y = np.meshgrid(np.arange(nx) * h - (nx - 1) * h / 2, np.arange(ny) * h, indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def test_a_step_becomes_the_screened_closed_form():
    """On a plane a step ``q = [x > 0]`` becomes ``1 - exp(-x / lambda) / 2`` (``x > 0``) and
    ``exp(x / lambda) / 2`` (``x < 0``), the screened equation's 1-D solution."""
    v, f = _plane()
    lam = 0.5
    u = screened_smoothing(v, f, np.full(len(v), lam))((v[:, 0] > 0).astype(float))
    x = v[:, 0]
    exact = np.where(x > 0, 1.0 - 0.5 * np.exp(-x / lam), 0.5 * np.exp(x / lam))
    near = np.abs(x) < 4.0                       # away from the strip's ends (no-flux there)
    assert np.abs(u - exact)[near].max() < 0.03  # the step sits between two nodes: O(h / lambda)
    assert np.abs(u - exact)[near & (np.abs(x) > 0.5)].max() < 0.01


def test_keeps_constants_conserves_the_total_and_stays_non_negative():
    m = sphere_mesh(10.0, 3)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    rng = np.random.default_rng(0)
    q = np.column_stack([np.ones(len(v)), rng.random(len(v)), (v[:, 2] > 4.0).astype(float)])
    lam = np.column_stack([np.full(len(v), 0.3), np.full(len(v), 1.0), 0.5 + 0.5 * (v[:, 0] > 0)])
    u = screened_smoothing(v, f, lam)(q)
    A = vertex_areas(v, f)
    assert np.allclose(u[:, 0], 1.0, atol=1e-10)
    assert np.allclose(A @ u, A @ q, rtol=1e-10)
    assert u.min() >= -1e-12 and u[:, 1].std() < q[:, 1].std()
    zero = screened_smoothing(v, f, np.zeros(len(v)))(q)
    assert np.allclose(zero, q)


def test_does_not_cross_a_thin_gap():
    """A 10 x 10 x 0.2 mm tile lit on its top face: the smoothed value under the top face's centre,
    on the bottom face 0.2 mm away, stays ~0 (the surface path round the rim is 5 mm); a Euclidean
    kernel of the same length would carry about half of it across."""
    m = subdivide(box_mesh((10.0, 10.0, 0.2), origin=(-5.0, -5.0, -0.1)), 0.25)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    top = v[:, 2] > 0.05
    u = screened_smoothing(v, f, np.full(len(v), 0.5))(top.astype(float))
    centre = (np.abs(v[:, 0]) < 1.0) & (np.abs(v[:, 1]) < 1.0)
    assert u[centre & top].min() > 0.99
    assert u[centre & ~top].max() < 1e-3


def test_bad_lengths_are_one_line():
    v, f = _plane(11, 3)
    with pytest.raises(InputError, match="smoothing lengths"):
        screened_smoothing(v, f, np.full(len(v) - 1, 0.5))
    with pytest.raises(InputError, match="smoothing lengths"):
        screened_smoothing(v, f, np.full(len(v), -1.0))


def test_smooth_subdivide_shades_a_coarse_sphere_smoothly():
    """The render mesh of a coarse mesh: the split vertices' normals interpolate the old faces'
    corner normals (within 1.5 degrees of the sphere's, against 7 for the flat faces' own), the
    old vertices keep theirs, and a mesh fine enough is returned as it is."""
    from glsldiff.mesh import sphere_mesh
    from glsldiff.mesh.ops import smooth_subdivide
    coarse = sphere_mesh(20.0, 2)
    fine, normals = smooth_subdivide(coarse, 1.0)
    assert len(fine.vertices) > 20 * len(coarse.vertices)
    true = fine.vertices / np.linalg.norm(fine.vertices, axis=1, keepdims=True)

    def worst(n):
        return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, true), -1.0, 1.0))).max()
    assert worst(normals) < 1.5 < 5.0 < worst(fine.vertex_normals)
    np.testing.assert_allclose(normals[:len(coarse.vertices)], coarse.vertex_normals, atol=1e-12)
    same, n_same = smooth_subdivide(coarse, 100.0)
    assert same is coarse and n_same is coarse.vertex_normals
