"""``glsldiff bench sphere-lights``: discretisations of a homogeneous sphere under directional
lights and a narrow spot, against the exact series (:mod:`glsldiff.oracle.sphere_series`).

Sphere R = 10 mm (the sphere bench's material: kappa = 1/3.15 mm, mu = 0.05 mm^-1, eta = 1.3).
Lights (irradiance 1, intensity 900 for the spot, source by the renderer's ``p1``
convention): directional from -z (onto a polycube face), from -x-z (a polycube edge), from
+x+y+z (a corner), and a spot 30 mm above the centre on +z aimed at it (cone 10 deg, smooth
falloff from 8 deg). Each discretisation
is solved to convergence (SuperLU, or pyamg far below the discretisation error on large grids;
``solver`` names what ran, ``solver_rtol`` its tolerance, ``residual`` the Jacobi-scaled residual
it reached), so the table shows discretisation error only:

* ``fem``: P1 finite elements on the pillowed polycube (:mod:`glsldiff.grids.tetrahedral.fem_grid`);
* ``fem-adapt``: the same grid refined for each light where its source is not linear over a
  surface edge (:mod:`glsldiff.grids.tetrahedral.adapt`, ``[polygrid] adapt = true``; what the scene default
  ``"auto"`` builds under a spot), compared at the unrefined
  grid's surface nodes (the first ones of the refined grid) so both rows share their points;
  ``nodes`` is then the refined count and ``adapt_s`` the refinement's time;
* ``paper`` / ``conservative``: the polygrid with the appendix-B weights and the paper's or
  the conservative stencil (:mod:`glsldiff.system.problem`);
* ``tetwild`` (on request; pytetwild): the same P1 elements on fTetWild meshes that follow the
  sphere (:mod:`glsldiff.grids.tetrahedral.tetwild`), series ``edge`` over the target edge lengths.

Error of the exitant bracket ``B = a phi - b q`` (the view-independent factor of the exitant
radiance, ``p1`` convention) at the surface / boundary nodes against the series at the same
points (projected on the sphere): ``rel_rms = ||B - B_ref|| / ||B_ref||`` and
``rel_max = max |B - B_ref| / max |B_ref|``. Refinement: series ``n`` (fixed polycube of
``cube_size``, more nodes per cube) and ``cubes`` (fixed ``n``, smaller cubes). Per light,
``sphere_error_<light>.png`` maps the error over the whole sphere for the finest grid of
each discretisation, carried to every point by the renderer's interpolation.

Timing: each solve (problem set-up, assembly, factorisation or AMG set-up, solve; for
``fem-adapt`` the refinement too) runs ``repeats`` times: ``t_median_s``, ``t_min_s``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff.bench.peers import fem_reference_label, reference_solve
from glsldiff.bench.timing import repeat
from glsldiff.core import io
from glsldiff.core.plotting import pyplot, save_figure
from glsldiff.grids.tetrahedral.adapt import refine_for_source
from glsldiff.grids.tetrahedral.fem_grid import build_fem_grid
from glsldiff.grids.polycube import polycube_from_mesh
from glsldiff.grids.polygrid import build_polygrid
from glsldiff.grids.tetrahedral.tetwild import cached_tetrahedralize
from glsldiff.mesh import sphere_mesh
from glsldiff.oracle.fem import solve_tet_direct
from glsldiff.oracle.sphere_lights import sphere_from_light
from glsldiff.physics.exitance import exitant_bracket
from glsldiff.physics.lights import DirectionalLight, SpotLight
from glsldiff.render.shading import surface_interpolation, vertex_interpolation
from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.tet_problem import TetProblem

KAPPA, MU, ETA = 1.0 / 3.15, 0.05, 1.3
#: A light's boundary source at surface points: ``points (P, 3) mm -> q (P,)``.
Source = Callable[[NDArray[np.float64]], NDArray[np.float64]]
DISCRETISATIONS = ("fem", "fem-adapt", "paper", "conservative")
#: Every discretisation the study knows (``tetwild`` needs the optional pytetwild).
ALL_DISCRETISATIONS = DISCRETISATIONS + ("tetwild",)


def bench_lights(radius: float) -> dict[str, Any]:
    """The study's lights by name (directions point towards the light, as in scenes): onto a
    polycube face (from -z), an edge, a corner, and a spot above +z aimed at the centre
    (DirectionalLight normalises the directions)."""
    return {"face": DirectionalLight(direction=(0.0, 0.0, -1.0), irradiance=(1.0, 1.0, 1.0)),
            "edge": DirectionalLight(direction=(-1.0, 0.0, -1.0), irradiance=(1.0, 1.0, 1.0)),
            "corner": DirectionalLight(direction=(1.0, 1.0, 1.0), irradiance=(1.0, 1.0, 1.0)),
            "spot": SpotLight(position=(0.0, 0.0, 3.0 * radius), direction=(0.0, 0.0, -1.0),
                              intensity=(900.0, 900.0, 900.0), cone_deg=10.0, falloff_deg=8.0)}


@dataclass
class Case:
    """One discretisation of the sphere: surface points, a solve per source, and the
    renderer's interpolation from those points to other surface points."""

    points: NDArray[np.float64]                       # (S, 3) mm, where B is compared
    solve: Callable[[Source], tuple[NDArray[np.float64], dict[str, object]]]   # q(points) -> B (S,), info
    info: dict[str, object]
    interpolation: Callable[[NDArray[np.float64]], Any]          # points (P, 3) -> (P, S) matrix


