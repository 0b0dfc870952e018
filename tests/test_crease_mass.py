"""The Robin term's surface mass at creases (:attr:`glsldiff.oracle.fem.TetGeometry.surface_mass`):
lumped on the edges of crease nodes, consistent elsewhere, so that an unlit face beside a lit one
across a crease keeps a non-negative fluence (issue 45 item 4: the crease specks of the CAD meshes)."""
from __future__ import annotations

import numpy as np
import pytest

import glsldiff.oracle.fem as fem
from glsldiff.grids.tetrahedral.fem_grid import build_fem_grid
from glsldiff.mesh import box_mesh
from glsldiff.oracle.fem import TetGeometry, solve_tet_direct
from glsldiff.system.tet_problem import TetProblem

HALF = np.array([6.0, 6.0, 3.0])     # a 12 x 12 x 6 mm box, h = 1 mm


@pytest.fixture(scope="module")
def box():
    return build_fem_grid(box_mesh(tuple(2.0 * HALF), origin=tuple(-HALF)), n=2, cube_size=2.0)


def test_crease_nodes_are_the_box_edges_and_the_mass_keeps_its_row_sums(box):
    geo = TetGeometry(box.positions, box.tets, box.surface)
    S = box.surface_nodes
    on_edge = (np.abs(np.abs(box.positions[S]) - HALF) < 1e-9).sum(axis=1) >= 2
    np.testing.assert_array_equal(geo.crease_nodes[S], on_edge)
    assert geo.crease_nodes.sum() == on_edge.sum() > 0
    M = geo.surface_mass
    np.testing.assert_allclose(np.asarray(M.sum(axis=1)).ravel(), geo.node_areas, rtol=1e-12, atol=1e-15)
    assert abs(M - M.T).max() == 0.0
    C = M.tocoo()
    off = (C.row != C.col) & (C.data != 0.0)
    assert not np.any(off & (geo.crease_nodes[C.row] | geo.crease_nodes[C.col]))   # lumped at the creases
    assert np.any(off)                                                                 # consistent elsewhere


def test_unlit_faces_beside_a_lit_one_stay_non_negative(box, monkeypatch):
    """Lit on the top face only, marble's kappa 0.111 mm at h = 1 mm: with the consistent mass
    everywhere the side faces' fluence next to the crease dips to -2.4 % of the largest; lumped at
    the creases, -0.07 %."""
    P = box.boundary_positions
    q = np.where(P[:, 2] > HALF[2] - 1e-6, 1.0, 0.0)[:, None] * np.ones(3)

    def lowest() -> float:
        phi = solve_tet_direct(TetProblem(box, 0.111, 0.002, q, eta=1.3))[0][box.surface_nodes, 0]
        return float(phi.min() / phi.max())
    assert lowest() > -1e-3
    monkeypatch.setattr(fem, "CREASE_LUMP_DEG", 180.0)      # no crease nodes: the consistent mass everywhere
    assert lowest() < -0.02


def test_flat_tetrahedra_lump_the_mass_at_their_surface_nodes(box):
    """An interior node pushed up close to the top face flattens the tetrahedra between it and
    the face: their surface nodes join the lumped ones (the consistent entries would add to their
    stiffness's positive couplings), and the mass keeps its row sums."""
    from glsldiff.grids.tetrahedral.shapes import SHAPE_TARGET, shape_quality
    X = box.positions.copy()
    S = box.surface_nodes
    inner = np.setdiff1d(np.unique(box.tets), S)
    v = inner[np.argmin(np.abs(X[inner, :2]).sum(axis=1) + np.abs(X[inner, 2] - HALF[2]))]   # under the top's centre
    assert HALF[2] - X[v, 2] > 0.2
    X[v, 2] = HALF[2] - 0.05                       # 5 % of h under the face
    q = shape_quality(X, box.tets)
    assert q.min() > 0 and (q < SHAPE_TARGET).any()
    geo = TetGeometry(X, box.tets, box.surface)
    flat = geo.flat_surface_nodes
    expect = np.zeros(len(X), dtype=bool)
    expect[box.tets[q < SHAPE_TARGET].ravel()] = True
    expect &= np.isin(np.arange(len(X)), S)
    np.testing.assert_array_equal(flat, expect)
    assert flat.any() and not (flat & geo.crease_nodes).all()
    C = geo.surface_mass.tocoo()
    off = (C.row != C.col) & (C.data != 0.0)
    assert not np.any(off & (flat[C.row] | flat[C.col]))
    np.testing.assert_allclose(np.asarray(geo.surface_mass.sum(axis=1)).ravel(), geo.node_areas, rtol=1e-12)
    plain = TetGeometry(box.positions, box.tets, box.surface)      # the undistorted box: no flat tetrahedra
    assert not plain.flat_surface_nodes.any()
