"""``glsldiff bench sphere``: the polygrid against the closed-form sphere (grid refinement).

A homogeneous sphere of radius R under a uniform boundary source q has the radial
solution ``phi(r) = a sinh(s r) / r`` (:func:`glsldiff.analytic.sphere_fluence`). For a
fixed polycube (cube edge ``cube_size``) and increasing nodes per cube ``n`` this builds the
polygrid of an icosphere, solves the discrete system directly (SuperLU, so only the
discretisation error is measured), and reports the relative L2 error of phi at the
boundary nodes and at the interior nodes, each against ``phi(|x - centre|)`` at the node's
own position. The same grid is also solved with the other weight fallbacks, which shows
what the fallback costs in accuracy, and (optionally) with the GLSL solver, which shows
the GPU error and time next to the direct solve.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Sequence

import numpy as np

from glsldiff import io
from glsldiff.errors import GlsldiffError
from glsldiff.analytic import sphere_fluence
from glsldiff.optics import boundary_constant
from glsldiff.polygrid import Polygrid, build_polygrid, with_weights
from glsldiff.problem import DiffusionProblem, relative_l2
from glsldiff.reference import solve_direct


def _errors(pg: Polygrid, phi: np.ndarray, exact: np.ndarray) -> tuple[float, float]:
    flat = phi.reshape(pg.size, 3)
    lat = pg.lattice
    return (relative_l2(flat[lat.boundary], exact[lat.boundary]),
            relative_l2(flat[lat.interior], exact[lat.interior]))


def sphere_study(ns: Sequence[int] = (4, 6, 8, 12), radius: float = 10.0, cube_size: float = 5.0,
                 kappa: float = 1.0 / 3.15, mu: float = 0.05, q: float = 1.0, subdivisions: int = 5,
                 glsl: bool = True, tol: float = 5e-7, out: Path | None = None,
                 variance_iterations: int = 100) -> list[dict[str, object]]:
    """Discretisation error of the polygrid sphere against the closed form, per ``n``."""
    from glsldiff.mesh import sphere_mesh

    mesh = sphere_mesh(radius, subdivisions=subdivisions)
    C = float(boundary_constant(1.3))
    rows: list[dict[str, object]] = []
    polycube = None
    for n in ns:
        t0 = time.perf_counter()
        pg = build_polygrid(mesh, n=n, cube_size=cube_size, polycube=polycube,
                            mapping={"variance_iterations": variance_iterations})
        polycube = pg.polycube
        build = time.perf_counter() - t0
        r = np.linalg.norm(pg.positions - mesh.vertices.mean(axis=0), axis=1)
        exact = np.repeat(sphere_fluence(r, radius, kappa, mu, C, q)[:, None], 3, axis=1)
        row: dict[str, object] = {"n": n, "h_mm": pg.lattice.h, "cubes": len(pg.lattice.cubes),
                                  "nodes": pg.n_active, "build_s": build,
                                  "fallback_nodes": pg.weight_stats.fallback if pg.weight_stats else 0}
        for fallback in ("blend", "axis", "none"):
            g = pg if fallback == "blend" else with_weights(pg, fallback=fallback)
            t1 = time.perf_counter()
            try:
                p = DiffusionProblem(g, kappa, mu, q, C=C)
                phi, _ = solve_direct(p)
            except GlsldiffError:  # raw weights may not even give a valid system
                row[f"err_boundary_{fallback}"] = row[f"err_interior_{fallback}"] = float("nan")
                continue
            eb, ei = _errors(g, phi, exact)
            row[f"err_boundary_{fallback}"] = eb
            row[f"err_interior_{fallback}"] = ei
            if fallback == "blend":
                row["direct_s"] = time.perf_counter() - t1
                if glsl:
                    from glsldiff.polydiffusion import solve_polygrid

                    phi_g, rep = solve_polygrid(p, tol=tol)
                    row["glsl_vs_direct"] = relative_l2(phi_g[g.active], phi[g.active])
                    row["glsl_s"] = rep.seconds
                    row["glsl_sweeps"] = rep.sweeps
        rows.append(row)
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        io.write_csv(out / "sphere.csv", rows)
        plot(rows, out / "sphere.png")
    return rows


def plot(rows: list[dict[str, object]], path: Path) -> None:
    """Error against spacing h (log-log), boundary and interior, per fallback."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = [float(r["h_mm"]) for r in rows]
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for key, style in (("err_boundary_blend", "o-"), ("err_interior_blend", "s-"),
                       ("err_boundary_none", "x--"), ("err_interior_none", "+--")):
        ax.loglog(h, [float(r[key]) for r in rows], style, label=key.replace("err_", ""))
    ax.set_xlabel("lattice spacing h [mm]")
    ax.set_ylabel("relative L2 error of phi vs closed form")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("polygrid sphere vs a sinh(s r)/r", fontsize=9)
    fig.tight_layout()
    with io.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
