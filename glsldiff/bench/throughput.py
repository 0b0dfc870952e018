"""Sweep throughput of the GLSL Jacobi solver: node updates per second of a polygrid against a
regular grid with the same node count in the same run, for each packing of the sweeps
(:data:`glsldiff.solve.stencil.PACKINGS`: the paper's quads/lines/points with per-primitive
offsets, or per-texel offset textures drawn as one quad). Part of ``glsldiff bench forward
--throughput``.

Each grid solves a homogeneous marble problem lit on its boundary; after a few warm-up sweeps
(shader compilation, first use; outside the clock), ``sweeps`` sweeps are timed with the GPU
finished (``ctx.finish``), no read-back inside the clock, ``repeats`` times
(:func:`glsldiff.bench.timing.repeat`): the rates are of the median run, ``t_min_s`` the fastest
(run-to-run noise on a shared 2-core VM is +-30 %). The solver's construction (texture upload,
shader compilation) and the warm-up sweeps are timed apart (``setup_s``, wall).
"""
from __future__ import annotations

import time
from typing import Any, Sequence

import numpy as np

from glsldiff import gl
from glsldiff.bench.progress import Cases
from glsldiff.bench.timing import repeat
from glsldiff.grids.cache import cached_polygrid
from glsldiff.grids.regular import RegularGrid
from glsldiff.mesh import GENERATED_MESHES, generated_mesh, load_mesh
from glsldiff.physics.material import preset
from glsldiff.solve.jacobi import GlslDiffusion
from glsldiff.solve.stencil import PACKINGS, pass_primitives, primitive_count
from glsldiff.system.problem import DiffusionProblem

#: (mesh, n per cube edge, target cube count) of the polygrids measured: the torus standing in for
#: the paper's "Hole" (36 cubes x 12^3, 54 k nodes), the bunny's default lattice (253 cubes x 8^3)
#: and the viewer's editing lattice (about 2000 cubes x 4^3), both ~125 k nodes.
POLYGRIDS = (("torus", 12, 36), ("bunny", 8, 253), ("bunny", 4, 2000))


def _problem(grid: Any) -> DiffusionProblem:
    kappa, mu = preset("marble").coefficients()
    shape = tuple(grid.shape) + (3,)
    if isinstance(grid, RegularGrid):
        n = grid.shape
        q: Any = {"z-": np.ones((n[1] - 2, n[2] - 2, 3))}
    else:
        q = np.ones((len(grid.graph.boundary), 3))
    return DiffusionProblem(grid, np.broadcast_to(kappa, shape), np.broadcast_to(mu, shape), q,
                            stencil="conservative")


def _rate(problem: DiffusionProblem, packing: str, sweeps: int, ctx: Any, repeats: int = 3) -> dict[str, Any]:
    t0 = time.perf_counter()
    with GlslDiffusion(problem, ctx, packing=packing) as lv:
        lv.sweep(5)                                   # compile, first-use costs: outside the clock
        setup = time.perf_counter() - t0

        def run() -> float:
            t = lv.sweep_seconds                      # GPU finished, no read-back
            lv.sweep(sweeps)
            return lv.sweep_seconds - t
        tim = repeat(run, repeats, seconds=lambda dt: dt)
        dt = tim.median
        return {"nodes updated": lv.updated_nodes,
                "draws per sweep": primitive_count(lv.primitives) if packing == "primitives" else 1,
                "ms/sweep": 1e3 * dt / sweeps, "ms/sweep min": 1e3 * tim.min / sweeps,
                "M upd/s": lv.updated_nodes * sweeps / dt / 1e6, **tim.columns(), "setup_s": setup}


def sweep_throughput(polygrids: Sequence[tuple[str, int, int]] = POLYGRIDS, sweeps: int = 200,
                     packings: Sequence[str] = PACKINGS, repeats: int = 3) -> list[dict[str, Any]]:
    """One row per grid and packing: node updates per second (median of ``repeats`` runs of
    ``sweeps`` sweeps) and the polygrid's cost per node relative to the regular grid of the
    same node count with the same packing."""
    ctx = gl.get_context()
    rows: list[dict[str, Any]] = []
    cases = Cases("bench throughput", len(polygrids) * len(packings))
    for mesh_name, n, cubes in polygrids:
        mesh = (generated_mesh(mesh_name, 100.0) if mesh_name in GENERATED_MESHES
                else load_mesh(mesh_name, size_mm=100.0))
        pg, _ = cached_polygrid(mesh, n=n, n_cubes=cubes)
        side = int(round(pg.n_active ** (1.0 / 3.0)))
        reg = RegularGrid(side, side, side, h=1.0)
        per_node = primitive_count(pass_primitives(pg)) / pg.n_active
        for packing in packings:
            cases.before(f"{mesh_name} polygrid ({pg.n_active:,} nodes) and a regular {side}^3, {packing} packing, "
                         f"{repeats} run(s) of {sweeps} sweeps")
            r_reg = _rate(_problem(reg), packing, sweeps, ctx, repeats)
            r_pg = _rate(_problem(pg), packing, sweeps, ctx, repeats)
            label = f"{mesh_name} {pg.shape[0]} cubes x {n}^3"     # a polygrid; the regular grid before it:
            rows.append({"grid": f"regular {side}^3", "packing": packing, **r_reg,   # the same node count
                         "cost/node vs regular": 1.0})
            rows.append({"grid": label, "packing": packing, **r_pg, "primitives per node": per_node,
                         "cost/node vs regular": r_reg["M upd/s"] / r_pg["M upd/s"]})
            cases.after(f"{r_pg['M upd/s']:.3g} M updates/s")
    return rows
