"""Multiresolution grids (grids/hierarchy.py: polygrids and regular grids) and the GLSL level stack
and schedules (solve/levels.py, solve/schedules.py, solve/multilevel.py).

Each GLSL pass is checked against its CPU twin on the same discrete system, on a mapped polygrid
and on a regular grid: prolongation against ``Transfer.prolong``, restriction against
``Transfer.restrict_kind``, the residual pass against ``(b - A x) / row scale`` of
:func:`glsldiff.oracle.assembly.assemble`, the damped sweep with an interior right-hand side
against ``x + omega D^-1 (b - A x)``, the 8-bit material against
:func:`glsldiff.solve.quantize.decode`. Whole solves are checked against the direct solve; the
adaptive one against its pinned system.
"""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.solve import quantize
from glsldiff.core.errors import InputError
from glsldiff.grids.graph import INACTIVE
from glsldiff.bench.convergence import run_scheme
from glsldiff.grids.hierarchy import Hierarchy, coarsen, coarsen_regular
from glsldiff.grids.regular import RegularGrid
from glsldiff.mesh import torus_mesh
from glsldiff.solve.jacobi import GlslDiffusion
from glsldiff.solve.multilevel import MultilevelDiffusion
from glsldiff.grids.polygrid import Polygrid, box_polygrid, build_polygrid
from glsldiff.system.problem import DiffusionProblem, level_problems, relative_l2
from glsldiff.oracle.assembly import assemble
from glsldiff.oracle.solvers import solve_direct
from glsldiff.system.report import CURRENT

@pytest.fixture(scope="module")
def torus_polygrid():
    """A mapped (distorted) polygrid of genus 1 (about 12k nodes); two levels, n = 6 and 3 (n = 2 has no
    interior nodes at this cube size)."""
    return build_polygrid(torus_mesh(20.0, 8.0, 32, 16), n=6, cube_size=8.0)


@pytest.fixture(scope="module")
def hier(torus_polygrid):
    return Hierarchy.build(torus_polygrid, 2)


@pytest.fixture(scope="module")
def slab_hier():
    """A regular grid (17 x 13 x 9 nodes, h = 1 mm) and two coarser levels (9 x 7 x 5, 5 x 4 x 3)."""
    return Hierarchy.build(RegularGrid(17, 13, 9, 1.0), 3)


@pytest.fixture(params=["polygrid", "regular"])
def any_hier(request):
    """The torus polygrid's hierarchy, then the regular grid's."""
    return request.getfixturevalue("hier" if request.param == "polygrid" else "slab_hier")


def _lit_problem(grid, stencil="paper", hetero=False):
    """Smooth directional light on the polygrid's normals, or on the regular grid's z- face and
    (weaker) x+ face; kappa 0.3 mm (log-normal per node when ``hetero``), mu per channel."""
    rng = np.random.default_rng(3)
    if isinstance(grid, Polygrid):
        q = np.maximum(grid.normals @ np.array([0.3, 0.2, 0.93]), 0.0)[:, None] * np.array([1.0, 0.7, 0.4])
    else:
        fy, fx = grid.face_shape("z-")
        ramp = np.linspace(0.2, 1.0, fx)[None, :, None] * np.ones((fy, 1, 1)) * np.array([1.0, 0.7, 0.4])
        q = grid.face_volume({"z-": ramp, "x+": 0.3})
    kappa, mu = 0.3, np.array([0.01, 0.03, 0.1])
    if hetero:
        kappa = 0.3 * np.exp(0.3 * rng.standard_normal(grid.shape))
    return DiffusionProblem(grid, kappa, mu, q, stencil=stencil)


def _row_scale(p: DiffusionProblem) -> np.ndarray:
    """Per active node: interior s_i, boundary d_b kappa_b (paper) or d_b; (n, 3)."""
    g = p.graph
    out = np.zeros((g.size, 3))
    out[g.interior] = g.scale[:, None]
    kb = p.kappa.reshape(-1, 3)[g.boundary] if p.stencil == "paper" else 1.0
    out[g.boundary] = g.d[:, None] * kb
    return out[g.active]


