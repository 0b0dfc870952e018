"""``glsldiff bench fit``: the paper's figures 11 and 13 on synthetic volumes, the
CPU (one SuperLU factor for all right-hand sides) vs GLSL (Jacobi) forward/adjoint paths, and
the time and memory of one objective evaluation against the grid size for the two CPU solvers
(SuperLU, pyamg; ``scale``), beside the paper's Table II.

All fits are of one channel (green) of a grey synthetic volume; E is the figure-11 error
over the pairs a back-lit capture observes (lit z- face to observed z+ face).
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from typing import Any
from pathlib import Path

import numpy as np

from glsldiff.grids.regular import RegularGrid
from glsldiff.bench.progress import Cases
from glsldiff.inverse.fit import FitOptions, fit_channel
from glsldiff.inverse.model import ForwardModel
from glsldiff.inverse.objective import Objective
from glsldiff.inverse.synthetic import bssrdf_error, camera_noise, region_patterns, synthetic_measurements
from glsldiff.bench.memory import PeakMemory
from glsldiff.physics.procedural import synthetic_volume
from glsldiff.bench.peers import direct_label, relax_label
from glsldiff.bench.timing import repeat, runs_note
from glsldiff.core.io import write_csv
from glsldiff.core.tables import print_table
from glsldiff import gl
from glsldiff.inverse.glsl import GlslForwardModel
from glsldiff.inverse.amg import AMG_RTOL
from glsldiff.core.plotting import pyplot, save_figure

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


#: Wang et al. 2008, Table II: grid (nx, ny, nz) -> material, illumination, hours for the whole
#: acquisition (all iterations, three channels; Core2Duo + GeForce 8800 GTX, GLSL multigrid).
TABLE_II = {(130, 53, 37): ("Wax I", "back", 2.0), (140, 75, 48): ("Wax II", "front", 4.0),
            (256, 256, 20): ("Marble", "back", 11.0), (128, 128, 41): ("Artificial Stone", "back", 3.0)}
#: Default grids of the scale study (nx, ny, nz).
SCALE_SIZES = ((32, 32, 10), (64, 64, 16), (96, 96, 20), (128, 128, 20))
#: SuperLU growth on these grids (one channel, 7-point): nnz(L+U) and factor seconds at 327k
#: nodes (128x128x20: 253 M, 67 s on the 2 shared cores) and the exponents of their growth with
#: the node count (65k -> 327k: n^1.5 and n^2.1): the scale study skips SuperLU where the
#: extrapolation exceeds its limits.
LU_REF_NODES, LU_REF_NNZ, LU_REF_SECONDS, LU_NNZ_EXP, LU_TIME_EXP = 327_184, 253e6, 67.0, 1.5, 2.1


def parse_size(text: str) -> tuple[int, int, int]:
    """``"NXxNYxNZ"`` -> ``(nx, ny, nz)``."""
    parts = text.lower().split("x")
    if len(parts) != 3 or not all(p.isdigit() and int(p) >= 3 for p in parts):
        raise argparse.ArgumentTypeError(f"expected NXxNYxNZ with each at least 3 (e.g. 64x64x16), got {text!r}")
    return int(parts[0]), int(parts[1]), int(parts[2])


def _superlu_estimate(n: int, measured: tuple[int, float, float] | None) -> tuple[float, float]:
    """(GiB, seconds) a SuperLU evaluation would take on ``n`` nodes: the reference growth of
    the factor (8-byte value + 4-byte index per nonzero) and of the factorisation time, or, once
    a row has been measured, that row's ``(nodes, seconds, peak GiB)`` grown the same way."""
    if measured is None:
        return (LU_REF_NNZ * 12 * (n / LU_REF_NODES) ** LU_NNZ_EXP / 2**30,
                LU_REF_SECONDS * (n / LU_REF_NODES) ** LU_TIME_EXP)
    nodes, seconds, gib = measured
    return gib * (n / nodes) ** LU_NNZ_EXP, seconds * (n / nodes) ** LU_TIME_EXP


