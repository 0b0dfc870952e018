"""CPU oracle solvers of the discrete system of :mod:`glsldiff.oracle.assembly`.

:func:`~glsldiff.oracle.assembly.assemble` builds, for all three channels at once, the block-diagonal system
``A x = b`` whose rows are exactly the relaxation formulas the GLSL shaders apply
(see :mod:`glsldiff.system.problem`): Jacobi is ``x <- x + D^-1 (b - A x)`` with
``D = diag(A)``. :class:`DirectSolver` factorises it (SuperLU) and :func:`jacobi`
runs the same Jacobi iteration in numpy. Both return ``(phi, report)`` with the
fluence ``phi`` as a ``(nz, ny, nx, 3)`` volume (0 at inactive edge/corner nodes).
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import Callable, Mapping

import numpy as np
import scipy.sparse.linalg as spla
from numpy.typing import ArrayLike, NDArray

from glsldiff.system.problem import DiffusionProblem
from glsldiff.core.errors import InputError, SolverError
from glsldiff.oracle.assembly import LinearSystem, assemble, assemble_rhs, diverged_message
from glsldiff.system.report import ConvergenceMonitor, SolveReport, contraction_error_estimate

logger = logging.getLogger(__name__)





class DirectSolver:
    """Sparse LU factorisation of the problem's matrix, reusable for many sources ``q``.

    Examples
    --------
    >>> from glsldiff.grids.regular import RegularGrid
    >>> p = DiffusionProblem(RegularGrid(5, 5, 5), kappa=0.5, mu=0.1, q={"z-": 1.0})
    >>> phi, rep = DirectSolver(p).solve()
    >>> bool(phi.min() >= 0 and rep.residual < 1e-12)
    True
    """

    def __init__(self, problem: DiffusionProblem) -> None:
        t0 = time.perf_counter()
        self.problem = problem
        self.system = assemble(problem)
        self._lu = [spla.splu(self.system.block(c)[0].tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1)
                    for c in range(3)]
        self.factor_seconds = time.perf_counter() - t0

    def solve(self, q: ArrayLike | Mapping[str, ArrayLike] | None = None) -> tuple[NDArray, SolveReport]:
        """Fluence for source ``q`` (default: the problem's own)."""
        t0 = time.perf_counter()
        p, s = self.problem, self.system
        prob = p if q is None else p.with_q(q)
        sysq = s if q is None else replace(s, b=assemble_rhs(prob))
        x = np.concatenate([self._lu[c].solve(sysq.b.reshape(3, s.n)[c]) for c in range(3)])
        seconds = time.perf_counter() - t0
        phi = prob.to_phi(s.to_volume(x, p.node_shape))
        rep = SolveReport("scipy-direct", nodes=s.n, residual=sysq.residual(x), seconds=seconds,
                          converged=True, error_estimate=0.0,
                          radiance=prob.exitant_radiance(phi))
        return phi, rep


def solve_direct(problem: DiffusionProblem) -> tuple[NDArray, SolveReport]:
    """Factorise and solve once; the report's time includes the factorisation."""
    solver = DirectSolver(problem)
    phi, rep = solver.solve()
    rep.seconds += solver.factor_seconds
    return phi, rep


def solve_amg(problem: DiffusionProblem, tol: float = 1e-12, maxiter: int = 200) -> tuple[NDArray, SolveReport]:
    """Algebraic multigrid (pyamg smoothed aggregation, GMRES-accelerated) per channel.

    The matrix is non-symmetric (boundary rows), so aggregation runs with
    ``symmetry="nonsymmetric"``. Used as the converged reference where a sparse LU
    factorisation does not fit (about 1e6 nodes). ``tol`` is the relative residual
    ``||b - A x|| / ||b||`` of each channel.
    """
    try:
        import pyamg
    except ImportError as exc:
        raise SolverError("solve_amg needs pyamg: pip install 'glsldiff[validation]'") from exc
    t0 = time.perf_counter()
    s = assemble(problem)
    n = s.n
    xs, cycles = [], 0
    for c in range(3):
        A, b = s.block(c)
        if not b.any():
            xs.append(np.zeros(n))
            continue
        ml = pyamg.smoothed_aggregation_solver(A, symmetry="nonsymmetric", max_coarse=500)
        res: list[float] = []
        xs.append(ml.solve(b, tol=tol, accel="gmres", maxiter=maxiter, residuals=res))
        cycles = max(cycles, len(res) - 1)
    x = np.concatenate(xs)
    phi = problem.to_phi(s.to_volume(x, problem.node_shape))
    res_final = s.residual(x)
    rep = SolveReport("pyamg-sa-gmres", nodes=n, sweeps=cycles, residual=res_final,
                      seconds=time.perf_counter() - t0, converged=bool(np.isfinite(res_final)),
                      error_estimate=float("nan"), radiance=problem.exitant_radiance(phi))
    return phi, rep


def relax(system: LinearSystem, advance: Callable[[int], NDArray], x: NDArray, tol: float,
          max_sweeps: int, check_every: int,
          callback: Callable[[NDArray], None] | None = None,
          floor_max: float = 1e-2) -> tuple[NDArray, str, list[tuple[int, float]], float]:
    """Drive an iterative solver of ``system`` with periodic float64 residual checks.

    ``advance(n)`` runs ``n`` more sweeps and returns the new iterate (channel-major
    unknown vector). The residual of each returned iterate is evaluated here, in
    float64, as ``max_c ||D^-1 (b - A x)|| / ||D^-1 b||`` (so an iterate frozen by
    rounding still shows its true residual), and fed to a :class:`ConvergenceMonitor`
    (``floor_max``: the largest residual taken for a rounding floor).

    Returns
    -------
    x, status, history, step
        Final iterate, monitor status, ``(sweeps, residual)`` pairs (the initial
        guess at 0 sweeps first) and ``||D^-1 (b - A x)||`` of the final iterate.
    """
    if check_every < 1 or max_sweeps < 0:
        raise InputError(f"check_every must be >= 1 and max_sweeps >= 0 (got check_every={check_every}, "
                         f"max_sweeps={max_sweeps})")
    zero_source = not np.any(system.b)
    monitor = ConvergenceMonitor(tol, max_sweeps, floor_max=floor_max)

    def check(sweeps: int, x: NDArray) -> tuple[str | None, float]:
        with np.errstate(over="ignore", invalid="ignore"):
            r = system.jacobi_step(x)
            res = float(np.linalg.norm(r)) if zero_source else system.residual(x, r)
            return monitor.update(sweeps, res), float(np.linalg.norm(r))

    status, step = check(0, x)
    sweeps = 0
    while status is None:
        n_run = min(check_every, max_sweeps - sweeps)
        x = advance(n_run)
        sweeps += n_run
        status, step = check(sweeps, x)
        if callback is not None:
            callback(x)
    return x, status, monitor.history, step


def jacobi(problem: DiffusionProblem, x0: NDArray | None = None, tol: float = 1e-6,
           maxiter: int = 10000, check_every: int = 10,
           residuals: list[float] | None = None,
           callback: Callable[[NDArray], None] | None = None) -> tuple[NDArray, SolveReport]:
    """Jacobi relaxation ``x <- x + D^-1 (b - A x)`` of the same system in numpy (float64).

    Parameters
    ----------
    x0
        Initial fluence volume ``(nz, ny, nx, 3)``; zero by default.
    tol
        Stop when the Jacobi-scaled residual (:meth:`LinearSystem.residual`) is <= tol.
    maxiter
        Sweep budget.
    check_every
        Sweeps between residual checks.
    residuals
        If a list is given, the residual at each check (initial guess first) is
        appended (pyamg convention).
    callback
        Called as ``callback(x)`` with the unknown vector after each check.

    Raises
    ------
    SolverError
        The iteration diverged (spectral radius >= 1).
    """
    t0 = time.perf_counter()
    s = assemble(problem)
    state = {"x": np.zeros_like(s.b) if x0 is None else s.from_volume(problem.from_phi(np.asarray(x0)))}

    def advance(n: int) -> NDArray:
        x = state["x"]
        with np.errstate(over="ignore", invalid="ignore"):
            for _ in range(n):
                x = x + s.jacobi_step(x)
        state["x"] = x
        return x

    x, status, history, step = relax(s, advance, state["x"], tol, maxiter, check_every, callback)
    if residuals is not None:
        residuals.extend(r for _, r in history)
    sweeps = history[-1][0]
    if status == "diverged":
        raise SolverError(diverged_message(problem, "numpy Jacobi", sweeps))
    converged = status == "converged"
    if not converged:
        logger.warning("numpy Jacobi did not converge (%s): residual %.3e after %d sweeps",
                       status, history[-1][1], sweeps)
    phi = problem.to_phi(s.to_volume(x, problem.node_shape))
    rep = SolveReport("numpy-jacobi", nodes=s.n, sweeps=sweeps, residual=history[-1][1],
                      seconds=time.perf_counter() - t0, converged=converged, residuals=history,
                      status=status,
                      error_estimate=contraction_error_estimate(history, step, float(np.linalg.norm(x))),
                      radiance=problem.exitant_radiance(phi))
    return phi, rep
