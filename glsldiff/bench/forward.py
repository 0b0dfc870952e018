"""``glsldiff bench forward``: error against run time of the forward solvers.

For each grid (a back-lit marble slab, whole back face lit) it runs

* the GLSL Jacobi solver (fp32 and/or fp16 buffers, no tolerance: it sweeps for ``seconds``),
  reading the fluence back at geometric checkpoints to measure the error;
* the numpy Jacobi iteration of the same system (float64, no tolerance, ``seconds`` budget);
* optionally (``schemes``) the multiresolution schedules of :mod:`glsldiff.solve.schedules` on the
  grid's regular-grid hierarchy (:func:`glsldiff.grids.hierarchy.coarsen_regular`; every axis
  needs an odd node count, e.g. 161x161x33), solved to the Jacobi-scaled residual ``tol``
  through the one GLSL stack, with the report's error estimate next to the measured error;
* the scipy direct solve (SuperLU) up to ``max_direct_nodes``, and algebraic multigrid (pyamg
  smoothed aggregation + GMRES to the relative residual :data:`AMG_RTOL`) on every grid. The
  reference every error is measured against (relative L2 of the fluence over the active
  nodes) is the direct solution where it ran, else the pyamg solution.

Timing (every method alike): each run builds its solver from scratch and the clock includes
that set-up: CPU, assembly and the LU factorisation or AMG set-up; GPU, the solver's
construction (texture upload, shader compilation), GPU finished (``ctx.finish()``) before the
clock stops. The GL context is created once, before any clock starts. The bench's own error
measurements (read-backs, errors against the reference) are outside the clock. Each method
runs ``repeats`` times: the first GLSL / numpy run sweeps for ``seconds``, the others redo its
sweeps, so every run does the same work; rows give the median and the minimum over the runs
(``t_median_s``, ``t_min_s``; the time to each error level likewise), the first run's time
(``t_first_s``) and, where the set-up is measured apart, its median (``setup_s``, part of
``t``); ``Mupd/s`` and ``sweeps/s`` are per second of solving, that set-up left out.

It writes ``forward.csv`` (one row per grid and method), ``forward_curves.csv`` (error vs time
checkpoints of the last run) and ``forward.png`` (error against time). Times in seconds,
errors are relative L2 errors of phi, ``residual`` the Jacobi-scaled residual reached.
"""
from __future__ import annotations

import logging
import re
import time
from pathlib import Path
from typing import Sequence

import numpy as np

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
from glsldiff.system.report import REFERENCE_TOL, RELAX_TOL, SolveReport
from glsldiff.bench.progress import Cases
from glsldiff.bench.peers import amg_label, direct_label, relax_label
from glsldiff.bench.timing import Timing, median_min, repeat, timing_columns
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


#: Error levels the rows give the time to, by their column names' spelling.
LEVELS = {"1e-3": 1e-3, "1e-4": 1e-4, "1e-5": 1e-5}
#: The relative residual pyamg (SA + GMRES) is solved to, on every grid.
AMG_RTOL = REFERENCE_TOL

Curve = list[tuple[int, float, float]]


def _first_time_below(curve: Curve, level: float) -> float:
    for _, t, e in curve:
        if e <= level:
            return t
    return float("nan")


def run_glsl(problem: DiffusionProblem, phi_ref: np.ndarray, precision: str, seconds: float,
             maxiter: int = 200_000) -> tuple[Curve, float]:
    """(sweeps, seconds, error) checkpoints of the GLSL Jacobi solver, and its set-up seconds.
    The clock runs from the solver's construction (texture upload, shader compilation) on,
    GPU finished, the read-backs for the error excluded; it sweeps until ``seconds`` have
    passed or ``maxiter`` sweeps are done (a repeat passes the first run's sweeps and an
    infinite budget: the checkpoints fall on the same sweeps)."""
    ctx = gl.get_context()
    mask = problem.grid.active
    t0 = time.perf_counter()
    with GlslDiffusion(problem, ctx, precision) as gpu:
        gpu.set_initial(None)
        ctx.finish()
        setup = elapsed = time.perf_counter() - t0
        curve = [(0, elapsed, 1.0)]
        sweeps, step = 0, 4
        while elapsed < seconds and sweeps < maxiter:
            n = min(step, maxiter - sweeps)
            t0 = time.perf_counter()
            gpu.sweep(n)
            ctx.finish()
            elapsed += time.perf_counter() - t0
            sweeps += n
            err = relative_l2(gpu.fluence(), phi_ref, mask)
            curve.append((sweeps, elapsed, err))
            if not np.isfinite(err):
                break
            step = min(int(step * 1.5) + 1, 2000)
    return curve, setup


