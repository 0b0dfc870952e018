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
from scipy.optimize import least_squares

from glsldiff.core.checks import choice, integer, real
from glsldiff.core.errors import SolverError
from glsldiff.core.io import write_npz
from glsldiff.grids.graph import INTERIOR
from glsldiff.inverse.checkpoint import ChannelProgress, Checkpoint
from glsldiff.inverse.glsl import GlslForwardModel
from glsldiff.inverse.measurements import Measurements
from glsldiff.inverse.model import SOLVERS, ForwardModel
from glsldiff.inverse.objective import Objective
from glsldiff.inverse.optimize import METHODS, Record, ScaledProblem, Trace, method_for, minimize
from glsldiff.inverse.ranges import PROFILE_TOLERANCE, CoefficientRanges, profile_ranges
from glsldiff.physics.exitance import EXITANT

Array = NDArray[np.float64]

STOP_FRACTION = 1e-4  # paper: stop when f_M < 1e-4 sum L_o^2
BACKENDS = ("cpu", "glsl")


@dataclass
class FitOptions:
    """Choices of a fit (defaults picked by measurement, see docs/guide/inverse.md)."""

    method: str = "lbfgs"
    lam: float = 1e-5
    lam_mu: float = 0.0           # ln-mu smoothness weight (glsldiff.inverse.objective)
    depth_weight: float = 1.0     # its z-edges weigh this many times the in-plane ones
    stencil: str = "conservative"
    face_mean: str = "arithmetic"
    kappa0: float = 0.3           # mm, initial value of the homogeneous fit
    mu0: float = 0.01             # mm^-1
    max_evals: int = 200          # heterogeneous stage, per channel
    max_seconds: float = math.inf  # heterogeneous stage, per channel
    homogeneous_evals: int = 40
    parameterization: str = "log"
    mu_gain: float = 1.0          # mu's (log) variables divided by this (glsldiff.inverse.optimize.ScaledProblem)
    backend: str = "cpu"          # "cpu": one SuperLU factor or pyamg hierarchy per material; "glsl": GPU Jacobi
    exitant: str = "p1"           # source and exitance convention of the forward model
    solver: str = "auto"          # cpu backend: "superlu", "pyamg", or "auto" (by node count, ForwardModel.method)

    def __post_init__(self) -> None:
        choice(self.backend, "backend", BACKENDS)
        choice(self.solver, "solver", SOLVERS)
        choice(self.exitant, "exitant", EXITANT)
        choice(self.method, "method", METHODS)
        real(self.kappa0, "kappa0 (mm)", 0.0, lo_open=True)
        real(self.mu0, "mu0 (mm^-1)", 0.0, lo_open=True)
        real(self.lam, "lambda", 0.0)
        real(self.lam_mu, "lambda_mu", 0.0)
        real(self.depth_weight, "depth_weight", 0.0)
        real(self.mu_gain, "mu_gain", 0.0, lo_open=True)
        for name in ("max_evals", "homogeneous_evals"):
            integer(getattr(self, name), name, 1, 2**62)


@dataclass
class ChannelFit:
    """Result of one channel: material over the active nodes and the two traces."""

    kappa: Array
    mu: Array
    homogeneous: tuple[float, float]
    homogeneous_trace: Trace
    trace: Trace
    data: float  # final data term (normalised squared error)
    snapshots: list = field(default_factory=list)
    ranges: CoefficientRanges | None = None  # how tightly the data pin the homogeneous material

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
    interrupted: bool = False  # Ctrl-C: the best material so far (see notes)


