"""The solvers' own error estimate (SolveReport.error_estimate, glsldiff.system.report.
contraction_error_estimate) against the true error of the same solve: the relative L2 distance
to the direct (scipy) solution of the same discrete system.

Systems: a back-lit marble block on a regular grid (GLSL and numpy Jacobi, the hierarchical
and multigrid schedules) and the P1 system of a pillowed sphere (tests/gather_systems.py:
gather Jacobi, AMG V-cycles and AMG-preconditioned CG, checked every 1 or 4 iterations).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.grids.regular import RegularGrid
from glsldiff.oracle.solvers import jacobi, solve_direct
from glsldiff.physics.material import preset
from glsldiff.solve.gather import GlslSparse
from glsldiff.solve.gather_multigrid import GlslSparseMultigrid
from glsldiff.solve.jacobi import GlslDiffusion
from glsldiff.solve.multilevel import MultilevelDiffusion
from glsldiff.system.problem import DiffusionProblem, relative_l2
from glsldiff.system.report import ESTIMATE_SAFETY, contraction_error_estimate

from gather_systems import p1_system, rel, spsolve3   # tests/gather_systems.py

#: The estimate is an upper one and at most this many times the true error, once two check
#: intervals ran (measured 1.1-3.6x over 90 solves, report.py).
TIGHT = 5.0


def test_one_interval_gives_the_bound_and_more_intervals_scale_it() -> None:
    # one interval: change / ((1 - rho) |x|)
    assert contraction_error_estimate([(0, 1.0), (10, 0.1)], 2.0, 4.0) == pytest.approx(0.5 / 0.9)
    # two intervals: scaled by ESTIMATE_SAFETY times the larger contraction (0.1 here), never raised
    est = contraction_error_estimate([(0, 1.0), (10, 0.1), (20, 0.01)], 2.0, 4.0)
    assert est == pytest.approx(0.5 / 0.9 * ESTIMATE_SAFETY * 0.1)
    slow = contraction_error_estimate([(0, 1.0), (10, 0.9), (20, 0.81)], 2.0, 4.0)
    assert slow == pytest.approx(0.5 / 0.1)
    # nothing contracted, or nothing to measure: unknown
    assert math.isnan(contraction_error_estimate([(0, 1.0), (10, 1.5)], 2.0, 4.0))
    assert math.isnan(contraction_error_estimate([(0, 1.0)], 2.0, 4.0))


@pytest.fixture(scope="module")
def block() -> tuple[DiffusionProblem, np.ndarray]:
    grid = RegularGrid(41, 41, 17, h=0.5)
    kappa, mu = preset("marble").coefficients()
    p = DiffusionProblem.from_irradiance(grid, kappa, mu, {"z-": 1.0}, eta=1.3)
    return p, solve_direct(p)[0]


def check(est: float, true: float, checks: int) -> None:
    assert true > 0.0 and np.isfinite(est)
    assert est >= true, f"estimate {est:.3g} below the true error {true:.3g}"
    if checks >= 2:
        assert est <= TIGHT * true, f"estimate {est:.3g} is {est / true:.1f}x the true error {true:.3g}"


@pytest.mark.parametrize("tol", [1e-3, 1e-5])
def test_jacobi_on_a_regular_grid(ctx, block, tol: float) -> None:
    p, ref = block
    phi, rep = jacobi(p, tol=tol, maxiter=100000)
    check(rep.error_estimate, relative_l2(phi, ref, p.grid.active), len(rep.history) - 1)
    with GlslDiffusion(p, ctx, "fp32") as s:
        phi, rep = s.solve(tol=tol, maxiter=100000)
    check(rep.error_estimate, relative_l2(phi, ref, p.grid.active), len(rep.history) - 1)


@pytest.mark.parametrize("scheme", ["hierarchical", "multigrid"])
def test_multilevel_schedules(ctx, block, scheme: str) -> None:
    p, ref = block
    hier = Hierarchy.build(p.grid, 3)
    for tol in (1e-3, 1e-5):            # the hierarchical 1e-3 solve stops after one interval
        with MultilevelDiffusion(hier, p, scheme, ctx=ctx) as s:
            phi, rep = s.solve(tol=tol, maxiter=100000)
        check(rep.error_estimate, relative_l2(phi, ref, p.grid.active), len(rep.history) - 1)


@pytest.fixture(scope="module")
def p1() -> tuple[list, np.ndarray, np.ndarray]:
    mats, b = p1_system(3, 4)
    return mats, b, spsolve3(mats, b)


@pytest.mark.parametrize("solver,every", [("pcg", 1), ("pcg", 4), ("vcycle", 1), ("vcycle", 4), ("jacobi", 50)])
def test_gather_solvers_on_the_p1_system(ctx, p1, solver: str, every: int) -> None:
    mats, b, ref = p1
    for tol in (1e-3, 1e-5):
        s = (GlslSparse(mats, b, ctx) if solver == "jacobi" else
             GlslSparseMultigrid(mats, b, ctx, accel="cg" if solver == "pcg" else None))
        try:
            x, rep = s.solve(tol=tol, maxiter=20000, check_every=every)
        finally:
            s.release()
        check(rep.error_estimate, rel(x, ref), len(rep.history) - 1)
