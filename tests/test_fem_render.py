"""The tetrahedral (P1) discretisation in scenes and the renderer: [polygrid] discretisation = "fem"."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.bench.meshes import mesh_bench
from glsldiff.bench.sphere_lights import sphere_light_study
from glsldiff.commands.cli import main
from glsldiff.core.errors import InputError
from glsldiff.grids.tetrahedral.fem_grid import build_fem_grid
from glsldiff.mesh import sphere_mesh
from glsldiff.oracle.fem import solve_tet_direct
from glsldiff.render.renderer import Renderer
from glsldiff.render.scene import parse_scene
from glsldiff.render.shading import surface_interpolation

LIGHT = [{"type": "directional", "direction": [0.3, 0.4, 1.0], "irradiance": [1.0, 1.0, 1.0]}]


def _scene(**polygrid):
    return {"mesh": {"source": "sphere", "size_mm": 20.0},
            "polygrid": {"n": 3, "cubes": 64, "discretisation": "fem", **polygrid},
            "lights": LIGHT, "output": {"width": 48, "height": 48}}


def test_scene_options():
    s = parse_scene(_scene())
    assert s.polygrid.discretisation == "fem" and s.polygrid.n == 3 and s.polygrid.levels == 1
    no_cubes = {**_scene(), "polygrid": {"n": 2, "discretisation": "fem"}}
    assert parse_scene(no_cubes).polygrid.cubes == 15000        # 120k nodes in cubes of 2^3
    default = parse_scene({"mesh": {"source": "sphere"}, "lights": LIGHT}).polygrid
    assert (default.discretisation, default.n, default.cubes, default.levels) == ("fem", 2, 15000, 1)
    lattice = parse_scene({"mesh": {"source": "sphere"}, "lights": LIGHT,
                           "polygrid": {"discretisation": "conservative"}}).polygrid
    assert (lattice.n, lattice.cubes, lattice.levels) == (8, 253, 3)
    with pytest.raises(InputError, match=r"\[polygrid\]\.levels: the fem discretisation \(the default\) solves on "
                                         r"one level .* discretisation = \"conservative\""):
        parse_scene({"mesh": {"source": "sphere"}, "lights": LIGHT, "polygrid": {"levels": 3}})
    with pytest.raises(InputError, match=r"\[polygrid\]\.discretisation: 'fvm' is not one of conservative, paper, fem"):
        parse_scene(_scene(discretisation="fvm"))
    with pytest.raises(InputError, match=r"n: must be even"):
        parse_scene({**_scene(), "polygrid": {"n": 3, "discretisation": "conservative"}})


def test_surface_interpolation_follows_the_surface():
    """Weights sum to 1 and reproduce a linear function of position at vertices on the surface
    triangles; a vertex takes only the three nodes of the triangle under it."""
    g = build_fem_grid(sphere_mesh(10.0, subdivisions=3), n=2, cube_size=5.0)
    nodes, tri = g.boundary_positions, g.surface_triangles
    rng = np.random.default_rng(1)
    t = rng.integers(0, len(tri), 200)
    w = rng.dirichlet(np.ones(3), 200)
    pts = np.einsum("ij,ijk->ik", w, nodes[tri[t]])
    W = surface_interpolation(pts, nodes, tri)
    np.testing.assert_allclose(np.asarray(W.sum(axis=1)).ravel(), 1.0, rtol=1e-12)
    f = nodes @ np.array([0.3, -1.2, 0.7]) + 2.0
    np.testing.assert_allclose(W @ f, pts @ np.array([0.3, -1.2, 0.7]) + 2.0, rtol=0, atol=1e-9)
    assert np.diff(W.indptr).max() <= 3


def test_render_pass2_equals_the_direct_solve(tmp_path):
    """The GLSL pass 2 of a fem scene equals the direct P1 solve at the surface nodes (<= 1e-3
    relative at tol 1e-5); the image is finite and lit (the cache is off: conftest.py)."""
    scene = parse_scene({**_scene(), "options": {"tol": 1e-5}})
    with Renderer() as r:
        img, rep = r.render(scene)
        assert rep.solver.converged and rep.solver.method.startswith("glsl-gather")
        phi_ref, _ = solve_tet_direct(r.fem_problem(scene))
        ref = phi_ref[r.polygrid.surface_nodes]
        assert np.linalg.norm(r.surface_fluence - ref) / np.linalg.norm(ref) < 1e-3
    assert np.isfinite(img).all() and img.max() > 0


def test_fem_command_line(tmp_path, capsys):
    path = tmp_path / "s.toml"
    path.write_text('[mesh]\nsource = "sphere"\nsize_mm = 20\n[polygrid]\nn = 2\ncubes = 64\n'
                    'discretisation = "fem"\n[[lights]]\ntype = "directional"\ndirection = [0, 0, 1]\n'
                    '[output]\nwidth = 32\nheight = 32\n')
    assert main(["render", str(path), "-o", str(tmp_path / "a.exr")]) == 0
    assert "tetrahedral polygrid built" in capsys.readouterr().err
    assert (tmp_path / "a.exr").is_file() and (tmp_path / "a.png").is_file()


def test_fem_sphere_converges_under_a_directional_light():
    """Exitant bracket vs the exact series, light onto a polycube face: the P1 error falls with
    n and is far below the conservative lattice stencil's at equal spacing. Measured: fem
    3.8 % / 2.1 % at n = 2 / 4 (h 2.5 / 1.25 mm), conservative lattice 29 % at n = 4."""
    rows = sphere_light_study(ns=(2, 4), polygrid_ns=(4,), cube_sizes=(), lights=("face",),
                              discretisations=("fem", "conservative"))
    fem = [r["rel_rms"] for r in rows if r["discretisation"] == "fem"]
    lattice = [r["rel_rms"] for r in rows if r["discretisation"] == "conservative"]
    assert fem[1] < 0.7 * fem[0] and fem[1] < 0.03, fem
    assert lattice[0] > 4 * fem[1], (lattice, fem)


def test_fem_second_render_takes_the_checked_cached_solution(tmp_path, monkeypatch):
    """With the cache on, a second render of a fem scene takes the cached pass-2 answer (its
    float64 residual measured when stored, its checksum verified; no GPU hierarchy, no
    assembly), with the same image; an answer changed after its checksum is solved again."""
    from glsldiff.core import cache

    monkeypatch.setenv("GLSLDIFF_CACHE", str(tmp_path / "cache"))
    scene = parse_scene(_scene())
    with Renderer() as r:
        a, rep_a = r.render(scene)
    with Renderer() as r:
        b, rep_b = r.render(scene)
    assert rep_a.solver.method.startswith("glsl-gather-multigrid")
    assert rep_b.solver.method.startswith("cached") and rep_b.solver.residual <= scene.options.tol
    np.testing.assert_array_equal(a, b)
    (entry,) = (tmp_path / "cache").glob("pass2-*.pkl")
    key = entry.stem.split("-", 1)[1]
    stored = cache.load("pass2", key, dict)
    cache.store("pass2", key, {**stored, "phi": 2.0 * stored["phi"]})
    with Renderer() as r:
        c, rep_c = r.render(scene)
    assert rep_c.solver.method.startswith("glsl-gather-multigrid") and rep_c.solver.converged
    assert np.abs(c - a).max() < 1e-2 * a.max()


def test_fem_system_is_the_last_frames_even_from_the_cache(tmp_path, monkeypatch):
    """``Renderer.fem_system`` holds the last frame's source, also when two frames in a row came
    from the disk cache (a cached frame assembles nothing: the system held the first light's
    source, and the oracle columns of a bench compared against the wrong light)."""
    from glsldiff.oracle.fem import tet_rhs

    monkeypatch.setenv("GLSLDIFF_CACHE", str(tmp_path / "cache"))
    back = [{**LIGHT[0], "direction": [-0.3, -0.4, -1.0]}]
    scenes = parse_scene(_scene()), parse_scene({**_scene(), "lights": back})
    with Renderer() as r:
        for s in scenes:
            r.render(s)
    with Renderer() as r:
        for s in scenes:
            _, rep = r.render(s)
            assert rep.solver.method.startswith("cached")
            np.testing.assert_array_equal(r.fem_system.b, tet_rhs(r.fem_problem(s)).T.reshape(-1))


def test_shell_mapped_volume_on_tetrahedra(tmp_path, monkeypatch):
    """A [material].volume block and a reflectance map are wrapped around a fem grid through
    the shell: surface nodes take the block's top layer, nodes deeper than the shell the core,
    and (u, v) follow the polycube face of the nearest surface node (one frame per face)."""
    from glsldiff.render.shellmap import map_shell, map_surface, shell_coordinates
    g = build_fem_grid(sphere_mesh(10.0, subdivisions=3), n=2, cube_size=2.5)
    top, bottom = (0.2, 0.3, 0.4), (0.5, 0.5, 0.5)
    kb = np.empty((4, 6, 6, 3))
    kb[0], kb[1:] = top, bottom
    mb = np.full((4, 6, 6, 3), 0.01)
    kappa, mu, info = map_shell(g, kb, mb, h_mm=0.5, core=((1.0, 1.0, 1.0), (0.02, 0.02, 0.02)))
    assert kappa.shape == (len(g.positions), 3) and info["seam_links"] == -1
    np.testing.assert_allclose(kappa[g.surface_nodes], np.broadcast_to(top, (len(g.surface_nodes), 3)), rtol=1e-12)
    geo = shell_coordinates(g, depth_from="mesh")
    deep = g.active & (geo["depth"] > 2.0 + 1e-9)
    assert deep.any()
    np.testing.assert_allclose(kappa[deep], 1.0) and np.testing.assert_allclose(mu[deep], 0.02)
    # the face a surface node reads is one of its own outer faces (at edges and corners the one
    # nearest its normal; staircase faces of a sphere may lie 78 deg off it)
    from glsldiff.grids.lattice import STEPS
    face = geo["face"][g.surface_nodes]
    assert np.all((STEPS[face] * g.outward_axes).sum(axis=1) == 1)
    assert np.all(np.einsum("ij,ij->i", STEPS[face], g.normals) > 0.0)   # never an inward face
    img = np.zeros((6, 6, 3))
    img[:, :3] = 1.0                                  # half the face white: both halves appear
    rho = map_surface(g, img, (3.0, 3.0))
    assert rho.shape == (len(g.surface_nodes), 3) and rho.min() < 0.05 and rho.max() > 0.95


def test_mesh_bench_checks_the_glsl_solve_against_the_oracle(tmp_path):
    """bench meshes on a torus: the grid is valid and covers the surface, the GLSL fluence
    is the oracle's solve of the same system (to the scene tol's 1e-4 residual: measured
    2.4e-4 of the largest fluence), the comparison with the 1:8 refined grid runs; the CSV and
    the render panel are written."""
    rows = mesh_bench(["torus"], cubes=[300], out=tmp_path, size=32)
    (row,) = rows
    assert row["front_status"] == row["back_status"] == "converged"
    assert row["inverted"] == 0 and row["coverage_max_h"] < 1.5
    assert 0 < row["glsl_vs_oracle"] < 2e-3
    assert 0 <= row["negative_nodes"] < 0.2 * row["nodes"] and row["positive_couplings"] > 0
    # against the grid's 1:8 refinement: a coarse grid (2.1k nodes) shows its error (measured
    # 7.8 % front, 8.1 % back)
    assert row["refined_nodes"] > 5 * row["nodes"]
    for light in ("front", "back"):
        assert 0.01 < row[f"{light}_vs_refined"] < 0.3 and row[f"{light}_vs_refined_max"] >= row[f"{light}_vs_refined"]
    assert row["back_negative"] >= 0 and row["back_negative_refined"] >= 0
    assert (tmp_path / "meshes.csv").is_file() and (tmp_path / "meshes.png").is_file()
