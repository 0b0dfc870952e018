"""``glsldiff bench convergence``: error against work and time (paper figure 15).

For a model (the "hole" model: a torus of about 36 cubes of 12^3; the bunny) in veined
marble under a directional light, each scheme of :mod:`glsldiff.solve.multilevel` runs from a
cold start, and at every check the error

    E = sum_b (L_b - L0_b)^2 / sum_b L0_b^2      over the boundary nodes b

is recorded against the node updates so far (figure 15's x axis) and the GPU time so far
(sweeps and transfer passes, GPU finished; read-backs and the CPU residual checks that
produce the curve are excluded). Every scheme solves to the Jacobi-scaled residual
:data:`SCHEME_TOL`. L0 is the converged discrete answer
(:func:`glsldiff.bench.peers.reference_solve`: SuperLU below 20k nodes, else pyamg SA + GMRES
to a relative residual of 1e-11; its row names which) and timed as the peer. L is the boundary
fluence phi_b: every exitant-radiance formula of the renderer is linear in phi_b at fixed
light, and phi_b is the part the solver controls.

Timing: set-up is included for every method in ``t_median_s`` / ``t_min_s`` (the time to the
target): a scheme's is its set-up (the hierarchy's build and the solver's construction with
its shader compilation, wall, ``setup_s``) plus its GPU time to the target
(``seconds_to_target``, figure 15's axis); the peer's is its whole solve (assembly, the LU
factorisation or the AMG set-up, the solve). Each runs ``repeats`` times (median and minimum).
The peer has no early stop: its time is to its full convergence, not to the target.

Also measured: the adaptive depths chosen for a requested error (:func:`choose_depths`),
a frame-coherent re-solve after a small light rotation against a cold start, and the error
each precision mode costs at convergence.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff.bench.peers import reference_solve, relax_label
from glsldiff.bench.progress import Cases
from glsldiff.bench.timing import median_min, repeat, timing_columns
from glsldiff.core import io
from glsldiff.core.errors import InputError, SolverError
from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.grids.polygrid import Polygrid, build_polygrid
from glsldiff.mesh import load_mesh, torus_mesh
from glsldiff.physics.procedural import marble_volume
from glsldiff.solve.multilevel import MultilevelDiffusion
from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.report import CURRENT
from glsldiff.core.plotting import pyplot, save_figure


def figure15_error(phi_b: NDArray, ref_b: NDArray) -> float:
    """``sum (L - L0)^2 / sum L0^2`` (paper section 6.2), all channels."""
    return float(np.sum((phi_b - ref_b) ** 2) / np.sum(ref_b ** 2))


def light_source(pg: Polygrid, direction: Sequence[float]) -> NDArray[np.float64]:
    """``(n_boundary, 3)`` source of a unit directional light along ``direction`` (towards
    the light), ``max(n . l, 0)``, unshadowed (the bench needs a smooth, lit/unlit source,
    not the renderer's pass 1)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    return np.maximum(pg.normals @ d, 0.0)[:, None] * np.ones(3)


def marble_problem(pg: Polygrid, q: NDArray, seed: int = 0, cells: int = 48) -> DiffusionProblem:
    """Veined marble (:func:`glsldiff.physics.procedural.marble_volume` sampled over the bounding box
    of the nodes, ``cells`` voxels along each axis, nearest voxel), conservative stencil:
    with the paper's stencil the boundary rows lose diagonal dominance where kappa changes
    between a boundary node and its partner (the veins do), and every scheme diverges."""
    kappa, mu = marble_volume((cells, cells, cells), seed=seed)
    pos = pg.positions
    lo, hi = pos.min(axis=0), pos.max(axis=0)
    idx = np.clip(((pos - lo) / np.maximum(hi - lo, 1e-9) * (cells - 1)).round().astype(int), 0, cells - 1)
    k = kappa[idx[:, 2], idx[:, 1], idx[:, 0]].reshape(pg.shape + (3,))
    m = mu[idx[:, 2], idx[:, 1], idx[:, 0]].reshape(pg.shape + (3,))
    return DiffusionProblem(pg, k, m, q, eta=1.3, stencil="conservative")


@dataclass
class Curve:
    """One scheme's run: error against work and GPU time, with its report."""

    scheme: str
    work: list[int]
    seconds: list[float]
    error: list[float]
    report: Any
    depths: Sequence[float | None] | None = None
    textures: list[dict[str, Any]] | None = None   # per level: blocks held, texels (MultilevelDiffusion.texture_rows)
    setup: float = math.nan   # wall seconds of the solver's construction (NaN: the caller's solver)

    def first_below(self, target: float) -> tuple[float, float]:
        """``(work, seconds)`` at the first check with error <= target (nan if never)."""
        for w, s, e in zip(self.work, self.seconds, self.error):
            if e <= target:
                return float(w), s
        return math.nan, math.nan


#: The Jacobi-scaled residual every scheme of the study solves to.
SCHEME_TOL = 1e-6


def run_scheme(hierarchy: Hierarchy, problem: DiffusionProblem, ref_b: NDArray, scheme: str,
               tol: float = SCHEME_TOL, check_every: int = 10, precision: str = "fp32",
               depths: Sequence[float | None] | None = None, maxiter: int = 20000,
               solver: MultilevelDiffusion | None = None, warm: bool = False, **options: Any) -> Curve:
    """Solve with ``scheme`` and record the figure-15 error at every check (``warm``: from the
    solver's current solution, frame coherence)."""
    own = solver is None
    t0 = time.perf_counter()
    s = solver if solver is not None else MultilevelDiffusion(hierarchy, problem, scheme, precision=precision,
                                                              depths=depths)
    setup = time.perf_counter() - t0 if own else math.nan
    pg = problem.grid
    b = pg.lattice.boundary
    work: list[int] = []
    secs: list[float] = []
    err: list[float] = []
    base = s.compute_seconds

    def record(x: NDArray) -> None:
        phi = s.problem.to_phi(s.finest.system.to_volume(x, s.problem.node_shape))
        work.append(s.work)
        secs.append(s.compute_seconds - base)
        err.append(figure15_error(phi.reshape(-1, 3)[b], ref_b))

    try:
        _, rep = s.solve(tol=tol, maxiter=maxiter, x0=CURRENT if warm else None, callback=record,
                         check_every=check_every, **options)
        textures = s.texture_rows()
    finally:
        if own:
            s.release()
    return Curve(scheme, work, secs, err, rep, depths, textures, setup)


def choose_depths(hierarchy: Hierarchy, problem: DiffusionProblem, ref_b: NDArray, target: float = 0.005,
                  factors: Sequence[float] = (1.5, 2.0, 3.0, 4.0, 6.0, 8.0), margin: float = 0.5,
                  precision: str = "fp32") -> tuple[list[float | None], list[dict[str, float]]]:
    """Adaptive depths for a requested figure-15 error.

    Candidates, cheapest first: the finest level updates nodes within ``f h_0`` of the surface
    and each coarser level (but the coarsest, always whole) twice the depth of the next finer
    one (figure 8: shallower at finer levels), for ``f`` in ``factors`` (``h_0`` = finest
    spacing). Each candidate is solved to convergence, so its error is what pinning the deep
    nodes to the coarse solution costs; the first whose error is below ``margin * target``
    wins (the margin leaves room for the iteration to reach ``target`` before it converges).
    The error falls with depth roughly like exp(-depth / diffusion length), so the search is
    short. Falls back to the deepest candidate if none qualifies.
    """
    h0 = hierarchy.grids[0].lattice.h
    L = hierarchy.levels
    tried = []
    best: list[float | None] | None = None
    for f in factors:
        depths: list[float | None] = [f * h0 * 2 ** lev for lev in range(L - 1)] + [None]
        c = run_scheme(hierarchy, problem, ref_b, "adaptive", tol=1e-6, check_every=50, depths=depths,
                       precision=precision)
        tried.append({"factor": f, "depth_finest_mm": depths[0], "error": c.error[-1],
                      "updated_finest": c.report.levels[-1]["updated"]})
        if c.error[-1] <= margin * target:
            best = depths
            break
    return (best if best is not None else depths), tried


def rotate(direction: Sequence[float], degrees: float) -> NDArray[np.float64]:
    """``direction`` rotated about the z axis."""
    a = math.radians(degrees)
    R = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return R @ np.asarray(direction, dtype=np.float64)


def reference(problem: DiffusionProblem, repeats: int = 1) -> tuple[NDArray, Any]:
    """Converged fluence and the timing of the direct (or pyamg) solve (its result: ``(phi,
    report, label, rtol)`` of :func:`glsldiff.bench.peers.reference_solve`), ``repeats`` runs."""
    tim = repeat(lambda: reference_solve(problem), repeats)
    return tim.result[0], tim


def study(name: str, pg: Polygrid, levels: int = 3, target: float = 0.005, light=(0.4, 0.3, 1.0),
          rotation: float = 5.0, precisions: Sequence[str] = ("fp32", "fp16", "paper"),
          schemes: Sequence[str] = ("single", "hierarchical", "adaptive", "multigrid"),
          maxiter: int = 20000, repeats: int = 1
          ) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[dict[str, Any]]]:
    """All measurements on one model: (summary rows, curve rows, extra rows); the peer and each
    scheme run ``repeats`` times (module docstring)."""
    t0 = time.perf_counter()
    hierarchy = Hierarchy.build(pg, levels)
    build = time.perf_counter() - t0              # shared by the schemes: in each one's set-up
    q = light_source(pg, light)
    problem = marble_problem(pg, q)
    ref, ref_t = reference(problem, repeats)
    _, ref_rep, ref_label, ref_rtol = ref_t.result
    b = pg.lattice.boundary
    ref_b = ref.reshape(-1, 3)[b]
    summary: list[dict[str, Any]] = [{"model": name, "method": f"{ref_label} (peer)", **ref_t.columns(),
                                      "seconds_to_target": math.nan, "setup_s": math.nan,
                                      "work_to_target": math.nan, "final_error": 0.0, "tol": ref_rtol,
                                      "residual": ref_rep.residual, "nodes": pg.n_active, "levels": "1",
                                      "note": "converged reference L0; time to its convergence"}]
    curves_rows: list[dict[str, Any]] = []
    extra: list[dict[str, Any]] = []
    depths, tried = choose_depths(hierarchy, problem, ref_b, target) if "adaptive" in schemes else (None, [])
    for t in tried:
        extra.append({"model": name, "what": "adaptive depth search", **t})
    curves = {}
    for scheme in schemes:
        label = relax_label(f"GLSL {scheme} fp32", SCHEME_TOL)
        try:
            runs = [run_scheme(hierarchy, problem, ref_b, scheme, depths=depths if scheme == "adaptive" else None,
                               maxiter=maxiter) for _ in range(repeats)]
        except SolverError as exc:  # a scheme that diverges is a result, not the end of the bench
            summary.append({"model": name, "method": label, "work_to_target": math.nan,
                            "seconds_to_target": math.nan, "final_error": math.nan, "tol": SCHEME_TOL,
                            "nodes": pg.n_active, "levels": "", "note": f"FAILED: {str(exc)[:90]}"})
            continue
        c = runs[-1]
        curves[scheme] = c
        w, _ = c.first_below(target)
        gpu, _ = median_min(r.first_below(target)[1] for r in runs)
        setups = [build + r.setup for r in runs]
        lv = c.report.levels
        summary.append({"model": name, "method": label,
                        **timing_columns([st + r.first_below(target)[1] for st, r in zip(setups, runs)]),
                        "seconds_to_target": gpu, "setup_s": float(np.median(setups)), "work_to_target": w,
                        "final_error": c.error[-1], "tol": SCHEME_TOL, "residual": c.report.residual,
                        "nodes": pg.n_active, "levels": " ".join(f"L{r['level']}:n{r['n']}x{r['sweeps']}" for r in lv),
                        "note": "" if scheme != "adaptive" else
                        "depths mm " + ",".join("all" if d is None else f"{d:.2f}" for d in depths)})
        if scheme == "adaptive":  # figure 8: blocks no node of a level uses are dropped from its textures
            for t in c.textures or []:
                extra.append({"model": name, "what": f"adaptive textures level {t['level']}",
                              "blocks": f"{t['blocks']}/{t['of_blocks']}", "texture": t["texture"],
                              "texels_vs_all_blocks": t["texels"] / t["full_texels"]})
        for wk, sk, ek in zip(c.work, c.seconds, c.error):
            curves_rows.append({"model": name, "scheme": scheme, "work": wk, "seconds": sk, "error": ek})
    single = [r for r in summary if r["method"] == relax_label("GLSL single fp32", SCHEME_TOL)]
    for r in summary:   # with set-up, as t_median_s
        r["speedup_vs_single"] = (single[0]["t_median_s"] / r["t_median_s"]
                                  if single and r.get("t_median_s", 0) > 0 else math.nan)

    # frame coherence: a small light rotation, warm (previous frame) vs cold (hierarchical)
    q2 = light_source(pg, rotate(light, rotation))
    ref2, _ = reference(problem.with_q(q2))
    ref2_b = ref2.reshape(-1, 3)[b]
    with MultilevelDiffusion(hierarchy, problem, "hierarchical") as s:
        run_scheme(hierarchy, problem, ref_b, "hierarchical", solver=s, maxiter=maxiter)
        s.set_q(q2)
        warm = run_scheme(hierarchy, problem.with_q(q2), ref2_b, "hierarchical", solver=s, warm=True,
                          maxiter=maxiter)
        s.set_q(q2)
        cold = run_scheme(hierarchy, problem.with_q(q2), ref2_b, "hierarchical", solver=s,
                          maxiter=maxiter)
    for label, c in (("cold", cold), ("warm (previous frame)", warm)):
        row = {"model": name, "what": f"light rotated {rotation} deg: {label}"}
        for t in (target, target / 10, target / 100):
            w, sec = c.first_below(t)
            row.update({f"work_to_{t:g}": w, f"seconds_to_{t:g}": sec})
        extra.append({**row, "fine_sweeps_to_tol": c.report.levels[-1]["sweeps"], "final_error": c.error[-1]})

    # precision: error at convergence (or at the rounding floor) against L0
    for prec in precisions:
        for scheme in ("hierarchical", "multigrid"):
            try:
                c = run_scheme(hierarchy, problem, ref_b, scheme, precision=prec, tol=1e-6,
                               maxiter=maxiter if scheme != "multigrid" else 200)
            except SolverError as exc:
                extra.append({"model": name, "what": f"precision {prec} ({scheme})", "status": "diverged",
                              "note": str(exc)[:90]})
                continue
            extra.append({"model": name, "what": f"precision {prec} ({scheme})", "status": c.report.status,
                          "final_error": c.error[-1], "min_error": min(c.error),
                          "finite": bool(np.all(np.isfinite(c.error)))})
    return summary, curves_rows, extra


