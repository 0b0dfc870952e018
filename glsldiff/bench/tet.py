"""``glsldiff tet MESH``: a TransCut tetrahedral mesh of MESH (fTetWild), its quality, the DE
matrix of eqs. 10-14 (:mod:`glsldiff.system.transcut`) and its solve by conjugate gradients
(scipy, Jacobi-preconditioned), by TransCut's multiresolution graph hierarchy
(:mod:`glsldiff.solve.graph_hierarchy`, with the paper's eq. 17 coarse operator and BiCG, and
with the Galerkin one and CG; CG on the fine level) and by
pyamg (smoothed aggregation, the peer), each as error against run time (TransCut figure 7's
analogue; the setup of the hierarchy and of pyamg is counted in their times and also reported
alone, the paper's T_b). ``refine`` 1:8-subdivides the mesh that many times (8x the
tetrahedra each) to time the solvers at the paper's 0.5-1 M tetrahedra without hours of fTetWild.

Light: a directional light of unit irradiance from ``light`` (towards the light), unshadowed
(``q = max(n.l, 0) F_t`` at each boundary node: exact for convex objects, an over-estimate in
self-shadowed parts). The reference is a direct (SuperLU) solve up to ``DIRECT_MAX_NODES``
unknowns, else pyamg to a relative residual of 1e-12. Error: ``max |phi - phi_ref| / max
phi_ref`` over the boundary nodes, after each iteration, against the wall time from the start
of the solve. Every iterative solver stops at the relative residual ``tol`` (``||r|| / ||b||``);
each row's ``method`` names the solver and that tolerance, ``residual`` is the one reached.
Each solve runs ``repeats`` times, its set-up (pyamg's, the hierarchy's) built once and added to
every run's times; the summary's times are the median (and ``seconds min`` the fastest) over
the runs, the CSV's rows the last run's iterations. Writes ``tet_<mesh>.csv`` (one row per solver
and iteration), ``tet_<mesh>_solvers.csv`` (one per solver) and ``tet_<mesh>.png`` (error against
time). Lengths in mm, coefficients in mm^-1.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import pyamg
import scipy.sparse as sp
from numpy.typing import NDArray

from glsldiff.bench.peers import JACOBI_CG, amg_label, fem_reference_label, krylov_label
from glsldiff.bench.timing import median_min
from glsldiff.core import io
from glsldiff.core.rng import pinned_global_rng
from glsldiff.core.errors import InputError
from glsldiff.core.plotting import pyplot, save_figure
from glsldiff.grids.tetrahedral.tetwild import TetMesh, cached_tetrahedralize, refine as refine_mesh
from glsldiff.mesh import Mesh
from glsldiff.oracle.fem import positive_couplings, solve_matrix_reference
from glsldiff.physics.material import coefficients
from glsldiff.physics.optics import transmitted_cosine
from glsldiff.solve.graph_hierarchy import COARSE_OPERATORS, GraphHierarchy, jacobi_cg
from glsldiff.system.transcut import de_matrix, de_rhs

__all__ = ["tet_study", "DIRECT_MAX_NODES"]

#: Above this many unknowns the reference is pyamg (SuperLU fill-in grows too fast).
DIRECT_MAX_NODES = 60_000


def _trace(name: str, run: Callable[[Callable[[NDArray], None]], NDArray], err: Callable[[NDArray], float],
           M: sp.csr_matrix, b: NDArray) -> tuple[list[dict[str, Any]], NDArray]:
    """Rows (iteration, seconds, error, residual) of one iterative solver; the error is
    evaluated after the run from the iterates kept by the callback (it costs no solve time)."""
    iterates: list[tuple[float, NDArray]] = []
    t0 = time.perf_counter()
    x = run(lambda xk: iterates.append((time.perf_counter() - t0, np.array(xk))))
    total = time.perf_counter() - t0
    rows = []
    bn = float(np.linalg.norm(b))
    for k, (t, xk) in enumerate(iterates, start=1):
        rows.append({"solver": name, "iteration": k, "seconds": t, "error": err(xk),
                     "residual": float(np.linalg.norm(b - M @ xk) / bn)})
    if rows:
        rows[-1]["seconds"] = total
    return rows, x


def tet_study(mesh: Mesh, edge_mm: float, sigma_a: float, sigma_s: float, eta: float,
              light: Sequence[float] = (0.0, 0.0, 1.0), tol: float = 1e-8, out: Path | None = None,
              status: Callable[[str], None] | None = None, refine: int = 0, levels: int = 4,
              coarse_tol: float = 0.1, repeats: int = 1
              ) -> tuple[TetMesh, list[dict[str, Any]], dict[str, Any], list[dict[str, Any]]]:
    """The study (module docstring): ``(tet mesh, rows, summary, solvers)``: the iterations, the
    mesh and set-up quantities, one row per solver (its label, the median and fastest times to
    1 % and 0.1 % with the set-up and without it, to its tolerance); each solve runs
    ``repeats`` times (its set-up once)."""
    if not (sigma_a >= 0 and sigma_s >= 0 and sigma_a + sigma_s > 0):
        raise InputError(f"sigma_a {sigma_a} and sigma_s' {sigma_s} mm^-1 must be >= 0 with a positive sum")
    tm, cached = cached_tetrahedralize(mesh, edge_mm, status=status)
    for _ in range(refine):
        tm = refine_mesh(tm)
    kappa, mu = coefficients(sigma_a, sigma_s)
    l = np.asarray(light, dtype=np.float64)
    l = l / np.linalg.norm(l)
    q = np.zeros(len(tm.positions))
    q[tm.surface_nodes] = transmitted_cosine(eta, tm.normals @ l)
    t0 = time.perf_counter()
    M = de_matrix(tm.positions, tm.tets, tm.surface, kappa, mu, eta, inert=tm.inert)
    b = de_rhs(tm.positions, tm.surface, q, eta)
    t_matrix = time.perf_counter() - t0
    if status:
        status(f"tet: {M.shape[0]:,} unknowns, {len(tm.tets):,} tetrahedra: reference solve")
    t0 = time.perf_counter()
    x_ref, _ = solve_matrix_reference(M, b, DIRECT_MAX_NODES, maxiter=500)
    t_ref = time.perf_counter() - t0
    nodes = tm.surface_nodes
    scale = float(np.abs(x_ref[nodes]).max())

    def err(x: NDArray) -> float:
        return float(np.abs(x[nodes] - x_ref[nodes]).max() / scale)

    # (solver id, label, runs of trace rows, setup seconds): each solve repeated, its set-up built once
    traced: list[tuple[str, str, list[list[dict[str, Any]]], float]] = []

    def solve(name: str, label: str, run: Callable[[Callable[[NDArray], None]], NDArray], setup: float = 0.0,
              start: int = 0) -> list[list[dict[str, Any]]]:
        runs = []
        for _ in range(repeats):
            rows_k, _ = _trace(name, run, err, M, b)
            for r in rows_k:
                r["iteration"] += start
                r["seconds"] += setup
                r["method"], r["tol"] = label, tol
            runs.append(rows_k)
        traced.append((name, label, runs, setup))
        return runs

    solve("cg (jacobi)", krylov_label(JACOBI_CG, tol), lambda cb: jacobi_cg(M, b, tol, callback=cb))
    t0 = time.perf_counter()
    with pinned_global_rng():
        ml = pyamg.smoothed_aggregation_solver(M, symmetry="symmetric")
    t_setup = time.perf_counter() - t0
    solve("pyamg (SA + cg)", amg_label("cg", tol),
          lambda cb: ml.solve(b, tol=tol, accel="cg", maxiter=500, callback=cb), t_setup)
    hier: dict[str, Any] = {}
    for coarse in COARSE_OPERATORS:
        if status:
            status(f"tet: TransCut hierarchy ({levels} levels, {coarse} coarse operator)")
        H = GraphHierarchy.build(M, tm.positions, levels=levels, coarse=coarse)
        info: dict[str, Any] = {}

        def transcut(cb: Callable[[NDArray], None], H: GraphHierarchy = H, info: dict[str, Any] = info) -> NDArray:
            x, rep = H.solve(b, tol=tol, coarse_tol=coarse_tol, callback=cb)
            info.update(rep)
            return x

        runs_c = solve(f"transcut hierarchy ({coarse})", krylov_label(f"TransCut {coarse}+CG", tol),
                       transcut, H.seconds, start=-1)      # the cascade's start is iteration 0 (its coarse
        for r in runs_c[-1]:                               # levels to coarse_tol: a column of its own)
            r["coarse_rtol"] = coarse_tol
        rows_c = runs_c[-1]
        hier[coarse] = {"nodes": " / ".join(f"{k:,}" for k in H.info["nodes"]), "build_s": H.seconds,
                        "start_error": rows_c[0]["error"] if rows_c else float("nan"),
                        "coarse_s": sum(r["seconds"] for r in info.get("cascade", [])),
                        "coarse_fallbacks": sum(r["fallback"] for r in info.get("cascade", []))}
    order = ["cg (jacobi)"] + [f"transcut hierarchy ({c})" for c in COARSE_OPERATORS] + ["pyamg (SA + cg)"]
    traced.sort(key=lambda t: order.index(t[0]))
    rows = [r for _, _, runs, _ in traced for r in runs[-1]]      # the last run's iterations
    q_rep = tm.quality
    ref_label, _ = fem_reference_label(M.shape[0], DIRECT_MAX_NODES)
    summary = {"tets": q_rep.tets, "nodes": q_rep.nodes, "from_cache": cached,
               "tetwild_s": q_rep.seconds.get("tetwild"),
               "min_dihedral_deg": q_rep.min_dihedral_deg, "slivers": q_rep.slivers, "matrix_s": t_matrix,
               "reference": ref_label, "reference_s": t_ref, "pyamg_setup_s": t_setup,
               "positive_offdiagonals": positive_couplings(M), "refined": refine,
               **{f"hierarchy ({c}): {k}": v for c, d in hier.items() for k, v in d.items()}}
    solvers: list[dict[str, Any]] = []
    for name, label, runs, setup in traced:
        sel = runs[-1]
        if not sel:
            continue
        row: dict[str, Any] = {"method": label}
        for level, text in ((1e-2, "1%"), (1e-3, "0.1%")):
            hits = [next((r["seconds"] for r in rs if r["error"] <= level), float("nan")) for rs in runs]
            row[f"t({text})"], row[f"t({text}) min"] = median_min(hits)
            # the set-up is reused while the mesh stays (relighting, painting)
            row[f"solve t({text})"], _ = median_min(h - setup for h in hits)
        med, lo = median_min(rs[-1]["seconds"] for rs in runs)
        row.update({"t_median_s": med, "t_min_s": lo, "repeats": len(runs), "setup_s": setup,
                    "iterations": sel[-1]["iteration"], "tol": tol, "residual": sel[-1]["residual"],
                    "error": sel[-1]["error"], "coarse_rtol": sel[-1].get("coarse_rtol", float("nan")), "id": name})
        solvers.append(row)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        io.write_csv(out / f"tet_{mesh.name}.csv", rows)
        io.write_csv(out / f"tet_{mesh.name}_solvers.csv", solvers)
        refined = f" (edge {edge_mm:g} mm 1:8-refined {refine}x)" if refine else ""
        _plot(rows, out / f"tet_{mesh.name}.png", f"{mesh.name}: {q_rep.tets:,} tetrahedra, edge {tm.edge_mm:g} mm{refined}")
    return tm, rows, summary, solvers


def _plot(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for name in dict.fromkeys(r["solver"] for r in rows):
        sel = [r for r in rows if r["solver"] == name]
        ax.semilogy([r["seconds"] for r in sel], [max(r["error"], 1e-16) for r in sel], ".-",
                    label=sel[0].get("method", name))
    ax.set_xlabel("wall time [s], setup included (hierarchy build, pyamg setup)")
    ax.set_ylabel("max boundary error / max phi")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, path, dpi=100)
