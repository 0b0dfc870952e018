"""The report every solver returns next to its solution, the stopping rule of the iterative
solvers and their default tolerances.

Every solver, CPU oracle or GLSL, has the pyamg/scipy-style signature
``solve(..., tol, maxiter, x0, callback, residuals) -> (solution, SolveReport)``:

``tol``
    Relaxation solvers (numpy and GLSL Jacobi, the multilevel schedules): the Jacobi-scaled
    residual ``max_c ||D^-1 (b - A x)|| / ||D^-1 b||``, default :data:`RELAX_TOL`. The
    algebraic-multigrid reference: the relative residual ``||b - A x|| / ||b||`` per channel,
    default :data:`REFERENCE_TOL`. A direct solve is exact and takes none.
``maxiter``
    Iteration budget: Jacobi sweeps, V-cycles (multigrid) or AMG cycles; default
    :data:`MAXITER` for relaxations.
``x0``
    Initial fluence (node array), ``None`` for the solver's cold start (zero, or a
    schedule's coarse-to-fine start), or :data:`CURRENT` for the GLSL solvers' current
    iterate on the GPU (restarts, frame coherence).
``callback``
    ``callback(x)`` after each residual check, ``x`` the unknown vector (channel-major,
    float64; see :class:`glsldiff.oracle.assembly.LinearSystem`).
``residuals``
    A list the solver fills with its residual history (initial residual first).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

RELAX_TOL = 1e-6        # relaxation solvers: Jacobi-scaled residual
REFERENCE_TOL = 1e-12   # algebraic multigrid reference: relative residual ||b - A x|| / ||b||
MAXITER = 20000         # relaxation solvers: sweeps (V-cycles for multigrid)
CURRENT = "current"     # x0: continue from the GLSL solver's current iterate


@dataclass
class SolveReport:
    """What a solve did and how far it is from the exact discrete answer.

    Attributes
    ----------
    method
        Solver name (``"glsl-jacobi-fp32"``, ``"numpy-jacobi"``, ``"scipy-direct"``, ...).
    nodes
        Unknowns per channel.
    sweeps
        Iterations run: Jacobi sweeps (finest level), V-cycles for multigrid, AMG cycles;
        0 for a direct solve.
    residual
        Final Jacobi-scaled residual ``max_c ||D^-1 (b - A x)|| / ||D^-1 b||``.
    seconds
        Wall-clock time of the solve (uploads and read-backs included).
    converged
        Whether ``residual <= tol`` was reached within the sweep budget.
    history
        ``(iteration, residual)`` pairs at each check, in order (the initial guess first).
    error_estimate
        Estimated relative L2 error of the unknown to the converged solution, from the
        change of the iterate over the last check interval and the residual's contraction
        over the last intervals (:func:`contraction_error_estimate`); ``nan`` when no
        contraction could be measured; 0 for a direct solve.
    error
        Relative L2 error against a reference solution, when the caller measured one.
    status
        ``"converged"``, ``"budget"`` (sweep budget spent) or ``"stalled"`` (the
        residual stopped falling: the iterate is at the precision floor of its buffers).
    radiance
        Exitant radiance per face (see ``DiffusionProblem.exitant_radiance``).
    levels
        Multiresolution solves (:mod:`glsldiff.solve.multilevel`): per level that ran, a dict with
        ``level`` (0 = finest), ``n``, ``nodes``, ``updated`` (nodes per sweep), ``sweeps``,
        ``residual`` and ``seconds``; empty for single-level solvers.
    work
        Node updates performed (sweeps times updated nodes, summed over levels), if counted.
    """

    method: str
    nodes: int
    sweeps: int = 0
    residual: float = float("nan")
    seconds: float = 0.0
    converged: bool = False
    history: list[tuple[int, float]] = field(default_factory=list)
    error_estimate: float = float("nan")
    error: float | None = None
    status: str = "converged"
    radiance: dict[str, NDArray[np.float64]] = field(default_factory=dict, repr=False)
    levels: list[dict[str, object]] = field(default_factory=list)
    work: int | None = None

    def summary(self) -> str:
        """One line for logs and the CLI."""
        err = "" if self.error is None else f", error {self.error:.2e}"
        est = "" if math.isnan(self.error_estimate) else f", est. error {self.error_estimate:.1e}"
        state = "converged" if self.converged else "NOT converged"
        line = (f"{self.method}: {self.sweeps} {'cycles' if 'multigrid' in self.method else 'sweeps'}, "
                f"residual {self.residual:.2e}{est}{err}, {self.seconds:.3f} s, {state}")
        for lv in self.levels:          # what a level measured: residual and time only where it has them
            res, secs = float(lv["residual"]), float(lv["seconds"])  # type: ignore[arg-type]
            line += (f"\n  level {lv['level']} (n={lv['n']}, {lv['updated']}/{lv['nodes']} nodes updated): "
                     f"{lv['sweeps']} sweeps" + ("" if math.isnan(res) else f", residual {res:.2e}")
                     + ("" if math.isnan(secs) else f", {secs:.3f} s")
                     + (f", texture {lv['texture']}" if "texture" in lv else ""))
        return line


def channel_ratio(num: NDArray, den: NDArray) -> float:
    """``max_c ||num_c|| / ||den_c||`` over channels (rows) with a non-zero denominator.

    With ``num = D^-1 (b - A x)`` and ``den = D^-1 b`` this is the Jacobi-scaled
    residual every iterative solver reports.
    """
    nn, dd = np.linalg.norm(num, axis=1), np.linalg.norm(den, axis=1)
    ok = dd > 0
    if not ok.any():
        return float(np.max(nn))
    return float(np.max(nn[ok] / dd[ok]))


#: Safety factor of the error estimate past its first check interval (:func:`contraction_error_estimate`).
ESTIMATE_SAFETY = 2.5


def contraction_error_estimate(history: list[tuple[int, float]], change_norm: float,
                               x_norm: float) -> float:
    """Relative error estimate (see :class:`SolveReport`) from the residual ``history`` and
    ``change_norm = ||x_n - x_{n-k}||``, the change of the iterate over the last check interval.

    With ``rho`` the residual's contraction over that interval, an iteration that contracts
    the error by ``rho`` per interval leaves ``rho / (1 - rho)`` times the last change, and
    the error before the interval was ``1 / (1 - rho)`` times it: the safe form when the error
    contracts much less than the residual. With one interval only that form is returned
    (it is about 1 after one interval from a zero start): the residual's first contraction
    can hide a slow error (the hierarchical schedule's coarse-to-fine start: residual
    contraction 0.004 over its one interval, where ``rho / (1 - rho)`` times the change was
    1/80 of the true error). From two intervals on it is scaled by ``ESTIMATE_SAFETY`` times
    the larger of the last two contractions (and never raised):
    measured over 90 solves (regular grid: GLSL and numpy Jacobi, the hierarchical,
    multigrid and adaptive schedules; polygrid Jacobi, both stencils; gather Jacobi, AMG
    V-cycles and PCG on P1 and 7-point systems, checks every 1-50 iterations, tol 1e-2 ..
    1e-6) 1.1-3.6x the true error where two or more intervals ran (the bound alone: 1.2-948x),
    never below it."""
    if len(history) < 2 or x_norm == 0.0:
        return float("nan")
    (n0, r0), (n1, r1) = history[-2], history[-1]
    if r0 <= 0.0 or r1 <= 0.0 or n1 <= n0 or r1 >= r0:
        return float("nan")
    bound = change_norm / ((1.0 - r1 / r0) * x_norm)
    if len(history) < 3 or history[-3][1] <= 0.0:
        return bound
    rho = max(r1 / r0, r0 / history[-3][1])
    return bound * min(1.0, ESTIMATE_SAFETY * rho)


class ConvergenceMonitor:
    """Stopping logic shared by the iterative solvers.

    Fed the residual at each check, it answers ``"converged"`` (residual <= tol),
    ``"diverged"`` (non-finite; four rising checks ending 100x above the best; or no
    improvement for ``patience`` checks while the residual keeps rising: the Jacobi
    matrix has spectral radius >= 1), ``"stalled"`` (no 1 % improvement of the best
    residual for ``patience`` checks without a rising trend, at a residual below
    ``floor_max``: the rounding floor of the arithmetic or storage; fp16 buffers floor
    near 2e-3, fp32 near 3e-7), ``"budget"`` (``maxiter`` spent) or ``None`` (go on).
    A residual above ``floor_max`` is never taken for a rounding floor: the iteration
    goes on until it converges, diverges or spends its budget.
    """

    def __init__(self, tol: float, maxiter: int, patience: int = 8,
                 floor_max: float = 1e-2) -> None:
        self.tol, self.maxiter, self.patience = tol, maxiter, patience
        self.floor_max = floor_max
        self.history: list[tuple[int, float]] = []
        self._best = float("inf")
        self._since_best = 0

    def update(self, sweeps: int, res: float) -> str | None:
        self.history.append((sweeps, res))
        if not math.isfinite(res):
            return "diverged"
        if res <= self.tol:
            return "converged"
        last = [r for _, r in self.history[-4:]]
        if len(last) == 4 and all(b > a for a, b in zip(last, last[1:])) and res > 100 * self._best:
            return "diverged"
        if res < 0.99 * self._best:
            self._best, self._since_best = res, 0
        else:
            self._since_best += 1
            if self._since_best >= self.patience:
                window = [r for _, r in self.history[-(self.patience + 1):]]
                rises = sum(b > a for a, b in zip(window, window[1:]))
                if rises >= 0.75 * self.patience and window[-1] > 1.5 * window[0]:
                    return "diverged"
                if res <= self.floor_max:
                    return "stalled"
        return "budget" if sweeps >= self.maxiter else None
