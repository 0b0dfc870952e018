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
