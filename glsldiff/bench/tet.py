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
of the solve. Writes ``tet_<mesh>.csv`` (one row per solver and iteration) and
``tet_<mesh>.png`` (error against time). Lengths in mm, coefficients in mm^-1.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import pyamg
import scipy.sparse as sp
from numpy.typing import NDArray

from glsldiff.core import io
from glsldiff.core.rng import pinned_global_rng
from glsldiff.core.errors import InputError
from glsldiff.core.plotting import pyplot, save_figure
from glsldiff.grids.tetwild import TetMesh, cached_tetrahedralize, refine as refine_mesh
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
              coarse_tol: float = 0.1) -> tuple[TetMesh, list[dict[str, Any]], dict[str, Any]]:
    """The study (module docstring): ``(tet mesh, rows, summary)``."""
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
    x_ref, ref_name = solve_matrix_reference(M, b, DIRECT_MAX_NODES, maxiter=500)
    t_ref = time.perf_counter() - t0
    nodes = tm.surface_nodes
    scale = float(np.abs(x_ref[nodes]).max())

    def err(x: NDArray) -> float:
        return float(np.abs(x[nodes] - x_ref[nodes]).max() / scale)

    cg_rows, _ = _trace("cg (jacobi)", lambda cb: jacobi_cg(M, b, tol, callback=cb), err, M, b)
    t0 = time.perf_counter()
    with pinned_global_rng():
        ml = pyamg.smoothed_aggregation_solver(M, symmetry="symmetric")
    t_setup = time.perf_counter() - t0
    amg_rows, _ = _trace("pyamg (SA + cg)", lambda cb: ml.solve(b, tol=tol, accel="cg", maxiter=500, callback=cb),
                         err, M, b)
    for r in amg_rows:
        r["seconds"] += t_setup
    h_rows: list[dict[str, Any]] = []
    hier: dict[str, Any] = {}
    setup = {"pyamg (SA + cg)": t_setup}
    for coarse in COARSE_OPERATORS:
        if status:
            status(f"tet: TransCut hierarchy ({levels} levels, {coarse} coarse operator)")
        H = GraphHierarchy.build(M, tm.positions, levels=levels, coarse=coarse)
        info: dict[str, Any] = {}

        def transcut(cb: Callable[[NDArray], None], H: GraphHierarchy = H, info: dict[str, Any] = info) -> NDArray:
            x, rep = H.solve(b, tol=tol, coarse_tol=coarse_tol, callback=cb)
            info.update(rep)
            return x

        rows_c, _ = _trace(f"transcut hierarchy ({coarse})", transcut, err, M, b)
        for r in rows_c:
            r["iteration"] -= 1                      # the cascade's start is iteration 0
            r["seconds"] += H.seconds
        h_rows += rows_c
        setup[f"transcut hierarchy ({coarse})"] = H.seconds
        hier[coarse] = {"nodes": " / ".join(f"{k:,}" for k in H.info["nodes"]), "build_s": H.seconds,
                        "start_error": rows_c[0]["error"] if rows_c else float("nan"),
                        "coarse_s": sum(r["seconds"] for r in info.get("cascade", [])),
                        "coarse_fallbacks": sum(r["fallback"] for r in info.get("cascade", []))}
    rows = cg_rows + h_rows + amg_rows
    q_rep = tm.quality
    summary = {"tets": q_rep.tets, "nodes": q_rep.nodes, "from_cache": cached,
               "tetwild_s": q_rep.seconds.get("tetwild"),
               "min_dihedral_deg": q_rep.min_dihedral_deg, "slivers": q_rep.slivers, "matrix_s": t_matrix,
               "reference": ref_name, "reference_s": t_ref, "pyamg_setup_s": t_setup,
               "positive_offdiagonals": positive_couplings(M), "refined": refine,
               **{f"hierarchy ({c}): {k}": v for c, d in hier.items() for k, v in d.items()}}
    for name in dict.fromkeys(r["solver"] for r in rows):
        sel = [r for r in rows if r["solver"] == name]
        if sel:
            summary[f"{name}: iterations"] = sel[-1]["iteration"]
            summary[f"{name}: seconds"] = sel[-1]["seconds"]
            summary[f"{name}: final error"] = sel[-1]["error"]
            for level, label in ((1e-2, "1 %"), (1e-3, "0.1 %")):
                hit = next((r for r in sel if r["error"] <= level), None)
                summary[f"{name}: seconds to {label}"] = hit["seconds"] if hit else float("nan")
                if name in setup:       # the setup is reused while the mesh stays (relighting, painting)
                    summary[f"{name}: solve-only seconds to {label}"] = (
                        hit["seconds"] - setup[name] if hit else float("nan"))
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        io.write_csv(out / f"tet_{mesh.name}.csv", rows)
        refined = f" (edge {edge_mm:g} mm 1:8-refined {refine}x)" if refine else ""
        _plot(rows, out / f"tet_{mesh.name}.png", f"{mesh.name}: {q_rep.tets:,} tetrahedra, edge {tm.edge_mm:g} mm{refined}")
    return tm, rows, summary


def _plot(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for name in dict.fromkeys(r["solver"] for r in rows):
        sel = [r for r in rows if r["solver"] == name]
        ax.semilogy([r["seconds"] for r in sel], [max(r["error"], 1e-16) for r in sel], ".-", label=name)
    ax.set_xlabel("wall time [s], setup included (hierarchy build, pyamg setup)")
    ax.set_ylabel("max boundary error / max phi")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    save_figure(fig, path, dpi=100)
