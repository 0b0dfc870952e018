"""The compiled loops of the tetrahedral grid's build against the numpy code they replace,
bit for bit (the grid a mesh gets must not change): the shape quality, the unique edges (and their
update by an edge split), the outer faces, the shape step's Nelder-Mead, the closest faces
(glsldiff.grids, glsldiff.mesh.closest), the inside test on a grid (glsldiff.mesh.inside); the
untangling's in test_untangle_kernels.py."""
from __future__ import annotations

import numpy as np
import pytest

import scipy.optimize as so

from glsldiff.grids.lattice import Lattice
from glsldiff.grids.tetrahedral.pillow import FACE_BITS, TET_EDGES, PillowComplex, unique_tet_edges
from glsldiff.grids.tetrahedral.shapes import shape_quality
from glsldiff.grids.tetrahedral.split import _split_round
from glsldiff.mesh import box_mesh, sphere_mesh
from glsldiff.mesh.inside import contains, contains_grid
from glsldiff.mesh.closest import (SERIAL_POINTS, _closest_faces, closest_on_triangle, closest_on_triangles,
                                   closest_points)


def _random_tets(seed: int, n: int = 400, t: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """Positions (mm, spread over six decades) and tetrahedra with shared nodes, flat and inverted ones."""
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n, 3)) * 10.0 ** rng.uniform(-3, 3, (n, 1))
    T = np.array([rng.choice(n, 4, replace=False) for _ in range(t)], dtype=np.int64)
    return X, T


def test_shape_quality_equals_numpy():
    X, T = _random_tets(2)
    P = X[T]
    E = P[:, TET_EDGES[:, 1]] - P[:, TET_EDGES[:, 0]]
    mean = np.sqrt(np.einsum("tek,tek->te", E, E)).mean(axis=1)
    a, b, c = E[:, 0].T, E[:, 1].T, E[:, 2].T
    det = (a[1] * b[2] - a[2] * b[1]) * c[0] + (a[2] * b[0] - a[0] * b[2]) * c[1] + (a[0] * b[1] - a[1] * b[0]) * c[2]
    assert np.array_equal(shape_quality(X, T), det * np.sqrt(2.0) / np.maximum(mean, 1e-300) ** 3)