def fit_homogeneous(objective: Objective, kappa0: float, mu0: float, max_evals: int
                    ) -> tuple[float, float, Trace, CoefficientRanges]:
    """Best homogeneous (kappa, mu): two unknowns (paper: "quickly computed ... with
    user-specified initial values"). Least squares on ``(log kappa, log mu)`` with scipy's
    trust-region reflective solver; each Jacobian costs two extra solves with the factor
    of the residual's evaluation (:meth:`Factorized.tangent`), not extra factorisations.
    The regulariser vanishes for a homogeneous volume. Also returns how tightly the data pin
    sigma_a and sigma_s' (:mod:`glsldiff.inverse.ranges`, from the final Jacobian)."""
    o = objective
    model = o.model
    if type(model) is not ForwardModel:  # e.g. the GLSL path: the two-unknown fit runs on the CPU
        model = ForwardModel(model.grid, model.stencil, model.face_mean, model.eta, model.C, model.exitant,
                             solver=model.solver)
    ones = np.ones(model.n)
    w = np.sqrt(o.W / o.norm)
    trace = Trace("homogeneous-trf")
    cache: dict[tuple[float, float], tuple] = {}
    t0 = time.perf_counter()

    def state(z: Array) -> tuple:
        key = (float(z[0]), float(z[1]))
        if key not in cache:
            cache.clear()
            fac = model.factorize(math.exp(z[0]) * ones, math.exp(z[1]) * ones)
            X = fac.solve(o.Q)
            r = (w * (fac.radiance(X, o.Q) - o.Y)).ravel()
            data = float(r @ r)
            trace.records.append(Record(len(trace.records) + 1, time.perf_counter() - t0, data, data,
                                        float("nan")))
            cache[key] = (fac, X, r)
        return cache[key]

    def jac(z: Array) -> Array:
        fac, X, _ = state(z)
        cols = []
        for i, (dk, dm) in enumerate(((fac.kappa, 0.0 * ones), (0.0 * ones, fac.mu))):  # d/dlog = value * d/dvalue
            dX = fac.tangent(X, o.Q, dk, dm, key=f"tangent{i}")
            cols.append((w * fac.radiance_tangent(X, dX, dk)).ravel())
        return np.stack(cols, axis=1)

    bounds = ([math.log(1e-4), math.log(1e-7)], [math.log(1e3), math.log(1e2)])
    z0 = np.clip([math.log(kappa0), math.log(mu0)], *bounds)
    res = least_squares(lambda z: state(z)[2], z0, jac=jac, bounds=bounds, method="trf",
                        x_scale=1.0, xtol=1e-6, ftol=1e-10, max_nfev=max_evals)
    trace.status = "converged" if res.status > 0 else "budget spent"
    trace.converged = res.status > 0
    trace.iterations = int(res.njev or 0)
    trace.seconds = time.perf_counter() - t0
    kappa, mu = math.exp(res.x[0]), math.exp(res.x[1])
    return kappa, mu, trace, profile_ranges(np.asarray(res.jac), kappa, mu, 2.0 * float(res.cost))


def fit_channel(model: ForwardModel, Q: Array, Y: Array, W: Array, options: FitOptions,
                callback: Callable[[Record], None] | None = None, snapshot_every: int = 0,
                channel: int = 0, checkpoint: Checkpoint | None = None,
                start: ChannelProgress | None = None) -> ChannelFit:
    """Homogeneous, then heterogeneous fit of one channel (sources/measurements/weights
    ``(n_boundary, M)``); ``snapshot_every`` keeps the material every that many iterations
    in ``ChannelFit.snapshots`` as ``(record, kappa, mu)``. ``checkpoint`` saves where the
    fit stands (as channel ``channel``) when due and at the end; ``start`` continues a saved
    one (:mod:`glsldiff.inverse.checkpoint`)."""
    method = method_for(options.method, 2 * model.n)  # before the homogeneous stage's minutes
    objective = Objective(model, Q, Y, W, lam=options.lam, lam_mu=options.lam_mu,
                          depth_weight=options.depth_weight)
    if start is None:
        k_h, m_h, h_trace, ranges = fit_homogeneous(objective, options.kappa0, options.mu0,
                                                    options.homogeneous_evals)
    else:
        (k_h, m_h), h_trace, ranges = start.homogeneous, start.homogeneous_trace, start.ranges
    mu_scale = max(m_h, 1e-2 / (3.0 * k_h))  # keep the mu variable O(1) even for mu_h -> 0 (1 % of sigma_t')
    problem = ScaledProblem(objective, k_h, mu_scale, method, options.max_evals,
                            options.max_seconds, callback, snapshot_every, options.parameterization, options.mu_gain)
    n = model.n
    z0 = problem.variables(np.full(n, k_h), np.full(n, m_h))
    if start is not None and start.kappa is not None:
        z0 = problem.variables(start.kappa, start.mu)
        problem.resume(start.trace, z0)

    def progress(done: bool) -> ChannelProgress:
        best = (None, None) if problem.best_z is None else problem.material(problem.best_z)
        return ChannelProgress(channel, (k_h, m_h), h_trace, ranges, problem.trace, *best, done)

    if checkpoint is not None:
        report = problem.callback

        def save_when_due(rec: Record) -> None:
            if report is not None:
                report(rec)
            if checkpoint.due():
                checkpoint.save(progress(False))

        problem.callback = save_when_due
    try:
        z = minimize(problem, z0, stopval=STOP_FRACTION)
    finally:   # also on an error or a Ctrl-C before the first evaluation: keep what is known
        if checkpoint is not None:
            checkpoint.save(progress(problem.trace.status not in ("interrupted", "running")))
    kappa, mu = problem.material(z)
    fit = ChannelFit(kappa, mu, (k_h, m_h), h_trace, problem.trace, problem.trace.best.data, ranges=ranges)
    fit.snapshots = [(rec, *problem.material(zs)) for rec, zs in problem.snapshots]
    return fit


