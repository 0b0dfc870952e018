"""The compiled P1 kernels (glsldiff.oracle.fem, glsldiff.oracle.fem_update) against the numpy
forms they replaced, bit for bit: the gradients and local stiffness, the stiffness summed per
edge and node, the CSR pattern and the node -> tetrahedra lists, and the assembled system."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from glsldiff.grids.tetrahedral.fem_grid import build_fem_grid
from glsldiff.grids.tetrahedral.pillow import TET_EDGES
from glsldiff.mesh import sphere_mesh
from glsldiff.oracle.fem import TetGeometry, gradients_numpy, local_stiffness_numpy, tet_geometry
from glsldiff.oracle.fem_update import P1Pattern, P1System, _node_tets


@pytest.fixture(scope="module")
def grid():
    return build_fem_grid(sphere_mesh(10.0, subdivisions=2), n=3, cube_size=5.0)


def _material(n: int, seed: int):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.1, 0.5, (n, 3)), rng.uniform(0.005, 0.1, (n, 3))


def _same(a, b) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)


@pytest.mark.parametrize("scale", [1e-3, 1e-1, 1.0, 1e1, 1e3])
def test_gradients_and_local_stiffness_equal_numpy(grid, scale):
    """Over five decades of sizes, with inert (degenerate) tetrahedra among them."""
    inert = np.zeros(len(grid.tets), dtype=bool)
    inert[::5] = True
    geo = TetGeometry(np.asarray(grid.positions) * scale, np.asarray(grid.tets), np.asarray(grid.surface), inert)
    args = (geo.positions, geo.tets, geo.volumes, geo.degenerate)
    assert _same(geo.gradients, gradients_numpy(*args))
    assert _same(geo.local_stiffness, local_stiffness_numpy(*args))
    some = np.array([7, 3, 3, 0, len(geo.tets) - 1])
    assert _same(geo.local_stiffness_of(some), local_stiffness_numpy(*args)[some])


def test_flat_tetrahedron_carries_nothing():
    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]], dtype=float)
    geo = TetGeometry(X, np.array([[0, 1, 2, 3], [0, 1, 4, 2]]), np.zeros((0, 3), dtype=np.int64))
    args = (geo.positions, geo.tets, geo.volumes, geo.degenerate)
    assert geo.degenerate.tolist() == [False, True]
    assert _same(geo.local_stiffness, local_stiffness_numpy(*args)) and not geo.local_stiffness[1].any()


def test_stiffness_sums_equal_the_bincount_form(grid):
    """Per edge and per node, tetrahedron by tetrahedron: the sums of ``np.bincount`` over the
    numpy local stiffness (the form the kernel replaced)."""
    geo = tet_geometry(grid)
    kappa, _ = _material(len(geo.positions), 1)
    off, diag = geo.stiffness_sums(kappa)
    Kl = local_stiffness_numpy(geo.positions, geo.tets, geo.volumes, geo.degenerate)
    edges, tet_edges = geo._edges
    for c in range(3):
        kt = kappa[geo.tets, c].mean(axis=1)
        ref_off = np.bincount(tet_edges.ravel(), (kt[:, None] * Kl[:, TET_EDGES[:, 0], TET_EDGES[:, 1]]).ravel(),
                              minlength=len(edges))
        ref_diag = np.bincount(geo.tets.ravel(), (kt[:, None] * np.diagonal(Kl, axis1=1, axis2=2)).ravel(),
                               minlength=len(geo.positions))
        assert np.array_equal(off[:, c], ref_off) and np.array_equal(diag[:, c], ref_diag)


def _pattern_numpy(geo: TetGeometry, active: np.ndarray):
    """The pattern by ``lexsort`` (the numpy build the kernel replaced)."""
    act = np.flatnonzero(active)
    n = act.size
    index = np.full(len(geo.positions), -1, dtype=np.int64)
    index[act] = np.arange(n)
    edges = geo._edges[0]
    ai, aj = index[edges[:, 0]], index[edges[:, 1]]
    live = (ai >= 0) & (aj >= 0)
    d = np.arange(n)
    rows = np.concatenate([ai[live], aj[live], d])
    cols = np.concatenate([aj[live], ai[live], d])
    order = np.lexsort((cols, rows))
    inv = np.empty_like(order)
    inv[order] = np.arange(order.size)
    ne = int(live.sum())
    pos_ij = np.full(len(edges), -1, dtype=np.int32)   # int32 where the entries allow (always here)
    pos_ji = np.full(len(edges), -1, dtype=np.int32)
    pos_ij[live], pos_ji[live] = inv[:ne], inv[ne:2 * ne]
    pos_ii = np.full(len(geo.positions), -1, dtype=np.int64)
    pos_ii[act] = inv[2 * ne:]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))]).astype(np.int32)
    return {"indptr": indptr, "indices": cols[order].astype(np.int32), "pos_ij": pos_ij, "pos_ji": pos_ji,
            "pos_ii": pos_ii}


def _surface_mass_numpy(geo: TetGeometry, pat: P1Pattern) -> np.ndarray:
    """The consistent surface mass on every pattern position (0 off the surface), as the
    pattern kept it before."""
    sm = geo.surface_mass.tocoo()
    r, c = pat.index[sm.row], pat.index[sm.col]
    ok = (r >= 0) & (c >= 0)
    n = pat.indptr.size - 1
    keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(pat.indptr)) * n + pat.indices
    return np.bincount(np.searchsorted(keys, r[ok] * n + c[ok]), sm.data[ok], minlength=pat.indices.size)


@pytest.mark.parametrize("drop", [0, 10])
def test_pattern_equals_the_lexsort_one(grid, drop):
    """With every node active, and with every ``drop``-th used node inactive too (edges to
    inactive nodes get -1)."""
    geo = tet_geometry(grid)
    active = np.asarray(grid.active, dtype=bool).copy()
    if drop:
        active[np.flatnonzero(active)[::drop]] = False
    ref = _pattern_numpy(geo, active)
    pat = P1Pattern.build(geo, active)
    for name, value in ref.items():
        assert _same(getattr(pat, name), value), name
    if drop:
        assert (pat.pos_ij < 0).any()
    dense = np.zeros(pat.indices.size)
    dense[pat.surface_pos] = pat.surface_mass
    assert np.all(np.diff(pat.surface_pos) > 0) and np.array_equal(dense, _surface_mass_numpy(geo, pat))
    flat = geo.tets.ravel()
    node_tets, node_ptr = _node_tets(geo.tets, len(geo.positions))
    assert _same(node_tets, np.argsort(flat, kind="stable") // 4)
    assert _same(node_ptr, np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=len(geo.positions)))]))


def test_assembly_equals_the_sparse_operator_form(grid):
    """:class:`P1System`'s values, bit for bit, those of the sparse products it used before
    (tetrahedron kappa by a mean operator, sums by the transposed scatter operators, onto the
    dense Robin term)."""
    geo = tet_geometry(grid)
    kappa, mu = _material(len(geo.positions), 2)
    P = P1System(geo, grid.active, 1.3, kappa, mu)
    Kl = local_stiffness_numpy(geo.positions, geo.tets, geo.volumes, geo.degenerate)
    tets, T, n_all = geo.tets, len(geo.tets), len(geo.positions)
    rows4, rows6 = np.arange(0, 4 * T + 1, 4), np.arange(0, 6 * T + 1, 6)
    mean = sp.csr_matrix((np.full(4 * T, 0.25), tets.ravel(), rows4), shape=(T, n_all))
    to_edges = sp.csr_matrix((Kl[:, TET_EDGES[:, 0], TET_EDGES[:, 1]].ravel(), geo._edges[1].ravel(), rows6),
                             shape=(T, len(geo._edges[0])))
    to_nodes = sp.csr_matrix((np.diagonal(Kl, axis1=1, axis2=2).ravel(), tets.ravel(), rows4), shape=(T, n_all))
    kt = mean @ kappa
    e, d = to_edges.T @ kt, to_nodes.T @ kt
    live = np.flatnonzero(P._pos_ij >= 0)
    act = P.active
    ref = np.empty_like(P.values)
    robin = _surface_mass_numpy(geo, P.pattern) / (2.0 * 1.3)
    for c in range(3):
        ref[c] = robin
        ref[c, P._pos_ij[live]] += e[live, c]
        ref[c, P._pos_ji[live]] += e[live, c]
        ref[c, P._pos_ii[act]] += d[act, c] + mu[act, c] * geo.node_volumes[act]
    assert np.array_equal(P.values, ref)
    assert np.array_equal(P.system.diag, P.values[:, P._pos_ii[act]].reshape(-1))
    A = P.system.A
    assert A.indices.dtype == np.int32 and np.shares_memory(A.data, P.values)
    assert np.array_equal(A.indptr[:P.n + 1], P.indptr) and np.array_equal(A.indices[:P.indices.size], P.indices)
