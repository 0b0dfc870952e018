"""Minimisers of f_M: NLopt (quasi-Newton, truncated Newton), SciPy's L-BFGS-B (for fits
beyond NLopt's variable limit) and the paper's Table I CG.

Every method works on scaled variables, ``z = (kappa / kappa_s, mu / mu_s)`` ("linear") or
``z = log(kappa / kappa_s), log(mu / mu_s)`` ("log", the default: chosen by measurement, the
linear form stalls NLopt's L-BFGS where mu sits on its bound 0), with the scales from the
homogeneous fit and bound constraints that keep kappa > 0 and mu >= 0. Each
evaluation is recorded in a :class:`Trace` (time, f, data term, gradient norm), so that
error against time and iterations can be plotted for every method alike.
"""
from __future__ import annotations

import math
import signal
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.checks import choice
from glsldiff.core.errors import InputError, SolverError
from glsldiff.inverse.objective import Objective

Array = NDArray[np.float64]

NLOPT_METHODS = {"lbfgs": "LD_LBFGS", "tnewton": "LD_TNEWTON_PRECOND_RESTART", "var2": "LD_VAR2"}
METHODS = (*NLOPT_METHODS, "lbfgsb", "cg")
#: NLopt's Luksan methods (lbfgs, tnewton, var2) stop with a bare ``runtime_error`` after the
#: first evaluation above about this many variables, at any vector storage (NLopt's LD_LBFGS,
#: LD_VAR2 and LD_TNEWTON_PRECOND_RESTART on a quadratic: 2,148,949 variables run, 2,149,739
#: fail): about 1.07 M nodes, less than the paper's 256 x 256 x 20 sample (1.31 M).
NLOPT_MAX_VARIABLES = 2_148_000
KAPPA_RANGE = (1e-2, 1e2)   # kappa stays within these factors of its homogeneous value
MU_RANGE = (1e-6, 1e3)      # mu within these factors of its scale ("linear": lower bound 0)
PARAMETERIZATIONS = ("log", "linear")


@dataclass
class Record:
    """One evaluation of f during a minimisation."""

    evaluation: int
    seconds: float
    value: float
    data: float
    grad_norm: float  # nan for line-search evaluations without a gradient


@dataclass
class Trace:
    """What a minimisation did: evaluations, gradients, time, how it stopped."""

    method: str
    records: list[Record] = field(default_factory=list)
    iterations: int = 0
    status: str = "running"
    converged: bool = False
    seconds: float = 0.0

    @property
    def best(self) -> Record:
        return min(self.records, key=lambda r: r.value)


class Budget(Exception):
    """Raised inside an objective callback when the evaluation/time budget is spent."""


