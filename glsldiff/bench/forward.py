"""``glsldiff bench forward``: error against run time of the forward solvers.

For each grid (a back-lit marble slab, whole back face lit) it runs

* the GLSL Jacobi solver (fp32 and/or fp16 buffers), timing only the sweeps
  (``ctx.finish()`` before the clock stops) and reading the fluence back at
  geometric checkpoints to measure the error;
* the numpy Jacobi iteration of the same system (float64), timed the same way;
* optionally (``schemes``) the multiresolution schedules of :mod:`glsldiff.solve.schedules` on the
  grid's regular-grid hierarchy (:func:`glsldiff.grids.hierarchy.coarsen_regular`; every axis
  needs an odd node count, e.g. 161x161x33), solved to ``tol`` through the one GLSL stack, timed
  by their GPU passes (sweeps and transfers, GPU finished; read-backs and residual checks out),
  with the report's error estimate next to the measured error;
* the scipy direct solve (SuperLU) up to ``max_direct_nodes``, and algebraic
  multigrid (pyamg) on every grid. The reference every error is measured against
  (relative L2 of the fluence over the active nodes) is the direct solution where it
  ran, else the pyamg solution at relative residual 1e-12.

It writes ``forward.csv`` (one row per grid and method), ``forward_curves.csv``
(error vs time checkpoints) and ``forward.png`` (error against time). Times in seconds, errors
are relative L2 errors of phi.
"""
from __future__ import annotations

import logging
import re
import time
from pathlib import Path
from typing import Sequence

import numpy as np
from tqdm import tqdm

from glsldiff import gl

from glsldiff.core import io
from glsldiff.core.errors import InputError
from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.grids.regular import RegularGrid
from glsldiff.oracle.solvers import DirectSolver, jacobi, solve_amg
from glsldiff.physics.procedural import marble_volume
from glsldiff.solve.jacobi import GlslDiffusion
from glsldiff.solve.multilevel import MultilevelDiffusion
from glsldiff.system.problem import DiffusionProblem, relative_l2
from glsldiff.system.report import RELAX_TOL, SolveReport
from glsldiff.core.plotting import pyplot, save_figure

logger = logging.getLogger(__name__)


class _Budget(Exception):
    """Raised by a solve callback when the time budget is spent."""


def parse_size(text: str) -> tuple[int, int, int]:
    m = re.fullmatch(r"(\d+)x(\d+)x(\d+)", text.strip())
    if not m:
        raise InputError(f"grid size {text!r}: expected NXxNYxNZ, e.g. 64x64x12")
    return int(m.group(1)), int(m.group(2)), int(m.group(3))


def slab_problem(nx: int, ny: int, nz: int, h: float = 0.5) -> DiffusionProblem:
    """Marble slab with the whole back face (z-) lit with q = 1."""
    grid = RegularGrid(nx, ny, nz, h)
    kappa, mu = marble_volume(grid.shape, seed=0)
    return DiffusionProblem(grid, kappa, mu, {"z-": 1.0})


def _first_time_below(curve: list[tuple[int, float, float]], level: float) -> float:
    for _, t, e in curve:
        if e <= level:
            return t
    return float("nan")


def run_glsl(problem: DiffusionProblem, phi_ref: np.ndarray, precision: str,
             seconds: float, maxiter: int = 200_000) -> list[tuple[int, float, float]]:
    """(sweeps, sweep seconds, error) checkpoints of the GLSL Jacobi solver."""
    ctx = gl.get_context()
    mask = problem.grid.active
    curve = [(0, 0.0, 1.0)]
    with GlslDiffusion(problem, ctx, precision) as gpu:
        gpu.set_initial(None)
        gpu.sweep(1)  # warm-up: shader compilation and first upload
        ctx.finish()
        gpu.set_initial(None)
        sweeps, elapsed, step = 0, 0.0, 4
        while elapsed < seconds and sweeps < maxiter:
            t0 = time.perf_counter()
            gpu.sweep(step)
            ctx.finish()
            elapsed += time.perf_counter() - t0
            sweeps += step
            err = relative_l2(gpu.fluence(), phi_ref, mask)
            curve.append((sweeps, elapsed, err))
            if not np.isfinite(err):
                break
            step = min(int(step * 1.5) + 1, 2000)
    return curve