def fem_case(g: Any, build: float, adapt: bool = False) -> Case:
    """The case of a tetrahedral grid (built in ``build`` seconds); ``adapt``: refined for each
    source first (:func:`glsldiff.grids.tetrahedral.adapt.refine_for_source`)."""

    def solve(source: Source) -> tuple[NDArray[np.float64], dict[str, object]]:
        grid, info = g, {}
        if adapt:
            grid, rep = refine_for_source(g, lambda P, N: source(P))
            info = {"nodes": grid.n_active, "surface_nodes": len(grid.surface_nodes), "adapt_edges": rep.edges,
                    "adapt_s": rep.seconds}
        q = np.asarray(source(grid.boundary_positions), dtype=np.float64)
        p = TetProblem(grid, KAPPA, MU, np.repeat(q[:, None], 3, axis=1), eta=ETA)
        phi, rep = solve_tet_direct(p)
        label, rtol = fem_reference_label(rep.nodes)
        info.update({"solver": label, "solver_rtol": rtol, "residual": rep.residual})
        return p.exitant_bracket(phi)[:len(g.surface_nodes), 0], info   # the unrefined grid's nodes come first
    return Case(g.boundary_positions, solve, {"h_mm": g.h, "nodes": g.n_active, "surface_nodes": len(g.surface_nodes),
                                              "inverted": g.quality.inverted, "build_s": build},
                lambda p: surface_interpolation(p, g.boundary_positions, g.surface_triangles))


def polygrid_case(pg: Any, build: float, stencil: str) -> Case:
    """The case of a polygrid (built in ``build`` seconds) with the ``paper`` or
    ``conservative`` stencil (both stencils share one polygrid)."""

    def solve(source: Source) -> tuple[NDArray[np.float64], dict[str, object]]:
        qs = np.repeat(np.asarray(source(pg.boundary_positions), dtype=np.float64)[:, None], 3, axis=1)
        p = DiffusionProblem(pg, KAPPA, MU, qs, eta=ETA, stencil=stencil)
        phi, rep, label, rtol = reference_solve(p)     # fluence (already converted from kappa phi)
        return (exitant_bracket(pg.boundary_values(phi), qs, ETA, "p1", p.C)[:, 0],
                {"solver": label, "solver_rtol": rtol, "residual": rep.residual})
    return Case(pg.boundary_positions, solve, {"h_mm": pg.lattice.h, "nodes": int(pg.n_active),
                                               "surface_nodes": len(pg.boundary_positions),
                                               "inverted": pg.mapping.inverted if pg.mapping else -1,
                                               "build_s": build},
                lambda p: vertex_interpolation(p, pg.boundary_positions))