@dataclass
class ScaledProblem:
    """f(z) over the scaled variables, with bounds, budgets and a trace."""

    objective: Objective
    kappa_scale: float
    mu_scale: float
    method: str = "lbfgs"
    max_evals: int = 200
    max_seconds: float = math.inf
    callback: Callable[[Record], None] | None = None
    snapshot_every: int = 0  # keep (record, z) every this many gradient evaluations (0: none)
    parameterization: str = "log"
    mu_gain: float = 1.0  # mu's variables are its (log) value divided by this: > 1 lets mu move faster

    def __post_init__(self) -> None:
        self.snapshots: list[tuple[Record, Array]] = []
        self.gradients = 0
        n = self.objective.model.n
        self.n = n
        choice(self.parameterization, "parameterization", PARAMETERIZATIONS)
        lo = np.concatenate([np.full(n, KAPPA_RANGE[0]), np.full(n, MU_RANGE[0])])
        hi = np.concatenate([np.full(n, KAPPA_RANGE[1]), np.full(n, MU_RANGE[1])])
        if self.parameterization == "log":
            self.lower, self.upper = np.log(lo), np.log(hi)
        else:
            lo[n:] = 0.0
            self.lower, self.upper = lo, hi
        self.lower[n:] /= self.mu_gain
        self.upper[n:] /= self.mu_gain
        self.trace = Trace(self.method)
        self._t0 = time.perf_counter()
        self.best_z: Array | None = None
        self.stop: Callable[[], None] | None = None  # set by optimisers that stop gracefully
        self.interrupt_pending = False  # a Ctrl-C held back until the objective's Python runs
        self._evaluating = False

    def resume(self, trace: Trace, best_z: Array) -> None:
        """Continue a run saved earlier (:mod:`glsldiff.inverse.checkpoint`): its records count
        against the budgets and its best point is kept until a better one is found."""
        self.trace.records = list(trace.records)
        self.gradients = sum(not math.isnan(r.grad_norm) for r in trace.records)
        self._t0 -= trace.records[-1].seconds if trace.records else 0.0
        self.best_z = np.array(best_z, dtype=np.float64)

    def material(self, z: Array) -> tuple[Array, Array]:
        """``(kappa, mu)`` over the active nodes for variables ``z``."""
        z = np.concatenate([z[: self.n], self.mu_gain * np.asarray(z[self.n:])])
        v = np.exp(z) if self.parameterization == "log" else z
        return v[: self.n] * self.kappa_scale, v[self.n:] * self.mu_scale

    def variables(self, kappa: Array, mu: Array) -> Array:
        """Inverse of :meth:`material`, clipped to the bounds."""
        v = np.concatenate([kappa / self.kappa_scale, mu / self.mu_scale])
        if self.parameterization == "log":
            v = np.log(np.maximum(v, 1e-300))
        v[self.n:] /= self.mu_gain
        return np.clip(v, self.lower, self.upper)

    def __call__(self, z: Array, grad: Array | None) -> float:
        """Objective in NLopt's convention (fills ``grad`` in place when it is non-empty).

        Ctrl-C inside an NLopt run stops it gracefully (NLopt would turn the exception into
        a bare runtime error): the trace says "interrupted" and the best point is kept."""
        try:
            if self.interrupt_pending:  # arrived while NLopt's own code ran (see _held_interrupts)
                raise KeyboardInterrupt
            self._evaluating = True
            try:
                return self._evaluate(z, grad)
            finally:
                self._evaluating = False
        except KeyboardInterrupt:
            self.interrupt_pending = True
            if self.stop is None or not self.trace.records:
                raise
            self.trace.status = "interrupted"
            self.stop()
            if grad is not None and grad.size > 0:
                grad[:] = 0.0
            return self.trace.best.value

    def _evaluate(self, z: Array, grad: Array | None) -> float:
        tr = self.trace
        # the starting point is always evaluated, so a spent budget still has a best point to keep
        if tr.records and (len(tr.records) >= self.max_evals or time.perf_counter() - self._t0 > self.max_seconds):
            tr.status = "budget spent"
            if self.stop is None:
                raise Budget
            self.stop()  # NLopt: force_stop, then return any finite value
            if grad is not None and grad.size > 0:
                grad[:] = 0.0
            return tr.best.value
        want = grad is not None and grad.size > 0
        ev = self.objective.evaluate(*self.material(np.asarray(z)), gradient=want)
        gnorm = float("nan")
        if want:
            kappa, mu = self.objective.last_material
            if self.parameterization == "log":  # d/dlog v = v d/dv
                grad[: self.n], grad[self.n:] = ev.grad_kappa * kappa, ev.grad_mu * mu * self.mu_gain
            else:
                grad[: self.n], grad[self.n:] = ev.grad_kappa * self.kappa_scale, ev.grad_mu * self.mu_scale * self.mu_gain
            gnorm = float(np.linalg.norm(grad))
        rec = Record(len(tr.records) + 1, time.perf_counter() - self._t0, ev.value, ev.data, gnorm)
        self.gradients += int(want)
        if want and self.snapshot_every and (self.gradients - 1) % self.snapshot_every == 0:
            self.snapshots.append((rec, np.array(z, dtype=np.float64)))
        if self.best_z is None or not tr.records or ev.value < tr.best.value:
            self.best_z = np.array(z, dtype=np.float64)
        tr.records.append(rec)
        if self.callback is not None:
            self.callback(rec)
        return ev.value

    def gradient(self, z: Array) -> tuple[float, Array]:
        g = np.empty_like(z)
        return self(z, g), g


def method_for(method: str, n: int) -> str:
    """The minimiser that runs ``method`` over ``n`` variables: NLopt's L-BFGS gives way to
    SciPy's L-BFGS-B (the same limited-memory quasi-Newton method, without NLopt's limit)
    above :data:`NLOPT_MAX_VARIABLES`; the other NLopt methods are an :class:`InputError`
    naming the fix there."""
    if method not in NLOPT_METHODS or n <= NLOPT_MAX_VARIABLES:
        return method
    if method == "lbfgs":
        return "lbfgsb"
    raise InputError(f"--method {method}: NLopt's {method} fails above {NLOPT_MAX_VARIABLES:,} variables and "
                     f"this fit has {n:,} (kappa and mu at {n // 2:,} nodes); use --method lbfgsb (SciPy's "
                     "L-BFGS-B, no such limit) or a coarser grid")


