"""CPU oracle solvers of the discrete system of :mod:`glsldiff.oracle.assembly`.

:func:`~glsldiff.oracle.assembly.assemble` builds, for all three channels at once, the
block-diagonal system ``A x = b`` whose rows are exactly the relaxation formulas the GLSL
shaders apply (see :mod:`glsldiff.system.problem`): Jacobi is ``x <- x + D^-1 (b - A x)`` with
``D = diag(A)``. :class:`DirectSolver` factorises it (SuperLU), :func:`solve_amg` runs
algebraic multigrid (pyamg) and :func:`jacobi` the Jacobi iteration in numpy. All return
``(phi, report)`` with the fluence ``phi`` as a node array (0 at inactive nodes), and take the
uniform arguments of :mod:`glsldiff.system.report` (``tol``, ``maxiter``, ``x0``, ``callback``,
``residuals``). :func:`relax` is the solve loop of every relaxation, CPU or GLSL.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Callable, Mapping

import numpy as np
import pyamg
import scipy.sparse.linalg as spla
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.interrupt import interruptible
from glsldiff.core.rng import pinned_global_rng
from glsldiff.core.errors import InputError, SolverError
from glsldiff.oracle.assembly import LinearSystem, assemble, assemble_rhs, diverged_message
from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.report import (MAXITER, REFERENCE_TOL, RELAX_TOL, ConvergenceMonitor, SolveReport,
                                    contraction_error_estimate)

logger = logging.getLogger(__name__)

Callback = Callable[[NDArray], None]


def _fill(residuals: list[float] | None, values: list[float]) -> None:
    """pyamg convention: the caller's list gets the history, initial residual first."""
    if residuals is not None:
        residuals[:] = values


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
        self._lu = [interruptible(spla.splu, self.system.block(c)[0].tocsc(), permc_spec="MMD_AT_PLUS_A",
                                  diag_pivot_thresh=0.1) for c in range(3)]
        self.factor_seconds = time.perf_counter() - t0

    def solve(self, q: ArrayLike | Mapping[str, ArrayLike] | None = None, *,
              callback: Callback | None = None,
              residuals: list[float] | None = None) -> tuple[NDArray, SolveReport]:
        """Fluence for source ``q`` (default: the problem's own). A direct solve is exact, so
        of the uniform arguments only ``callback`` (called once, with the solution) and
        ``residuals`` (filled with the final residual) apply."""
        t0 = time.perf_counter()
        p, s = self.problem, self.system
        prob = p if q is None else p.with_q(q)
        sysq = s if q is None else replace(s, b=assemble_rhs(prob))
        x = np.concatenate([self._lu[c].solve(sysq.b.reshape(3, s.n)[c]) for c in range(3)])
        seconds = time.perf_counter() - t0
        phi = prob.to_phi(s.to_volume(x, p.node_shape))
        res = sysq.residual(x)
        _fill(residuals, [res])
        if callback is not None:
            callback(x)
        rep = SolveReport("scipy-direct", nodes=s.n, residual=res, seconds=seconds, converged=True,
                          history=[(0, res)], error_estimate=0.0, radiance=prob.exitant_radiance(phi))
        return phi, rep


def solve_direct(problem: DiffusionProblem, *, callback: Callback | None = None,
                 residuals: list[float] | None = None) -> tuple[NDArray, SolveReport]:
    """Factorise and solve once (:meth:`DirectSolver.solve`); the report's time includes the
    factorisation."""
    solver = DirectSolver(problem)
    phi, rep = solver.solve(callback=callback, residuals=residuals)
    rep.seconds += solver.factor_seconds
    return phi, rep


