"""The report every solver returns next to its solution."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray


@dataclass
class SolveReport:
    """What a solve did and how far it is from the exact discrete answer.

    Attributes
    ----------
    method
        Solver name (``"glsl-jacobi"``, ``"numpy-jacobi"``, ``"scipy-direct"``).
    sweeps
        Jacobi sweeps run (0 for a direct solve).
    residual
        Final Jacobi-scaled residual ``max_c ||D^-1 (b - A x)|| / ||D^-1 b||``.
    seconds
        Wall-clock time of the solve (uploads and read-backs included).
    converged
        Whether ``residual <= tol`` was reached within the sweep budget.
    residuals
        ``(sweep, residual)`` pairs at each check, in order.
    error_estimate
        Estimated relative L2 error to the converged solution from the observed
        contraction rate rho: ``||x_{n+1} - x_n|| / ((1 - rho) ||x_n||)``; ``nan`` when
        rho could not be estimated.
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
    residuals: list[tuple[int, float]] = field(default_factory=list)
    error_estimate: float = float("nan")
    error: float | None = None
    device: str = "cpu"
    status: str = "converged"
    radiance: dict[str, NDArray[np.float64]] = field(default_factory=dict, repr=False)
    levels: list[dict[str, object]] = field(default_factory=list)
    work: int | None = None

    @property
    def node_updates_per_second(self) -> float:
        return self.nodes * self.sweeps / self.seconds if self.seconds > 0 else float("nan")

    def summary(self) -> str:
        """One line for logs and the CLI."""
        err = "" if self.error is None else f", error {self.error:.2e}"
        est = "" if math.isnan(self.error_estimate) else f", est. error {self.error_estimate:.1e}"
        state = "converged" if self.converged else "NOT converged"
        line = (f"{self.method}: {self.sweeps} {'cycles' if 'multigrid' in self.method else 'sweeps'}, "
                f"residual {self.residual:.2e}{est}{err}, {self.seconds:.3f} s, {state}")
        for lv in self.levels:
            res = float(lv["residual"])  # type: ignore[arg-type]
            line += (f"\n  level {lv['level']} (n={lv['n']}, {lv['updated']}/{lv['nodes']} nodes updated): "
                     f"{lv['sweeps']} sweeps, residual {'-' if math.isnan(res) else f'{res:.2e}'}, "
                     f"{float(lv['seconds']):.3f} s"  # type: ignore[arg-type]
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


def contraction_error_estimate(residuals: list[tuple[int, float]], step_norm: float,
                               x_norm: float) -> float:
    """Relative error estimate from the last two residual checks (see :class:`SolveReport`)."""
    if len(residuals) < 2 or x_norm == 0.0:
        return float("nan")
    (n0, r0), (n1, r1) = residuals[-2], residuals[-1]
    if r0 <= 0.0 or r1 <= 0.0 or n1 <= n0 or r1 >= r0:
        return float("nan")
    rho = (r1 / r0) ** (1.0 / (n1 - n0))
    return step_norm / ((1.0 - rho) * x_norm)


class ConvergenceMonitor:
    """Stopping logic shared by the iterative solvers.

    Fed the residual at each check, it answers ``"converged"`` (residual <= tol),
    ``"diverged"`` (non-finite; four rising checks ending 100x above the best; or no
    improvement for ``patience`` checks while the residual keeps rising: the Jacobi
    matrix has spectral radius >= 1), ``"stalled"`` (no 1 % improvement of the best
    residual for ``patience`` checks without a rising trend, at a residual below
    ``floor_max``: the rounding floor of the arithmetic or storage; fp16 buffers floor
    near 2e-3, fp32 near 3e-7), ``"budget"`` (sweep budget spent) or ``None`` (go on).
    A residual above ``floor_max`` is never taken for a rounding floor: the iteration
    goes on until it converges, diverges or spends its budget.
    """

    def __init__(self, tol: float, max_sweeps: int, patience: int = 8,
                 floor_max: float = 1e-2) -> None:
        self.tol, self.max_sweeps, self.patience = tol, max_sweeps, patience
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
        return "budget" if sweeps >= self.max_sweeps else None
