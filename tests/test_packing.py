"""The "texels" packing (per-texel offset textures, one quad per sweep) against the paper's
primitives: the same shader rows on the same texels, so sweeps and residuals agree to the last
bit on polygrids (paper and conservative stencils), with update masks, damping, an interior
right-hand side, fp16 buffers and 8-bit material; and the multilevel schedules run on it."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff import gl
from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.grids.polygrid import box_polygrid
from glsldiff.grids.regular import RegularGrid
from glsldiff.solve.jacobi import GlslDiffusion
from glsldiff.solve.multilevel import MultilevelDiffusion
from glsldiff.solve.stencil import offset_textures, pass_primitives
from glsldiff.system.problem import DiffusionProblem

pytestmark = pytest.mark.usefixtures("ctx")


def _problem(grid, stencil="conservative", seed=0):
    rng = np.random.default_rng(seed)
    shape = tuple(grid.shape) + (3,)
    kappa = rng.uniform(0.1, 1.0, shape)
    mu = rng.uniform(0.001, 0.05, shape)
    if isinstance(grid, RegularGrid):
        q = {"z-": rng.uniform(0.0, 1.0, (grid.shape[1] - 2, grid.shape[2] - 2, 3))}
    else:
        q = rng.uniform(0.0, 1.0, (len(grid.graph.boundary), 3))
    return DiffusionProblem(grid, kappa, mu, q, stencil=stencil)


def _mapped():
    pg = box_polygrid((2, 3, 2), 6, 6.0)
    rng = np.random.default_rng(3)          # distort the positions: non-uniform weights
    pg.positions[:] += rng.normal(0.0, 0.05, pg.positions.shape)
    return pg


CASES = {
    "polygrid paper": dict(grid=lambda: box_polygrid((2, 3, 2), 6, 6.0), stencil="paper"),
    "polygrid conservative": dict(grid=lambda: box_polygrid((3, 2, 2), 4, 4.0), stencil="conservative"),
    "polygrid, update mask": dict(grid=lambda: box_polygrid((2, 2, 2), 6, 6.0), update=True),
    "polygrid, damped + rhs": dict(grid=lambda: box_polygrid((2, 2, 2), 6, 6.0), damping=0.7, interior_rhs=True),
    "polygrid fp16": dict(grid=lambda: box_polygrid((2, 2, 1), 8, 8.0), precision="fp16"),
    "polygrid 8-bit material": dict(grid=lambda: box_polygrid((2, 2, 1), 8, 8.0), precision="paper"),
    "regular grid": dict(grid=lambda: RegularGrid(12, 10, 6, h=0.5)),
}


@pytest.mark.parametrize("name", list(CASES))
def test_texels_packing_equals_primitives(ctx, name):
    c = CASES[name]
    grid = c["grid"]()
    prob = _problem(grid, c.get("stencil", "conservative"))
    update = None
    if c.get("update"):
        update = np.random.default_rng(1).uniform(size=grid.size) < 0.7
    kw = dict(precision=c.get("precision", "fp32"), update=update, damping=c.get("damping", 1.0),
              interior_rhs=c.get("interior_rhs", False))
    x0 = np.random.default_rng(2).uniform(0.0, 1.0, tuple(grid.shape) + (3,))
    out = {}
    for packing in ("primitives", "texels"):
        with GlslDiffusion(prob, ctx, packing=packing, **kw) as lv:
            lv.set_initial(x0)
            lv.state.write(lv.state.read("src"), "dst")    # both buffers, as the schedules' starts do
            if kw["interior_rhs"]:
                lv.textures["u_q"].write(np.ascontiguousarray(grid.pack(x0 * 0.1)).tobytes(), alignment=1)
            lv.sweep(7)
            x = lv.unknown()
            with gl.keep_framebuffer(ctx), gl.Resources() as held:
                res = held.add(gl.PingPong.create(ctx, lv.size, "fp32"))
                res.dst.use()
                res.dst.clear()
                lv.residual(res.dst)
                r = res.read("dst", size=lv.size)
            out[packing] = (x, r)
    np.testing.assert_array_equal(out["texels"][0], out["primitives"][0])
    np.testing.assert_array_equal(out["texels"][1], out["primitives"][1])
    assert np.abs(out["texels"][0]).max() > 0


def test_offset_textures_hold_the_primitives_offsets():
    pg = box_polygrid((2, 2, 1), 4, 4.0)
    a, b = offset_textures(pg)
    prims = pass_primitives(pg)
    assert (a[..., 3] == 1).sum() == prims["interior"].texels and (a[..., 3] == 2).sum() == prims["boundary"].texels
    unpack = lambda v: np.stack([(v >> 16).astype(np.int64) - 32768, (v & 0xFFFF).astype(np.int64) - 32768], -1)
    for (x0, y0, x1, y1), off in zip(prims["interior"].rects, prims["interior"].offsets):
        got = np.concatenate([unpack(a[y0:y1, x0:x1, :3]), unpack(b[y0:y1, x0:x1, :3])], axis=2)
        assert (got == off[None, None]).all()


@pytest.mark.parametrize("scheme", ["hierarchical", "multigrid"])
def test_multilevel_schedules_on_texels(ctx, scheme, monkeypatch):
    pg = box_polygrid((2, 2, 2), 8, 8.0)
    prob = _problem(pg)
    hier = Hierarchy.build(pg, 2)
    sols = {}
    for packing in ("primitives", "texels"):
        monkeypatch.setenv("GLSLDIFF_PACKING", packing)
        with MultilevelDiffusion(hier, prob, scheme, ctx=ctx) as ml:
            assert ml.finest.packing == packing
            phi, rep = ml.solve(tol=1e-5)
        assert rep.converged
        sols[packing] = (phi, rep.sweeps)
    np.testing.assert_array_equal(sols["texels"][0], sols["primitives"][0])
    assert sols["texels"][1] == sols["primitives"][1]


def test_default_packing_by_grid_and_environment(ctx, monkeypatch):
    monkeypatch.delenv("GLSLDIFF_PACKING", raising=False)
    pg, reg = box_polygrid((2, 2, 2), 4, 4.0), RegularGrid(48, 48, 24, h=1.0)
    with GlslDiffusion(_problem(pg), ctx) as a, GlslDiffusion(_problem(reg), ctx) as b:
        # the measured choice (llvmpipe): many small blocks -> texels, a few slice quads -> primitives
        assert a.packing == "texels" and b.packing == "primitives"
    monkeypatch.setenv("GLSLDIFF_PACKING", "primitives")
    with GlslDiffusion(_problem(pg), ctx) as a:
        assert a.packing == "primitives"
    monkeypatch.setenv("GLSLDIFF_PACKING", "quads")
    from glsldiff.core.errors import InputError
    with pytest.raises(InputError, match="GLSLDIFF_PACKING"):
        GlslDiffusion(_problem(pg), ctx)