def run_numpy(problem: DiffusionProblem, phi_ref: np.ndarray, seconds: float,
              check_every: int, max_sweeps: int | None = None) -> Curve:
    """(sweeps, seconds, error) checkpoints of the numpy Jacobi iteration (float64, no
    tolerance), assembly and the iteration's own residual checks in the clock, the error
    measurements out; it stops once ``seconds`` have passed or at ``max_sweeps``."""
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
        if elapsed > seconds or (max_sweeps is not None and curve[-1][0] >= max_sweeps):
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
                   tol: float = RELAX_TOL) -> tuple[Curve, SolveReport | None, dict[str, float]]:
    """(iterations, seconds, error) checkpoints of ``scheme`` on the grid's hierarchy, solved
    to ``tol`` (within ``seconds``), its report (``None`` when the time ran out) and its
    times: ``wall`` from the hierarchy's build on (the solver's construction, shader
    compilation and its own residual checks in, the bench's error measurements out),
    ``setup`` (build and construction) and ``gpu`` (the solve's GPU passes alone). The
    multigrid runs with an undamped coarse correction (the trilinear prolongation of a regular
    grid needs none)."""
    ctx = gl.get_context()
    mask = problem.grid.active
    options = {"coarse_correction": 1.0} if scheme == "multigrid" else {}
    t_start = time.perf_counter()
    hierarchy = Hierarchy.build(problem.grid, levels)
    with MultilevelDiffusion(hierarchy, problem, scheme, ctx=ctx, **options) as solver:
        ctx.finish()
        setup = time.perf_counter() - t_start
        curve = [(0, setup, 1.0)]
        excluded = 0.0

        def record(x: np.ndarray) -> None:
            nonlocal excluded
            t0 = time.perf_counter()
            elapsed = t0 - t_start - excluded
            phi = problem.to_phi(solver.finest.system.to_volume(x, problem.node_shape))
            curve.append((len(curve), elapsed, relative_l2(phi, phi_ref, mask)))
            excluded += time.perf_counter() - t0
            if elapsed > seconds:
                raise _Budget

        try:
            _, rep = solver.solve(tol=tol, maxiter=200 if scheme == "multigrid" else 200_000, callback=record)
        except _Budget:
            rep = None
        wall = time.perf_counter() - t_start - excluded
        gpu = solver.compute_seconds
    return curve, rep, {"wall": wall, "setup": setup, "gpu": gpu}


def _level_columns(curves: Sequence[Curve]) -> dict[str, float]:
    """Per error level, the median and min over the runs of the time to reach it."""
    cols: dict[str, float] = {}
    for name, level in LEVELS.items():
        med, lo = median_min(_first_time_below(c, level) for c in curves)
        cols[f"t(err<{name})"] = med
        cols[f"t(err<{name}) min"] = lo
    return cols


def _peer_row(size: str, n: int, method: str, tol: float, timing: Timing, err: float, residual: float,
              ref_name: str, setup: float = float("nan")) -> dict[str, object]:
    reached = {name: err <= lv for name, lv in LEVELS.items()}     # one point in time: its error at its time
    return {"grid": size, "nodes": n, "method": method, **timing.columns(first=True), "final_error": err,
            "tol": tol, "residual": residual, "setup_s": setup, "sweeps": 0, "sweeps/s": float("nan"),
            "Mupd/s": float("nan"), "est_error": float("nan"),
            **{k: v for lv in LEVELS for k, v in ((f"t(err<{lv})", timing.median if reached[lv] else float("nan")),
                                                  (f"t(err<{lv}) min", timing.min if reached[lv] else float("nan")))},
            "reference": ref_name, "device": "cpu"}