# ---------------------------------------------------------------- CPU hierarchy
def test_coarsen_box_is_the_coarse_lattice():
    """On a box at lattice positions the coarse interior nodes are the coarse cell centres,
    the coarse boundary nodes stay on the fine boundary layer, and the transfers average."""
    pg = box_polygrid((3, 3, 2), 8, 8.0)
    cg, t = coarsen(pg)
    lat = cg.lattice
    assert lat.n == 4
    np.testing.assert_allclose(cg.positions[lat.interior], lat.lattice_positions[lat.interior], atol=1e-12)
    # boundary nodes: the mean of their boundary children, half a fine step outside the
    # coarse cell centre along the outward axis (the fine boundary layer)
    off = cg.positions[lat.boundary] - lat.lattice_positions[lat.boundary]
    np.testing.assert_allclose(off, 0.5 * pg.lattice.h * lat.outward, atol=1e-12)
    for R in (t.restrict_kind, t.restrict_all):
        sums = np.asarray(R.sum(axis=1)).ravel()
        assert np.all(np.isclose(sums, 1.0) | (sums == 0))
    active_f = pg.lattice.kind != INACTIVE
    per_row = np.diff(t.prolong.indptr)
    assert np.all(per_row[active_f] == 1) and np.all(per_row[~active_f] == 0)  # a copy of one node
    assert np.all(lat.kind[t.prolong.indices] != INACTIVE) and np.all(t.prolong.data == 1.0)
    # a constant field survives prolongation and restriction
    ones_c = np.ones(lat.size_nodes)
    np.testing.assert_allclose((t.prolong @ ones_c)[active_f], 1.0)


def test_coarsen_rejects_odd_n():
    with pytest.raises(InputError, match="even"):
        coarsen(box_polygrid((2, 2, 2), 5, 5.0))
    with pytest.raises(InputError, match="no interior node"):
        Hierarchy.build(box_polygrid((1, 1, 1), 4, 4.0), 2)


def test_coarsen_regular_grid():
    """Vertex-centred coarsening of a regular grid: (n + 1) / 2 nodes per axis at spacing 2h, the
    boundary faces kept; prolongation = trilinear interpolation of the active coarse nodes (exact
    for a linear field wherever no edge node drops out, rows summing to 1); restriction = full
    weighting normalised per row, over fine nodes of the coarse node's kind (restrict_kind) or
    all of them (restrict_all); even or small axes are rejected."""
    g = RegularGrid(13, 9, 7, 0.5)
    cg, t = coarsen_regular(g)
    assert (cg.nx, cg.ny, cg.nz, cg.h) == (7, 5, 4, 1.0)
    np.testing.assert_allclose(cg.positions[-1], g.positions[-1])          # same far corner, mm
    fk, ck = g.kind.ravel(), cg.kind.ravel()
    act_f, act_c = fk != INACTIVE, ck != INACTIVE
    rows = np.asarray(t.prolong.sum(axis=1)).ravel()
    np.testing.assert_allclose(rows[act_f], 1.0, rtol=1e-14)
    assert np.all(rows[~act_f] == 0) and np.all(act_c[t.prolong.indices])
    assert np.diff(t.prolong.indptr).max() == 8
    linear = lambda pos: pos @ np.array([1.0, -2.0, 0.5]) + 3.0  # noqa: E731
    fine = t.prolong @ linear(cg.positions)
    z, y, x = np.indices(g.shape).reshape(3, -1)
    deep = (x >= 2) & (x <= g.nx - 3) & (y >= 2) & (y <= g.ny - 3) & (z >= 2) & (z <= g.nz - 3)
    np.testing.assert_allclose(fine[deep], linear(g.positions)[deep], rtol=1e-13)
    for R, same_kind in ((t.restrict_kind, True), (t.restrict_all, False)):
        sums = np.asarray(R.sum(axis=1)).ravel()
        assert np.all(np.isclose(sums, 1.0) | (sums == 0)) and np.all(np.isclose(sums[act_c], 1.0))
        coo = R.tocoo()
        if same_kind:
            assert np.all(ck[coo.row] == fk[coo.col])
    assert np.diff(t.restrict_kind.indptr).max() == 27
    # interior rows: full weighting, the transposed interpolation weights / 8
    i = np.flatnonzero(ck == 1)[0]
    np.testing.assert_allclose(t.restrict_kind[i].data.sum(), 1.0)
    np.testing.assert_allclose(np.sort(t.restrict_kind[i].data * 8)[-1], 1.0)
    for bad in ((12, 9, 7), (13, 9, 3)):
        with pytest.raises(InputError, match="odd node count"):
            coarsen_regular(RegularGrid(*bad))
    assert [gr.shape for gr in Hierarchy.build(RegularGrid(161, 161, 33), 4).grids] == [
        (33, 161, 161), (17, 81, 81), (9, 41, 41), (5, 21, 21)]


