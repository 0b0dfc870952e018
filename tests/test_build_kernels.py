"""The compiled loops of the tetrahedral grid's build against the numpy code they replace,
bit for bit (the grid a mesh gets must not change): the shape quality, the unique edges, the
closest faces (glsldiff.grids, glsldiff.mesh.closest); the untangling's in test_untangle_kernels.py."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.grids.tetrahedral.pillow import TET_EDGES, unique_tet_edges
from glsldiff.grids.tetrahedral.shapes import shape_quality
from glsldiff.mesh import sphere_mesh
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


def test_unique_tet_edges_equals_numpy_unique():
    X, T = _random_tets(3, n=50)
    n = len(X)
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