def forward(sizes: Sequence[str], out: Path, max_direct_nodes: int = 200_000,
            seconds: float = 20.0, precisions: Sequence[str] = ("fp32", "fp16"),
            schemes: Sequence[str] = (), levels: int = 4, tol: float = RELAX_TOL,
            repeats: int = 3) -> list[dict[str, object]]:
    """Run the benchmark, write CSV + PNG, return the summary rows. ``schemes`` (e.g.
    ``("multigrid", "hierarchical")``) adds the multiresolution schedules on ``levels`` levels
    (fewer where the grid cannot be coarsened), solved to ``tol``; every method runs
    ``repeats`` times (module docstring)."""
    rows: list[dict[str, object]] = []
    curves: list[dict[str, object]] = []
    t0 = time.perf_counter()
    device = gl.describe(gl.get_context())       # the GL context: created before any clock starts
    context_s = time.perf_counter() - t0         # (0 when it existed already): a column of the GPU rows
    cases = Cases("bench forward", len(sizes))
    for size in sizes:
        nx, ny, nz = parse_size(size)
        problem = slab_problem(nx, ny, nz)
        n = problem.grid.n_active
        cases.before(f"grid {size} ({n:,} nodes): SuperLU, pyamg, Jacobi {'/'.join(precisions)}, numpy"
                     + (f", {'/'.join(schemes)}" if schemes else "") + f"; {repeats} run(s) each")
        peers = []
        if n <= max_direct_nodes:
            factor: list[float] = []

            def direct() -> tuple[np.ndarray, SolveReport]:
                solver = DirectSolver(problem)          # assembly + factorisation
                factor.append(solver.factor_seconds)
                return solver.solve()
            tim = repeat(direct, repeats)
            peers.append((direct_label(), float("nan"), tim, tim.result[0], tim.result[1].residual,
                          float(np.median(factor))))
        tim = repeat(lambda: solve_amg(problem, tol=AMG_RTOL), repeats)
        peers.append((amg_label("gmres", AMG_RTOL), AMG_RTOL, tim, tim.result[0], tim.result[1].residual,
                      float("nan")))
        ref_name, phi_ref = peers[0][0], peers[0][3]
        for method, ptol, tim, phi, residual, setup in peers:
            err = relative_l2(phi, phi_ref, problem.grid.active)
            rows.append(_peer_row(size, n, method, ptol, tim, err, residual, ref_name, setup))
            curves.append({"grid": size, "method": method, "sweeps": 0, "seconds": tim.median, "error": err})
        # (method, device, tol, curves of the runs, extra columns)
        runs: list[tuple[str, str, float, list[Curve], dict[str, object]]] = []
        for p in precisions:
            first, setup0 = run_glsl(problem, phi_ref, p, seconds)
            more = [run_glsl(problem, phi_ref, p, float("inf"), maxiter=first[-1][0]) for _ in range(repeats - 1)]
            runs.append((relax_label(f"GLSL Jacobi {p}", None), device, float("nan"), [first] + [c for c, _ in more],
                         {"setups": [setup0] + [s for _, s in more]}))
        check = max(5, 2_000_000 // n)
        first = run_numpy(problem, phi_ref, seconds, check_every=check)
        more_np = [run_numpy(problem, phi_ref, float("inf"), check, max_sweeps=first[-1][0])
                   for _ in range(repeats - 1)]
        runs.append((relax_label("numpy Jacobi f64", None), "cpu", float("nan"), [first] + more_np, {}))
        lv = regular_levels(problem.grid, levels)
        for scheme in schemes if lv > 1 else ():
            results = [run_multilevel(problem, phi_ref, scheme, lv, seconds, tol) for _ in range(repeats)]
            _, srep, _ = results[-1]
            last = results[-1][0]
            extra: dict[str, object] = {
                "sweeps": srep.sweeps if srep else last[-1][0],
                "work": srep.work if srep else float("nan"),
                "est_error": srep.error_estimate if srep else float("nan"),
                "residual": srep.residual if srep else float("nan"),
                "status": srep.status if srep else "time budget",
                "setups": [t["setup"] for _, _, t in results],
                "gpu_s": float(np.median([t["gpu"] for _, _, t in results])),
                "times": [t["wall"] for _, _, t in results]}
            runs.append((relax_label(f"GLSL {scheme} fp32", tol), device, tol, [c for c, _, _ in results],
                         {"levels": lv, **extra}))
        if schemes and lv == 1:
            logger.warning("grid %s cannot be coarsened (every axis needs an odd node count >= 5): "
                           "no multilevel runs", size)
        for method, dev, rtol, cs, more in runs:
            last = cs[-1]
            sweeps, _, err = last[-1]
            times: list[float] = more.pop("times", [c[-1][1] for c in cs])   # type: ignore[assignment]
            setups: list[float] | None = more.pop("setups", None)              # type: ignore[assignment]
            timing = timing_columns(times, first=True)
            # the rates: per second of solving, the set-up left out where it was measured apart
            t = float(np.median([a - b for a, b in zip(times, setups)] if setups else times))
            sweeps = int(more.pop("sweeps", sweeps))      # type: ignore[call-overload]
            work = more.pop("work", None)
            updates = float(work) if work is not None else n * sweeps  # type: ignore[arg-type]
            rows.append({"grid": size, "nodes": n, "method": method, **timing, "final_error": err, "tol": rtol,
                         "residual": more.pop("residual", float("nan")),
                         "setup_s": float(np.median(setups)) if setups else float("nan"),
                         "sweeps": sweeps, "sweeps/s": float("nan") if work is not None else sweeps / t,
                         "Mupd/s": updates / t / 1e6, "est_error": more.pop("est_error", float("nan")),
                         **_level_columns(cs), "reference": ref_name, "device": dev,
                         **({"gl_context_s": context_s} if dev != "cpu" else {}), **more})
            curves += [{"grid": size, "method": method, "sweeps": s, "seconds": tt, "error": e}
                       for s, tt, e in last[1:]]
        cases.after()
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
        ax.set_xlabel("time [s], set-up included (last run)")
        ax.set_ylabel("relative L2 error of phi vs reference")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"glsldiff forward solvers, {device}", fontsize=9)
    save_figure(fig, path, dpi=110)