def test_regular_hierarchy_levels(slab_hier):
    """The coarse regular level's direct solution, prolonged, is a useful initial guess (within
    25 % of the fine solution; the first-order boundary rows at h = 2 mm cost most of it), and the
    restricted source stays on the boundary."""
    p = _lit_problem(slab_hier.grids[0])
    probs = level_problems(slab_hier, p)
    phi_f, _ = solve_direct(probs[0])
    phi_c, _ = solve_direct(probs[1])
    g = slab_hier.grids[0]
    err = relative_l2(slab_hier.prolong_phi(phi_c, 1)[g.active], phi_f[g.active])
    print(f"regular 17x13x9 -> 9x7x5: prolonged coarse solution vs fine: {err:.3f}")
    assert err < 0.25
    assert np.all(probs[2].q[probs[2].grid.kind != 2] == 0)
    np.testing.assert_allclose(slab_hier.restrict_q(p.q, 2), probs[2].q)


def test_mapped_hierarchy_levels(torus_polygrid, hier):
    """Coarse level of a mapped polygrid: boundary nodes on the fine surface, weights valid,
    and its direct solution prolonged is a useful initial guess (within 25 % of the fine one)."""
    cg = hier.grids[1]
    assert cg.n == torus_polygrid.n // 2 and cg.weights.min() > 0
    d_b = hier.depth(1)[cg.lattice.boundary]
    assert np.median(d_b) < 0.5 * cg.lattice.h
    p = _lit_problem(torus_polygrid)
    fine, coarse = level_problems(hier, p)
    phi_f, _ = solve_direct(fine)
    phi_c, _ = solve_direct(coarse)
    guess = hier.prolong_phi(phi_c, 1)
    assert relative_l2(guess[torus_polygrid.active], phi_f[torus_polygrid.active]) < 0.25


# ---------------------------------------------------------------- GLSL passes vs CPU
@pytest.mark.parametrize("stencil", ["paper", "conservative"])
def test_prolong_pass_matches_cpu(ctx, any_hier, stencil):
    hier = any_hier
    p = _lit_problem(hier.grids[0], stencil, hetero=True)
    with MultilevelDiffusion(hier, p, "hierarchical", ctx=ctx) as s:
        coarse = s.levels[1]
        rng = np.random.default_rng(0)
        phi_c = rng.uniform(0.5, 2.0, coarse.problem.grid.shape + (3,))
        coarse.set_initial(phi_c)
        s.stack.prolong(1)
        got = s.finest.fluence()
        want = hier.prolong_phi(phi_c * coarse.problem.grid.active[..., None], 1)
        act = hier.grids[0].active
        np.testing.assert_allclose(got[act], want[act], rtol=2e-6)
        # both buffers hold it (nodes no sweep updates keep it)
        other = s.finest.state.read("dst", size=s.finest.size)
        np.testing.assert_allclose(hier.grids[0].unpack(other)[act], s.finest.unknown()[act], rtol=0)


def test_damped_correction_pass_matches_cpu(ctx, any_hier):
    """Multigrid prolongation adds alpha * P e to the fine state (alpha = coarse_correction)."""
    hier = any_hier
    p = _lit_problem(hier.grids[0], "conservative", hetero=True)
    with MultilevelDiffusion(hier, p, "multigrid", ctx=ctx, coarse_correction=0.7) as s:
        fine, coarse = s.levels[:2]
        rng = np.random.default_rng(3)
        x = rng.uniform(0.5, 1.0, fine.problem.grid.shape + (3,))
        e = rng.uniform(-1.0, 1.0, coarse.problem.grid.shape + (3,))
        fine.set_initial(x)
        coarse.set_initial(e)
        s.stack.prolong(1, s.schedule.coarse_correction)
        act = hier.grids[0].active
        want = x + 0.7 * hier.prolong_phi(e * coarse.problem.grid.active[..., None], 1)
        np.testing.assert_allclose(fine.unknown()[act], want[act], rtol=2e-6, atol=1e-6)


