"""The built-in default job: a back-lit heterogeneous marble slab (Wang et al. 2008, section 4.1).

The slab's back face (z-) is split into 4 x 4 regions, lit one at a time as by the
paper's projector; each lighting is solved on the GPU path (GLSL Jacobi to the Jacobi-scaled
residual ``tol``) and the front face (z+) exitant radiance is written as OpenEXR, plus a
tone-mapped PNG contact sheet. Each image's GPU solution is compared with the scipy direct solve
(SuperLU) of the same discrete system, and the paper stencil with the conservative one.

Timing (one run per image): both solvers are set up once, outside every row's time, and the
set-up is reported apart (:func:`run` returns it with the rows): the GPU solver's construction
(texture upload, shader compilation) and its CPU system for the residual checks; the SuperLU
assembly and factorisation. ``gpu_s`` is the solve (sweeps, residual checks), ``direct_s`` the
triangular solves with the stored factors.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm
from numpy.typing import NDArray

from glsldiff import gl

from glsldiff.bench.peers import direct_label, relax_label
from glsldiff.core import io
from glsldiff.solve.jacobi import GlslDiffusion
from glsldiff.grids.regular import RegularGrid
from glsldiff.inverse.synthetic import region_patterns
from glsldiff.physics.exitance import source_from_irradiance
from glsldiff.physics.optics import fresnel_transmittance
from glsldiff.physics.procedural import marble_volume
from glsldiff.system.problem import DiffusionProblem, relative_l2
from glsldiff.oracle.solvers import DirectSolver

from glsldiff.system.report import SolveReport

logger = logging.getLogger(__name__)


@dataclass
class DemoConfig:
    """Scene and solver settings of the default job (lengths in mm)."""

    nx: int = 64
    ny: int = 64
    nz: int = 12
    h: float = 0.5
    regions: int = 4
    irradiance: float = 1.0      # projector irradiance on a lit region (arbitrary units)
    eta: float = 1.3
    tol: float = 5e-7
    maxiter: int = 20000
    precision: str = "fp32"
    seed: int = 0
    out: Path = Path("glsldiff-out")


def region_sources(grid: RegularGrid, regions: int, irradiance: float, eta: float,
                   exitant: str = "p1") -> list[dict[str, NDArray]]:
    """Back-face (z-) sources, one per lit region, row-major over (y, x) regions: the source
    of ``exitant``'s convention for the transmitted irradiance ``E_t = F_t(eta, 1) E`` of
    normal-incidence projector irradiance ``E`` (:func:`source_from_irradiance`)."""
    value = float(source_from_irradiance(float(fresnel_transmittance(eta, 1.0)) * irradiance, eta, exitant))
    return [{"z-": q} for q in region_patterns(grid, "z-", regions, value)]


def front_image(report: SolveReport) -> NDArray[np.float64]:
    """Front-face (z+) radiance as an image, row 0 = largest y (camera looking down -z)."""
    return report.radiance["z+"][::-1]


def run(cfg: DemoConfig, progress: bool = True) -> list[dict[str, object]]:
    """Solve all lightings, write the images, return the table rows (the last one: the set-up
    times, module docstring)."""
    grid = RegularGrid(cfg.nx, cfg.ny, cfg.nz, cfg.h)
    kappa, mu = marble_volume(grid.shape, seed=cfg.seed)
    sources = region_sources(grid, cfg.regions, cfg.irradiance, cfg.eta)
    problem = DiffusionProblem(grid, kappa, mu, sources[0], eta=cfg.eta)
    direct = DirectSolver(problem)
    ctx = gl.get_context()
    rows, images = [], []
    out = Path(cfg.out)
    labels = {"gpu": relax_label(f"GLSL Jacobi {cfg.precision}", cfg.tol), "direct": direct_label()}
    t0 = time.perf_counter()
    with GlslDiffusion(problem, ctx, cfg.precision) as gpu:
        gpu.full_system                      # the residual checks' CPU system: set-up, not the first image's solve
        ctx.finish()
        gpu_setup = time.perf_counter() - t0
        for i, q in enumerate(tqdm(sources, desc="lightings", disable=not progress)):
            gpu.set_q(q)
            phi, rep = gpu.solve(tol=cfg.tol, maxiter=cfg.maxiter)
            phi_ref, rep_ref = direct.solve(q)
            rep.error = relative_l2(phi, phi_ref, grid.active)
            img = front_image(rep)
            err_img = relative_l2(img, front_image(rep_ref))
            name = f"front_r{i // cfg.regions}c{i % cfg.regions}.exr"
            io.write_exr(out / name, img, {"glsldiff": "front-face exitant radiance (P1, calibrated "
                                                         "against Monte Carlo; physics.exitance)",
                                            "units": "radiance per unit projector irradiance, sr^-1"})
            images.append(img)
            rows.append({"image": name, "sweeps": rep.sweeps, "residual": rep.residual,
                         "est_error": rep.error_estimate, "error_phi": rep.error,
                         "error_image": err_img, "gpu_s": rep.seconds,
                         "direct_s": rep_ref.seconds, "status": rep.status, **labels, "tol": cfg.tol})
    exposure = 1.0 / max(float(np.percentile(np.concatenate([im.ravel() for im in images]), 99.5)), 1e-30)
    io.write_png(out / "contact_sheet.png", io.contact_sheet(images, cfg.regions, exposure, scale=4))
    rows.append({**stencil_difference(
        problem.with_q(sources[(cfg.regions // 2) * cfg.regions + cfg.regions // 2]), ctx, cfg), **labels,
        "tol": cfg.tol})
    rows.append({"image": "set-up (once, no row above)", "gpu_s": gpu_setup, "direct_s": direct.factor_seconds,
                 "status": "", **labels, "tol": cfg.tol})
    io.write_csv(out / "report.csv", rows)
    logger.info("direct factorisation %.2f s; renderer %s", direct.factor_seconds, gl.describe(ctx))
    return rows


def stencil_difference(problem: DiffusionProblem, ctx: object, cfg: DemoConfig) -> dict[str, object]:
    """Front-image difference between the paper stencil and the conservative one (the row's
    solve columns: the conservative solve, its set-up excluded as in the other rows)."""
    cons = replace(problem, stencil="conservative")
    reps = []
    for p in (problem, cons):
        with GlslDiffusion(p, ctx, cfg.precision) as gpu:  # type: ignore[arg-type]
            gpu.full_system                # set-up, outside the solve's time as in the other rows
            reps.append(gpu.solve(tol=cfg.tol, maxiter=cfg.maxiter)[1])
    return {"image": "paper vs conservative (centre)", "sweeps": reps[1].sweeps,
            "residual": reps[1].residual, "est_error": reps[1].error_estimate, "error_phi": float("nan"),
            "error_image": relative_l2(front_image(reps[0]), front_image(reps[1])),
            "gpu_s": reps[1].seconds, "direct_s": float("nan"), "status": reps[1].status}