def solve_amg(problem: DiffusionProblem, tol: float = REFERENCE_TOL, maxiter: int = 200,
              x0: ArrayLike | None = None, callback: Callback | None = None,
              residuals: list[float] | None = None) -> tuple[NDArray, SolveReport]:
    """Algebraic multigrid (pyamg smoothed aggregation, GMRES-accelerated) per channel.

    The matrix is non-symmetric (boundary rows), so aggregation runs with
    ``symmetry="nonsymmetric"``. Used as the converged reference where a sparse LU
    factorisation does not fit (about 1e6 nodes). ``tol`` is the relative residual
    ``||b - A x|| / ||b||`` of each channel, ``maxiter`` the cycles per channel, ``x0`` an
    initial fluence. The channels are solved one after the other, so ``callback`` is called
    once, with the solution, and ``residuals`` gets per cycle the largest relative residual
    over the channels (a finished channel keeps its last one).
    """
    t0 = time.perf_counter()
    s = assemble(problem)
    n = s.n
    start = None if x0 is None else s.from_volume(problem.from_phi(np.asarray(x0, dtype=np.float64)))
    xs, hist = [], []
    for c in range(3):
        A, b = s.block(c)
        if not b.any():
            xs.append(np.zeros(n))
            continue
        with pinned_global_rng():
            ml = pyamg.smoothed_aggregation_solver(A, symmetry="nonsymmetric", max_coarse=500)
        res: list[float] = []
        guess = None if start is None else start[c * n:(c + 1) * n]
        xs.append(ml.solve(b, x0=guess, tol=tol, accel="gmres", maxiter=maxiter, residuals=res))
        hist.append(np.asarray(res) / np.linalg.norm(b))
    x = np.concatenate(xs)
    cycles = max((len(h) - 1 for h in hist), default=0)
    merged = [float(max(h[min(i, len(h) - 1)] for h in hist)) for i in range(cycles + 1)] if hist else [0.0]
    _fill(residuals, merged)
    if callback is not None:
        callback(x)
    phi = problem.to_phi(s.to_volume(x, problem.node_shape))
    res_final = s.residual(x)
    rep = SolveReport("pyamg-sa-gmres", nodes=n, sweeps=cycles, residual=res_final,
                      seconds=time.perf_counter() - t0, converged=bool(np.isfinite(res_final)),
                      history=list(enumerate(merged)), error_estimate=float("nan"),
                      radiance=problem.exitant_radiance(phi))
    return phi, rep


#: :func:`solve_reference`: SuperLU below this many active nodes (it took 17 minutes and 3.8 GB
#: on the 6^3-per-cube bunny), pyamg above ...
REFERENCE_MAX_DIRECT = 20_000
#: ... to this relative residual (SA + GMRES: the preconditioned residual).
REFERENCE_AMG_RTOL = 1e-11


def solve_reference(problem: DiffusionProblem, max_direct_nodes: int = REFERENCE_MAX_DIRECT
                    ) -> tuple[NDArray, SolveReport]:
    """The converged discrete answer a study measures against: SuperLU below
    ``max_direct_nodes`` active nodes, else pyamg to :data:`REFERENCE_AMG_RTOL` (both far below
    any discretisation or iteration error a study looks at)."""
    if problem.grid.n_active < max_direct_nodes:
        return solve_direct(problem)
    return solve_amg(problem, tol=REFERENCE_AMG_RTOL)


@dataclass
class Relaxation:
    """What :func:`relax` ended with: the final iterate, the monitor's status, the
    ``(iteration, residual)`` history (initial guess first) and the error estimate."""

    x: NDArray[np.float64]
    status: str
    history: list[tuple[int, float]]
    error_estimate: float

    @property
    def iterations(self) -> int:
        return self.history[-1][0]

    @property
    def residual(self) -> float:
        return self.history[-1][1]

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    def report(self, method: str, problem: DiffusionProblem, system: LinearSystem,
               seconds: float) -> tuple[NDArray, SolveReport]:
        """The fluence and the :class:`SolveReport` of this relaxation of ``problem``."""
        phi = problem.to_phi(system.to_volume(self.x, problem.node_shape))
        return phi, SolveReport(method, nodes=system.n, sweeps=self.iterations, residual=self.residual,
                                seconds=seconds, converged=self.converged, history=self.history,
                                status=self.status, error_estimate=self.error_estimate,
                                radiance=problem.exitant_radiance(phi))