@pytest.mark.parametrize("stencil", ["paper", "conservative"])
def test_residual_and_restrict_passes_match_cpu(ctx, any_hier, stencil):
    hier = any_hier
    p = _lit_problem(hier.grids[0], stencil, hetero=True)
    with MultilevelDiffusion(hier, p, "multigrid", ctx=ctx) as s:
        fine = s.finest
        rng = np.random.default_rng(1)
        x_vol = rng.uniform(0.0, 1.0, fine.problem.grid.shape + (3,))
        fine.set_initial(x_vol)  # fluence
        sysf = assemble(fine.problem)
        x = sysf.from_volume(fine.unknown())
        want = ((sysf.b - sysf.A @ x).reshape(3, -1).T / _row_scale(fine.problem))
        tex = s.stack.residual(0)
        g = fine.problem.grid
        got_full = g.unpack(np.frombuffer(tex.read(), dtype="f4").reshape(fine.size[1], fine.size[0], 4))
        got = got_full.reshape(-1, 3)[g.graph.active]
        np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-5 * np.abs(want).max())
        s.stack.restrict(0)
        cg = s.levels[1].problem.grid
        rhs = s.levels[1].textures["u_q"]
        got_c = cg.unpack(np.frombuffer(rhs.read(), dtype="f4").reshape(s.levels[1].size[1], s.levels[1].size[0], 4))
        full = np.zeros((g.size, 3))
        full[g.graph.active] = got
        want_c = (hier.transfers[0].restrict_kind @ full).reshape(cg.shape + (3,))
        np.testing.assert_allclose(got_c, want_c, rtol=1e-5, atol=1e-6 * np.abs(want_c).max())


def test_damped_sweep_with_interior_rhs_matches_cpu(ctx, any_hier):
    """A coarse multigrid level: one damped sweep with f at interior and g at boundary rows."""
    cg = any_hier.grids[1]
    p = _lit_problem(cg, hetero=True)
    rng = np.random.default_rng(2)
    rhs = rng.uniform(-1.0, 1.0, (cg.size, 3)) * (cg.graph.kind != INACTIVE)[:, None]
    with GlslDiffusion(p, ctx, damping=0.7, interior_rhs=True) as s:
        s.textures["u_q"].write(np.ascontiguousarray(cg.pack(rhs.reshape(cg.shape + (3,)))).tobytes(), alignment=1)
        x_vol = rng.uniform(0.0, 1.0, cg.shape + (3,))
        s.set_initial(x_vol)
        sysc = assemble(p)
        x = sysc.from_volume(s.unknown())
        b = (rhs[sysc.active] * _row_scale(p)).T.reshape(-1)
        want = x + 0.7 * (b - sysc.A @ x) / sysc.diag
        s.sweep(1)
        np.testing.assert_allclose(sysc.from_volume(s.unknown()), want, rtol=1e-5, atol=1e-6)


def test_material_8bit_matches_decoded_cpu(ctx, torus_polygrid):
    """'paper' precision: one sweep sees exactly the decoded 8-bit material (fp16 state)."""
    rng = np.random.default_rng(4)
    kappa = 0.05 * 1e4 ** rng.uniform(0, 1, torus_polygrid.shape + (3,))  # contrast 1e4
    mu = rng.uniform(0.0, 0.5, torus_polygrid.shape + (3,))
    p = DiffusionProblem(torus_polygrid, kappa, mu, 1.0, stencil="conservative")
    k8, m8 = quantize.decode(p.kappa.reshape(-1, 3), p.mu.reshape(-1, 3), torus_polygrid.active.reshape(-1))
    assert np.max(np.abs(np.log(k8 / p.kappa.reshape(-1, 3)))[torus_polygrid.active.reshape(-1)]) <= np.log(1e4) / 510 + 1e-12
    p8 = DiffusionProblem(torus_polygrid, k8.reshape(kappa.shape), m8.reshape(mu.shape), 1.0, stencil="conservative")
    with GlslDiffusion(p, ctx, "paper") as s:
        x_vol = rng.uniform(0.2, 1.0, torus_polygrid.shape + (3,))
        s.set_initial(x_vol)
        s8 = assemble(p8)
        x = s8.from_volume(s.unknown())
        s.sweep(1)
        want = x + s8.jacobi_step(x)
        np.testing.assert_allclose(s8.from_volume(s.unknown()), want, rtol=3e-3, atol=1e-3)