def minimize(problem: ScaledProblem, z0: Array, stopval: float, ftol_rel: float = 1e-7) -> Array:
    """Minimise from ``z0`` until ``f < stopval``, the relative change of f falls below
    ``ftol_rel``, or the budget is spent. Returns the best ``z``; ``problem.trace`` says why
    it stopped."""
    choice(problem.method, "method", METHODS)
    z0 = np.clip(np.asarray(z0, dtype=np.float64), problem.lower, problem.upper)
    tr = problem.trace
    try:
        if problem.method == "cg":
            table1_cg(problem, z0, stopval, ftol_rel)
        elif problem.method == "lbfgsb":
            _lbfgsb(problem, z0, stopval, ftol_rel)
        else:
            _nlopt(problem, z0, stopval, ftol_rel)
    except Budget:
        tr.status = "budget spent"
    except KeyboardInterrupt:  # Ctrl-C: keep the best point so far (the caller saves it)
        if problem.best_z is None:
            raise
        tr.status = "interrupted"
    tr.seconds = time.perf_counter() - problem._t0
    tr.converged = tr.status.startswith("converged")
    if problem.best_z is None:
        raise SolverError(f"{problem.method}: no evaluation of the objective was possible")
    return problem.best_z


def _nlopt(problem: ScaledProblem, z0: Array, stopval: float, ftol_rel: float) -> None:
    import nlopt  # only the nlopt methods need it (~50 ms import)

    if z0.size > NLOPT_MAX_VARIABLES:   # a problem built directly, not through method_for
        raise InputError(f"--method {problem.method}: NLopt fails above {NLOPT_MAX_VARIABLES:,} variables and this "
                         f"fit has {z0.size:,}; use --method lbfgsb")
    opt = nlopt.opt(getattr(nlopt, NLOPT_METHODS[problem.method]), z0.size)
    opt.set_min_objective(problem)
    opt.set_lower_bounds(problem.lower)
    opt.set_upper_bounds(problem.upper)
    opt.set_stopval(stopval)
    opt.set_ftol_rel(ftol_rel)
    problem.stop = opt.force_stop
    if problem.method == "lbfgs":
        opt.set_vector_storage(10)
    try:
        with _held_interrupts(problem):
            opt.optimize(z0)
        code = opt.last_optimize_result()
    except nlopt.RoundoffLimited:
        code = "roundoff"
    except nlopt.ForcedStop:
        code = nlopt.FORCED_STOP
    except Exception:
        if problem.interrupt_pending:  # whatever NLopt made of the Ctrl-C
            raise KeyboardInterrupt from None
        raise
    if problem.interrupt_pending and problem.trace.status != "interrupted":
        raise KeyboardInterrupt  # came after the last evaluation: minimize keeps the best point
    problem.trace.iterations = problem.gradients
    if code == nlopt.FORCED_STOP:
        return  # budget or Ctrl-C: status already set
    problem.trace.status = {"roundoff": "converged (roundoff limited)",nlopt.STOPVAL_REACHED: "converged (f < eps)",
                            nlopt.FTOL_REACHED: "converged (f stopped changing)",
                            nlopt.XTOL_REACHED: "converged (x stopped changing)",
                            nlopt.SUCCESS: "converged",
                            nlopt.MAXEVAL_REACHED: "budget spent"}.get(code, f"nlopt code {code}")


class _Reached(Exception):
    """Raised inside SciPy's L-BFGS-B when f fell below the stop value (it has no such rule)."""


def _lbfgsb(problem: ScaledProblem, z0: Array, stopval: float, ftol_rel: float) -> None:
    """SciPy's L-BFGS-B with NLopt's stop rules: ``f < stopval`` after any evaluation, and a
    relative change of f below ``ftol_rel`` between iterations (SciPy's own ``ftol`` is
    relative to ``max(|f|, 1)``, an absolute rule for f_M << 1, so it is switched off).
    10 stored corrections, as for NLopt's L-BFGS."""
    from scipy.optimize import Bounds, minimize as scipy_minimize

    def fun(z: Array) -> tuple[float, Array]:
        f, g = problem.gradient(z)
        if f < stopval:
            raise _Reached
        return f, g

    last = [math.inf]

    def iteration(intermediate_result: object) -> None:
        problem.trace.iterations += 1
        f = float(intermediate_result.fun)  # type: ignore[attr-defined]
        if abs(last[0] - f) <= ftol_rel * abs(f):
            problem.trace.status = "converged (f stopped changing)"
            raise StopIteration
        last[0] = f

    try:
        res = scipy_minimize(fun, z0, jac=True, method="L-BFGS-B", callback=iteration,
                             bounds=Bounds(problem.lower, problem.upper),
                             options=dict(maxcor=10, ftol=0.0, gtol=0.0, maxiter=2**31 - 1, maxfun=2**31 - 1))
    except _Reached:
        problem.trace.status = "converged (f < eps)"
        return
    if problem.trace.status != "running":   # stopped by the rules above, a budget or Ctrl-C
        return
    if res.success:
        problem.trace.status = "converged"
    elif "ABNORMAL" in str(res.message):    # the line search found no decrease: NLopt's "roundoff limited"
        problem.trace.status = "converged (roundoff limited)"
    else:
        problem.trace.status = f"L-BFGS-B: {res.message}"