def run_numpy(problem: DiffusionProblem, phi_ref: np.ndarray, seconds: float,
              check_every: int) -> list[tuple[int, float, float]]:
    """(sweeps, seconds, error) checkpoints of the numpy Jacobi iteration (float64)."""
    mask = problem.grid.active
    curve = [(0, 0.0, 1.0)]
    t_start = time.perf_counter()
    excluded = 0.0
    shape = problem.grid.shape

    def callback(x: np.ndarray) -> None:
        nonlocal excluded
        t0 = time.perf_counter()
        # x is channel-major over the active nodes
        vol = np.zeros(shape + (3,))
        vol[mask] = x.reshape(3, -1).T
        err = relative_l2(problem.to_phi(vol), phi_ref, mask)
        elapsed = t0 - t_start - excluded
        curve.append((curve[-1][0] + check_every, elapsed, err))
        excluded += time.perf_counter() - t0
        if elapsed > seconds:
            raise _Budget

    try:
        jacobi(problem, tol=0.0, maxiter=10**9, check_every=check_every, callback=callback)
    except _Budget:
        pass
    return curve


def regular_levels(grid: RegularGrid, wanted: int) -> int:
    """Levels of a regular-grid hierarchy, at most ``wanted``: a level is coarsened while every
    axis has an odd node count >= 5 (:func:`glsldiff.grids.hierarchy.coarsen_regular`)."""
    dims, levels = (grid.nx, grid.ny, grid.nz), 1
    while levels < wanted and all(n % 2 == 1 and n >= 5 for n in dims):
        dims = tuple((n + 1) // 2 for n in dims)
        levels += 1
    return levels


def run_multilevel(problem: DiffusionProblem, phi_ref: np.ndarray, scheme: str, levels: int, seconds: float,
                   tol: float = RELAX_TOL) -> tuple[list[tuple[int, float, float]], SolveReport | None, float]:
    """(iterations, GPU seconds, error) checkpoints of ``scheme`` on the grid's hierarchy, solved
    to ``tol`` (within ``seconds`` of GPU time), its report (``None`` when the time ran out) and
    the solve's wall time without the bench's own error measurements. The multigrid runs with
    an undamped coarse correction (the trilinear prolongation of a regular grid needs none)."""
    ctx = gl.get_context()
    mask = problem.grid.active
    hierarchy = Hierarchy.build(problem.grid, levels)
    options = {"coarse_correction": 1.0} if scheme == "multigrid" else {}
    curve = [(0, 0.0, 1.0)]
    with MultilevelDiffusion(hierarchy, problem, scheme, ctx=ctx, **options) as solver:
        quiet = logging.getLogger("glsldiff").level
        logging.getLogger("glsldiff").setLevel(logging.ERROR)  # the warm-up ends on its budget
        try:  # warm-up: every pass drawn once (shader compilation on first use)
            solver.solve(maxiter=1)
        finally:
            logging.getLogger("glsldiff").setLevel(quiet)
        base, excluded = solver.compute_seconds, 0.0

        def record(x: np.ndarray) -> None:
            nonlocal excluded
            t0 = time.perf_counter()
            phi = problem.to_phi(solver.finest.system.to_volume(x, problem.node_shape))
            elapsed = solver.compute_seconds - base
            curve.append((len(curve), elapsed, relative_l2(phi, phi_ref, mask)))
            excluded += time.perf_counter() - t0
            if elapsed > seconds:
                raise _Budget

        t0 = time.perf_counter()
        try:
            _, rep = solver.solve(tol=tol, maxiter=200 if scheme == "multigrid" else 200_000, callback=record)
        except _Budget:
            rep = None
        wall = time.perf_counter() - t0 - excluded
    return curve, rep, wall


def forward(sizes: Sequence[str], out: Path, max_direct_nodes: int = 200_000,
            seconds: float = 20.0, precisions: Sequence[str] = ("fp32", "fp16"),
            schemes: Sequence[str] = (), levels: int = 4, tol: float = RELAX_TOL) -> list[dict[str, object]]:
    """Run the benchmark, write CSV + PNG, return the summary rows. ``schemes`` (e.g.
    ``("multigrid", "hierarchical")``) adds the multiresolution schedules on ``levels`` levels
    (fewer where the grid cannot be coarsened), solved to ``tol``."""
    rows: list[dict[str, object]] = []
    curves: list[dict[str, object]] = []
    device = gl.describe(gl.get_context())
    for size in tqdm(sizes, desc="grids"):
        nx, ny, nz = parse_size(size)
        problem = slab_problem(nx, ny, nz)
        n = problem.grid.n_active
        peers = []
        if n <= max_direct_nodes:
            t0 = time.perf_counter()
            phi_direct, rep = DirectSolver(problem).solve()
            peers.append(("scipy-direct (SuperLU)", phi_direct, time.perf_counter() - t0, rep.residual))
        phi_amg, rep = solve_amg(problem)
        peers.append(("pyamg (SA + GMRES)", phi_amg, rep.seconds, rep.residual))
        ref_name, phi_ref = peers[0][0], peers[0][1]
        for method, phi, secs, residual in peers:
            err = relative_l2(phi, phi_ref, problem.grid.active)
            rows.append({"grid": size, "nodes": n, "method": method, "sweeps": 0,
                         "sweeps/s": float("nan"), "Mupd/s": float("nan"), "seconds": secs,
                         "final_error": err, "est_error": float("nan"), "residual": residual,
                         "t(err<1e-3)": secs, "t(err<1e-4)": secs, "t(err<1e-5)": secs,
                         "reference": ref_name, "device": "cpu"})
            curves.append({"grid": size, "method": method, "sweeps": 0, "seconds": secs, "error": err})
        runs = [(f"glsl-jacobi-{p}", device, run_glsl(problem, phi_ref, p, seconds)) for p in precisions]
        runs.append(("numpy-jacobi-f64", "cpu",
                     run_numpy(problem, phi_ref, seconds, check_every=max(5, 2_000_000 // n))))
        extra: dict[str, dict[str, object]] = {}
        lv = regular_levels(problem.grid, levels)
        for scheme in schemes if lv > 1 else ():
            curve, srep, wall = run_multilevel(problem, phi_ref, scheme, lv, seconds, tol)
            method = f"glsl-{scheme}-fp32 ({lv} levels)"
            runs.append((method, device, curve))
            extra[method] = {"sweeps": srep.sweeps if srep else curve[-1][0], "wall_s": wall,
                             "work": srep.work if srep else float("nan"),
                             "est_error": srep.error_estimate if srep else float("nan"),
                             "residual": srep.residual if srep else float("nan"),
                             "status": srep.status if srep else "time budget"}
        if schemes and lv == 1:
            logger.warning("grid %s cannot be coarsened (every axis needs an odd node count >= 5): "
                           "no multilevel runs", size)
        for method, dev, curve in runs:
            sweeps, secs, err = curve[-1]
            more = extra.get(method, {})
            sweeps = int(more.get("sweeps", sweeps))  # type: ignore[call-overload]
            updates = float(more["work"]) if more else n * sweeps  # type: ignore[arg-type]
            rows.append({"grid": size, "nodes": n, "method": method, "sweeps": sweeps,
                         "sweeps/s": float("nan") if more else sweeps / secs, "Mupd/s": updates / secs / 1e6,
                         "seconds": secs, "final_error": err, "est_error": more.get("est_error", float("nan")),
                         "residual": more.get("residual", float("nan")),
                         "t(err<1e-3)": _first_time_below(curve, 1e-3),
                         "t(err<1e-4)": _first_time_below(curve, 1e-4),
                         "t(err<1e-5)": _first_time_below(curve, 1e-5), "reference": ref_name,
                         "device": dev, **({"wall_s": more["wall_s"], "status": more["status"]} if more else {})})
            curves += [{"grid": size, "method": method, "sweeps": s, "seconds": t, "error": e}
                       for s, t, e in curve[1:]]
    if not rows:
        raise InputError("no grid was benchmarked")
    io.write_csv(out / "forward.csv", rows)
    io.write_csv(out / "forward_curves.csv", curves)
    plot(curves, out / "forward.png", device)
    return rows


def plot(curves: list[dict[str, object]], path: Path, device: str) -> None:
    """Error against time, one panel per grid."""
    plt = pyplot()

    grids = list(dict.fromkeys(c["grid"] for c in curves))
    fig, axes = plt.subplots(1, len(grids), figsize=(5 * len(grids), 4), squeeze=False)
    for ax, g in zip(axes[0], grids):
        for method in dict.fromkeys(c["method"] for c in curves if c["grid"] == g):
            pts = [(c["seconds"], max(float(c["error"]), 1e-16)) for c in curves
                   if c["grid"] == g and c["method"] == method]
            t, e = zip(*pts)
            if len(pts) == 1:  # a direct / multigrid peer: one point in time
                ax.axvline(t[0], ls="--", color="k" if "direct" in method else "grey",
                           label=f"{method} ({t[0]:.2g} s)")
            else:
                ax.loglog(t, e, marker=".", label=method)
        ax.set_title(f"{g}")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("relative L2 error of phi vs direct")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"glsldiff forward solvers, {device}", fontsize=9)
    save_figure(fig, path, dpi=110)