# ---------------------------------------------------------------- whole solves
@pytest.mark.parametrize("stencil", ["paper", "conservative"])
@pytest.mark.parametrize("scheme", ["single", "hierarchical", "multigrid"])
def test_multilevel_solves_match_direct(ctx, any_hier, scheme, stencil):
    """Every schedule on both grid types converges to the direct solution (2e-5)."""
    hier = any_hier
    p = _lit_problem(hier.grids[0], stencil)
    ref, _ = solve_direct(p)
    with MultilevelDiffusion(hier, p, scheme, ctx=ctx) as s:
        phi, rep = s.solve(tol=1e-6, maxiter=20000 if scheme != "multigrid" else 100)
    act = hier.grids[0].active
    assert rep.converged and relative_l2(phi[act], ref[act]) < 2e-5
    assert len(rep.levels) == (1 if scheme == "single" else hier.levels)
    assert rep.work > 0 and "level 0" in rep.summary()


def test_hierarchical_start_saves_fine_sweeps(ctx, any_hier):
    hier = any_hier
    p = _lit_problem(hier.grids[0])
    with MultilevelDiffusion(hier, p, "single", ctx=ctx) as s:
        _, single = s.solve(tol=1e-5)
    with MultilevelDiffusion(hier, p, "hierarchical", ctx=ctx) as s:
        _, hier_rep = s.solve(tol=1e-5)
    fine_sweeps = hier_rep.levels[-1]["sweeps"]
    assert hier_rep.levels[-1]["level"] == 0 and fine_sweeps < single.sweeps
    assert hier_rep.work < single.work


def test_adaptive_pins_deep_nodes(ctx, any_hier):
    """Deep nodes keep the coarse value, the solve converges on the pinned system, and the
    boundary values stay within a few percent of the full solve."""
    hier = any_hier
    pg = hier.grids[0]
    p = _lit_problem(pg)
    ref, _ = solve_direct(p)
    h = pg.lattice.h if isinstance(pg, Polygrid) else pg.h
    depths = [3.0 * h] + [None] * (hier.levels - 1)
    with MultilevelDiffusion(hier, p, "adaptive", ctx=ctx, depths=depths) as s:
        mask = s.stack.masks[0]
        assert mask is not None and 0 < mask.sum() < pg.n_active
        assert np.all(mask[pg.graph.boundary])
        phi, rep = s.solve(tol=1e-6)
        pinned = s.finest.system  # deep rows: diag x = diag x_prolonged, captured after prolongation
        x = pinned.from_volume(s.finest.unknown())
        fixed = np.tile(~mask[pinned.active], 3)
    assert rep.converged and rep.levels[-1]["updated"] == int(mask.sum())
    np.testing.assert_allclose(x[fixed], (pinned.b / pinned.diag)[fixed], rtol=1e-12)
    assert np.any(x[fixed] != 0)
    b = pg.graph.boundary
    err = relative_l2(phi.reshape(-1, 3)[b], ref.reshape(-1, 3)[b])
    assert 0 < err < 0.05


def test_adaptive_drops_unused_blocks(ctx):
    """Figure 8's "removed from textures": on a 3x3x3-cube box the deep z-slices are dropped
    from the finest level's textures, which get smaller, and the fluence is the same as with
    every block kept (the nodes no level holds get the coarse value copied down)."""
    pg = box_polygrid((3, 3, 3), 6, size=6.0)
    h2 = Hierarchy.build(pg, 2)
    p = _lit_problem(pg)
    depths = [pg.lattice.h, None]
    out = {}
    for drop in (True, False):
        with MultilevelDiffusion(h2, p, "adaptive", ctx=ctx, depths=depths, drop_blocks=drop) as s:
            out[drop], rep = s.solve(tol=1e-6)
            rows = s.texture_rows()
        assert rep.converged
        if drop:
            assert rows[0]["blocks"] < rows[0]["of_blocks"] and rows[0]["texels"] < rows[0]["full_texels"]
            used = s.schedule.used[0]
            assert not used.all() and np.all(used[pg.lattice.boundary])
        else:
            assert all(r["blocks"] == r["of_blocks"] for r in rows)
    act = pg.active
    assert np.isfinite(out[True]).all() and np.all(out[True][act] > 0)
    np.testing.assert_allclose(out[True][act], out[False][act], rtol=1e-5, atol=1e-7)


