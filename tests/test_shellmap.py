"""Shell mapping of an acquired block onto polygrids (glsldiff.render.shellmap): depth layering on a
box and on a mesh sphere, tiling period and face frames on a box, the inner core and its
blend, the result as a diffusion problem, bad input."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.grids.graph import BOUNDARY, INACTIVE
from glsldiff.physics.material import coefficients, preset
from glsldiff.physics.procedural import marble_volume
from glsldiff.grids.polygrid import box_polygrid
from glsldiff.system.problem import DiffusionProblem
from glsldiff.grids.lattice import STEPS
from glsldiff.render.shellmap import FACE_FRAMES, map_shell, map_surface, shell_coordinates

RGB_A = np.array([1.0, 2.0, 4.0])
RGB_S = np.array([1.0, 0.8, 0.6])


def _z_block(nz: int, ny: int = 2, nx: int = 3):
    """A block that depends on depth only: sigma_a and sigma_s' grow with z (per RGB)."""
    z = np.arange(nz, dtype=float)
    sa = 0.01 * (1.0 + z)[:, None] * RGB_A
    ss = (1.0 + 0.6 * z + 0.2 * z**2)[:, None] * RGB_S
    k, m = coefficients(sa, ss)
    st = sa + ss
    shape = (nz, ny, nx, 3)
    return (np.broadcast_to(k[:, None, None], shape).copy(), np.broadcast_to(m[:, None, None], shape).copy(),
            st, sa, k)


def _profile(depth, h, table):
    """Linear interpolation of a per-layer (nz, 3) table at depth/h, clamped."""
    x = np.asarray(depth) / h
    return np.stack([np.interp(x, np.arange(len(table)), table[:, c]) for c in range(3)], axis=-1)


@pytest.fixture(scope="module")
def box():
    return box_polygrid((3, 3, 3), 4, size=2.0)  # 12^3 nodes, h = 0.5 mm


# ---------------------------------------------------------------- depth layering
def test_depth_layering_on_a_box(box):
    """Box: depth is the exact distance to the boundary-node planes, and every shell node
    holds the block's depth profile interpolated linearly in sigma_t and mu."""
    h = 0.4
    kb, mb, st, sa, kprof = _z_block(5)
    kappa, mu, info = map_shell(box, kb, mb, h, core="marble")
    lat = box.lattice
    act = lat.kind != INACTIVE
    g = lat.coords
    want_depth = box.lattice.h * np.minimum(g, 11 - g).min(axis=1)
    depth = info["depth"].ravel()
    np.testing.assert_allclose(depth[act], want_depth[act], atol=1e-12)
    assert info["depth_from"] == "nodes" and info["depth_max_mm"] == pytest.approx(2.5)

    shell = act & (depth <= (5 - 1) * h + 1e-9)  # below: pure block (blend starts at thickness - h)
    assert set(np.round(depth[shell], 6)) == {0.0, 0.5, 1.0, 1.5}
    k, m = kappa.reshape(-1, 3)[shell], mu.reshape(-1, 3)[shell]
    np.testing.assert_allclose(1.0 / (3.0 * k), _profile(depth[shell], h, st), rtol=1e-12)
    np.testing.assert_allclose(m, _profile(depth[shell], h, sa), rtol=1e-12)
    # the test tells sigma_t interpolation from kappa interpolation
    assert np.max(np.abs(k / _profile(depth[shell], h, kprof) - 1.0)) > 0.01
    # depth 0 (boundary nodes) reads z = 0 exactly
    b = lat.boundary
    np.testing.assert_allclose(kappa.reshape(-1, 3)[b], np.broadcast_to(kprof[0], (b.size, 3)), rtol=1e-12)


