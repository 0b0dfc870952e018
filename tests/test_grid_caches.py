"""On-disk caches of what is a pure function of a grid or of constants (issue 42, item 4): the
P1 geometric factors (:func:`glsldiff.oracle.fem.cached_tet_geometry`), the render mesh's
interpolation onto the grid surface (:func:`glsldiff.render.shading.cached_surface_interpolation`),
the half-space tables (:func:`glsldiff.physics.adding_doubling.halfspace_tables`) and the
H-function tables (:mod:`glsldiff.physics.halfspace`). Each must give the arrays a fresh
computation gives, bit for bit, and a cache that is off or damaged must cost speed only."""
from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from glsldiff.core import cache
from glsldiff.grids.tetrahedral.fem_grid import build_fem_grid
from glsldiff.mesh import sphere_mesh, subdivide
from glsldiff.oracle.fem import CACHED_FACTORS, cached_tet_geometry, tet_geometry
from glsldiff.physics import halfspace
from glsldiff.physics.adding_doubling import HalfspaceTables, _build_tables, halfspace_tables
from glsldiff.render.shading import cached_surface_interpolation, surface_interpolation


@pytest.fixture(scope="module")
def grid():
    return build_fem_grid(sphere_mesh(10.0, subdivisions=3), n=3, cube_size=5.0)


@pytest.fixture
def cache_dir(tmp_path, monkeypatch) -> Path:
    folder = tmp_path / "cache"
    monkeypatch.setenv("GLSLDIFF_CACHE", str(folder))
    return folder


def _entries(folder: Path, kind: str) -> list[Path]:
    return sorted(folder.glob(f"{kind}-*.pkl")) if folder.is_dir() else []


