"""``glsldiff bench sphere``: the polygrid against the closed-form sphere (grid refinement).

A homogeneous sphere of radius R under a uniform boundary source q has the radial
solution ``phi(r) = a sinh(s r) / r`` (:func:`glsldiff.oracle.closed_forms.sphere_fluence`). The
polygrid of an icosphere is refined in two ways: series ``n`` keeps the polycube (cube edge
``cube_size``) and raises the nodes per cube ``n``; series ``cubes`` keeps ``n`` and
shrinks the cubes. Each grid is solved to convergence (:func:`glsldiff.bench.peers.reference_solve`:
SuperLU below 20k nodes, else pyamg SA + GMRES to a relative residual of 1e-11; ``reference``
names which), so only the discretisation error is measured: the relative L2 error of phi at
the boundary nodes and at the interior nodes, each against ``phi(|x - centre|)`` at the
node's own position, and the local (truncation) error of the exact solution per row kind
(:func:`truncation`). Series ``n`` also solves with the other weight fallbacks (what the
fallback costs in accuracy) and, optionally, with the GLSL solver to the Jacobi-scaled residual
``tol`` (GPU error and time next to the reference solve's).

Timing: the reference and the GLSL solve of the default weights run ``repeats`` times each,
set-up included in both (assembly and the LU factorisation or AMG set-up; the GLSL solver's
construction: texture upload, shader compilation): ``t_median_s`` / ``t_min_s`` of the reference
solve, ``glsl_t_median_s`` / ``glsl_t_min_s`` of the GLSL one.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Sequence

import numpy as np

from glsldiff.core import io
from glsldiff.core.errors import GlsldiffError
from glsldiff.oracle.closed_forms import sphere_fluence
from glsldiff.physics.optics import boundary_constant
from glsldiff.grids.polygrid import Polygrid, build_polygrid, with_weights
from glsldiff.mesh import sphere_mesh
from glsldiff.system.problem import DiffusionProblem, relative_l2
from glsldiff.grids.graph import BOUNDARY, INTERIOR
from glsldiff.oracle.assembly import assemble
from glsldiff.bench.peers import reference_solve, relax_label
from glsldiff.bench.progress import Cases
from glsldiff.bench.timing import repeat
from glsldiff.solve.jacobi import solve_glsl
from glsldiff.core.plotting import pyplot, save_figure

def _errors(pg: Polygrid, phi: np.ndarray, exact: np.ndarray) -> tuple[float, float]:
    flat = phi.reshape(pg.size, 3)
    lat = pg.lattice
    return (relative_l2(flat[lat.boundary], exact[lat.boundary]),
            relative_l2(flat[lat.interior], exact[lat.interior]))


def truncation(p: DiffusionProblem, exact: np.ndarray) -> dict[str, float]:
    """Local error of the discrete system: mean ``|b - A x| / (diag(A) x)`` of the exact
    solution ``x`` (channel 0, in the problem's unknown), over the boundary rows whose
    partner is theirs alone, the boundary rows of partners shared at polycube edges, and
    the interior rows."""
    pg = p.grid
    s = assemble(p)
    A, b = s.block(0)
    x = np.asarray(p.from_phi(exact.reshape(p.node_shape + (3,)))).reshape(-1, 3)[s.active, 0]
    rel = np.abs(b - A @ x) / (s.diag[:s.n] * np.abs(x))
    lat = pg.lattice
    shared = np.zeros(lat.size_nodes, dtype=bool)
    shared[lat.boundary] = lat.partner_count[lat.link] > 1
    kind, sh = lat.kind[s.active], shared[s.active]
    groups = {"boundary_single": (kind == BOUNDARY) & ~sh, "boundary_shared": sh, "interior": kind == INTERIOR}
    return {f"trunc_{k}": float(rel[m].mean()) if m.any() else float("nan") for k, m in groups.items()}


def sphere_study(ns: Sequence[int] = (4, 6, 8, 12), radius: float = 10.0, cube_size: float = 5.0,
                 kappa: float = 1.0 / 3.15, mu: float = 0.05, q: float = 1.0, subdivisions: int = 5,
                 glsl: bool = True, tol: float = 5e-7, out: Path | None = None,
                 variance_iterations: int = 100, cube_sizes: Sequence[float] = (),
                 n_fixed: int = 4, repeats: int = 1) -> list[dict[str, object]]:
    """Discretisation error of the polygrid sphere against the closed form.

    Two refinements: series ``"n"`` keeps the polycube (cube edge ``cube_size``) and raises
    the nodes per cube ``n``; series ``"cubes"`` keeps ``n = n_fixed`` and shrinks the cube
    edge through ``cube_sizes`` (a new polycube each time). Both halve h; only the second
    also shrinks the region the polycube-to-sphere map distorts. Homogeneous channel 0
    carries q; the other channels are 0 (pyamg skips them, SuperLU still factors them).
    The reference and GLSL solves of the default weights run ``repeats`` times (module docstring).
    """
    mesh = sphere_mesh(radius, subdivisions=subdivisions)
    C = float(boundary_constant(1.3))
    rows: list[dict[str, object]] = []
    polycube = None
    runs = [("n", n, cube_size) for n in ns] + [("cubes", n_fixed, c) for c in cube_sizes]
    cases = Cases("bench sphere", len(runs))
    for series, n, size in runs:
        cases.before(f"series {series}, n = {n}, cubes of {size:g} mm: polygrid, reference solves"
                     + (", GLSL solve" if glsl else ""))
        t0 = time.perf_counter()
        pg = build_polygrid(mesh, n=n, cube_size=size, polycube=polycube if series == "n" else None,
                            mapping={"variance_iterations": variance_iterations})
        if series == "n":
            polycube = pg.polycube
        build = time.perf_counter() - t0
        r = np.linalg.norm(pg.positions - mesh.vertices.mean(axis=0), axis=1)
        exact = np.zeros((pg.size, 3))
        exact[:, 0] = sphere_fluence(r, radius, kappa, mu, C, q)
        row: dict[str, object] = {"series": series, "n": n, "cube_mm": size, "h_mm": pg.lattice.h,
                                  "cubes": len(pg.lattice.cubes), "nodes": pg.n_active, "build_s": build,
                                  "fallback_nodes": pg.weight_stats.fallback if pg.weight_stats else 0}
        for fallback in ("blend", "axis", "none") if series == "n" else ("blend",):
            g = pg if fallback == "blend" else with_weights(pg, fallback=fallback)
            try:
                p = DiffusionProblem(g, kappa, mu, (q, 0.0, 0.0), C=C)
                ref = repeat(lambda: reference_solve(p), repeats if fallback == "blend" else 1)
            except GlsldiffError:  # raw weights may not even give a valid system
                row[f"err_boundary_{fallback}"] = row[f"err_interior_{fallback}"] = float("nan")
                continue
            phi, ref_rep, ref_label, ref_rtol = ref.result
            eb, ei = _errors(g, phi, exact)
            row[f"err_boundary_{fallback}"] = eb
            row[f"err_interior_{fallback}"] = ei
            if fallback == "blend":
                row.update({"reference": ref_label, "reference_rtol": ref_rtol,
                            "reference_residual": ref_rep.residual, **ref.columns()})
                row.update(truncation(p, exact))
                if glsl:
                    gt = repeat(lambda: solve_glsl(p, tol=tol), repeats)
                    phi_g, rep = gt.result
                    row["glsl"] = relax_label("GLSL Jacobi fp32", tol)
                    row["glsl_vs_reference"] = relative_l2(phi_g[g.active], phi[g.active])
                    row.update({"glsl_tol": tol, "glsl_residual": rep.residual, "glsl_t_median_s": gt.median,
                                "glsl_t_min_s": gt.min, "glsl_sweeps": rep.sweeps})
        rows.append(row)
        cases.after(f"{pg.n_active:,} nodes, boundary error {row.get('err_boundary_blend', float('nan')):.3g}")
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        io.write_csv(out / "sphere.csv", rows)
        plot(rows, out / "sphere.png")
    return rows


def plot(rows: list[dict[str, object]], path: Path) -> None:
    """Error against spacing h (log-log), boundary and interior, per fallback."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(6, 4.2))
    styles = {("n", "boundary"): "o-", ("n", "interior"): "s-", ("cubes", "boundary"): "o--",
              ("cubes", "interior"): "s--"}
    for series, label in (("n", "fixed polycube, n up"), ("cubes", "n fixed, cubes smaller")):
        sel = [r for r in rows if r["series"] == series]
        if not sel:
            continue
        h = [float(r["h_mm"]) for r in sel]
        for part in ("boundary", "interior"):
            ax.loglog(h, [float(r[f"err_{part}_blend"]) for r in sel], styles[series, part],
                      label=f"{part}: {label}")
    ax.set_xlabel("lattice spacing h [mm]")
    ax.set_ylabel("relative L2 error of phi vs closed form")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("polygrid sphere vs a sinh(s r)/r", fontsize=9)
    save_figure(fig, path, dpi=110)
