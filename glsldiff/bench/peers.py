"""The benchmarks' peer solvers and their labels: each label names the library, the method and
the stopping tolerance the code passes, or ``direct`` for a factorisation. The label functions
take the same value the call gets, so a label cannot drift from what ran.

Tolerances: ``rtol`` is the relative residual as the library tests it (pyamg GMRES: the
preconditioned ``||M r|| / ||M b||``; pyamg and scipy CG: ``||r|| / ||b||``); ``tol`` is the
Jacobi-scaled residual ``max_c ||D^-1 (b - A x)|| / ||D^-1 b||`` of glsldiff's relaxations
(:mod:`glsldiff.system.report`). The residual a bench reports as reached is the Jacobi-scaled
one unless its caption says otherwise.
"""
from __future__ import annotations

import math

from numpy.typing import NDArray

from glsldiff.oracle import fem
from glsldiff.oracle import solvers
from glsldiff.oracle.solvers import REFERENCE_AMG_RTOL, solve_reference
from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.report import REFERENCE_TOL, SolveReport

__all__ = ["JACOBI_CG", "tol_text", "direct_label", "amg_label", "krylov_label", "relax_label", "reference_solve",
           "reference_label", "fem_reference_label", "REFERENCE_MAX_DIRECT", "REFERENCE_AMG_RTOL"]

#: Polygrid references (the sphere, convergence and polygrid studies): SuperLU below this many
#: active nodes, pyamg SA + GMRES to REFERENCE_AMG_RTOL above (the oracle's
#: :func:`~glsldiff.oracle.solvers.solve_reference`, which gets this value; a test may lower it).
REFERENCE_MAX_DIRECT = solvers.REFERENCE_MAX_DIRECT


#: scipy's conjugate gradients with the Jacobi (diagonal) preconditioner (glsldiff.oracle's jacobi_cg).
JACOBI_CG = "scipy CG + Jacobi"


def tol_text(tol: float) -> str:
    """A tolerance as the labels print it (``1e-12``)."""
    return f"{tol:g}"


def direct_label() -> str:
    """scipy's sparse LU (SuperLU): a factorisation, no tolerance."""
    return "scipy SuperLU, direct"


def amg_label(accel: str, rtol: float) -> str:
    """pyamg smoothed aggregation accelerated by ``accel`` (``"gmres"``, ``"cg"``) to ``rtol``."""
    return f"pyamg SA + {accel.upper()}, rtol {tol_text(rtol)}"


def krylov_label(method: str, rtol: float) -> str:
    """A Krylov solver named by ``method`` (e.g. ``"scipy CG + Jacobi"``) to ``rtol``."""
    return f"{method}, rtol {tol_text(rtol)}"


def relax_label(method: str, tol: float | None) -> str:
    """A glsldiff relaxation (``"GLSL Jacobi fp32"``, ``"numpy Jacobi f64"``) stopped at the
    Jacobi-scaled residual ``tol``; ``None``: no tolerance, stopped by a time or sweep budget."""
    return f"{method}, " + ("no tol" if tol is None else f"tol {tol_text(tol)}")


def reference_label(n_active: int) -> tuple[str, float]:
    """``(label, rtol)`` of :func:`reference_solve` on ``n_active`` nodes (``rtol`` NaN: direct)."""
    if n_active < REFERENCE_MAX_DIRECT:
        return direct_label(), math.nan
    return amg_label("gmres", REFERENCE_AMG_RTOL), REFERENCE_AMG_RTOL


def reference_solve(problem: DiffusionProblem) -> tuple[NDArray, SolveReport, str, float]:
    """The converged polygrid answer the studies measure against, as
    :func:`~glsldiff.oracle.solvers.solve_reference` computes it (SuperLU factorisation and
    solve below :data:`REFERENCE_MAX_DIRECT` nodes, else pyamg SA + GMRES to
    :data:`REFERENCE_AMG_RTOL`; assembly included in the report's seconds), with its label:
    ``(phi, report, label, rtol)``."""
    label, rtol = reference_label(problem.grid.n_active)
    phi, rep = solve_reference(problem, max_direct_nodes=REFERENCE_MAX_DIRECT)
    return phi, rep, label, rtol


def fem_reference_label(n: int, max_direct: int = fem.DIRECT_MAX_NODES) -> tuple[str, float]:
    """``(label, rtol)`` of :func:`glsldiff.oracle.fem.solve_matrix_reference` on ``n``
    unknowns: SuperLU up to ``max_direct``, else pyamg SA + CG to
    :data:`~glsldiff.system.report.REFERENCE_TOL`."""
    if n <= max_direct:
        return direct_label(), math.nan
    return amg_label("cg", REFERENCE_TOL), REFERENCE_TOL
