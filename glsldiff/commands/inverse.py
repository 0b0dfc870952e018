"""``glsldiff synth`` and ``glsldiff fit``: synthetic measurements and the inverse fit."""
from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np

from glsldiff.core.tables import print_table
from glsldiff.commands.fit_output import FitProgress, verdict
from glsldiff.core import arguments as A
from glsldiff.core.errors import InputError
from glsldiff.core.io import check_output, read_npz
from glsldiff.bench import fit as fit_bench
from glsldiff.core.io import write_csv, write_exr, write_npz
from glsldiff.inverse.figures import depth_slices
from glsldiff.inverse.checkpoint import CHECKPOINT_EVERY_S, Checkpoint, checkpoint_path, load_checkpoint
from glsldiff.inverse.amg import AUTO_MAX_DIRECT
from glsldiff.inverse.fit import FitOptions, fit_measurements, save_material
from glsldiff.inverse.model import SOLVERS, resolve_solver
from glsldiff.inverse.optimize import METHODS, NLOPT_MAX_VARIABLES, method_for
from glsldiff.inverse.measurements import Measurements, load_measurements, save_measurements
from glsldiff.inverse.reflectance import diffuse_reflectance
from glsldiff.inverse.synthetic import BSSRDF_MAX_SOURCES, SYNTH_SETUPS, bssrdf_error, coefficient_errors, synthetic_measurements
from glsldiff.physics.procedural import SYNTHETIC_KINDS, synthetic_volume
from glsldiff.physics.exitance import EXITANT