def sphere_light_study(ns: Sequence[int] = (2, 4, 8), polygrid_ns: Sequence[int] = (4, 6, 8),
                       cube_size: float = 5.0, cube_sizes: Sequence[float] = (5.0, 3.333, 2.5),
                       n_fixed: int = 2, polygrid_n_fixed: int = 4, radius: float = 10.0,
                       tet_edges: Sequence[float] = (2.5, 1.67, 1.25),
                       discretisations: Sequence[str] = DISCRETISATIONS, lights: Sequence[str] | None = None,
                       out: Path | None = None, progress: Callable[[str], None] | None = None,
                       repeats: int = 1) -> list[dict[str, object]]:
    """The table (module docstring); writes ``sphere_lights.csv`` and ``.png`` into ``out``;
    each solve runs ``repeats`` times."""
    mesh = sphere_mesh(radius, subdivisions=5)
    all_lights = bench_lights(radius)
    names = list(lights) if lights else list(all_lights)
    series = {k: sphere_from_light(all_lights[k], radius, KAPPA, MU, ETA) for k in names}
    polycubes: dict[float, Any] = {}
    grids: dict[tuple[str, int, float], tuple[Any, float]] = {}   # (fem | lattice, n, cube): grid, build s
    solved: dict[tuple[str, int, float], tuple[Case, dict[str, Any]]] = {}
    finest: dict[str, tuple[int, Case, dict[str, NDArray[np.float64]]]] = {}   # disc -> n, case, B per light
    rows: list[dict[str, object]] = []
    for disc in discretisations:
        if disc == "tetwild":             # cs: the target edge length
            runs = [("edge", 0, e) for e in tet_edges]
        else:
            fem = disc.startswith("fem")
            runs = ([("n", n, cube_size) for n in (ns if fem else polygrid_ns)]
                    + [("cubes", n_fixed if fem else polygrid_n_fixed, c) for c in cube_sizes])
        for ser, n, cs in runs:
            if (disc, n, cs) not in solved:   # the grid both series share is built and solved once
                if progress:
                    progress(f"sphere-lights: {disc}, " + (f"edge {cs:g} mm" if disc == "tetwild" else
                                                           f"n = {n}, cube {cs:g} mm"))
                kind = ("fem" if disc.startswith("fem") else disc if disc == "tetwild"
                        else "lattice")        # paper and conservative: one polygrid; fem and fem-adapt: one grid
                if (kind, n, cs) not in grids:
                    t0 = time.perf_counter()
                    if kind == "tetwild":
                        grid, _ = cached_tetrahedralize(mesh, cs, status=progress)
                    else:
                        if cs not in polycubes:
                            polycubes[cs] = polycube_from_mesh(mesh, cube_size=cs)
                        grid = (build_fem_grid if kind == "fem" else build_polygrid)(mesh, n=n, polycube=polycubes[cs])
                    grids[kind, n, cs] = (grid, time.perf_counter() - t0)
                case = (fem_case(*grids[kind, n, cs], adapt=disc == "fem-adapt") if kind in ("fem", "tetwild")
                        else polygrid_case(*grids[kind, n, cs], disc))
                results = {}
                for k in names:
                    tim = repeat(lambda: case.solve(series[k].source), repeats)
                    B, extra = tim.result
                    results[k] = (B, tim.columns(), extra)
                solved[disc, n, cs] = (case, results)
            case, results = solved[disc, n, cs]
            if ser in ("n", "edge") and disc != "paper":      # the last of series n goes into the error maps
                finest[disc] = (n, case, {k: B for k, (B, _, _) in results.items()})
            for k in names:
                B, secs, extra = results[k]
                ref = series[k].exitant_bracket(case.points)
                where = {"n": "", "cube_mm": "", "edge_mm": cs} if disc == "tetwild" else {"n": n, "cube_mm": cs,
                                                                                          "edge_mm": ""}
                rows.append({"discretisation": disc, "series": ser, **where, **case.info, "adapt_edges": 0,
                             "adapt_s": 0.0, **extra, "light": k,
                             "rel_rms": float(np.linalg.norm(B - ref) / np.linalg.norm(ref)),
                             "rel_max": float(np.abs(B - ref).max() / np.abs(ref).max()),
                             **secs, "series_terms": series[k].n_terms})
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        io.write_csv(out / "sphere_lights.csv", rows)
        plot(rows, out / "sphere_lights.png")
        weights: dict[str, Any] = {}
        for k in names:
            error_maps({(f"{d}, h = {case.info['h_mm']:g} mm" if d == "tetwild" else f"{d}, n = {n}"): (case, Bs[k])
                        for d, (n, case, Bs) in finest.items()},
                       series[k], radius, out / f"sphere_error_{k}.png", weights=weights)
    return rows


