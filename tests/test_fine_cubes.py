"""Tetrahedral grids fall back to cubes of FINE_CUBE_NODES nodes where cubes of the n asked
for cannot carry the mesh (glsldiff.grids.tetrahedral.fem_grid, step 7)."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.grids.tetrahedral.fem_grid import COVERAGE_TARGET, FINE_CUBE_NODES, FINE_TRIGGER, build_fem_grid
from glsldiff.grids.polycube import outside_distance, polycube_from_cubes, polycube_from_mesh
from glsldiff.mesh import box_mesh, sphere_mesh, surface_samples


@pytest.fixture(scope="module")
def sphere():
    return sphere_mesh(10.0, subdivisions=3)


def test_outside_distance_of_a_polycube() -> None:
    pc = polycube_from_cubes([[0, 0, 0], [1, 0, 0]], 2.0)   # the box [0, 4] x [0, 2] x [0, 2] mm
    d = outside_distance(pc, [[1.0, 1.0, 1.0], [7.0, 1.0, 1.0], [5.0, 3.0, 1.0], [2.0, -0.5, 2.5]])
    assert d == pytest.approx([0.0, 3.0, np.sqrt(2.0), np.sqrt(0.5)])


def test_smooth_mesh_keeps_the_cubes_asked_for(sphere) -> None:
    g = build_fem_grid(sphere, n=4, cube_size=5.0)   # a sphere lies ~0.47 cubes = 1.9 h outside
    assert g.complex.lattice.n == 4 and g.polycube.size == 5.0
    assert g.quality.fine_reason == "" and g.quality.requested_n == 0


def test_cubes_too_coarse_for_the_surface(sphere) -> None:
    pc = polycube_from_mesh(sphere, cube_size=5.0, thin_parts=False)
    gap = outside_distance(pc, surface_samples(sphere, 5.0 / 8)).max() / (5.0 / 8)
    assert gap > FINE_TRIGGER   # cubes of 8 nodes: the surface is farther out than the trigger
    g = build_fem_grid(sphere, n=8, cube_size=5.0)
    q = g.quality
    assert g.complex.lattice.n == FINE_CUBE_NODES
    assert g.polycube.size == pytest.approx(5.0 * FINE_CUBE_NODES / 8)     # the same h
    assert g.h == pytest.approx(5.0 / 8)
    assert q.requested_n == 8 and "outside" in q.fine_reason
    assert q.inverted == 0 and q.coverage_max <= COVERAGE_TARGET


def test_no_polycube_of_large_cubes_falls_back(sphere) -> None:
    with pytest.raises(InputError):
        polycube_from_mesh(sphere, cube_size=15.0)   # no 15 mm cube is half inside
    g = build_fem_grid(sphere, n=8, cube_size=15.0)
    assert g.complex.lattice.n == FINE_CUBE_NODES and "no polycube" in g.quality.fine_reason
    assert g.quality.inverted == 0


def test_over_the_node_budget_falls_back_to_the_requested_budget() -> None:
    plate = box_mesh((60.0, 60.0, 1.0), origin=(-30.0, -30.0, -0.5))
    # 20 cubes of n = 8 asked for: the search snaps the cubes to the 1 mm thickness, 3,600 of
    # them, 1.8 M lattice nodes; the fine cubes are searched for 20 * 4^3 cubes instead
    g = build_fem_grid(plate, n=8, n_cubes=20)
    q = g.quality
    assert g.complex.lattice.n == FINE_CUBE_NODES and "limit" in q.fine_reason
    assert g.n_active < 100_000
    assert q.inverted == 0 and q.coverage_max <= COVERAGE_TARGET


def test_n_two_has_no_fallback(sphere) -> None:
    with pytest.raises(InputError, match="polycube"):
        build_fem_grid(sphere, n=2, cube_size=15.0)


def test_render_report_says_which_cubes() -> None:
    """A scene asking for n = 8 on a sphere too small for cubes of 8 nodes renders from cubes
    of 2 and says so in its report, with the same spacing h."""
    from glsldiff.render.renderer import Renderer
    from glsldiff.render.scene import parse_scene
    scene = parse_scene({"mesh": {"source": "sphere", "size_mm": 20.0},
                         "polygrid": {"n": 8, "cubes": 30, "discretisation": "fem"},
                         "material": {"preset": "marble"}, "lights": [{"type": "directional", "direction": [0, 0, 1]}],
                         "output": {"width": 32, "height": 32}})
    said: list[str] = []
    with Renderer(status=said.append) as r:
        img, rep = r.render(scene)
        pg = r.polygrid
    assert np.isfinite(img).all() and img.max() > 0
    grid = next(n for n in rep.notes if n.startswith("grid: tetrahedral (fem)"))
    assert f"cubes of {FINE_CUBE_NODES} nodes per edge (n = 8 asked for: " in grid
    assert any("cubes of 2 nodes per edge at about the same spacing instead: with n = 8" in s for s in said)
    assert pg.complex.lattice.n == FINE_CUBE_NODES and pg.quality.inverted == 0


def test_retries_other_cube_sizes_until_the_targets_are_met(monkeypatch, sphere) -> None:
    """Step 8's control flow, on stand-in builds: a first grid that misses the targets is built
    again at the sizes of RETRY_SIZES in turn, the first one meeting both ends the search, the
    best is kept and the report says what it took (the real builds: the bench's meshes)."""
    from types import SimpleNamespace

    from glsldiff.grids.tetrahedral import fem_grid
    from glsldiff.grids.tetrahedral.fem_grid import MappingQuality, RETRY_SIZES

    outcomes = {1.0: (1, 1.1), RETRY_SIZES[0]: (0, 2.0), RETRY_SIZES[1]: (0, 1.2), RETRY_SIZES[2]: (0, 1.0)}
    calls = []

    def fake(mesh, n, cube_size, n_cubes, threshold, mapping, budget, repairs=True):
        size = 2.0 if cube_size is None else cube_size
        calls.append(round(size / 2.0, 6))
        inverted, coverage = outcomes[round(size / 2.0, 6)]
        q = MappingQuality(inverted=inverted, coverage_max=coverage)
        if cube_size is None:
            q.requested_n, q.fine_reason = 8, "too coarse"
        return SimpleNamespace(quality=q, complex=SimpleNamespace(lattice=SimpleNamespace(n=2)),
                               polycube=SimpleNamespace(size=size))

    monkeypatch.setattr(fem_grid, "_build_searched", fake)
    g = build_fem_grid(sphere, n=8, n_cubes=40)
    assert calls == [1.0, RETRY_SIZES[0], RETRY_SIZES[1]]      # stops at the first that meets both targets
    assert g.quality.inverted == 0 and g.quality.coverage_max == 1.2
    assert g.quality.retries == 2 and g.quality.size_factor == RETRY_SIZES[1]
    assert g.quality.requested_n == 8 and g.quality.fine_reason == "too coarse"
    calls.clear()
    outcomes.update({f: (3, 1.0) for f in RETRY_SIZES})           # none helps: the first is kept
    g = build_fem_grid(sphere, n=8, n_cubes=40)
    assert calls == [1.0, *RETRY_SIZES] and g.quality.inverted == 1 and g.quality.size_factor == 1.0
    assert g.quality.retries == len(RETRY_SIZES)


def test_maps_the_other_repairs_until_one_meets_the_targets(monkeypatch, sphere) -> None:
    """Step 9's control flow, on stand-in polycubes and mappings: where the search repaired the
    cubes, its other repairs are mapped in its order (each ungrown, then grown if that misses)
    until one meets the targets, and that grid is kept; the retries of step 8 are not needed
    (the real case: CGAL's camel, whose first repair left 1.53 h)."""
    from types import SimpleNamespace

    from glsldiff.grids.polycube import Polycube
    from glsldiff.grids.tetrahedral import fem_grid
    from glsldiff.grids.tetrahedral.fem_grid import MappingQuality

    thresholds = (0.7, 0.3, 0.2, 0.5)   # the repairs, least inside volume left out first
    coverage = {(0.7, 0): 1.75, (0.7, 1): 1.53, (0.3, 0): 1.57, (0.3, 1): 1.6, (0.2, 0): 1.22, (0.5, 0): 1.0}
    mapped = []

    def candidates(mesh, cube_size=None, n_cubes=None, threshold=0.5, thin_parts=True):
        for t in thresholds:
            yield Polycube(np.array([[0, 0, 0]]), 1.0, np.zeros(3), np.ones(1), t, int(thin_parts), 3, "repaired")

    def fake_map(mesh, polycube, n, mapping, budget):
        mapped.append((polycube.threshold, polycube.grown))
        return SimpleNamespace(quality=MappingQuality(coverage_max=coverage[mapped[-1]]), polycube=polycube,
                               complex=SimpleNamespace(lattice=SimpleNamespace(n=n)))

    monkeypatch.setattr(fem_grid, "polycube_candidates", candidates)
    monkeypatch.setattr(fem_grid, "_map_polycube", fake_map)
    g = build_fem_grid(sphere, n=2, cube_size=1.0)
    assert mapped == [(0.7, 0), (0.7, 1), (0.3, 0), (0.3, 1), (0.2, 0)]   # stops at the first that meets them
    assert g.polycube.threshold == 0.2 and g.quality.coverage_max == 1.22 and g.quality.retries == 0


def test_cubes_snapped_far_beyond_the_count_fall_back() -> None:
    """A 1 mm plate at n = 6 and 12 cubes: the search snaps the cubes to the thickness (3,600
    of them, 780k lattice nodes, within the limit but 300x the request); the fine cubes keep
    the request's node budget."""
    plate = box_mesh((60.0, 60.0, 1.0), origin=(-30.0, -30.0, -0.5))
    g = build_fem_grid(plate, n=6, n_cubes=12)
    assert g.complex.lattice.n == FINE_CUBE_NODES and "asked for" in g.quality.fine_reason
    assert g.n_active < 100_000 and g.quality.inverted == 0