def fill_unseen(volume: Array, known: NDArray[np.bool_]) -> Array:
    """Copy into every node outside ``known`` the value of its nearest known node."""
    if known.all():
        return volume
    idx = ndimage.distance_transform_edt(~known, return_distances=False, return_indices=True)
    return volume[tuple(idx)]


def fit_measurements(meas: Measurements, options: FitOptions | None = None,
                     callback: Callable[[int, Record], None] | None = None, checkpoint: Checkpoint | None = None,
                     resume: dict[int, ChannelProgress] | None = None) -> FitResult:
    """Fit every channel of ``meas``; ``callback(channel, record)`` after each evaluation.
    ``checkpoint`` saves the progress every few minutes and on Ctrl-C; ``resume`` (loaded from
    one) takes its finished channels as they are and continues the unfinished one."""
    options = options or FitOptions()
    t0 = time.perf_counter()
    if options.backend == "glsl":
        model: ForwardModel = GlslForwardModel(meas.grid, options.stencil, options.face_mean, meas.eta, meas.C,
                                               options.exitant)
    else:
        model = ForwardModel(meas.grid, options.stencil, options.face_mean, meas.eta, meas.C, options.exitant,
                             solver=options.solver)
    shared = meas.grey()
    fits: list[ChannelFit] = []
    notes: list[str] = ["grey data: one fit served all three channels"] if shared else []
    interrupted = False
    try:
        for c in range(1 if shared else 3):
            saved = (resume or {}).get(c)
            if saved is not None and saved.done:
                fits.append(ChannelFit(saved.kappa, saved.mu, saved.homogeneous, saved.homogeneous_trace, saved.trace,
                                       saved.trace.best.data, ranges=saved.ranges))
                if checkpoint is not None:
                    checkpoint.channels[c] = saved
                notes.append(f"channel {'RGB'[c]} taken from the checkpoint ({len(saved.trace.records)} evaluations)")
                continue
            if saved is not None:
                notes.append(f"channel {'RGB'[c]} resumed from the checkpoint after {len(saved.trace.records)} "
                             "evaluations")
            cb = (lambda rec, c=c: callback(c, rec)) if callback else None
            fits.append(fit_channel(model, *meas.channel(c), options, cb, channel=c, checkpoint=checkpoint,
                                    start=saved))
            if fits[-1].trace.status == "interrupted":
                interrupted = True
                notes.append(f"interrupted in channel {'RGB'[c]} after {len(fits[-1].trace.records)} evaluations: "
                             "its best material so far is saved")
                if len(fits) < (1 if shared else 3):
                    notes.append(f"channels {'RGB'[len(fits):]} were not fitted: they hold a copy of channel "
                                 f"{'RGB'[c]}")
                break
    finally:
        if hasattr(model, "release"):
            model.release()
    if shared:
        fits = fits * 3
    fits += [fits[-1]] * (3 - len(fits))
    g = meas.grid
    kappa = np.stack([model.volume(f.kappa, 0.0) for f in fits], axis=-1)
    mu = np.stack([model.volume(f.mu, 0.0) for f in fits], axis=-1)
    kind = g.kind
    kappa = np.stack([fill_unseen(kappa[..., c], g.active) for c in range(3)], axis=-1)
    mu = np.stack([fill_unseen(mu[..., c], kind == INTERIOR) for c in range(3)], axis=-1)
    if not np.all(np.isfinite(kappa)) or not np.all(np.isfinite(mu)):
        raise SolverError("the fit produced non-finite coefficients")
    return FitResult(kappa, mu, fits, g.h, time.perf_counter() - t0, options, shared, notes, interrupted)


def save_material(path: str | os.PathLike, result: FitResult) -> Path:
    """Write the fitted material (kappa mm, mu mm^-1, ``(nz, ny, nx, 3)``) and fit summary
    to ``.npz`` atomically."""
    o = result.options
    arrays = dict(kappa=result.kappa, mu=result.mu, h=result.h, method=o.method, lam=o.lam, backend=o.backend,
                  solver=o.solver,
                  stencil=o.stencil, face_mean=o.face_mean, exitant=o.exitant, seconds=result.seconds,
                  data_error=np.array([f.data for f in result.channels]),
                  converged=np.array([f.converged for f in result.channels]),
                  interrupted=result.interrupted,
                  homogeneous=np.array([f.homogeneous for f in result.channels]),
                  # per channel: sigma_a lo, hi, sigma_s' lo, hi [mm^-1] keeping the homogeneous data term
                  # within ranges_tolerance of its minimum (glsldiff.inverse.ranges); NaN where not computed or the
                  # homogeneous fit is not physical (sigma_s' < 0)
                  homogeneous_ranges=np.array([[*f.ranges.sigma_a_range, *f.ranges.sigma_s_range] if f.ranges
                                               else [np.nan] * 4 for f in result.channels]),
                  ranges_tolerance=PROFILE_TOLERANCE)
    return write_npz(path, **arrays)