def test_depth_layering_on_a_mesh_sphere(sphere_polygrid):
    """Sphere mesh: the mesh depth is R - |p| up to the icosphere's facets; the nodes depth
    is an upper bound within one lattice step; node values follow the profile of their depth."""
    h = 0.5
    kb, mb, st, sa, _ = _z_block(8)  # shell 4 mm of a 10 mm sphere
    kappa, mu, info = map_shell(sphere_polygrid, kb, mb, h, core=(0.2, (0.01, 0.02, 0.03)))
    assert info["depth_from"] == "mesh" and info["mesh_queries"] > 0
    act = sphere_polygrid.active.ravel()
    depth = info["depth"].ravel()
    radial = 10.0 - np.linalg.norm(sphere_polygrid.positions, axis=1)
    inside = act & (depth < info["thickness_mm"])
    sag = 0.05  # icosphere (subdivisions 4) facets lie up to ~0.02 mm inside the sphere
    assert np.all(np.abs(depth[inside] - radial[inside]) < sag)
    nodes = shell_coordinates(sphere_polygrid, depth_from="nodes")["depth"]
    assert np.all(nodes[act] >= depth[act] - 1e-9)
    assert np.max(nodes[inside] - depth[inside]) < sphere_polygrid.lattice.h
    assert np.max(nodes[inside] - depth[inside]) > 0.05  # the mesh query changes something

    shell = act & (depth <= 7 * h)
    assert shell.sum() > 1000
    k, m = kappa.reshape(-1, 3)[shell], mu.reshape(-1, 3)[shell]
    np.testing.assert_allclose(1.0 / (3.0 * k), _profile(depth[shell], h, st), rtol=1e-12)
    np.testing.assert_allclose(m, _profile(depth[shell], h, sa), rtol=1e-12)
    core = act & (depth >= info["thickness_mm"])
    assert core.sum() == info["n_core"] > 100
    np.testing.assert_allclose(kappa.reshape(-1, 3)[core], 0.2)
    np.testing.assert_allclose(mu.reshape(-1, 3)[core], np.broadcast_to([0.01, 0.02, 0.03], (core.sum(), 3)))


# ---------------------------------------------------------------- tiling and face frames
def _x_block(values, nz=2, ny=1):
    """Block varying along x only: sigma_t = values[ix] * RGB_S, mu = 0.01."""
    st = np.asarray(values, dtype=float)[None, None, :, None] * RGB_S
    kb = np.broadcast_to(1.0 / (3.0 * st), (nz, ny, len(values), 3)).copy()
    return kb, np.full_like(kb, 0.01)


def _face(pg, slot):
    """Boundary nodes of one outward slot, and their lattice coordinates."""
    lat = pg.lattice
    b = lat.boundary[lat.outward_slot[lat.boundary] == slot]
    return b, lat.coords[b]


def _sigma_t(kappa, nodes):
    return 1.0 / (3.0 * kappa.reshape(-1, 3)[nodes, 0])


def test_tiling_period_and_face_frames():
    """A block varying in x tiles with period nx h along the +z face (u = x), 2 nx h at
    scale 2, runs along y on the +x face (u = y, no dependence on z) and along -x on the
    -z face (u = -x: not mirrored seen from outside)."""
    pg = box_polygrid((4, 2, 2), 4, size=2.0)  # 16 x 8 x 8 nodes, h = 0.5 mm
    vals = np.array([1.0, 2.0, 4.0])
    kb, mb = _x_block(vals)
    kappa, _, info = map_shell(pg, kb, mb, 0.5)
    assert info["period_mm"] == (1.5, 0.5)

    top, g = _face(pg, 5)
    st = _sigma_t(kappa, top)
    # u / h = gx + 0.5: halfway between voxels gx and gx + 1 (periodic)
    want = 0.5 * (vals[g[:, 0] % 3] + vals[(g[:, 0] + 1) % 3])
    np.testing.assert_allclose(st, want, rtol=1e-12)
    by_x = {int(x): st[g[:, 0] == x] for x in np.unique(g[:, 0])}
    assert all(np.ptp(v) < 1e-12 for v in by_x.values())  # no dependence on y
    line = np.array([by_x[x][0] for x in sorted(by_x)])
    np.testing.assert_allclose(line[3:], line[:-3], rtol=1e-12)  # period 3 nodes = 1.5 mm
    assert np.ptp(line) > 1.0

    k2, _, info2 = map_shell(pg, kb, mb, 0.5, scale=2.0)
    assert info2["period_mm"] == (3.0, 1.0) and info2["thickness_mm"] == 2.0
    line2 = np.array([_sigma_t(k2, top[g[:, 0] == x])[0] for x in sorted(by_x)])
    np.testing.assert_allclose(line2[6:], line2[:-6], rtol=1e-12)
    assert np.max(np.abs(line2[3:] - line2[:-3])) > 0.5

    side, gs = _face(pg, 1)  # +x face: u = y
    st = _sigma_t(kappa, side)
    np.testing.assert_allclose(st, 0.5 * (vals[gs[:, 1] % 3] + vals[(gs[:, 1] + 1) % 3]), rtol=1e-12)

    bottom, gb = _face(pg, 4)  # -z face: u = -x, u / h = -gx - 0.5
    st = _sigma_t(kappa, bottom)
    np.testing.assert_allclose(st, 0.5 * (vals[(-gb[:, 0] - 1) % 3] + vals[-gb[:, 0] % 3]), rtol=1e-12)


