"""``glsldiff cut``: TransCut's cut of a scene's fTetWild mesh, rendered, and what the update
costs on the CPU (TransCut section 5.1: "the entire linear system is recomputed").

:func:`update_seconds` times the steps after a cut on the cut mesh, one channel: the cut itself
(removal, relaxation, boundary; from its report), the DE matrix of eqs. 10-14
(:func:`glsldiff.system.transcut.de_matrix`), TransCut's hierarchy
(:class:`glsldiff.solve.graph_hierarchy.GraphHierarchy`) and the re-solve to a relative residual
``tol`` (``||r|| / ||b||``) from zero, by Jacobi-preconditioned CG and by the hierarchy's cascade
(coarse operator :data:`COARSE`, its levels to :data:`COARSE_RTOL`) + CG; each step names the
solver and tolerance. Each solve's error is against a direct (SuperLU; pyamg SA + CG above 20k
unknowns) solve of the same system, named in its detail. Seconds on this machine's CPU, one run
each; the hierarchy's solve excludes its build (its own row).
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from glsldiff.bench.peers import JACOBI_CG, fem_reference_label, krylov_label
from glsldiff.grids.tetrahedral.tetcut import CutReport
from glsldiff.grids.tetrahedral.tetwild import TetMesh
from glsldiff.oracle.fem import solve_matrix_reference
from glsldiff.solve.graph_hierarchy import GraphHierarchy, jacobi_cg
from glsldiff.system.transcut import de_matrix, de_rhs

__all__ = ["update_seconds", "COARSE", "COARSE_RTOL"]

#: The hierarchy's coarse operator and its coarse levels' relative residual in the re-solve.
COARSE = "paper"
COARSE_RTOL = 1e-3


def update_seconds(tm: TetMesh, report: CutReport, kappa: NDArray, mu: NDArray, q: NDArray, eta: float,
                   tol: float) -> list[dict[str, Any]]:
    """Rows (step, seconds, detail) of a cut's update (module docstring): ``kappa`` (mm) and
    ``mu`` (mm^-1) per node of the cut mesh ``tm``, ``q`` per node (boundary nodes' values used)."""
    rows: list[dict[str, Any]] = [{"step": f"cut ({k})", "seconds": v, "detail": ""} for k, v in report.seconds.items()]
    t0 = time.perf_counter()
    M = de_matrix(tm.positions, tm.tets, tm.surface, np.asarray(kappa)[tm.tets].mean(axis=1),
                  np.asarray(mu)[tm.tets].mean(axis=1), eta, inert=tm.inert)
    b = de_rhs(tm.positions, tm.surface, q, eta)
    rows.append({"step": "DE matrix (eqs. 10-14)", "seconds": time.perf_counter() - t0,
                 "detail": f"{M.shape[0]:,} unknowns, {len(tm.tets):,} tetrahedra"})
    t0 = time.perf_counter()
    H = GraphHierarchy.build(M, tm.positions, coarse=COARSE)
    rows.append({"step": "TransCut hierarchy", "seconds": time.perf_counter() - t0,
                 "detail": " / ".join(f"{k:,}" for k in H.info["nodes"]) + " nodes"})
    ref, _ = solve_matrix_reference(M, b)
    ref_label, _ = fem_reference_label(M.shape[0])
    scale = float(np.abs(ref).max())
    t0 = time.perf_counter()
    x = jacobi_cg(M, b, tol)
    rows.append({"step": f"re-solve from zero: {krylov_label(JACOBI_CG, tol)}",
                 "seconds": time.perf_counter() - t0,
                 "detail": f"max error {np.abs(x - ref).max() / scale:.2g} of max phi (vs {ref_label})"})
    t_cg = rows[-1]["seconds"]
    x, info = H.solve(b, tol=tol, coarse_tol=COARSE_RTOL)
    rows.append({"step": "re-solve: " + krylov_label(f"hierarchy cascade ({COARSE}, coarse rtol {COARSE_RTOL:g}) + CG",
                                                     tol), "seconds": info["seconds"],
                 "detail": f"max error {np.abs(x - ref).max() / scale:.2g} of max phi (vs {ref_label})"})
    cut_s = sum(report.seconds.values())
    t_m = rows[len(report.seconds)]["seconds"]
    t_h = rows[len(report.seconds) + 1]["seconds"]
    rows.append({"step": "total: cut + matrix + CG", "seconds": cut_s + t_m + t_cg,
                 "detail": "TransCut reports < 3 s (the cut alone about 2 s) on a 2010 PC + GPU"})
    rows.append({"step": "total: cut + matrix + hierarchy + its solve", "seconds": cut_s + t_m + t_h + info["seconds"],
                 "detail": "the paper's path"})
    return rows
