"""Polygrid lattice, packing and primitives, and the GLSL polygrid solver against the CPU oracle.

Meshes are not needed here (lattice positions, or lattice positions with a smooth
distortion); mesh-built polygrids are tested in test_polygrid_mesh.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.grids.graph import BOUNDARY, INACTIVE, INTERIOR
from glsldiff.grids.regular import RegularGrid
from glsldiff.grids.lattice import OPPOSITE, STEPS, Lattice
from glsldiff.packing import Mosaic, decompose
from glsldiff.solve.jacobi import GlslDiffusion, solve_glsl
from glsldiff.solve.stencil import pass_primitives
from glsldiff.grids.polygrid import Polygrid, box_polygrid, lattice_polygrid, node_weights
from glsldiff.system.problem import DiffusionProblem, relative_l2
from glsldiff.oracle.assembly import assemble
from glsldiff.oracle.solvers import solve_direct

L_SHAPE = [[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [0, 2, 0], [0, 0, 1]]
# a ring of 8 cubes around a hole (genus 1), two layers thick
RING = [[x, y, z] for z in range(2) for y in range(3) for x in range(3) if (x, y) != (1, 1)]


def _scanline(cubes):
    c = np.asarray(cubes)
    return c[np.lexsort((c[:, 0], c[:, 1], c[:, 2]))]


def _to_nodes(lat: Lattice, vol: np.ndarray) -> np.ndarray:
    """Regular-grid volume [z, y, x, ...] of the box -> polygrid node array."""
    c = lat.coords
    return vol[c[:, 2], c[:, 1], c[:, 0]].reshape(lat.shape + vol.shape[3:])


def _sine_kappa(shape, contrast=4.0):
    z, y, x = np.meshgrid(*[np.linspace(0, 1, s) for s in shape], indexing="ij")
    base = 0.5 + 0.5 * np.sin(3 * x + 2 * y) * np.cos(2 * z)
    k = 0.3 * contrast ** base
    return np.stack([k, 0.8 * k, 0.6 * k], axis=-1)


def _distorted(lat: Lattice, amplitude: float) -> Polygrid:
    """Lattice positions bent by a smooth map x -> x + a h sin(...): a distorted polygrid."""
    p = lat.lattice_positions
    s = lat.size * 2.0
    disp = amplitude * lat.h * np.stack([np.sin(p[:, 1] / s * 3 + p[:, 2] / s), np.sin(p[:, 2] / s * 2 + p[:, 0] / s),
                                         np.sin(p[:, 0] / s * 2.5 + p[:, 1] / s)], axis=1)
    pos = p + disp
    w, ws = node_weights(pos, lat)
    return Polygrid(lat, pos, lat.outward.copy(), w, ws)


# ---------------------------------------------------------------- lattice
@pytest.mark.parametrize("cubes, n", [((1, 1, 1), 5), ((3, 2, 2), 4), ((2, 1, 3), 6)])
def test_box_lattice_is_the_regular_grid(cubes, n):
    """A box of cubes classifies exactly like RegularGrid: faces boundary, edges/corners removed."""
    pg = box_polygrid(cubes, n, size=2.0)
    g = RegularGrid(cubes[0] * n, cubes[1] * n, cubes[2] * n, h=2.0 / n)
    assert np.array_equal(_to_nodes(pg.lattice, g.kind[..., None])[..., 0], pg.kind)
    assert pg.n_interior == g.n_interior and pg.n_boundary == g.n_boundary


@pytest.mark.parametrize("cubes, n", [(L_SHAPE, 4), (RING, 5), (L_SHAPE, 3)])
def test_lattice_invariants(cubes, n):
    """Interior nodes have six interior/boundary neighbours at unit lattice steps; every boundary
    node links to exactly one interior node, one step against its outward direction, and its
    outward neighbour is absent or removed; no interior node reads a removed node."""
    lat = Lattice.build(_scanline(cubes), n, 1.0)
    kind = lat.kind
    nb = lat.neighbours
    assert np.all(kind[nb] != INACTIVE)
    steps = lat.coords[nb] - lat.coords[lat.interior, None, :]
    assert np.array_equal(steps, np.broadcast_to(STEPS, steps.shape))
    b = lat.boundary
    assert np.all(kind[lat.link] == INTERIOR)
    out = lat.outward_slot[b]
    assert np.array_equal(lat.coords[lat.link] - lat.coords[b], STEPS[OPPOSITE[out]])
    outer = lat.lattice_neighbours[b, out]
    assert np.all((outer < 0) | (kind[np.maximum(outer, 0)] == INACTIVE))
    assert lat.n_interior + lat.n_boundary + lat.n_removed == lat.size_nodes
    # the graph the solvers use is consistent
    pg = lattice_polygrid(lat)
    pg.graph.check()


def test_lattice_concave_edges_keep_their_nodes():
    """At the concave edges of an L-shape no node is removed that a convex-only rule would keep:
    the concave corner nodes are interior and read two boundary nodes that link elsewhere."""
    lat = Lattice.build(_scanline(L_SHAPE), 4, 1.0)
    assert lat.shared_partners > 0
    counts = np.bincount(lat.link, minlength=lat.size_nodes)
    reads_boundary = (lat.kind[lat.neighbours] == BOUNDARY).sum(axis=1)
    partner_of = counts[lat.interior]
    assert np.any(reads_boundary > partner_of)  # concave: reads boundary nodes it is not linked from


def test_lattice_bad_input():
    with pytest.raises(InputError, match="duplicate"):
        Lattice.build([[0, 0, 0], [0, 0, 0]], 4, 1.0)
    with pytest.raises(InputError, match=r"\(k, 3\)"):
        Lattice.build(np.zeros((3, 2)), 4, 1.0)
    with pytest.raises(InputError, match="n=1"):
        Lattice.build([[0, 0, 0]], 1, 1.0)
    with pytest.raises(InputError, match="no interior node"):
        Lattice.build([[0, 0, 0]], 2, 1.0)
    with pytest.raises(InputError, match="cube size"):
        Lattice.build([[0, 0, 0]], 4, -1.0)


# ---------------------------------------------------------------- packing and primitives
def test_mosaic_round_trip_and_texels():
    m = Mosaic(5, 5, 23, max_texture_size=64)
    data = np.random.default_rng(0).normal(size=(23 * 25, 3)).astype(np.float32)
    tex = m.pack(data)
    assert tex.shape == (m.texture_size[1], m.texture_size[0], 4)
    back = m.unpack(tex).reshape(-1, 3)
    np.testing.assert_array_equal(back, data)
    xy = m.texel(np.arange(23 * 25))
    np.testing.assert_array_equal(tex[xy[:, 1], xy[:, 0], :3], data)


def test_mosaic_drops_blocks():
    """A mosaic keeping some blocks tiles only those: smaller texture, the same values at the
    kept nodes, texel (-1, -1) and the fill value at the dropped ones."""
    kept = np.zeros(23, dtype=bool)
    kept[[0, 3, 4, 10, 22]] = True
    full, m = Mosaic(5, 5, 23, max_texture_size=64), Mosaic(5, 5, 23, max_texture_size=64, kept=kept)
    assert m.n_slots == 5 and np.prod(m.texture_size) < np.prod(full.texture_size)
    data = np.random.default_rng(1).normal(size=(23 * 25, 3)).astype(np.float32)
    tex = m.pack(data)
    assert tex.shape == (m.texture_size[1], m.texture_size[0], 4)
    keep_nodes = m.kept_nodes()
    back = m.unpack(tex, fill=-7.0).reshape(-1, 3)
    np.testing.assert_array_equal(back[keep_nodes], data[keep_nodes])
    assert np.all(back[~keep_nodes] == -7.0)
    xy = m.texel(np.arange(23 * 25))
    assert np.all(xy[~keep_nodes] == -1)
    np.testing.assert_array_equal(tex[xy[keep_nodes, 1], xy[keep_nodes, 0], :3], data[keep_nodes])
    with pytest.raises(InputError, match="at least one"):
        Mosaic(5, 5, 23, kept=np.zeros(23, dtype=bool))
    with pytest.raises(InputError, match="kept has shape"):
        Mosaic(5, 5, 23, kept=np.ones(5, dtype=bool))


def test_figure6_layout():
    """Cube c's slice z is texture block c * n + z: cubes in scan-line order, slices by increasing z."""
    pg = box_polygrid((2, 2, 1), 4)
    lat = pg.lattice
    flat = np.arange(lat.size_nodes)
    block = flat // 16
    cube, z = np.divmod(block, 4)
    np.testing.assert_array_equal(lat.coords[:, 2] % 4, z)
    np.testing.assert_array_equal(lat.coords // 4, lat.cubes[cube])
    np.testing.assert_array_equal(lat.cubes, _scanline(lat.cubes))


@pytest.mark.parametrize("cubes, n", [(L_SHAPE, 4), (RING, 5), ((2, 2, 2), 6)])
def test_primitives_cover_each_node_once_with_its_own_offsets(cubes, n):
    """Every interior (boundary) texel is in exactly one rectangle, whose offsets are the
    texel's own six neighbour offsets (partner offset); quads, lines and points all occur."""
    lat = (box_polygrid(cubes, n).lattice if isinstance(cubes, tuple)
           else Lattice.build(_scanline(cubes), n, 1.0))
    pg = lattice_polygrid(lat)
    prims = pass_primitives(pg)
    m = pg.mosaic
    for name, nodes, want in (("interior", lat.interior, m.texel(lat.neighbours) - m.texel(lat.interior)[:, None]),
                              ("boundary", lat.boundary, (m.texel(lat.link) - m.texel(lat.boundary))[:, None])):
        p = prims[name]
        w, h = m.texture_size
        cover = np.zeros((h, w), dtype=int)
        offs = np.zeros((h, w, 6, 2), dtype=np.int64)
        for (x0, y0, x1, y1), o in zip(p.rects, p.offsets):
            cover[y0:y1, x0:x1] += 1
            offs[y0:y1, x0:x1] = o
        t = m.texel(nodes)
        expect = np.zeros((h, w), dtype=int)
        expect[t[:, 1], t[:, 0]] = 1
        np.testing.assert_array_equal(cover, expect)
        np.testing.assert_array_equal(offs[t[:, 1], t[:, 0], :want.shape[1]], want)
        assert p.texels == len(nodes)
    kinds = prims["interior"].kinds
    if len(lat.cubes) > 1:
        assert kinds["quads"] > 0 and kinds["lines"] > 0 and kinds["points"] > 0


def test_decompose_empty():
    p = decompose(np.zeros((0, 2), np.int64), np.zeros((0, 6, 2), np.int64))
    assert p.rects.shape == (0, 4) and p.texels == 0


# ---------------------------------------------------------------- GLSL vs CPU
def _sine_problem(pg: Polygrid, stencil="paper", seed=0, q_scale=1.0):
    rng = np.random.default_rng(seed)
    p = pg.positions.reshape(pg.shape + (3,))
    lo, hi = pg.positions.min(0), pg.positions.max(0)
    u = (p - lo) / (hi - lo)
    k = 0.3 * 3.0 ** (0.5 + 0.5 * np.sin(3 * u[..., 0] + 2 * u[..., 1]) * np.cos(2 * u[..., 2]))
    kappa = np.stack([k, 0.8 * k, 0.6 * k], axis=-1)
    mu = 0.05 + 0.2 * u
    q = q_scale * rng.uniform(0.0, 1.0, (pg.n_boundary, 3)) * (pg.boundary_positions[:, :1] < lo[0] + 0.6 * (hi - lo)[0])
    return DiffusionProblem(pg, kappa, mu, q, stencil=stencil)


@pytest.mark.parametrize("stencil", ["paper", "conservative"])
@pytest.mark.parametrize("geometry", ["L", "ring-distorted"])
def test_sweeps_equal_numpy_jacobi(ctx, stencil, geometry):
    """GLSL sweeps (quads/lines/points, both passes) equal x + D^-1 (b - A x) of the oracle."""
    lat = Lattice.build(_scanline(L_SHAPE if geometry == "L" else RING), 5, 2.0)
    pg = lattice_polygrid(lat) if geometry == "L" else _distorted(lat, 0.25)
    p = _sine_problem(pg, stencil)
    s = assemble(p)
    rng = np.random.default_rng(1)
    x = rng.uniform(0.5, 1.0, s.b.shape)
    with GlslDiffusion(p, ctx) as solver:
        solver.set_initial(p.to_phi(s.to_volume(x, p.node_shape)))
        solver.sweep(7)
        got = s.from_volume(solver.unknown())
    for _ in range(7):
        x = x + s.jacobi_step(x)
    assert relative_l2(got, x) < 2e-6


@pytest.mark.parametrize("stencil", ["paper", "conservative"])
def test_box_equals_regular_grid(ctx, stencil):
    """Acceptance: on an axis-aligned box the polygrid system is the regular grid's, and the
    GLSL solution on the polygrid equals the regular-grid solutions (direct and GLSL) to <= 1e-4."""
    n, cubes, size = 5, (3, 2, 2), 2.5
    pg = box_polygrid(cubes, n, size)
    g = RegularGrid(cubes[0] * n, cubes[1] * n, cubes[2] * n, h=size / n)
    kappa = _sine_kappa(g.shape)
    mu = np.full(g.shape + (3,), 0.1)
    qv = g.face_volume({"z-": np.random.default_rng(0).uniform(0.5, 1.5, g.face_shape("z-") + (3,)), "x+": 0.3})
    pr = DiffusionProblem(g, kappa, mu, qv, stencil=stencil)
    pp = DiffusionProblem(pg, _to_nodes(pg.lattice, kappa), _to_nodes(pg.lattice, mu), _to_nodes(pg.lattice, qv),
                          stencil=stencil)
    phi_r, _ = solve_direct(pr)
    phi_p, _ = solve_direct(pp)
    act = pg.active
    assert relative_l2(phi_p[act], _to_nodes(pg.lattice, phi_r)[act]) < 1e-12
    phi_g, rep = solve_glsl(pp, ctx, tol=5e-7)
    phi_rg, _ = solve_glsl(pr, ctx, tol=5e-7)
    assert rep.method == "glsl-jacobi-fp32"
    assert relative_l2(phi_g[act], phi_p[act]) <= 1e-4
    assert relative_l2(phi_g[act], _to_nodes(pg.lattice, phi_rg)[act]) <= 1e-4
    assert rep.radiance.shape == (pg.n_boundary, 3)


def test_distorted_polygrid_matches_direct(ctx):
    """Distorted ring (appendix-B weights from non-orthogonal stencils): GLSL = direct to 1e-4."""
    lat = Lattice.build(_scanline(RING), 6, 3.0)
    pg = _distorted(lat, 0.3)
    p = _sine_problem(pg, "paper")
    phi_d, _ = solve_direct(p)
    phi_g, rep = solve_glsl(p, ctx, tol=5e-7)
    assert relative_l2(phi_g[pg.active], phi_d[pg.active]) <= 1e-4
    assert rep.status in ("converged", "stalled")


def test_fp16_polygrid(ctx):
    lat = Lattice.build(_scanline(L_SHAPE), 5, 2.0)
    pg = lattice_polygrid(lat)
    p = _sine_problem(pg)
    phi_d, _ = solve_direct(p)
    phi_h, rep = solve_glsl(p, ctx, precision="fp16", tol=1e-6, maxiter=3000)
    err = relative_l2(phi_h[pg.active], phi_d[pg.active])
    assert err < 2e-2 and np.all(np.isfinite(phi_h))


def test_polygrid_q_validation():
    pg = box_polygrid((1, 1, 1), 5)
    with pytest.raises(InputError, match="q has shape"):
        DiffusionProblem(pg, 1.0, 0.1, np.ones((pg.n_boundary + 1, 3)))
    bad = np.zeros(pg.shape)
    bad.reshape(-1)[pg.lattice.interior[0]] = 1.0
    with pytest.raises(InputError, match="not boundary nodes"):
        DiffusionProblem(pg, 1.0, 0.1, bad)
    q = np.ones(pg.n_boundary)
    q[3] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        DiffusionProblem(pg, 1.0, 0.1, q)
