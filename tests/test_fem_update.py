"""The P1 system updated in place (glsldiff.oracle.fem_update) against a fresh assembly
(glsldiff.oracle.fem.assemble_tet) of the same material."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.grids.tetrahedral.fem_grid import build_fem_grid
from glsldiff.mesh import sphere_mesh
from glsldiff.oracle.fem import assemble_tet, tet_geometry
from glsldiff.oracle.fem_update import P1Pattern, P1System, cached_p1_pattern
from glsldiff.system.tet_problem import TetProblem


@pytest.fixture(scope="module")
def grid():
    return build_fem_grid(sphere_mesh(10.0, subdivisions=2), n=3, cube_size=5.0)


def _material(g, seed: int):
    rng = np.random.default_rng(seed)
    n = len(g.positions)
    return rng.uniform(0.1, 0.5, (n, 3)), rng.uniform(0.005, 0.1, (n, 3))


def _fresh(g, kappa, mu, C=2.0):
    return assemble_tet(TetProblem(g, kappa, mu, np.zeros((len(g.surface_nodes), 3)), C=C))


def _dense_equal(P: P1System, ref) -> float:
    """Largest entry difference over the largest entry."""
    d = (P.system.A - ref.A).tocoo()
    return float(np.abs(d.data).max(initial=0.0) / np.abs(ref.A.data).max())


def test_assembly_equals_assemble_tet(grid):
    kappa, mu = _material(grid, 1)
    P = P1System(tet_geometry(grid), grid.active, 2.0, kappa, mu)
    ref = _fresh(grid, kappa, mu)
    assert _dense_equal(P, ref) < 1e-13
    np.testing.assert_allclose(P.system.diag, ref.diag, rtol=1e-13)
    for c, M in enumerate(P.matrices()):
        assert abs(M - ref.block(c)[0]).max() < 1e-13 * abs(ref.A).max()


def test_local_edit_updates_only_its_rows(grid):
    kappa, mu = _material(grid, 2)
    P = P1System(tet_geometry(grid), grid.active, 2.0, kappa, mu)
    before = P.values.copy()
    centre = grid.positions[np.argmin(np.linalg.norm(grid.positions - [3.0, 0.0, 0.0], axis=1))]
    near = np.linalg.norm(grid.positions - centre, axis=1) < 2.5
    k2, m2 = kappa.copy(), mu.copy()
    k2[near] *= 0.5
    m2[near, 1] *= 3.0
    mats = P.matrices()                      # made before the edit: they must follow it
    up = P.set_material(k2, m2)
    ref = _fresh(grid, k2, m2)
    assert _dense_equal(P, ref) < 1e-13
    for c, M in enumerate(mats):
        assert abs(M - ref.block(c)[0]).max() < 1e-13 * abs(ref.A).max()
    np.testing.assert_allclose(P.system.diag, ref.diag, rtol=1e-13)
    assert set(up.nodes) == set(np.flatnonzero(near))
    # rows outside the edit's neighbourhood keep their exact values
    outside = np.setdiff1d(np.arange(P.n), up.rows)
    pos = P.row_positions(outside)
    assert np.array_equal(P.values[:, pos], before[:, pos])
    assert 0 < len(up.rows) < P.n // 2
    # the rows that changed are the edited nodes and their neighbours
    changed = np.unique(np.nonzero(P.values != before)[1])
    rows_of = np.repeat(np.arange(P.n), np.diff(P.indptr))
    assert set(np.unique(rows_of[changed])) <= set(up.rows)


def test_undo_returns_to_the_first_system(grid):
    kappa, mu = _material(grid, 3)
    P = P1System(tet_geometry(grid), grid.active, 2.0, kappa, mu)
    first = P.values.copy()
    k2 = kappa.copy()
    k2[: len(k2) // 3] *= 1.7
    for _ in range(5):
        P.set_material(k2, mu * 1.1)
        P.set_material(kappa, mu)
    np.testing.assert_allclose(P.values, first, rtol=0, atol=1e-13 * np.abs(first).max())


def test_bad_material_is_refused(grid):
    kappa, mu = _material(grid, 4)
    P = P1System(tet_geometry(grid), grid.active, 2.0, kappa, mu)
    with pytest.raises(InputError, match="shape"):
        P.set_rhs(np.zeros((3, P.n)))
    with pytest.raises(InputError, match="zero volume"):
        P.set_material(kappa, np.where(np.arange(len(mu))[:, None] == 0, -1e6, mu))


def test_lumped_boundary_mass_equals_assemble_tet(grid):
    kappa, mu = _material(grid, 5)
    P = P1System(tet_geometry(grid), grid.active, 1.7, kappa, mu, boundary_mass="lumped")
    ref = assemble_tet(TetProblem(grid, kappa, mu, np.zeros((len(grid.surface_nodes), 3)), C=1.7,
                                  boundary_mass="lumped"))
    assert _dense_equal(P, ref) < 1e-13


def test_cached_pattern_equals_a_built_one(grid, tmp_path, monkeypatch):
    monkeypatch.setenv("GLSLDIFF_CACHE", str(tmp_path))
    geo = tet_geometry(grid)
    built = P1Pattern.build(geo, np.asarray(grid.active, bool))
    first = cached_p1_pattern(geo, grid.active)        # computed and stored
    again = cached_p1_pattern(geo, grid.active)        # read back
    assert list(tmp_path.glob("p1pattern-*"))
    for name in ("index", "indptr", "indices", "pos_ij", "pos_ji", "pos_ii", "surface_pos", "surface_mass"):
        assert np.array_equal(getattr(first, name), getattr(built, name))
        assert np.array_equal(getattr(again, name), getattr(built, name))
    kappa, mu = _material(grid, 6)
    a = P1System(geo, grid.active, 2.0, kappa, mu, pattern=again)
    b = P1System(geo, grid.active, 2.0, kappa, mu)
    assert np.array_equal(a.values, b.values)
