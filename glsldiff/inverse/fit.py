"""Fit kappa and mu of a block sample to its measurements, channel by channel.

:func:`fit_channel` runs the paper's two stages for one RGB channel: a homogeneous fit
(two unknowns, from user-given initial values) and then the heterogeneous fit from it.
:func:`fit_measurements` does all three channels (one fit when the data are grey) and
returns a :class:`FitResult` with full ``(nz, ny, nx, 3)`` volumes.

Nodes the data cannot see are filled, not left at arbitrary values: mu at boundary nodes
(the boundary row carries no absorption) and both coefficients at the inactive edge and
corner nodes take the value of the nearest node that carries them.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from glsldiff.errors import InputError, SolverError
from glsldiff.graph import INTERIOR
from glsldiff.inverse.measurements import Measurements
from glsldiff.inverse.model import ForwardModel
from glsldiff.inverse.objective import Objective
from glsldiff.inverse.optimize import METHODS, Record, ScaledProblem, Trace, minimize
from glsldiff.io import atomic_path

Array = NDArray[np.float64]

STOP_FRACTION = 1e-4  # paper: stop when f_M < 1e-4 sum L_o^2


@dataclass
class FitOptions:
    """Choices of a fit (defaults picked by measurement, see the README)."""

    method: str = "lbfgs"
    lam: float = 1e-5
    stencil: str = "conservative"
    face_mean: str = "arithmetic"
    kappa0: float = 0.3           # mm, initial value of the homogeneous fit
    mu0: float = 0.01             # mm^-1
    max_evals: int = 200          # heterogeneous stage, per channel
    max_seconds: float = math.inf  # heterogeneous stage, per channel
    homogeneous_evals: int = 40

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"method={self.method!r}; choose one of {METHODS}")
        for name in ("kappa0", "mu0"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"{name}={v!r} must be finite and > 0")
        if not (np.isfinite(self.lam) and self.lam >= 0):
            raise InputError(f"lambda={self.lam!r} must be finite and >= 0")
        if self.max_evals < 1 or self.homogeneous_evals < 1:
            raise InputError("max_evals and homogeneous_evals must be >= 1")


@dataclass
class ChannelFit:
    """Result of one channel: material over the active nodes and the two traces."""

    kappa: Array
    mu: Array
    homogeneous: tuple[float, float]
    homogeneous_trace: Trace
    trace: Trace
    data: float  # final data term (normalised squared error)

    @property
    def converged(self) -> bool:
        return self.trace.converged


@dataclass
class FitResult:
    """Fitted volumes ``(nz, ny, nx, 3)`` and one :class:`ChannelFit` per channel."""

    kappa: Array
    mu: Array
    channels: list[ChannelFit]
    h: float
    seconds: float
    options: FitOptions
    shared: bool = False  # one fit served all three (grey) channels
    notes: list[str] = field(default_factory=list)


def fit_homogeneous(objective: Objective, kappa0: float, mu0: float, max_evals: int) -> tuple[float, float, Trace]:
    """Best homogeneous (kappa, mu): two unknowns, fitted in log space with NLopt L-BFGS
    (the paper uses its CG here; with two unknowns the choice hardly matters)."""
    import nlopt

    ones = np.ones(objective.model.n)
    trace = Trace("homogeneous-lbfgs")
    best: list = [math.inf, (math.log(kappa0), math.log(mu0))]
    t0 = time.perf_counter()

    def f(z: Array, grad: Array) -> float:
        k, m = math.exp(z[0]), math.exp(z[1])
        ev = objective.evaluate(k * ones, m * ones, gradient=grad.size > 0)
        if grad.size > 0:
            grad[0] = k * float(ev.grad_kappa.sum())
            grad[1] = m * float(ev.grad_mu.sum())
        trace.records.append(Record(len(trace.records) + 1, time.perf_counter() - t0, ev.value, ev.data,
                                    float(np.linalg.norm(grad)) if grad.size else float("nan")))
        if ev.value < best[0]:
            best[:] = [ev.value, (float(z[0]), float(z[1]))]
        return ev.value

    opt = nlopt.opt(nlopt.LD_LBFGS, 2)
    opt.set_min_objective(f)
    opt.set_lower_bounds([math.log(1e-4), math.log(1e-7)])
    opt.set_upper_bounds([math.log(1e3), math.log(1e2)])
    opt.set_xtol_rel(1e-4)
    opt.set_maxeval(max_evals)
    try:
        opt.optimize([math.log(kappa0), math.log(mu0)])
        code = opt.last_optimize_result()
        trace.status = "budget spent" if code == nlopt.MAXEVAL_REACHED else "converged"
    except nlopt.RoundoffLimited:
        trace.status = "converged (roundoff limited)"
    trace.converged = trace.status.startswith("converged")
    trace.iterations = len(trace.records)
    trace.seconds = time.perf_counter() - t0
    return math.exp(best[1][0]), math.exp(best[1][1]), trace


def fit_channel(model: ForwardModel, Q: Array, Y: Array, W: Array, options: FitOptions,
                callback: Callable[[Record], None] | None = None) -> ChannelFit:
    """Homogeneous, then heterogeneous fit of one channel (sources/measurements/weights
    ``(n_boundary, M)``)."""
    objective = Objective(model, Q, Y, W, lam=options.lam)
    k_h, m_h, h_trace = fit_homogeneous(objective, options.kappa0, options.mu0, options.homogeneous_evals)
    mu_scale = max(m_h, 1e-3 / (3.0 * k_h))  # keep the mu variable O(1) even for mu_h -> 0
    problem = ScaledProblem(objective, k_h, mu_scale, options.method, options.max_evals,
                            options.max_seconds, callback)
    n = model.n
    z0 = np.concatenate([np.ones(n), np.full(n, m_h / mu_scale)])
    z = minimize(problem, z0, stopval=STOP_FRACTION)
    kappa, mu = problem.material(z)
    return ChannelFit(kappa, mu, (k_h, m_h), h_trace, problem.trace, problem.trace.best.data)


def fill_unseen(volume: Array, known: NDArray[np.bool_]) -> Array:
    """Copy into every node outside ``known`` the value of its nearest known node."""
    if known.all():
        return volume
    idx = ndimage.distance_transform_edt(~known, return_distances=False, return_indices=True)
    return volume[tuple(idx)]


def fit_measurements(meas: Measurements, options: FitOptions | None = None,
                     callback: Callable[[int, Record], None] | None = None) -> FitResult:
    """Fit every channel of ``meas``; ``callback(channel, record)`` after each evaluation."""
    options = options or FitOptions()
    t0 = time.perf_counter()
    model = ForwardModel(meas.grid, options.stencil, options.face_mean, meas.eta, meas.C)
    shared = meas.grey()
    fits: list[ChannelFit] = []
    for c in range(1 if shared else 3):
        cb = (lambda rec, c=c: callback(c, rec)) if callback else None
        fits.append(fit_channel(model, *meas.channel(c), options, cb))
    if shared:
        fits = fits * 3
    g = meas.grid
    kappa = np.stack([model.volume(f.kappa, 0.0) for f in fits], axis=-1)
    mu = np.stack([model.volume(f.mu, 0.0) for f in fits], axis=-1)
    kind = g.kind
    kappa = np.stack([fill_unseen(kappa[..., c], g.active) for c in range(3)], axis=-1)
    mu = np.stack([fill_unseen(mu[..., c], kind == INTERIOR) for c in range(3)], axis=-1)
    if not np.all(np.isfinite(kappa)) or not np.all(np.isfinite(mu)):
        raise SolverError("the fit produced non-finite coefficients")
    notes = [] if not shared else ["grey data: one fit served all three channels"]
    return FitResult(kappa, mu, fits, g.h, time.perf_counter() - t0, options, shared, notes)


def save_material(path: str | os.PathLike, result: FitResult) -> Path:
    """Write the fitted material (kappa mm, mu mm^-1, ``(nz, ny, nx, 3)``) and fit summary
    to ``.npz`` atomically."""
    o = result.options
    arrays = dict(kappa=result.kappa, mu=result.mu, h=result.h, method=o.method, lam=o.lam,
                  stencil=o.stencil, face_mean=o.face_mean, seconds=result.seconds,
                  data_error=np.array([f.data for f in result.channels]),
                  converged=np.array([f.converged for f in result.channels]),
                  homogeneous=np.array([f.homogeneous for f in result.channels]))
    with atomic_path(path, ".npz") as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    return Path(path)