def test_surface_map_reads_like_the_block_top_layer():
    """A face map (one pixel per voxel) lands at the boundary nodes exactly where the block's
    top layer does (same coordinates and tiling), on every face of a box."""
    pg = box_polygrid((4, 2, 2), 4, size=2.0)
    vals = np.array([1.0, 2.0, 4.0])
    kb, mb = _x_block(vals, ny=2)
    kappa, _, _ = map_shell(pg, kb, mb, 0.5)
    top = 1.0 / (3.0 * kb[0])                                  # (ny, nx, 3) sigma_t of the top layer
    got = map_surface(pg, top, (3 * 0.5, 2 * 0.5))
    b = pg.lattice.boundary
    np.testing.assert_allclose(got, 1.0 / (3.0 * kappa.reshape(-1, 3)[b]), rtol=1e-12)
    twice = map_surface(pg, top, (3.0, 2.0))                   # a map over twice the extent
    assert not np.allclose(twice, got)
    with pytest.raises(InputError, match="surface map"):
        map_surface(pg, top[..., 0], (1.5, 1.0))
    with pytest.raises(InputError, match="period_mm"):
        map_surface(pg, top, (0.0, 1.0))


def test_v_is_up_on_side_faces_and_y_on_top():
    """A block varying in y: on the +y face it varies with z (v = z), on the +z face with y."""
    pg = box_polygrid((2, 2, 2), 4, size=2.0)
    vals = np.array([1.0, 3.0, 7.0])
    st = vals[None, :, None, None] * RGB_S
    kb = np.broadcast_to(1.0 / (3.0 * st), (2, 3, 1, 3)).copy()
    kappa, _, _ = map_shell(pg, kb, np.zeros_like(kb), 0.5)
    for slot, axis in ((3, 2), (0, 2), (5, 1), (4, 1)):  # +y, -x: v = z; +z, -z: v = y
        nodes, g = _face(pg, slot)
        want = 0.5 * (vals[g[:, axis] % 3] + vals[(g[:, axis] + 1) % 3])
        assert np.ptp(want) > 1.0
        np.testing.assert_allclose(_sigma_t(kappa, nodes), want, rtol=1e-12)


def test_shell_coordinates_use_the_nodes_own_polycube_position(sphere_polygrid):
    """(u, v) are the node's own lattice position in its face's frame (not its nearest
    boundary node's), so a lattice column below a face shares the face's (u, v); boundary
    nodes take their own face; the frames are right-handed seen from outside."""
    geo = shell_coordinates(sphere_polygrid, depth_from="nodes")
    lat = sphere_polygrid.lattice
    lp = lat.lattice_positions
    ua, us, va = FACE_FRAMES[geo["face"]].T
    rows = np.arange(lp.shape[0])
    np.testing.assert_array_equal(geo["u"], us * lp[rows, ua])
    np.testing.assert_array_equal(geo["v"], lp[rows, va])
    np.testing.assert_array_equal(geo["face"][lat.boundary], lat.outward_slot[lat.boundary])
    e = np.eye(3)
    for slot, (a, sign, b) in enumerate(FACE_FRAMES):
        np.testing.assert_array_equal(np.cross(sign * e[a], e[b]), STEPS[slot])