def plot(curves: list[dict[str, Any]], path: Path, target: float) -> None:
    """Figure 15: error against node updates (100K) and against GPU seconds, per model."""
    plt = pyplot()

    models = sorted({r["model"] for r in curves})
    fig, axes = plt.subplots(len(models), 2, figsize=(10, 3.8 * len(models)), squeeze=False)
    for i, model in enumerate(models):
        for scheme in dict.fromkeys(r["scheme"] for r in curves if r["model"] == model):
            sel = [r for r in curves if r["model"] == model and r["scheme"] == scheme and r["error"] > 0]
            axes[i, 0].semilogy([r["work"] / 1e5 for r in sel], [r["error"] for r in sel], label=scheme)
            axes[i, 1].semilogy([r["seconds"] for r in sel], [r["error"] for r in sel], label=scheme)
        for ax, xl in zip(axes[i], ("node updates [100K]", "GPU time [s]")):
            ax.axhline(target, color="grey", ls=":", lw=1)
            ax.set_xlabel(xl)
            ax.set_ylabel("sum (L-L0)^2 / sum L0^2")
            ax.set_title(model, fontsize=9)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=8)
    save_figure(fig, path, dpi=110)


def hole_polygrid(n: int = 12, cubes: int = 36) -> Polygrid:
    """The "hole" model: a torus (R = 30 mm, r = 12 mm) with a polycube of about ``cubes`` cubes."""
    return build_polygrid(torus_mesh(30.0, 12.0), n=n, n_cubes=cubes)