def _scale_case(size: tuple[int, int, int], h: float, conditions: int, noise: float, points: int, step: float,
                volume: str) -> tuple:
    """Grid, sources Q, measurements Y (the true material's radiance, pyamg to 1e-12, camera
    noise), weights W (the observed z+ face) and ``points`` materials: the truth perturbed by
    5 % per node, then each point a further ``step`` (relative, per node) from the previous one,
    as successive evaluations of a fit."""
    nx, ny, nz = size
    grid = RegularGrid(nx, ny, nz, h=h)
    k, m = synthetic_volume((nz, ny, nx), volume, seed=1)
    model = ForwardModel(grid, solver="pyamg", amg_rtol=1e-12)
    kt, mt = model.active_values(k[..., CHANNEL]), model.active_values(m[..., CHANNEL])
    n = max(int(round(math.sqrt(conditions))), 1)
    Q = grid.face_to_boundary("z-", np.stack(region_patterns(grid, "z-", n), axis=-1))
    fac = model.factorize(kt, mt)
    Y = camera_noise(fac.radiance(fac.solve(Q), Q), 2, noise)
    W = np.repeat((grid.face_to_boundary("z+", np.ones(grid.face_shape("z+"))) > 0)[:, None], Q.shape[1], axis=1)
    Y = Y * W
    rng = np.random.default_rng(0)
    kp, mp = kt * (1 + 0.05 * rng.standard_normal(kt.size)), mt * (1 + 0.05 * rng.standard_normal(mt.size))
    pts = []
    for _ in range(points):
        pts.append((kp.copy(), mp.copy()))
        kp, mp = kp * (1 + step * rng.standard_normal(kp.size)), mp * (1 + step * rng.standard_normal(mp.size))
    return grid, Q, Y, W.astype(np.float64), pts


def scale_study(sizes: list[tuple[int, int, int]], h: float = 0.5, conditions: int = 16, repeats: int = 2,
                noise: float = 0.01, volume: str = "mixed", superlu_max_gib: float = 12.0,
                superlu_max_s: float = 900.0, step: float = 0.01) -> list[dict]:
    """Seconds and peak memory of one objective evaluation (value and gradient: one channel,
    ``conditions`` forward and as many adjoint solves) against the grid size, for SuperLU (a
    factor per material) and pyamg (:mod:`glsldiff.inverse.amg`). Each solver evaluates
    ``1 + repeats`` successive materials of a fit-like sequence (:func:`_scale_case`): the
    first (``t_first_s``: cold, a full set-up and no warm start) and the median of the others
    (``t_eval_s``: pyamg warm-started, its hierarchy updated by Galerkin products where the
    material changed little). ``f_rel_diff`` and ``grad_rel_diff``: the pyamg value and
    gradient at the last material against SuperLU's. SuperLU is skipped where its extrapolated
    factor exceeds ``superlu_max_gib`` or ``superlu_max_s`` (the row says so)."""
    rows: list[dict] = []
    measured: tuple[int, float, float] | None = None
    cases = Cases("bench fit: scale", len(sizes) * 2)
    for size in sizes:
        grid, Q, Y, W, pts = _scale_case(size, h, conditions, noise, repeats + 1, step, volume)
        n = grid.graph.active.size
        paper = TABLE_II.get(tuple(size))
        ref = None
        for solver in ("superlu", "pyamg"):
            label = f"{size[0]}x{size[1]}x{size[2]}"
            row: dict = dict(grid=label, nodes=n, solver=solver, conditions=Q.shape[1])
            if solver == "superlu":
                gib, sec = _superlu_estimate(n, measured)
                if gib > superlu_max_gib or sec > superlu_max_s:
                    row.update(t_eval_s=math.nan,
                               note=f"skipped: extrapolated {gib:.3g} GiB, {sec / 60:.3g} min per evaluation "
                               f"(limits {superlu_max_gib:g} GiB, {superlu_max_s / 60:g} min)")
                    rows.append(row)
                    cases.before(f"{label} superlu skipped")
                    cases.after("")
                    continue
            cases.before(f"{label} ({n} nodes) {solver}: {1 + repeats} evaluations")
            model = ForwardModel(grid, solver=solver)
            obj = Objective(model, Q, Y, W)
            times = []
            with PeakMemory() as mem:
                for kp, mp in pts:
                    t0 = time.perf_counter()
                    ev = obj.evaluate(kp, mp)
                    times.append(time.perf_counter() - t0)
            st = model.stats
            warm = times[1:] or times
            row.update(t_eval_s=float(statistics.median(warm)), t_min_s=min(warm), t_first_s=times[0],
                       repeats=len(warm), prepare_s=st.factor_seconds / len(times),
                       solve_s=st.solve_seconds / len(times), peak_MiB=mem.mib)
            grad = np.concatenate([ev.grad_kappa, ev.grad_mu])
            if solver == "superlu":
                ref = (ev.value, grad)
                if not math.isnan(mem.mib):
                    measured = (n, times[0], mem.mib / 1024)
                row.update(its=math.nan, f_rel_diff=0.0, grad_rel_diff=0.0, note="reference")
            else:
                row.update(its=st.iterations / max(st.solves, 1), setups=st.setups, galerkin=st.galerkin,
                           worst_residual=st.worst_residual)
                if ref is not None:
                    row.update(f_rel_diff=abs(ev.value - ref[0]) / abs(ref[0]),
                               grad_rel_diff=float(np.linalg.norm(grad - ref[1]) / np.linalg.norm(ref[1])), note="")
                else:
                    row.update(f_rel_diff=math.nan, grad_rel_diff=math.nan, note="no SuperLU reference")
            if paper is not None:
                row["paper"] = f"{paper[0]}: {paper[2]:g} h whole fit"
            cases.after(f"{row['t_eval_s']:.2f} s per evaluation, {mem.mib:.0f} MiB")
            rows.append(row)
            del model, obj
    return rows