@contextmanager
def _held_interrupts(problem: ScaledProblem):
    """While NLopt runs, raise Ctrl-C's KeyboardInterrupt only inside the objective's own
    handler. Raised anywhere else (in NLopt's C code the signal waits for the next Python
    bytecode, which is the callback's entry, outside its ``try``) NLopt turns it into a bare
    ``runtime_error``. Elsewhere the interrupt is only noted and raised at the next
    evaluation's start or after NLopt returns. Only on the main thread, and only over
    Python's default handler."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return

    def hold(signum: int, frame: object) -> None:
        problem.interrupt_pending = True
        if problem._evaluating:
            raise KeyboardInterrupt

    old = signal.signal(signal.SIGINT, hold)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def _line_search(problem: ScaledProblem, z: Array, f0: float, d: Array, max_evals: int = 10) -> tuple[float, float]:
    """Golden-section search of ``t -> f(z + t d)`` on ``[0, t_max]`` (bounds respected);
    returns ``(t, f)``, ``t = 0`` if no step decreases f."""
    with np.errstate(divide="ignore", invalid="ignore"):
        room = np.where(d > 0, (problem.upper - z) / d, np.where(d < 0, (problem.lower - z) / d, np.inf))
    t_max = float(np.min(room))
    t = min(t_max, 0.3 / max(float(np.max(np.abs(d))), 1e-300))  # first trial: <= 30 % change of a variable
    f = lambda s: problem(z + s * d, None)  # noqa: E731
    a, fa, b, fb = 0.0, f0, t, f(t)
    n = 1
    while fb < fa and b < t_max and n < max_evals // 2:  # expand the bracket while f falls
        a, fa = b, fb
        b = min(t_max, b / GOLDEN**2)
        fb = f(b)
        n += 1
    lo, hi = (0.0, b) if a == 0.0 else (a * GOLDEN**2, b)
    x1, x2 = hi - GOLDEN * (hi - lo), lo + GOLDEN * (hi - lo)
    f1, f2 = f(x1), f(x2)
    best = min((f0, 0.0), (fa, a), (fb, b), (f1, x1), (f2, x2))
    while n < max_evals:
        if f1 < f2:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - GOLDEN * (hi - lo)
            f1 = f(x1)
            best = min(best, (f1, x1))
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + GOLDEN * (hi - lo)
            f2 = f(x2)
            best = min(best, (f2, x2))
        n += 1
    return best[1], best[0]


def table1_cg(problem: ScaledProblem, z: Array, stopval: float, ftol_rel: float) -> None:
    """The paper's Table I: Polak-Ribiere conjugate gradient with a golden-section line search
    along ``d`` (kappa and mu move together), stopping at ``f < stopval``."""
    tr = problem.trace
    f, g = problem.gradient(z)
    p = -g
    d = p.copy()
    while True:
        if f < stopval:
            tr.status = "converged (f < eps)"
            return
        free = ~(((z <= problem.lower) & (d < 0)) | ((z >= problem.upper) & (d > 0)))
        d = np.where(free, d, 0.0)
        if float(d @ p) <= 0:  # not a descent direction any more: restart along -g
            d = np.where(free, p, 0.0)
        t, f_new = _line_search(problem, z, f, d)
        tr.iterations += 1
        if t == 0.0:
            tr.status = "converged (no descent along the search direction)"
            return
        z = np.clip(z + t * d, problem.lower, problem.upper)
        if abs(f - f_new) <= ftol_rel * abs(f):
            tr.status = "converged (f stopped changing)"
            return
        f, g = problem.gradient(z)
        p_new = -g
        beta = max(float(p_new @ (p_new - p)) / max(float(p @ p), 1e-300), 0.0)
        d = p_new + beta * d
        p = p_new