@pytest.mark.parametrize("n, t", [(50, 3000), (300, 20000)])   # the second: > 64 neighbours per node
def test_unique_tet_edges_equals_numpy_unique(n, t):
    X, T = _random_tets(3, n=n, t=t)
    a, b = T[:, TET_EDGES[:, 0]], T[:, TET_EDGES[:, 1]]
    keys, inverse = np.unique(np.minimum(a, b) * n + np.maximum(a, b), return_inverse=True)
    edges, te = unique_tet_edges(T, n)
    assert np.array_equal(edges, np.stack([keys // n, keys % n], axis=1))
    assert np.array_equal(te, inverse.reshape(len(T), 6))


def test_closest_on_triangle_kernel_equals_numpy():
    rng = np.random.default_rng(4)
    p, t = rng.standard_normal((2000, 3)) * 3.0, rng.standard_normal((2000, 3, 3))
    t[:50, 2] = t[:50, 1]                                   # degenerate triangles
    bary = closest_on_triangles(p, t[:, 0], t[:, 1], t[:, 2])
    kern = np.array([closest_on_triangle(*p[i], tuple(t[i].ravel())) for i in range(len(p))])
    assert np.array_equal(kern, bary)


def _brute_force_faces(mesh, p: np.ndarray) -> np.ndarray:
    """The first face of least squared distance, distances as closest_points computes them."""
    t = mesh.triangles
    out = np.empty(len(p), dtype=np.int64)
    for i, q in enumerate(p):
        qq = np.repeat(q[None], len(t), axis=0)
        cp = np.einsum("ij,ijk->ik", closest_on_triangles(qq, t[:, 0], t[:, 1], t[:, 2]), t)
        out[i] = np.argmin(((qq - cp) ** 2).sum(axis=1))
    return out


def test_closest_faces_first_of_equals_on_one_and_many_threads():
    mesh = sphere_mesh(10.0, subdivisions=2)
    rng = np.random.default_rng(5)
    V = np.asarray(mesh.vertices)
    p = np.concatenate([rng.uniform(-15, 15, (SERIAL_POINTS, 3)), V, 0.5 * (V[mesh.faces[:, 0]] + V[mesh.faces[:, 1]])])
    many = _closest_faces(mesh, p)
    one = np.concatenate([_closest_faces(mesh, p[i:i + 100]) for i in range(0, len(p), 100)])
    assert np.array_equal(many, one)
    sub = np.r_[0:200, SERIAL_POINTS:SERIAL_POINTS + 150, len(p) - 150:len(p)]   # inside/outside, vertices, edges
    assert np.array_equal(many[sub], _brute_force_faces(mesh, p[sub]))
    assert np.array_equal(closest_points(mesh, p)[2], many)


def test_a_parallel_kernels_serial_twin_is_compiled_apart():
    """``kernel(parallel=True)``'s ``.serial``: the same loops on one thread, the same answer,
    compiled without ``parallel`` under its own name (numba's disk cache keys neither flag)."""
    from glsldiff.mesh.closest import _nearest_faces
    mesh = sphere_mesh(10.0, subdivisions=2)
    bvh = mesh.bvh
    p = np.random.default_rng(7).uniform(-12, 12, (300, 3))
    vi = bvh.tree.query(p)[1].astype(np.int64)
    lo, hi = bvh.heap_boxes
    args = (p, vi, bvh.vf_order, bvh.vf_start, mesh.triangles, lo, hi, bvh.depth, bvh.leaf_faces, True)
    many, one = np.empty(len(p), np.int64), np.empty(len(p), np.int64)
    _nearest_faces(*args, many)
    _nearest_faces.serial(*args, one)
    assert np.array_equal(many, one)
    serial, threaded = _nearest_faces._compile(False), _nearest_faces._compile()
    if hasattr(serial, "targetoptions"):             # compiled (not GLSLDIFF_JIT=0)
        assert serial.py_func.__qualname__ == threaded.py_func.__qualname__ + "_serial"
        assert not serial.targetoptions.get("parallel") and threaded.targetoptions.get("parallel")


def test_split_round_updates_the_unique_edges():
    """Each round of an edge split passes on the new grid's unique edges without sorting them
    again: equal to unique_tet_edges of its tetrahedra, over rounds that split edges next to
    earlier midpoints."""
    X, T = _random_tets(6, n=120, t=1500)
    F = np.zeros((0, 3), dtype=np.int64)
    edges, te = unique_tet_edges(T, len(X))
    for _ in range(4):
        free = np.ones(len(T), dtype=bool)
        chosen = []
        for e in np.random.default_rng(len(X)).permutation(len(edges)):   # no two in one tetrahedron
            ts = np.flatnonzero((te == e).any(axis=1))
            if free[ts].all():
                free[ts] = False
                chosen.append(e)
        X, T, F, edges, te = _split_round(X, T, F, edges, te, np.array(chosen[:60], dtype=np.int64))
        want_edges, want_te = unique_tet_edges(T, len(X))
        assert np.array_equal(edges, want_edges) and np.array_equal(te, want_te)


def test_outer_faces_equal_the_sorted_quad_count():
    """The outer faces (faces of one cell), found by their axis and lowest corner, are those a
    count of the sorted corner quadruples finds."""
    rng = np.random.default_rng(8)
    cubes = np.argwhere(rng.random((5, 4, 3)) < 0.6)
    cx = PillowComplex(Lattice(cubes, 3, 2.0, np.zeros(3)))
    quads = np.concatenate([cx.cells[:, bits] for bits in FACE_BITS.values()])
    _, inv, cnt = np.unique(np.sort(quads, axis=1), axis=0, return_inverse=True, return_counts=True)
    assert np.array_equal(cx.outer_quads, quads[cnt[inv.ravel()] == 1])


def test_contains_grid_equals_contains_on_vertices_and_faces():
    """The grid's inside test (crossings above each point, per column) equals the per-point one
    where grid points lie on mesh vertices, edges and faces (crossings at their own height)."""
    s = sphere_mesh(2.0, 3)
    v = np.asarray(s.vertices)
    for xs, ys, zs in [(np.unique(v[:40, 0]), np.unique(v[:40, 1]), np.unique(v[:, 2])),
                       (np.linspace(-2.5, 2.5, 21), np.linspace(-2.5, 2.5, 11), np.linspace(-2, 2, 17))]:
        pts = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), -1).reshape(-1, 3)
        assert np.array_equal(contains_grid(s, xs, ys, zs).ravel(), contains(s, pts))
    box = box_mesh([3, 2, 1])
    xs, ys, zs = np.arange(0, 3.01, 0.5), np.arange(0, 2.01, 0.5), np.arange(0, 1.01, 0.25)
    pts = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), -1).reshape(-1, 3)
    assert np.array_equal(contains_grid(box, xs, ys, zs).ravel(), contains(box, pts))