def add_parsers(sub: argparse._SubParsersAction, bsub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("synth", help="render synthetic measurements of a heterogeneous block (npz)")
    p.add_argument("out", help="measurements file to write (.npz); the true material goes to OUT_truth.npz")
    p.add_argument("--size", type=A.integer(3, 1024), nargs=3, default=(32, 32, 10), metavar=("NX", "NY", "NZ"),
                   help="nodes per axis of the block")
    p.add_argument("--h", type=A.positive, default=1.0,
                   help="node spacing, mm (default: a 31 x 31 x 9 mm tile, 3.6 red diffusion lengths wide)")
    p.add_argument("--n", type=A.integer(1, 64), default=4, help="n x n projector regions")
    p.add_argument("--setup", choices=SYNTH_SETUPS, default=None,
                   help="(default: both; back with --renderer mitsuba) back-lit thin block (transmission), front-lit "
                        "thick block (reflection; not with --renderer mitsuba), or both: back-lit and observed on both "
                        "faces (transmission plus reflection, fitted together)")
    p.add_argument("--volume", choices=SYNTHETIC_KINDS, default="bands",
                   help="the synthetic material (docs/guide/inverse.md: what surface data determine in each)")
    p.add_argument("--noise", type=A.nonnegative, default=None,
                   help="relative shot noise at the bright end (default 0.01; none with --renderer mitsuba)")
    p.add_argument("--saturation", type=A.positive, default=None, help="clip radiance at this value")
    p.add_argument("--seed", type=A.seed, default=0, help="random seed of the volume and the noise")
    p.add_argument("--grey", action="store_true",
                   help="the volume's green channel in all three (one fit serves all; one Monte Carlo render "
                        "per region instead of three)")
    p.add_argument("--renderer", choices=("diffusion", "mitsuba"), default="diffusion",
                   help="render the captures with glsldiff's diffusion model, or path trace them with Mitsuba 3 "
                        "(back or both setup, eta = 1; glsldiff.validation.measure)")
    p.add_argument("--spp", type=A.integer(4, 1 << 20), default=1024,
                   help="Monte Carlo samples per pixel with --renderer mitsuba (a power of 4)")
    p.add_argument("--reflection-from", type=A.nonnegative, default=0.0, metavar="MM",
                   help="--renderer mitsuba --setup both: fit the lit face's reflection only this far (mm) from a "
                        "lit region and beyond (the diffusion model is too bright next to it: 2 mm in "
                        "docs/guide/inverse.md)")
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("fit", help="fit kappa and mu to measurements by inverse diffusion")
    p.add_argument("measurements", help=".npz measurements (see glsldiff.inverse.measurements)")
    p.add_argument("-o", "--out", default="material.npz", help="fitted material (.npz)")
    p.add_argument("--method", choices=METHODS, default="lbfgs",
                   help="optimiser: NLopt's lbfgs, tnewton or var2, SciPy's lbfgsb (lbfgs becomes lbfgsb above "
                        f"NLopt's limit of {NLOPT_MAX_VARIABLES:,} variables), or cg (the paper's Table I)")
    p.add_argument("--lam", type=A.nonnegative, default=1e-5, help="kappa-gradient regularisation weight")
    p.add_argument("--lam-mu", type=A.nonnegative, default=0.0,
                   help="weight of the absorption smoothness term sum (ln mu_i - ln mu_j)^2 over node edges (0: off)")
    p.add_argument("--depth-weight", type=A.nonnegative, default=1.0,
                   help="--lam-mu: weight of the edges along the depth (z) against the in-plane ones")
    p.add_argument("--mu-gain", type=A.positive, default=1.0,
                   help="the minimiser's mu variables are ln mu divided by this (> 1: mu moves faster against kappa)")
    p.add_argument("--stencil", choices=("conservative", "paper"), default="conservative",
                   help="finite-difference stencil of the forward model")
    p.add_argument("--exitant", choices=EXITANT, default="p1",
                   help="forward model's source and exitance: p1 (calibrated against Monte Carlo: "
                        "physical kappa and mu) or the paper's net flux")
    p.add_argument("--backend", choices=("cpu", "glsl"), default="cpu",
                   help="forward/adjoint solves: one SuperLU factor (cpu) or GLSL Jacobi (glsl)")
    p.add_argument("--solver", choices=SOLVERS, default="auto",
                   help="--backend cpu: one SuperLU factor per material, pyamg multigrid + CG (warm-started, for "
                        f"large grids), or auto: SuperLU up to {AUTO_MAX_DIRECT} active nodes, pyamg above")
    p.add_argument("--gl", choices=("egl", "osmesa", "auto"), help="GL backend for --backend glsl")
    p.add_argument("--max-evals", type=A.integer(1), default=200, help="evaluations per channel")
    p.add_argument("--max-seconds", type=A.number(0.0, lo_open=True, allow_inf=True), default=math.inf, help="time budget per channel")
    p.add_argument("--kappa0", type=A.positive, default=0.3, help="initial kappa of the homogeneous fit, mm")
    p.add_argument("--mu0", type=A.nonnegative, default=0.01, help="initial mu of the homogeneous fit, 1/mm")
    p.add_argument("--truth", default=None, help="true material (.npz) to report the figure-11 error E")
    p.add_argument("--transport-rounds", type=A.integer(0), default=0, metavar="R",
                   help="after the diffusion fit, R rounds of transport refinement: the fitted material's captures "
                        "path traced by Mitsuba 3, their difference from the diffusion model's taken out of the "
                        "measurements, and the fit run again (measurements of `synth --renderer mitsuba` only; "
                        "glsldiff.validation.refine)")
    p.add_argument("--transport-spp", type=A.integer(1), default=1024, metavar="SPP",
                   help="--transport-rounds: Monte Carlo samples per pixel of each round's render (a power of 4)")
    p.add_argument("--truth-sources", type=A.integer(1), default=BSSRDF_MAX_SOURCES, metavar="N",
                   help="--truth: E samples at most N source nodes of the lit face (every 4th node, or sparser "
                        "above N); each costs 6 solves")
    p.add_argument("--no-png", action="store_true", help="skip the depth-slice pictures")
    p.add_argument("--resume", action="store_true",
                   help="continue the fit saved in OUT_checkpoint.npz (written every --checkpoint-every seconds "
                        "and on Ctrl-C; deleted when the fit ends)")
    p.add_argument("--checkpoint-every", type=A.positive, default=CHECKPOINT_EVERY_S, metavar="SECONDS",
                   help="seconds between checkpoints")
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("reflectance", help="measured diffuse surface reflectance (paper sec. 6.1): a uniformly "
                                          "lit front image minus the fitted material's multiple scattering")
    p.add_argument("measurements", help="front-lit .npz measurements holding the uniformly lit condition")
    p.add_argument("material", help="fitted material .npz (glsldiff fit -o)")
    p.add_argument("--condition", type=A.integer(0), default=0, help="index of the uniformly lit condition")
    p.add_argument("--irradiance", type=A.positive, nargs="+", default=None, metavar="E",
                   help="irradiance of the uniform light (1 or 3 values, camera units x sr); "
                        "default: the condition's q / F_t at normal incidence")
    p.add_argument("-o", "--out", default="reflectance.exr", help="albedo map (.exr), [material].reflectance")
    p.set_defaults(func=cmd_reflectance)

    b = bsub.add_parser("fit", help="inverse diffusion: figure 11 (E vs measurements, vs iterations), "
                                    "figure 13 (lambda), CPU vs GLSL forward solves, SuperLU vs pyamg against the "
                                    "grid size (scale)")
    b.add_argument("--size", type=A.integer(3, 1024), nargs=3, default=(32, 32, 8), metavar=("NX", "NY", "NZ"),
                   help="nodes per axis of the synthetic block")
    b.add_argument("--h", type=A.positive, default=0.5, help="node spacing, mm")
    b.add_argument("--n", type=A.integer(1, 64), nargs="+", default=[1, 2, 3, 4, 5, 6], help="n for n x n measurements")
    b.add_argument("--methods", nargs="+", default=["lbfgs", "cg"], choices=METHODS,
                   help="optimisers to compare (cg = the paper's Table I)")
    b.add_argument("--lams", type=A.nonnegative, nargs="+", default=[1e-4, 1e-5, 1e-6],
                   help="regularisation weights of the figure-13 study")
    b.add_argument("--max-evals", type=A.integer(1), default=150, help="evaluations per fit")
    b.add_argument("--noise", type=A.nonnegative, default=0.01, help="relative shot noise of the measurements")
    b.add_argument("--volume", choices=SYNTHETIC_KINDS, default="mixed",
                   help="the synthetic material")
    b.add_argument("--skip", nargs="*", default=[], choices=("measurements", "lambda", "backends", "scale"),
                   help="parts of the benchmark to leave out")
    b.add_argument("--scale-sizes", type=fit_bench.parse_size, nargs="+", default=None, metavar="NXxNYxNZ",
                   help="grids of the scale part (time and memory per evaluation, SuperLU vs pyamg); default "
                        + " ".join(f"{x}x{y}x{z}" for x, y, z in fit_bench.SCALE_SIZES))
    b.add_argument("--scale-repeats", type=A.integer(1, 100), default=2,
                   help="timed evaluations per solver and grid in the scale part, after a first (cold) one")
    b.add_argument("--superlu-max-gib", type=A.positive, default=12.0,
                   help="scale part: skip SuperLU where one evaluation would take more than this many GiB (peak, "
                        "extrapolated from the last grid measured)")
    b.add_argument("--superlu-max-s", type=A.positive, default=900.0,
                   help="scale part: skip SuperLU where one factorisation would exceed this many seconds "
                        "(extrapolated)")
    b.add_argument("--out", default="bench-out", help="output folder (CSV + PNG)")
    b.add_argument("--gl", choices=("egl", "osmesa", "auto"), help="GL backend for the GLSL path")
    b.set_defaults(func=cmd_bench_fit)


def cmd_synth(args: argparse.Namespace) -> int:
    out = check_output(args.out)
    truth = check_output(out.with_name(out.stem + "_truth.npz"))
    nx, ny, nz = args.size
    if args.setup is None:   # Mitsuba: the reflection's model error spoils the fit (docs/guide/inverse.md)
        args.setup = "back" if args.renderer == "mitsuba" else "both"
    kappa, mu = synthetic_volume((nz, ny, nx), args.volume, seed=args.seed)
    if args.grey:
        kappa, mu = (np.repeat(a[..., 1:2], 3, axis=-1) for a in (kappa, mu))
    if args.reflection_from and (args.renderer, args.setup) != ("mitsuba", "both"):
        raise InputError("--reflection-from masks the reflection of Mitsuba captures; use it with --renderer mitsuba "
                         "--setup both")
    if args.renderer == "mitsuba":
        meas = _mitsuba_synth(args, kappa, mu)
    else:
        meas = synthetic_measurements(kappa, mu, args.h, args.n, args.setup,
                                      noise=0.01 if args.noise is None else args.noise,
                                      saturation=args.saturation, seed=args.seed + 1)
    save_measurements(out, meas)
    write_npz(truth, kappa=kappa, mu=mu, h=args.h)
    setup = "back-lit, both faces observed," if args.setup == "both" else f"{args.setup}-lit"
    print(f"wrote {meas.M} {setup} measurements of a {nx}x{ny}x{nz} {args.volume} block "
          f"(h = {args.h} mm, {args.renderer}) to {out} and the true material to {truth}")
    return 0


def _mitsuba_synth(args: argparse.Namespace, kappa: np.ndarray, mu: np.ndarray) -> Measurements:
    """The captures path traced by Mitsuba 3 (:mod:`glsldiff.validation.measure`)."""
    from glsldiff.validation.measure import MITSUBA_SETUPS, mitsuba_measurements
    from glsldiff.validation.mitsuba_scene import load_mitsuba

    if args.setup not in MITSUBA_SETUPS:
        raise InputError(f"--renderer mitsuba renders the back-lit setups only; use --setup "
                         f"{' or '.join(MITSUBA_SETUPS)}")
    if args.noise or args.saturation is not None:
        raise InputError("--noise and --saturation apply to the diffusion renderer; Monte Carlo has its own "
                         "noise (set it with --spp)")
    load_mitsuba("scalar_rgb")             # a missing Mitsuba fails before any work

    def progress(done: int, total: int, seconds: float) -> None:
        print(f"  region {done}/{total}: {seconds:.0f} s", flush=True)

    meas, info = mitsuba_measurements(kappa, mu, args.h, args.n, args.spp, args.seed, progress, args.setup,
                                      args.reflection_from)
    shares = ", ".join(f"{100 * v:.1f} % of the {face} image" for face, v in info["unscattered_shares"].items())
    print(f"Mitsuba: {info['regions']} regions at {info['spp']} spp in {info['seconds']:.0f} s; unscattered light "
          f"removed ({shares})")
    return meas


def _load_truth(path: str, shape: tuple[int, ...], what: str = "--truth file") -> dict[str, np.ndarray]:
    """The arrays of a material ``.npz`` (kappa, mu on the measurements' grid ``shape``, and
    whatever else it holds, e.g. the stencil it was fitted with)."""
    d = read_npz(path, what, ("kappa", "mu"))
    k, m = d["kappa"], d["mu"]
    if k.shape[:3] != tuple(shape) or m.shape != k.shape:
        raise InputError(f"{what} {path!r}: kappa/mu have shape {k.shape}/{m.shape}, the measurements' "
                         f"grid is {tuple(shape)}")
    return d


def cmd_fit(args: argparse.Namespace) -> int:
    out = check_output(args.out)
    options = FitOptions(method=args.method, lam=args.lam, lam_mu=args.lam_mu, depth_weight=args.depth_weight,
                         mu_gain=args.mu_gain, stencil=args.stencil, kappa0=args.kappa0,
                         mu0=args.mu0, max_evals=args.max_evals, max_seconds=args.max_seconds,
                         backend=args.backend, exitant=args.exitant, solver=args.solver)
    if args.backend == "glsl" and args.solver != "auto":
        raise InputError("--solver chooses the CPU backend's solver; --backend glsl solves by Jacobi on the GPU")
    meas = load_measurements(args.measurements)
    n_variables = 2 * meas.grid.graph.active.size
    options.method = method_for(args.method, n_variables)
    if options.method != args.method:
        print(f"--method {args.method}: NLopt's L-BFGS fails above {NLOPT_MAX_VARIABLES:,} variables and this fit "
              f"has {n_variables:,}; running SciPy's L-BFGS-B (lbfgsb) instead")
    truth = None
    if args.truth:
        d = _load_truth(args.truth, meas.shape)
        truth = (d["kappa"], d["mu"])
    saved = checkpoint_path(out)
    resume = None
    if args.resume:
        if not saved.is_file():
            raise InputError(f"--resume: there is no checkpoint {str(saved)!r} to continue (it is written beside "
                             "-o OUT); drop --resume to start the fit")
        resume = load_checkpoint(saved, meas, options, options.method)
    elif saved.exists():
        raise InputError(f"{str(saved)!r} holds an unfinished fit: continue it with --resume, or delete it to "
                         "start again")
    checkpoint = Checkpoint(saved, meas, options, args.checkpoint_every, options.method)
    transport = None
    if args.transport_rounds:
        transport = _transport(meas, args.transport_spp)
    progress = FitProgress(options.max_evals)
    print(f"fit: {meas.M} conditions lit on {meas.lit_face}, observed on {' and '.join(meas.observed_faces)}, "
          f"{meas.shape[2]}x{meas.shape[1]}x{meas.shape[0]} nodes; {options.method}, at most {options.max_evals} "
          f"evaluations per channel; stop when the objective (data term plus regularisation) < 1e-4 of the "
          "measured power", flush=True)
    try:
        result = fit_measurements(meas, options, progress, checkpoint, resume)
    finally:
        progress.flush()
    fits = result.channels[:1] if result.shared else result.channels
    rows = [dict(channel=c, evaluation=r.evaluation, seconds=r.seconds, f=r.value, data=r.data, grad_norm=r.grad_norm)
            for c, f in enumerate(fits) for r in f.trace.records if not math.isnan(r.grad_norm)]
    save_material(out, result)
    trace = out.with_name(out.stem + "_trace.csv")
    if rows:
        write_csv(trace, rows)
    if result.interrupted:
        for note in result.notes:
            print(note)
        print(f"interrupted: wrote the best material so far to {out}" + (f" and {trace}" if rows else "")
              + f"; continue with --resume (from {saved})")
        return 130
    checkpoint.remove()
    seconds, E = result.seconds, None
    if transport is not None:
        t0 = time.perf_counter()
        refined = _refine(args, meas, options, result, transport, truth, out)
        if refined is None:
            return 130
        result, E = refined
        seconds += time.perf_counter() - t0
    table = []
    for c, f in enumerate(result.channels):
        table.append(dict(channel="RGB"[c], kappa_h=f.homogeneous[0], mu_h=f.homogeneous[1],
                          hom_evals=len(f.homogeneous_trace.records), evals=len(f.trace.records),
                          data=f.data, status=f.trace.status, seconds=f.trace.seconds))
    if truth is not None and E is None:
        E = _truth_error(args, meas, options, truth, result)
    solver = f" ({resolve_solver(options.solver, meas.grid.graph.active.size)})" if options.backend == "cpu" else ""
    print_table(f"inverse diffusion, {meas.M} measurements, {meas.shape[2]}x{meas.shape[1]}x{meas.shape[0]} "
                f"nodes, method {options.method}, lambda {options.lam:g}"
                + (f", lambda_mu {options.lam_mu:g} (depth x{options.depth_weight:g})" if options.lam_mu else "")
                + f", {options.backend} solves{solver}", table)
    for note in result.notes:
        print(note)
    for c, f in enumerate(result.channels[:1] if result.shared else result.channels):
        if f.ranges is not None:
            print(("" if result.shared else f"channel {'RGB'[c]}: ") + f.ranges.describe())
    coefficients = None
    if E is not None:
        print(f"figure-11 error E vs the true material ({meas.lit_face} -> {' and '.join(meas.observed_faces)} "
              f"pairs): {E:.5f}")
        coefficients = coefficient_errors(meas.grid, truth, (result.kappa, result.mu))
        print_table("against the truth: means over the interior nodes (mm^-1) and median relative error per node "
                    "(sa = sigma_a, ss = sigma_s')",
                    [{"channel": r["channel"], "sa_true": r["sigma_a_true"], "sa_fit": r["sigma_a_fit"],
                      "sa_err": r["sigma_a_median_rel_err"], "ss_true": r["sigma_s_true"], "ss_fit": r["sigma_s_fit"],
                      "ss_err": r["sigma_s_median_rel_err"]} for r in coefficients])
    print(verdict(result, E, coefficients))
    if not args.no_png:
        png = out.with_name(out.stem + "_slices.png")
        depth_slices(png, result.kappa, result.mu, meas.h, truth=truth)
        print(f"wrote {png}")
    print(f"wrote {out} and {trace} in {seconds:.1f} s" + (" (with the transport refinement; the trace is the diffusion "
                                                         "fit's)" if transport is not None else ""))
    return 0


def _transport(meas: Measurements, spp: int):
    """The Mitsuba renderer of --transport-rounds, its inputs checked before the fit."""
    from glsldiff.validation.mitsuba import check_ldsampler_spp
    from glsldiff.validation.mitsuba_scene import load_mitsuba
    from glsldiff.validation.refine import mitsuba_transport

    check_ldsampler_spp(spp)
    transport = mitsuba_transport(meas, spp)
    load_mitsuba("scalar_rgb")             # a missing Mitsuba fails before the fit
    return transport


def _truth_error(args: argparse.Namespace, meas: Measurements, options: FitOptions, truth, result) -> float:
    """E of a fitted material against ``--truth``, over the pairs the captures observe."""
    return bssrdf_error(meas.grid, truth, (result.kappa, result.mu), sources=(meas.lit_face,),
                        receivers=meas.observed_faces, stencil=options.stencil, eta=meas.eta,
                        max_sources=args.truth_sources)


def _refine(args: argparse.Namespace, meas: Measurements, options: FitOptions, result, transport, truth, out):
    """--transport-rounds after the diffusion fit: one line per round, the material saved
    after each. Returns the last round's material and its E (None without --truth); None
    after a Ctrl-C (``out`` then holds the last finished round's)."""
    from glsldiff.validation.refine import transport_refine

    last_E: float | None = None

    def error(r) -> str:
        nonlocal last_E
        if truth is None:
            return ""
        last_E = _truth_error(args, meas, options, truth, r)
        return f", E = {last_E:.5f}"

    print(f"transport refinement: {args.transport_rounds} round(s), Mitsuba 3 at {args.transport_spp} spp; "
          f"the diffusion fit took {result.seconds:.0f} s{error(result)}", flush=True)

    def report(rnd) -> None:
        save_material(out, rnd.result)
        print(f"  round {rnd.round}: defect T - D {100 * rnd.defect:.1f} % rms of the data; Monte Carlo of the "
              f"material against the data {rnd.transport_misfit:.2e}; refit data term {rnd.data:.2e}"
              f"{error(rnd.result)} ({rnd.seconds:.0f} s)", flush=True)

    try:
        rounds = transport_refine(meas, options, result, args.transport_rounds, transport, report)
    except KeyboardInterrupt:
        print(f"interrupted during transport refinement: {out} holds the last finished round's material (or the "
              "diffusion fit's)")
        return None
    return rounds[-1].result, last_E


def cmd_reflectance(args: argparse.Namespace) -> int:
    out = check_output(args.out)
    if out.suffix.lower() != ".exr":
        raise InputError(f"output {str(out)!r} must be an .exr file")
    if args.irradiance is not None and len(args.irradiance) not in (1, 3):
        raise InputError(f"--irradiance takes 1 or 3 values, got {len(args.irradiance)}")
    meas = load_measurements(args.measurements)
    d = _load_truth(args.material, meas.shape, "material file")
    k, m = d["kappa"], d["mu"]
    fitted = {key: str(d[key]) for key in ("stencil", "face_mean", "exitant") if key in d}   # the fit's options
    r = diffuse_reflectance(meas, k, m, args.condition, args.irradiance, **fitted)
    write_exr(out, r.rho.astype(np.float32), {"glsldiff": "diffuse surface reflectance, one pixel per block "
                                                          f"node of face {meas.observed_face}"})
    print(r.summary())
    print(f"wrote {out} ({r.rho.shape[1]}x{r.rho.shape[0]}); use it as [material].reflectance with the "
          "block volume")
    return 0


def cmd_bench_fit(args: argparse.Namespace) -> int:
    if args.gl:
        os.environ["GLSLDIFF_GL"] = args.gl
    fit_bench.run(args)
    return 0