def error_maps(cases: dict[str, tuple[Case, NDArray[np.float64]]], series: Any, radius: float, path: Path,
               height: int = 180, weights: dict[str, Any] | None = None) -> dict[str, float]:
    """Lat-long maps (z up) of ``|B - B_series| / max B_series`` over the whole sphere for
    each discretisation (its case and its solved ``B`` at the case's points), the discrete
    ``B`` carried to each pixel's surface point by the
    renderer's own interpolation (barycentric on the surface triangles for fem, nearest-node
    weights for the lattice); one row per case in ``path`` (PNG, 0 .. 5 % colour scale).
    ``weights``: a dict that keeps each case's interpolation matrix, by name, between calls
    (the maps of several lights share it). Returns the RMS of each map."""
    weights = {} if weights is None else weights
    plt = pyplot()
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = (np.arange(2 * height) + 0.5) / (2 * height) * 2 * np.pi
    T, P = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    ref = series.exitant_bracket(radius * dirs)
    scale = float(np.abs(ref).max())
    fig, axes = plt.subplots(len(cases), 1, figsize=(7, 3.3 * len(cases)), squeeze=False)
    rms = {}
    for ax, (name, (case, B)) in zip(axes[:, 0], cases.items()):
        if name not in weights:                        # the same for every light's map
            weights[name] = case.interpolation(radius * dirs)
        W = weights[name]
        err = (np.abs(W @ B - ref) / scale).reshape(T.shape)
        rms[name] = float(np.sqrt((err ** 2).mean()))
        im = ax.imshow(err, extent=(0, 360, 180, 0), vmin=0.0, vmax=0.05, cmap="magma", aspect="auto")
        ax.set_title(f"{name}: |B - B_series| / max B, RMS {rms[name]:.2%}", fontsize=9)
        ax.set_xlabel("azimuth [deg]")
        ax.set_ylabel("polar angle from +z [deg]")
        fig.colorbar(im, ax=ax, fraction=0.03)
    save_figure(fig, path, dpi=100)
    return rms


def plot(rows: list[dict[str, object]], path: Path) -> None:
    """rel_rms against h per discretisation and light (log-log), both refinements."""
    plt = pyplot()
    lights = sorted({str(r["light"]) for r in rows})
    fig, axes = plt.subplots(1, len(lights), figsize=(3.3 * len(lights), 3.4), sharey=True, squeeze=False)
    colours = {"fem": "C0", "fem-adapt": "C4", "paper": "C3", "conservative": "C1", "tetwild": "C2"}
    for ax, light in zip(axes[0], lights):
        for disc in ALL_DISCRETISATIONS:
            for ser, style in (("n", "o-"), ("cubes", "s--"), ("edge", "^-")):
                sel = [r for r in rows if r["light"] == light and r["discretisation"] == disc and r["series"] == ser]
                if sel:
                    ax.loglog([float(r["h_mm"]) for r in sel], [float(r["rel_rms"]) for r in sel], style,
                              color=colours[disc], label=f"{disc}, " + {"n": "n up", "cubes": "cubes smaller",
                                                                                  "edge": "edge shorter"}[ser])
        ax.set_title(light, fontsize=9)
        ax.set_xlabel("h [mm]")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("relative RMS of B vs series")
    axes[0][-1].legend(fontsize=6)
    save_figure(fig, path, dpi=110)