def test_mirror_tiling_is_continuous():
    """A ramp block: wrap tiling jumps back at every period, mirror tiling never jumps by
    more than one ramp step and repeats every 2 nx voxels."""
    pg = box_polygrid((4, 1, 1), 8, size=2.0)  # h = 0.25 mm, 32 nodes along x
    ramp = np.array([1.0, 2.0, 3.0, 4.0])
    kb, mb = _x_block(ramp)
    top, g = _face(pg, 5)
    order = np.argsort(g[:, 0] + 100 * g[:, 1])
    row = top[order][g[order, 1] == g[order, 1].min()]  # one row of the top face, by x
    lines = {}
    for tiling in ("wrap", "mirror"):
        kappa, _, _ = map_shell(pg, kb, mb, 0.5, tiling=tiling)  # 2 nodes per voxel
        lines[tiling] = _sigma_t(kappa, row)
    assert np.max(np.abs(np.diff(lines["wrap"]))) > 1.4
    assert np.max(np.abs(np.diff(lines["mirror"]))) <= 0.5 + 1e-12
    m = lines["mirror"]
    np.testing.assert_allclose(m[16:], m[:-16], rtol=1e-12)  # 2 * 4 voxels * 2 nodes per voxel


# ---------------------------------------------------------------- core
def test_core_blend_and_removed_nodes(box):
    """Nodes at depth >= thickness hold the core exactly, nodes in the last voxel blend
    linearly (in sigma_t and mu) towards it, removed nodes hold the core."""
    kb, mb = marble_volume((4, 5, 6), seed=3)
    kc, mc = preset("potato").coefficients()
    kappa, mu, info = map_shell(box, kb, mb, 0.5, core="potato", thickness_mm=1.25)
    free_k, free_mu, free = map_shell(box, kb, mb, 0.5, core="potato", thickness_mm=100.0)
    assert free["n_core"] == 0 and free["n_shell"] == box.n_active
    depth = info["depth"].ravel()
    act = box.active.ravel()
    K, M, FK, FM = (a.reshape(-1, 3) for a in (kappa, mu, free_k, free_mu))

    core = act & (depth >= 1.25)
    assert core.sum() == info["n_core"] > 0 and info["n_shell"] + info["n_core"] == box.n_active
    np.testing.assert_allclose(K[core], np.broadcast_to(kc, (core.sum(), 3)), rtol=1e-12)
    np.testing.assert_allclose(M[core], np.broadcast_to(mc, (core.sum(), 3)), rtol=1e-12)
    dead = ~act
    assert dead.sum() > 0
    np.testing.assert_allclose(K[dead], np.broadcast_to(kc, (dead.sum(), 3)), rtol=1e-12)

    pure = act & (depth <= 0.75)
    np.testing.assert_allclose(K[pure], FK[pure], rtol=1e-12)
    blend = act & (np.abs(depth - 1.0) < 1e-9)  # t = (1.0 - 0.75) / 0.5 = 0.5
    assert blend.sum() == info["n_blend"] > 0
    np.testing.assert_allclose(1.0 / (3.0 * K[blend]), 0.5 / (3.0 * FK[blend]) + 0.5 / (3.0 * kc), rtol=1e-12)
    np.testing.assert_allclose(M[blend], 0.5 * FM[blend] + 0.5 * mc, rtol=1e-12)
    assert np.all(3.0 * K[act] * M[act] <= 1.0 + 1e-12)  # physical block -> physical nodes