def bunny_polygrid(n: int = 8, cubes: int = 253) -> Polygrid:
    """The bunny (100 mm) with the paper's 253-cube target."""
    return build_polygrid(load_mesh("bunny", size_mm=100.0), n=n, n_cubes=cubes)


def convergence_bench(models: Sequence[str] = ("hole", "bunny"), out: Path | None = None, target: float = 0.005,
                      hole_n: int = 12, bunny_n: int = 8, **options: Any) -> tuple[list, list, list]:
    """Run :func:`study` on each model; write CSVs and the plot to ``out``."""
    builders = {"hole": lambda: hole_polygrid(hole_n), "bunny": lambda: bunny_polygrid(bunny_n)}
    unknown = [m for m in models if m not in builders]
    if unknown:
        raise InputError(f"unknown model(s) {unknown}; choose from {sorted(builders)}")
    summary, curves, extra = [], [], []
    cases = Cases("bench convergence", len(models))
    for m in models:
        cases.before(f"{m}: the peer's converged solve, then each scheme to error {target:g}")
        s, c, e = study(m, builders[m](), target=target, **options)
        cases.after()
        summary += s
        curves += c
        extra += e
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        io.write_csv(out / "convergence_summary.csv", summary)
        io.write_csv(out / "convergence_curves.csv", curves)
        io.write_csv(out / "convergence_extra.csv", extra)
        plot(curves, out / "convergence.png", target)
    return summary, curves, extra