def _same(a, b) -> bool:
    """Bit-for-bit equality of arrays, sparse matrices and tuples of them (dtype included)."""
    if isinstance(a, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if sp.issparse(a):
        a, b = sp.csr_matrix(a), sp.csr_matrix(b)
        return (a.shape == b.shape and np.array_equal(a.indptr, b.indptr) and np.array_equal(a.indices, b.indices)
                and np.array_equal(a.data, b.data))
    return a.dtype == b.dtype and np.array_equal(a, b)


def test_memo_computes_once_per_key(cache_dir):
    calls = []

    def compute() -> np.ndarray:
        calls.append(1)
        return np.arange(3.0)

    assert _same(cache.memo("test", "k", np.ndarray, compute), np.arange(3.0))
    assert _same(cache.memo("test", "k", np.ndarray, compute), np.arange(3.0))
    assert len(calls) == 1 and len(_entries(cache_dir, "test")) == 1


def test_cached_tet_geometry_equals_a_fresh_one(grid, cache_dir):
    """The first call writes one entry, the second reads it: every cached factor, the
    stiffness built from them and the gradients computed lazily are those of a fresh geometry."""
    first = cached_tet_geometry(grid)
    assert len(_entries(cache_dir, "tetgeo")) == 1
    again = cached_tet_geometry(grid)
    assert set(CACHED_FACTORS) <= set(vars(again))          # pre-filled, not recomputed
    fresh = tet_geometry(grid)
    for geo in (first, again):
        for name in CACHED_FACTORS:
            assert _same(getattr(geo, name), getattr(fresh, name)), name
        kappa = np.linspace(0.5, 2.0, len(grid.positions))
        assert _same(geo.stiffness(kappa), fresh.stiffness(kappa))
        assert _same(geo.gradients, fresh.gradients)
    assert len(_entries(cache_dir, "tetgeo")) == 1


def test_cached_tet_geometry_keys_and_failures(grid, cache_dir, monkeypatch):
    """Another set of inert tetrahedra is another entry; a damaged entry is recomputed (and
    rewritten); with the cache off nothing is written and the factors stay lazy."""
    @dataclass
    class Grid:
        positions: np.ndarray
        tets: np.ndarray
        surface: np.ndarray
        inert: np.ndarray | None = None

    plain = Grid(grid.positions, grid.tets, grid.surface)
    inert = np.zeros(len(grid.tets), dtype=bool)
    inert[::7] = True
    flagged = Grid(grid.positions, grid.tets, grid.surface, inert)
    cached_tet_geometry(plain)
    geo = cached_tet_geometry(flagged)
    assert len(_entries(cache_dir, "tetgeo")) == 2
    assert _same(geo.degenerate, tet_geometry(flagged).degenerate) and geo.degenerate[::7].all()
    for entry in _entries(cache_dir, "tetgeo"):
        entry.write_bytes(b"not a pickle")
    again = cached_tet_geometry(flagged)
    assert _same(again.local_stiffness, tet_geometry(flagged).local_stiffness)
    monkeypatch.setenv("GLSLDIFF_CACHE", "off")
    lazy = cached_tet_geometry(plain)
    assert not set(CACHED_FACTORS) & set(vars(lazy))
    assert _same(lazy.local_stiffness, tet_geometry(plain).local_stiffness)


def test_cached_surface_interpolation_equals_a_fresh_one(grid, cache_dir):
    mesh = sphere_mesh(10.0, subdivisions=3)
    v = np.asarray(subdivide(mesh, grid.h).vertices)
    fresh = surface_interpolation(v, grid.boundary_positions, grid.surface_triangles)
    first = cached_surface_interpolation(v, grid.boundary_positions, grid.surface_triangles)
    again = cached_surface_interpolation(v, grid.boundary_positions, grid.surface_triangles)
    assert _same(first, fresh) and _same(again, fresh)
    assert len(_entries(cache_dir, "interp")) == 1
    other = cached_surface_interpolation(v[: len(v) // 2], grid.boundary_positions, grid.surface_triangles)
    assert _same(other, fresh[: len(v) // 2]) and len(_entries(cache_dir, "interp")) == 2


def test_halfspace_tables_from_the_cache_equal_computed_ones(cache_dir):
    """``halfspace_tables`` without its per-process memo: computed and written, then read."""
    computed = _build_tables(1.3)
    for _ in range(2):
        t = halfspace_tables.__wrapped__(1.3)
        assert isinstance(t, HalfspaceTables) and t.eta == 1.3
        for f in fields(HalfspaceTables)[1:]:
            assert _same(getattr(t, f.name), getattr(computed, f.name)), f.name
    assert len(_entries(cache_dir, "halfspace")) == 1
    halfspace_tables.__wrapped__(1.0)
    assert len(_entries(cache_dir, "halfspace")) == 2


def _scalar_h(a: float, nodes: np.ndarray, weights: np.ndarray, mu_out: np.ndarray) -> np.ndarray:
    """The H-function tables' former scalar solve: the fixed point on the Gauss nodes, run anew
    for every set of output cosines, then evaluated there."""
    H = np.ones_like(nodes)
    kernel = weights[None, :] / (nodes[:, None] + nodes[None, :])
    for _ in range(20000):
        new = 1.0 / (1.0 - 0.5 * a * nodes * (kernel @ H))
        done = np.max(np.abs(new - H)) < 1e-13
        H = new
        if done:
            break
    return 1.0 / (1.0 - 0.5 * a * mu_out * ((weights[None, :] / (mu_out[:, None] + nodes[None, :])) @ H))


def test_h_function_tables_equal_the_scalar_solves_and_come_back_from_the_cache(cache_dir):
    """One fixed point per albedo (it used to be solved twice) gives the same rows, bit for bit,
    at albedo 1 (the 20000-iteration row), near it and far from it; the cached tables are the
    computed ones."""
    u, mu, H, D, M = halfspace._build_tables()
    x, w = np.polynomial.legendre.leggauss(96)
    nodes, weights = 0.5 * (x + 1.0), 0.5 * w
    for i in (0, 1, 40, len(u) - 1):
        a = 1.0 - u[i] * u[i]
        assert np.array_equal(H[i], _scalar_h(a, nodes, weights, mu))
        Hn = _scalar_h(a, nodes, weights, nodes)
        tH = weights * nodes * Hn
        assert np.array_equal(D[i], 2.0 * (tH[None, :] / (mu[:, None] + nodes[None, :])).sum(axis=1))
        assert M[i] == 2.0 * float(tH.sum())
    for _ in range(2):
        assert _same(halfspace._tables.__wrapped__(), (u, mu, H, D, M))
    assert len(_entries(cache_dir, "hfunction")) == 1


def test_cached_load_mesh_equals_load_mesh(tmp_path, cache_dir):
    """A mesh file read through the cache is the mesh :func:`load_mesh` gives (arrays, name,
    repairs); another size or other bytes are other entries; a file that does not load raises
    every time and leaves nothing behind."""
    from glsldiff.core.errors import InputError
    from glsldiff.mesh import cached_load_mesh, load_mesh

    path = tmp_path / "t.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 5\n")
    fresh = load_mesh(str(path), size_mm=20.0)
    assert fresh.repairs                                  # the duplicate vertex was merged
    for _ in range(2):
        m = cached_load_mesh(str(path), size_mm=20.0)
        assert _same(m.vertices, fresh.vertices) and _same(m.faces, fresh.faces)
        assert (m.name, m.repairs) == (fresh.name, fresh.repairs)
    assert len(_entries(cache_dir, "mesh")) == 1
    cached_load_mesh(str(path), size_mm=10.0)
    assert len(_entries(cache_dir, "mesh")) == 2
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 99\n")
    for _ in range(2):
        with pytest.raises(InputError, match="line 8: face names vertex 99"):
            cached_load_mesh(str(path), size_mm=20.0)
    assert len(_entries(cache_dir, "mesh")) == 2


def test_vein_lattice_from_the_cache_equals_the_computed_one(cache_dir):
    """The veins material's lattice, read back from the cache, is marble_volume's, bit for bit."""
    from glsldiff.physics.material import preset
    from glsldiff.physics.procedural import marble_volume
    from glsldiff.render.materials import _vein_lattice

    base = preset("marble")
    args = (16, 3, tuple(base.sigma_a), tuple(base.sigma_s_prime), base.eta, "marble", None)
    fresh = marble_volume((16,) * 3, seed=3, base=base)
    for _ in range(2):
        assert _same(_vein_lattice.__wrapped__(*args), fresh)
    assert len(_entries(cache_dir, "veins")) == 1
    _vein_lattice.__wrapped__(16, 4, *args[2:])
    assert len(_entries(cache_dir, "veins")) == 2