def relax(system: LinearSystem, advance: Callable[[int], NDArray], x: NDArray, *, tol: float,
          maxiter: int, check_every: int, callback: Callback | None = None,
          residuals: list[float] | None = None, floor_max: float = 1e-2, patience: int = 8,
          name: str = "Jacobi", problem: DiffusionProblem | None = None) -> Relaxation:
    """The solve loop of every relaxation (numpy Jacobi, GLSL Jacobi, the multilevel schedules):
    drive an iterative solver of ``system`` with periodic float64 residual checks.

    ``advance(n)`` runs ``n`` more iterations (sweeps, V-cycles) and returns the new iterate
    (channel-major unknown vector). The residual of each returned iterate is evaluated here, in
    float64, as ``max_c ||D^-1 (b - A x)|| / ||D^-1 b||`` (so an iterate frozen by rounding
    still shows its true residual; with a zero right-hand side, ``||D^-1 (b - A x)||``) and fed
    to a :class:`ConvergenceMonitor` (``floor_max``: the largest residual taken for a rounding
    floor; ``patience``: checks without progress before it decides). ``callback(x)`` runs
    after each check, ``residuals`` gets the history.

    Raises
    ------
    InputError
        ``check_every < 1`` or ``maxiter < 0``.
    SolverError
        The iteration diverged (message from :func:`diverged_message` when ``problem`` is given).
    """
    if check_every < 1 or maxiter < 0:
        raise InputError(f"check_every must be >= 1 and maxiter >= 0 (got check_every={check_every}, "
                         f"maxiter={maxiter})")
    zero_source = not np.any(system.b)
    if zero_source:
        logger.warning("%s: the source is zero in every channel, so the solution is 0 (no light enters); "
                       "the residual is measured absolutely", name)
    monitor = ConvergenceMonitor(tol, maxiter, patience=patience, floor_max=floor_max)

    def check(iterations: int, x: NDArray) -> str | None:
        with np.errstate(over="ignore", invalid="ignore"):
            r = system.jacobi_step(x)
            res = float(np.linalg.norm(r)) if zero_source else system.residual(x, r)
            return monitor.update(iterations, res)

    status = check(0, x)
    done, change = 0, float("nan")
    while status is None:
        n_run = min(check_every, maxiter - done)
        x_new = advance(n_run)
        with np.errstate(over="ignore", invalid="ignore"):
            change = float(np.linalg.norm(x_new - x))
        x = x_new
        done += n_run
        status = check(done, x)
        if callback is not None:
            callback(x)
    history = monitor.history
    _fill(residuals, [r for _, r in history])
    if status == "diverged":
        raise SolverError(diverged_message(problem, name, done) if problem is not None
                          else f"{name} diverged after {done} sweeps")
    if status != "converged":   # the report carries it; each caller decides (render: an error)
        logger.info("%s did not converge (%s): residual %.3e after %d iterations",
                       name, status, history[-1][1], done)
    return Relaxation(x, status, history, contraction_error_estimate(history, change, float(np.linalg.norm(x))))


def jacobi(problem: DiffusionProblem, tol: float = RELAX_TOL, maxiter: int = MAXITER,
           x0: ArrayLike | None = None, callback: Callback | None = None,
           residuals: list[float] | None = None, *, check_every: int = 10) -> tuple[NDArray, SolveReport]:
    """Jacobi relaxation ``x <- x + D^-1 (b - A x)`` of the same system in numpy (float64).

    Parameters
    ----------
    tol
        Stop when the Jacobi-scaled residual (:meth:`LinearSystem.residual`) is <= tol.
    maxiter
        Sweep budget.
    x0
        Initial fluence (node array); zero by default.
    callback
        Called as ``callback(x)`` with the unknown vector after each check.
    residuals
        If a list is given, it gets the residual at each check (initial guess first; pyamg
        convention).
    check_every
        Sweeps between residual checks.

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

    result = relax(s, advance, state["x"], tol=tol, maxiter=maxiter, check_every=check_every,
                   callback=callback, residuals=residuals, name="numpy Jacobi", problem=problem)
    return result.report("numpy-jacobi", problem, s, time.perf_counter() - t0)