def test_core_mean_and_pair(box):
    kb, mb = marble_volume((4, 5, 6), seed=1)
    kappa, mu, info = map_shell(box, kb, mb, 0.5)  # core="mean", thickness 2 mm
    core = box.active.ravel() & (info["depth"].ravel() >= 2.0)
    assert core.sum() > 0
    st_mean = (1.0 / (3.0 * kb[-1])).mean(axis=(0, 1))
    np.testing.assert_allclose(1.0 / (3.0 * kappa.reshape(-1, 3)[core]), np.broadcast_to(st_mean, (core.sum(), 3)))
    np.testing.assert_allclose(mu.reshape(-1, 3)[core], np.broadcast_to(mb[-1].mean(axis=(0, 1)), (core.sum(), 3)))
    np.testing.assert_allclose(info["core_kappa"], 1.0 / (3.0 * st_mean))
    assert not np.allclose(info["core_kappa"], kb[-1, 0, 0])  # the mean, not a corner voxel

    kappa, mu, info = map_shell(box, kb[..., 0], mb[..., 0], 0.5, core=(0.3, 0.02))  # grey block
    np.testing.assert_allclose(kappa.reshape(-1, 3)[core], 0.3)
    np.testing.assert_allclose(mu.reshape(-1, 3)[core], 0.02)


def test_result_is_a_diffusion_problem(box):
    kb, mb = marble_volume((6, 8, 8), seed=0)
    kappa, mu, info = map_shell(box, kb, mb, 0.25, core="marble", scale=1.5)
    assert kappa.shape == mu.shape == box.shape + (3,)
    assert np.all(np.isfinite(kappa)) and np.all(kappa > 0) and np.all(mu >= 0)
    p = DiffusionProblem(box, kappa, mu, q=1.0)
    np.testing.assert_allclose(p.kappa[box.active], kappa[box.active])
    assert sum(info["faces"].values()) == info["n_active"] == box.n_active
    assert info["seam_links"] > 0 and info["seconds"] >= 0.0
    assert info["depth_min_mm"] == 0.0 and info["depth_max_mm"] == pytest.approx(2.5)


# ---------------------------------------------------------------- bad input
GOOD = (np.full((2, 3, 4, 3), 0.2), np.full((2, 3, 4, 3), 0.01))


def _nan():
    k = GOOD[0].copy()
    k[1, 2, 3, 0] = np.nan
    return k


@pytest.mark.parametrize("change, field", [
    ({"kappa_block": np.full((2, 3, 4, 2), 0.2)}, "kappa_block"),
    ({"kappa_block": np.full((3, 4, 3), 0.2)}, "kappa_block"),  # grey but mismatched
    ({"mu_block": np.full((5, 4, 3), 0.01)}, "mu_block"),
    ({"kappa_block": np.zeros((2, 3, 4, 3))}, "kappa_block"),
    ({"kappa_block": _nan()}, "kappa_block"),
    ({"mu_block": np.full((2, 3, 4, 3), np.inf)}, "mu_block"),
    ({"mu_block": np.full((2, 3, 4, 3), -0.01)}, "mu_block"),
    ({"h_mm": 0.0}, "h_mm"),
    ({"h_mm": float("nan")}, "h_mm"),
    ({"thickness_mm": -1.0}, "thickness_mm"),
    ({"thickness_mm": 0.0}, "thickness_mm"),
    ({"scale": 0.0}, "scale"),
    ({"core": "unobtainium"}, "core"),
    ({"core": (0.0, 0.01)}, "core kappa"),
    ({"core": (0.2, -1.0)}, "core mu"),
    ({"core": 3.0}, "core"),
    ({"tiling": "clamp"}, "tiling"),
    ({"depth_from": "mesh"}, "depth_from"),  # the box has no mesh
    ({"depth_from": "exact"}, "depth_from"),
    ({"pg": "not a polygrid"}, "Polygrid"),
])
def test_bad_input(box, change, field):
    args = {"pg": box, "kappa_block": GOOD[0], "mu_block": GOOD[1], "h_mm": 0.5}
    args.update(change)
    with pytest.raises(InputError, match=field):
        map_shell(**args)


def test_good_input_passes(box):
    """The bad-input cases differ from this one only in the named field."""
    _, _, info = map_shell(box, *GOOD, h_mm=0.5)
    assert info["n_active"] == box.n_active
    assert BOUNDARY in np.unique(box.kind)