def test_frame_coherence_saves_sweeps(ctx, hier):
    """After a small light move, the previous frame's solution reaches a figure-15 error of
    1e-3 with under half the node updates of a cold hierarchical start."""
    pg = hier.grids[0]
    p = _lit_problem(pg)
    l2 = np.array([0.3, 0.2, 0.93]) + np.array([0.05, -0.03, 0.0])
    q2 = np.maximum(pg.normals @ (l2 / np.linalg.norm(l2)), 0.0)[:, None] * np.array([1.0, 0.7, 0.4])
    p2 = p.with_q(q2)
    ref, _ = solve_direct(p2)
    ref_b = ref.reshape(-1, 3)[pg.lattice.boundary]
    with MultilevelDiffusion(hier, p, "hierarchical", ctx=ctx) as s:
        s.solve(tol=1e-5)
        s.set_q(q2)
        warm = run_scheme(hier, p2, ref_b, "hierarchical", solver=s, warm=True, tol=1e-5, check_every=5)
        cold = run_scheme(hier, p2, ref_b, "hierarchical", solver=s, tol=1e-5, check_every=5)
    assert warm.report.converged and warm.error[-1] < 1e-8
    assert warm.first_below(1e-3)[0] < 0.5 * cold.first_below(1e-3)[0]
    with MultilevelDiffusion(hier, p, "adaptive", ctx=ctx, depths=[2.0, None]) as s:
        with pytest.raises(InputError, match="coherence"):
            s.solve(x0=CURRENT)


@pytest.mark.parametrize("case", ["huge_mu", "zero_mu", "kappa_contrast"])
def test_paper_precision_stiff_cases_stay_finite(ctx, hier, case):
    """fp16 radiance + 8-bit material on the foundation's stiff cases: no NaN/Inf, no
    divergence, and an error against the fp32 direct solve at the fp16 level."""
    pg = hier.grids[0]
    rng = np.random.default_rng(5)
    kappa, mu, stencil = 0.3, 0.01, "paper"
    if case == "huge_mu":
        mu = 1e3
    elif case == "zero_mu":
        mu = 0.0
    else:
        kappa = np.where(rng.uniform(size=pg.shape) < 0.5, 1e-3, 10.0)
        stencil = "conservative"
    p = DiffusionProblem(pg, kappa, mu, 1.0, stencil=stencil)
    ref, _ = solve_direct(p)
    with MultilevelDiffusion(hier, p, "hierarchical", ctx=ctx, precision="paper") as s:
        phi, rep = s.solve(tol=1e-4, maxiter=4000)
    assert np.isfinite(phi).all() and rep.status != "diverged"
    act = pg.active
    assert relative_l2(phi[act], ref[act]) < 0.05


def test_bad_options(ctx, hier):
    p = _lit_problem(hier.grids[0])
    with pytest.raises(InputError, match="scheme"):
        MultilevelDiffusion(hier, p, "vcycle", ctx=ctx)
    with pytest.raises(InputError, match="depths"):
        MultilevelDiffusion(hier, p, "hierarchical", ctx=ctx, depths=[1.0, None])
    with pytest.raises(InputError, match="entries"):
        MultilevelDiffusion(hier, p, "adaptive", ctx=ctx, depths=[1.0])
    with pytest.raises(InputError, match="precision"):
        GlslDiffusion(p, ctx, "fp8")
    for bad in (0.0, 1.5, float("nan"), "0.7"):
        with pytest.raises(InputError, match="coarse_correction"):
            MultilevelDiffusion(hier, p, "multigrid", ctx=ctx, coarse_correction=bad)