def _finish(fig: Any, ax: Any, path: Path) -> None:
    """Grid lines and legends on every panel of ``ax``, then the figure written to ``path``
    (:func:`~glsldiff.core.plotting.save_figure`: atomically) and closed."""
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=7)
    save_figure(fig, path, dpi=100)


def plot_scale(rows: list[dict], path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(9.5, 3.8))
    for solver, mark, color in (("superlu", "s-", "C0"), ("pyamg", "o-", "C1")):
        rr = [r for r in rows if r["solver"] == solver and not math.isnan(r.get("t_eval_s", math.nan))]
        if not rr:
            continue
        x = [r["nodes"] for r in rr]
        ax[0].loglog(x, [r["t_eval_s"] for r in rr], mark, color=color, label=f"{solver} (in sequence)")
        ax[0].loglog(x, [r["t_first_s"] for r in rr], mark[0] + ":", color=color, alpha=0.6, label=f"{solver} (first)")
        ax[1].loglog(x, [max(r["peak_MiB"], 1.0) for r in rr], mark, color=color, label=solver)
    ax[0].set(xlabel="active nodes", ylabel="seconds per evaluation",
              title="value + gradient, one channel, 16 conditions")
    ax[1].set(xlabel="active nodes", ylabel="peak MiB added", title="memory")
    _finish(fig, ax, path)


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
    _finish(fig, ax, path)


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
    if "scale" not in args.skip:
        sizes = [tuple(s) for s in getattr(args, "scale_sizes", None) or SCALE_SIZES]
        repeats = getattr(args, "scale_repeats", 2)
        s_rows = scale_study(sizes, args.h, 16, repeats, args.noise, args.volume,
                             getattr(args, "superlu_max_gib", 12.0), getattr(args, "superlu_max_s", 900.0))
        out.mkdir(parents=True, exist_ok=True)
        write_csv(out / "fit_scale.csv", s_rows)
        plot_scale(s_rows, out / "fit_scale.png")
        shown = [dict(grid=r["grid"], nodes=r["nodes"], solver=r["solver"], t_eval_s=r["t_eval_s"],
                      t_first_s=r.get("t_first_s", math.nan), peak_MiB=r.get("peak_MiB", math.nan),
                      its=r.get("its", math.nan), f_rel_diff=r.get("f_rel_diff", math.nan),
                      grad_rel_diff=r.get("grad_rel_diff", math.nan)) for r in s_rows]
        print_table(f"time per objective evaluation (value + gradient, one channel, 16 conditions: 16 forward + 16 "
                    f"adjoint solves) against the grid, {args.volume} volume, h = {args.h} mm; t_eval_s: "
                    f"{runs_note(repeats)} of a fit-like sequence after a first (cold) one; peak_MiB: resident memory "
                    f"added; its: pyamg CG iterations per right-hand side (to relative residual {AMG_RTOL:g}); "
                    "f/grad_rel_diff: pyamg against SuperLU at the same material", shown,
                    rest=f"all in {out}/fit_scale.csv")
        for r in s_rows:
            if r.get("note") and r["note"] != "reference":
                print(f"{r['grid']} {r['solver']}: {r['note']}")
        print("paper, Table II (whole acquisition: hours per sample, GeForce 8800 GTX; time per evaluation not "
              "stated): " + "; ".join(f"{v[0]} {k[0]}x{k[1]}x{k[2]} {v[1]}-lit {v[2]:g} h"
                                      for k, v in TABLE_II.items()))
    if rows:
        plot(rows, curves, lam_rows, out / "fit.png")
    print("E: figure-11 diffuse-BSSRDF error over (lit z-, observed z+) node pairs vs the true volume; "
          "data: normalised squared radiance error (the noise floor is about noise^2).")
    pngs = (["fit.png"] if rows else []) + (["fit_scale.png"] if "scale" not in args.skip else [])
    print(f"wrote CSV files{' and ' + ', '.join(pngs) if pngs else ''} to {out}/")
