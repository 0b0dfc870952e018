"""``glsldiff bench fit``: the paper's figures 11 and 13 on synthetic volumes, and the
CPU (one SuperLU factor for all right-hand sides) vs GLSL (Jacobi) forward/adjoint paths.

All fits are of one channel (green) of a grey synthetic volume; E is the figure-11 error
over the pairs a back-lit capture observes (lit z- face to observed z+ face).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from glsldiff.grids.regular import RegularGrid
from glsldiff.bench.progress import Cases
from glsldiff.inverse.fit import FitOptions, fit_channel
from glsldiff.inverse.model import ForwardModel
from glsldiff.inverse.objective import Objective
from glsldiff.inverse.synthetic import bssrdf_error, synthetic_measurements
from glsldiff.physics.procedural import synthetic_volume
from glsldiff.bench.peers import direct_label, relax_label
from glsldiff.bench.timing import repeat, runs_note
from glsldiff.core.io import write_csv
from glsldiff.core.tables import print_table
from glsldiff import gl
from glsldiff.inverse.glsl import GlslForwardModel
from glsldiff.core.plotting import pyplot

CHANNEL = 1


def _grey(v: np.ndarray) -> np.ndarray:
    return np.repeat(v[..., CHANNEL:CHANNEL + 1], 3, axis=-1)


class Case:
    """A grey synthetic volume and an E evaluator for fitted active-node vectors."""

    def __init__(self, size: tuple[int, int, int], h: float, volume: str, seed: int = 1) -> None:
        nx, ny, nz = size
        k, m = synthetic_volume((nz, ny, nx), volume, seed=seed)
        self.kappa, self.mu = _grey(k), _grey(m)
        self.h = h
        self.grid = RegularGrid(nx, ny, nz, h=h)
        self.model = ForwardModel(self.grid)

    def measurements(self, n: int, noise: float, seed: int = 2):
        return synthetic_measurements(self.kappa, self.mu, self.h, n, "back", noise=noise, seed=seed)

    def error(self, kappa: np.ndarray, mu: np.ndarray) -> float:
        vol = lambda v: np.repeat(self.model.volume(v, 1.0)[..., None], 3, axis=-1)  # noqa: E731
        return bssrdf_error(self.grid, (self.kappa, self.mu), (vol(kappa), vol(mu)), channels=(CHANNEL,))

    def true_vectors(self) -> tuple[np.ndarray, np.ndarray]:
        return (self.model.active_values(self.kappa[..., CHANNEL]),
                self.model.active_values(self.mu[..., CHANNEL]))


def _fit(case: Case, meas, method: str, lam: float, max_evals: int, snapshot_every: int = 0):
    """One fit; Ctrl-C inside it (which a fit answers by keeping its best point) ends the bench."""
    model = ForwardModel(case.grid)
    t0 = time.perf_counter()
    fit = fit_channel(model, *meas.channel(CHANNEL), FitOptions(method=method, lam=lam, max_evals=max_evals),
                      snapshot_every=snapshot_every)
    if fit.trace.status == "interrupted" or fit.homogeneous_trace.status == "interrupted":
        raise KeyboardInterrupt
    return fit, time.perf_counter() - t0, model


def measurements_study(case: Case, ns: list[int], methods: list[str], max_evals: int, noise: float,
                       lam: float = 1e-5) -> tuple[list[dict], list[dict]]:
    """E against the number of measurements n x n (figure 11 left) and, for the largest n
    up to 16 measurements, E and wall time against iterations (figure 11 right)."""
    rows, curves = [], []
    n_curve = max([n for n in ns if n * n <= 16] or ns[:1])
    cases = Cases("bench fit: measurements", len(ns) * len(methods))
    for n in ns:
        meas = case.measurements(n, noise)
        for method in methods:
            snap = (1 if method == "cg" else 5) if n == n_curve else 0  # CG: few, long iterations
            cases.before(f"{method}, {n * n} measurements, at most {max_evals} evaluations")
            fit, seconds, model = _fit(case, meas, method, lam, max_evals, snap)
            E_h = case.error(np.full(model.n, fit.homogeneous[0]), np.full(model.n, fit.homogeneous[1]))
            E = case.error(fit.kappa, fit.mu)
            cases.after(f"E {E:.3g}")
            rows.append(dict(measurements=n * n, method=method, E=E, E_homogeneous=E_h, data=fit.data,
                             evals=len(fit.trace.records), iterations=fit.trace.iterations,
                             factorizations=model.stats.factorizations, seconds=seconds,
                             status=fit.trace.status))
            t_h = fit.homogeneous_trace.seconds
            for rec, k, m in fit.snapshots:
                curves.append(dict(method=method, measurements=n * n, evaluation=rec.evaluation,
                                   seconds=t_h + rec.seconds, f=rec.value, data=rec.data, E=case.error(k, m)))
    return rows, curves


def lambda_study(case: Case, lams: list[float], n: int, max_evals: int, noise: float) -> list[dict]:
    """Figure 13: fit error and kappa smoothness for several lambda."""
    meas = case.measurements(n, noise)
    kt, mt = case.true_vectors()
    obj = Objective(case.model, *meas.channel(CHANNEL))
    reg_true, _ = obj.regularizer(kt)
    inner = case.grid.kind.reshape(-1)[case.grid.graph.active] == 1
    rows = []
    cases = Cases("bench fit: lambda", len(lams))
    for lam in lams:
        cases.before(f"lambda {lam:g}, at most {max_evals} evaluations")
        fit, seconds, _ = _fit(case, meas, "lbfgs", lam, max_evals)
        cases.after(f"E {case.error(fit.kappa, fit.mu):.3g}")
        reg, _ = obj.regularizer(fit.kappa)
        rows.append(dict(lam=lam, E=case.error(fit.kappa, fit.mu), data=fit.data,
                         grad_kappa_sq=reg, grad_kappa_sq_true=reg_true,
                         kappa_rel_error=float(np.linalg.norm((fit.kappa - kt)[inner]) / np.linalg.norm(kt[inner])),
                         seconds=seconds, status=fit.trace.status))
    return rows


def backend_study(case: Case, n: int, noise: float, repeats: int = 3) -> list[dict]:
    """Seconds per objective+gradient evaluation: SuperLU (one factor, all 2M right-hand
    sides) vs GLSL Jacobi to its model's ``tol`` (3 conditions per solve, warm-started from the
    previous evaluation, as in a fit), and their gradient gap. Each path first evaluates once
    outside the clock (``warmup_s``: GL context use, shader compilation, first upload; for
    SuperLU the same first evaluation), then ``repeats`` evaluations at as many perturbed points
    are timed one by one: median and minimum (``t_median_s``, ``t_min_s``)."""

    meas = case.measurements(n, noise)
    Q, Y, W = meas.channel(CHANNEL)
    kt, mt = case.true_vectors()
    rng = np.random.default_rng(0)
    points = [(kt * (1 + 0.05 * rng.standard_normal(kt.size)), mt) for _ in range(repeats + 1)]
    rows, grads = [], {}
    for path in ("superlu", "glsl"):
        model = ForwardModel(case.grid) if path == "superlu" else GlslForwardModel(case.grid)
        label = direct_label() if path == "superlu" else relax_label("GLSL Jacobi fp32", model.tol)
        obj = Objective(model, Q, Y, W)
        t0 = time.perf_counter()
        obj.evaluate(*points[0])  # warm-up (GL compile / first upload): outside the clock
        warmup = time.perf_counter() - t0
        todo = iter(points[1:])
        tim = repeat(lambda: obj.evaluate(*next(todo)), repeats)
        ev = tim.result
        grads[path] = np.concatenate([ev.grad_kappa, ev.grad_mu])
        device = "cpu" if path == "superlu" else gl.describe(model._solver.ctx)
        rows.append(dict(path=label, device=device, seconds_per_gradient=tim.median, **tim.columns(),
                         warmup_s=warmup, tol=getattr(model, "tol", float("nan")), measurements=meas.M,
                         sweeps=getattr(model, "sweeps", 0)))
        if hasattr(model, "release"):
            model.release()
    gap = float(np.linalg.norm(grads["glsl"] - grads["superlu"]) / np.linalg.norm(grads["superlu"]))
    for r in rows:
        r["gradient_gap"] = gap
    return rows


def plot(rows: list[dict], curves: list[dict], lam_rows: list[dict], path: Path) -> None:
    plt = pyplot()

    panels = 3 if lam_rows else 2
    fig, ax = plt.subplots(1, panels + 1, figsize=(4.2 * (panels + 1), 3.6))
    for method in sorted({r["method"] for r in rows}):
        rr = [r for r in rows if r["method"] == method]
        ax[0].semilogy([r["measurements"] for r in rr], [r["E"] for r in rr], "o-", label=method)
        cc = [c for c in curves if c["method"] == method]
        ax[1].semilogy([c["evaluation"] for c in cc], [c["E"] for c in cc], ".-", label=method)
        ax[2].semilogy([c["seconds"] for c in cc], [c["E"] for c in cc], ".-", label=method)
    if rows:
        ax[0].semilogy([r["measurements"] for r in rows if r["method"] == rows[0]["method"]],
                       [r["E_homogeneous"] for r in rows if r["method"] == rows[0]["method"]], "k:",
                       label="homogeneous init")
    ax[0].set(xlabel="measurements (n x n)", ylabel="E", title="figure 11: E vs measurements")
    ax[1].set(xlabel="objective evaluations", ylabel="E", title="E vs iterations")
    ax[2].set(xlabel="wall time (s)", ylabel="E", title="E vs time")
    if lam_rows:
        ax[3].loglog([r["lam"] for r in lam_rows], [r["E"] for r in lam_rows], "o-", label="E")
        ax[3].loglog([r["lam"] for r in lam_rows], [r["kappa_rel_error"] for r in lam_rows], "s-",
                     label="kappa rel. error")
        ax[3].set(xlabel="lambda", title="figure 13: regularisation")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run(args: argparse.Namespace) -> None:
    out = Path(args.out)   # created when the first study's results are written
    case = Case(tuple(args.size), args.h, args.volume)
    nx, ny, nz = args.size
    title = f"{nx}x{ny}x{nz} {args.volume} volume, h = {args.h} mm, noise {args.noise:g}"
    rows, curves, lam_rows = [], [], []
    if "measurements" not in args.skip:
        rows, curves = measurements_study(case, args.n, args.methods, args.max_evals, args.noise)
        out.mkdir(parents=True, exist_ok=True)
        write_csv(out / "fit_measurements.csv", rows)
        write_csv(out / "fit_iterations.csv", curves)
        print_table(f"figure 11: E vs measurements ({title})", rows)
    if "lambda" not in args.skip:
        lam_rows = lambda_study(case, args.lams, 4, args.max_evals, args.noise)
        out.mkdir(parents=True, exist_ok=True)
        write_csv(out / "fit_lambda.csv", lam_rows)
        print_table(f"figure 13: regularisation, 16 measurements ({title})", lam_rows)
    if "backends" not in args.skip:
        repeats = getattr(args, "repeat", 3)
        print(f"bench fit: timing one gradient on each path ({repeats} runs each)", file=sys.stderr, flush=True)
        b_rows = backend_study(case, 4, args.noise, repeats)
        out.mkdir(parents=True, exist_ok=True)
        write_csv(out / "fit_backends.csv", b_rows)
        print_table(f"forward+adjoint paths, 16 measurements ({title}); seconds per gradient: "
                    f"{runs_note(repeats)}, warm-up outside the clock", b_rows,
                    first=("path", "seconds_per_gradient", "t_min_s", "warmup_s", "gradient_gap"),
                    rest=f"all in {out}/fit_backends.csv")
    if rows:
        plot(rows, curves, lam_rows, out / "fit.png")
    print("E: figure-11 diffuse-BSSRDF error over (lit z-, observed z+) node pairs vs the true volume; "
          "data: normalised squared radiance error (the noise floor is about noise^2).")
    print(f"wrote CSV files{' and fit.png' if rows else ''} to {out}/")
