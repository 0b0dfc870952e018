"""The pillowed polycube complex (grids.tetrahedral.pillow), its mapping (grids.tetrahedral.fem_grid) and the P1
finite elements on it (oracle.fem)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from glsldiff.grids.tetrahedral.fem_grid import build_fem_grid
from glsldiff.grids.lattice import Lattice
from glsldiff.grids.tetrahedral.pillow import PillowComplex, prism_tets, signed_volumes
from glsldiff.grids.polycube import polycube_from_mesh
from glsldiff.mesh import sphere_mesh
from glsldiff.oracle.closed_forms import sphere_fluence
from glsldiff.oracle.fem import TetGeometry, assemble_p1
from glsldiff.physics.optics import boundary_constant


def _canonical(tri):
    """Rotate each triangle so its smallest index comes first (keeps orientation)."""
    r = np.argmin(tri, axis=1)
    return np.take_along_axis(tri, (np.arange(3)[None] + r[:, None]) % 3, axis=1)


def _faces(tets):
    """Outward-oriented faces of right-handed tetrahedra."""
    return np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])


@pytest.fixture(scope="module", params=[(2, [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0)]),
                                        (3, [(x, y, z) for x in range(3) for y in range(3) for z in range(2)
                                             if (x, y, z) != (1, 1, 1)])],
                ids=["L-shape-n2", "notched-n3"])
def complex_(request):
    n, cubes = request.param
    return PillowComplex.build(Lattice(np.array(cubes), n, 4.0, np.zeros(3)))


def test_complex_is_conforming_and_consistently_oriented(complex_):
    """Every interior face is shared by two tetrahedra with opposite orientations; the faces
    used once are exactly the surface triangles, with the same orientation; the surface is
    a closed two-manifold."""
    F = _canonical(_faces(complex_.tets))
    key = np.sort(F, axis=1)
    _, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    assert cnt.max() == 2
    parity = np.where(F[:, 1] < F[:, 2], 1, -1)
    assert np.all(np.bincount(inv, parity)[cnt == 2] == 0)
    once = F[cnt[inv] == 1]
    surf = _canonical(complex_.surface)
    assert {tuple(t) for t in once} == {tuple(t) for t in surf}
    e = np.sort(np.concatenate([surf[:, [0, 1]], surf[:, [1, 2]], surf[:, [2, 0]]]), axis=1)
    assert np.all(np.unique(e, axis=0, return_counts=True)[1] == 2)


def test_reference_geometry_fills_the_polycube(complex_):
    """Lattice nodes at cell centres and surface nodes on the polycube surface: no negative
    tetrahedron (zero-volume ones at saddle vertices), volumes adding up to the polycube's,
    as does the volume the surface encloses."""
    X = complex_.reference_positions()
    v = signed_volumes(X, complex_.tets)
    lat = complex_.lattice
    cube_volume = len(lat.cubes) * lat.size ** 3
    assert v.min() >= -1e-12 * lat.size ** 3
    assert v.sum() == pytest.approx(cube_volume, rel=1e-12)
    S = X[complex_.surface]
    assert np.einsum("ij,ij->i", S[:, 0], np.cross(S[:, 1], S[:, 2])).sum() / 6 == pytest.approx(cube_volume, rel=1e-12)


def test_prism_split_is_conforming_on_shared_faces():
    """Two prisms sharing a quadrilateral face cut it along the same diagonal (the one
    through its lowest index), whatever their own vertex order."""
    rng = np.random.default_rng(0)
    for _ in range(50):
        a, b, c, d, e, f, g, h = rng.permutation(40)[:8]
        # prism 1: (a b c | d e f), prism 2 shares the quad (b c | e f): (b g c | e h f)
        P = np.array([[a, b, c, d, e, f], [b, g, c, e, h, f]])
        T = np.take_along_axis(P, prism_tets(P).reshape(2, -1), axis=1).reshape(2, 3, 4)

        def diagonals(tets):   # which diagonal of the quad (b c f e) the tetrahedra contain
            return {pair for pair in ((b, f), (c, e)) if any(set(pair) <= set(t) for t in tets)}
        assert diagonals(T[0]) == diagonals(T[1]) and len(diagonals(T[0])) == 1
        assert min(b, c, e, f) in next(iter(diagonals(T[0])))


def test_p1_sphere_converges_to_the_closed_form():
    """Uniform source on a sphere (R = 10 mm, the sphere bench's material): the P1 solution
    on the mapped pillowed polycube converges to the radial closed form. Measured:
    surface relative L2 2.0 %, 1.2 %, 0.48 % at n = 2, 4, 8 (cube 5 mm)."""
    R, kappa, mu = 10.0, 1 / 3.15, 0.05
    C = float(boundary_constant(1.3))
    mesh = sphere_mesh(R, subdivisions=4)
    pc = polycube_from_mesh(mesh, cube_size=5.0)
    errs = []
    for n in (2, 4):
        g = build_fem_grid(mesh, n=n, polycube=pc)
        assert g.quality.inverted == 0
        act = np.flatnonzero(g.active)
        A, b = assemble_p1(TetGeometry(g.positions, g.tets, g.surface), kappa, mu, 1.0, C)
        assert abs(A - A.T).max() < 1e-12 * abs(A).max()
        phi = np.zeros(len(g.positions))
        phi[act] = spla.spsolve(A[act][:, act].tocsc(), b[act])
        S = g.surface_nodes
        ex = sphere_fluence(np.linalg.norm(g.positions[S], axis=1), R, kappa, mu, C, 1.0)
        errs.append(np.linalg.norm(phi[S] - ex) / np.linalg.norm(ex))
    assert errs[1] < 0.7 * errs[0] and errs[1] < 0.015, errs


def test_p1_is_exact_for_a_constant_without_absorption():
    """mu = 0, q = 1: phi = 1 everywhere solves the continuous problem and the discrete one
    (the stiffness rows sum to zero), on any mapped grid."""
    mesh = sphere_mesh(10.0, subdivisions=3)
    g = build_fem_grid(mesh, n=3, cube_size=5.0)
    act = np.flatnonzero(g.active)
    A, b = assemble_p1(TetGeometry(g.positions, g.tets, g.surface), 0.3, 0.0, 1.0, 2.0)
    phi = spla.spsolve(A[act][:, act].tocsc(), b[act])
    np.testing.assert_allclose(phi, 1.0, rtol=1e-10)


@pytest.mark.parametrize("extents", [(100.0, 100.0, 100.0), (100.0, 100.0, 2.0)], ids=["cube", "tile"])
def test_box_keeps_its_edges_and_corners(extents):
    """A box mesh with a target cube count gets the exact polycube (the cube edge snapped to
    divide its extents) and its surface nodes keep the box's corners and edges: every box
    corner is a surface node, every surface node lies on the box surface, and no tetrahedron
    is inverted."""
    from glsldiff.mesh import box_mesh

    mesh = box_mesh(extents)
    g = build_fem_grid(mesh, n=2, n_cubes=400)
    ext = np.asarray(extents)
    r = ext / g.polycube.size
    np.testing.assert_allclose(r, np.round(r), atol=1e-9)
    S = g.boundary_positions
    d = np.min(np.linalg.norm(S[None] - mesh.vertices[:, None], axis=2), axis=1)
    assert d.max() < 1e-6 * ext.max()                  # the 8 corners
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    on_face = np.min(np.minimum(np.abs(S - lo), np.abs(S - hi)), axis=1)
    assert on_face.max() < 1e-6 * ext.max()
    assert g.quality.inverted == 0 and g.quality.corner_nodes == 8


def test_zero_volume_tetrahedra_carry_nothing():
    """A flat tetrahedron (four coplanar corners) gets no stiffness or mass; the others are
    assembled as before (node 4, used by the flat one only, has an empty row)."""
    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]], dtype=float)
    good = np.array([[0, 1, 2, 3]])
    geo_good = TetGeometry(X[:4], good, np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
    geo_both = TetGeometry(X, np.array([[0, 1, 2, 3], [0, 1, 4, 2]]), geo_good.surface)
    assert geo_both.degenerate.tolist() == [False, True]
    K1, K2 = geo_good.stiffness(1.0).toarray(), geo_both.stiffness(1.0).toarray()
    np.testing.assert_allclose(K2[:4, :4], K1)
    assert not K2[4].any() and geo_both.node_volumes[4] == 0


def test_bunny_grid_has_no_inverted_tetrahedra():
    """The scanned bunny (1600 cubes of n = 2): the harmonic placement leaves ~130 inverted
    tetrahedra at folds of the surface map; untangling, with the surface nodes sliding on the
    mesh where needed, leaves none (measured: 129 -> 0)."""
    from glsldiff.mesh import load_mesh

    g = build_fem_grid(load_mesh("bunny", size_mm=100.0), n=2, n_cubes=1600)
    assert g.quality.untangled > 50          # the case is a real one
    assert g.quality.inverted == 0
    assert np.abs(signed_volumes(g.positions, g.tets)).min() > 0


def test_cow_grid_covers_its_ears_and_horns_without_inverted_tetrahedra():
    """The cow at the scenes' default (n = 2, 15,000 cubes): its ears and horns are thinner
    than a cube. With the polycube grown into them, tip nodes and crease nodes let slide where
    tetrahedra stay flat, every mesh vertex lies within 1.5 h of a surface node and no
    tetrahedron is inverted (measured: coverage 1.39 h, 167 cubes grown, 36 tip nodes, 40
    released; the ungrown polycube's grid, mapped first: 3.91 h and 8 inverted). The shape
    step lifts most flat tetrahedra without costing coverage (measured: 1,251 -> 96 below
    quality 0.1, worst 6.2e-4 -> 1.5e-3)."""
    from glsldiff.mesh import load_mesh

    g = build_fem_grid(load_mesh("cow", size_mm=100.0), n=2, n_cubes=15000)
    q = g.quality
    assert q.thin_cubes > 100 and q.tip_nodes > 0 and q.released > 0   # each step did something
    assert q.inverted == 0 and q.worst_quality > 0
    assert q.coverage_max <= 1.5
    assert q.reshaped > 0 and q.poor < q.poor_before / 5
    # the long edges of the stretched ear and horn tetrahedra are split (measured 3.4k new
    # nodes), and the split grid's surface data line up
    assert q.split_edges > 1000 and 0 < q.split_surface_nodes < q.split_edges
    S = len(g.surface_nodes)
    assert len(g.normals) == len(g.outward_axes) == S == len(g.complex.outer) + q.split_surface_nodes
    assert g.surface_triangles.min() == 0 and g.surface_triangles.max() == S - 1
    assert len(g.reference_positions()) == len(g.positions) == g.complex.n_nodes + q.split_edges
    assert np.allclose(np.linalg.norm(g.normals, axis=1), 1.0)
    # the split cuts slivers into flatter halves; the shape step runs again on its interior
    # nodes (measured: 453 -> 330 below 0.1), and the boundary stays where it was:
    # every surface midpoint is still the midpoint of its surface edge
    assert q.split_poor < 0.85 * q.split_poor_before
    new = g.complex.n_nodes + np.arange(q.split_edges)
    on_surface = np.isin(new, g.surface_nodes)
    P = g.split.parents[on_surface]
    assert np.array_equal(g.positions[new[on_surface]], 0.5 * (g.positions[P[:, 0]] + g.positions[P[:, 1]]))


def test_surface_mass_rows_sum_to_the_lumped_areas_and_lower_the_sphere_error():
    """The consistent surface mass is symmetric, inside the stiffness pattern, its rows sum to
    the lumped areas; on the sphere bench's sphere at h = 0.625 mm (n = 2, 1.25 mm cubes) it
    lowers the error of B against the series for a face light and the 10 deg spot. Measured:
    face 0.61 -> 0.59 %, spot 5.39 -> 4.89 % (relative RMS)."""
    from glsldiff.bench.sphere_lights import ETA, KAPPA, MU, bench_lights
    from glsldiff.oracle.fem import solve_tet_direct
    from glsldiff.oracle.sphere_lights import sphere_from_light
    from glsldiff.system.tet_problem import TetProblem
    g = build_fem_grid(sphere_mesh(10.0, subdivisions=5), n=2, cube_size=1.25)
    geo = TetGeometry(g.positions, g.tets, g.surface)
    M = geo.surface_mass
    np.testing.assert_allclose(np.asarray(M.sum(axis=1)).ravel(), geo.node_areas, rtol=1e-12, atol=1e-15)
    assert abs(M - M.T).max() == 0.0
    K = geo.stiffness(1.0)
    assert (abs(K) + abs(M)).nnz == K.nnz                      # no entry outside the stiffness pattern
    pts = g.boundary_positions
    for name in ("face", "spot"):
        series = sphere_from_light(bench_lights(10.0)[name], 10.0, KAPPA, MU, ETA)
        ref = series.exitant_bracket(pts)
        q = np.repeat(series.source(pts)[:, None], 3, axis=1)
        err = {}
        for mass in ("lumped", "consistent"):
            p = TetProblem(g, KAPPA, MU, q, eta=ETA, boundary_mass=mass)
            B = p.exitant_bracket(solve_tet_direct(p)[0])[:, 0]
            err[mass] = np.linalg.norm(B - ref) / np.linalg.norm(ref)
        assert err["consistent"] < 0.99 * err["lumped"], (name, err)


def test_untangle_keeps_tangent_nodes_in_their_planes():
    """An inverted tetrahedron whose apex may slide only in a tilted plane through it (the
    tangent penalty of untangle): the apex moves within the plane and the tetrahedron turns
    positive; without the penalty the apex moves straight along the volume gradient, off the
    plane."""
    from glsldiff.grids.tetrahedral.fem_grid import untangle
    X = np.array([[0, 0, 0], [0, 1, 0], [0, 0, 1], [-0.5, 0.2, 0.2]])   # 6V = apex x: inverted
    T = np.array([[0, 1, 2, 3]])
    ref = np.array([1.0])                                                 # 6V of the apex at x = 1
    free = np.array([False, False, False, True])
    n = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    tangent = np.zeros_like(X)
    tangent[3] = n
    Y, Z = X.copy(), X.copy()
    assert untangle(Y, T, free, ref, tangent=tangent) == 1
    untangle(Z, T, free, ref)
    assert signed_volumes(Y, T)[0] > 0 and signed_volumes(Z, T)[0] > 0
    off_y, off_z = abs((Y[3] - X[3]) @ n), abs((Z[3] - X[3]) @ n)
    assert off_y < 0.1 * np.linalg.norm(Y[3] - X[3]) and off_z > 0.5 * np.linalg.norm(Z[3] - X[3])


def test_tips_get_a_surface_node():
    """A thin pyramid whose apex the surface nodes do not reach: the nearest free node (within
    3 h) moves onto the apex; fixed nodes stay; nodes already within reach are not moved."""
    from glsldiff.grids.tetrahedral.fem_grid import TIP_REACH, _snap_tips
    from glsldiff.mesh import mesh_from_arrays
    V = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [0, 0, 10]], dtype=float)
    F = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
    mesh = mesh_from_arrays(V, F)
    t = np.linspace(0.0, 0.75, 7)[:, None]
    xs = np.concatenate([V[:4], (1 - t) * V[0] + t * V[4], (1 - t) * V[2] + t * V[4]])   # up to z = 7.5
    fixed = np.zeros(len(xs), dtype=bool)
    fixed[10] = True                                 # the highest node on the first edge
    out, moved = _snap_tips(mesh, xs, fixed, h=1.0)
    assert moved.sum() == 1 and not moved[10]
    k = int(np.flatnonzero(moved)[0])
    np.testing.assert_allclose(out[k], V[4])
    np.testing.assert_array_equal(out[~moved], xs[~moved])
    gap = np.linalg.norm(out[:, None] - V[None], axis=2).min(axis=0)
    assert gap.max() <= TIP_REACH
