"""The ``glsldiff`` command: ``render``, ``validate``, ``demo``, ``bench forward|sphere|convergence|fit``, ``polygrid``, ``tet``, ``cut``,
``synth``, ``fit``, ``info``.

Errors a user can cause are printed as one line without a traceback (exit code 2).
"""
from __future__ import annotations

import argparse
import contextlib
import logging
import os
import re
import signal
import sys
import threading
from dataclasses import replace
from typing import Any, Sequence

import numpy as np

from glsldiff.core import arguments as A
from glsldiff.core import interrupt
from glsldiff.core.heartbeat import Heartbeat
from glsldiff.core.errors import GlsldiffError, InputError
from glsldiff.core.tables import print_table
from glsldiff import gl
from glsldiff.bench import demo
from glsldiff.bench import forward as forward_bench
from glsldiff.bench import polygrid as polygrid_study
from glsldiff.bench.convergence import convergence_bench
from glsldiff.bench.meshes import MESHES as BENCH_MESHES, mesh_bench
from glsldiff.bench.sphere import sphere_study
from glsldiff.bench.tet import tet_study
from glsldiff.bench.cut import update_seconds
from glsldiff.bench.edit import EDIT_MODELS, edit_study, save_edit_study
from glsldiff.bench.frames import MODES as FRAME_MODES, frames_study, save_frames_study
from glsldiff.bench.throughput import sweep_throughput
from glsldiff.bench.timing import runs_note
from glsldiff.bench.sphere_lights import (ALL_DISCRETISATIONS as SPHERE_ALL_DISCRETISATIONS,
                                          DISCRETISATIONS as SPHERE_DISCRETISATIONS, sphere_light_study)
from glsldiff.commands.capture import add_capture_parser
from glsldiff.commands.edit import add_parser as add_edit_parser, add_view_parser
from glsldiff.commands.inverse import add_parsers
from glsldiff.core import io
from glsldiff.core.io import check_output_folder, created_folders_removed_on_failure
from glsldiff.figures import polygrid_figure
from glsldiff.grids.polygrid import build_polygrid
from glsldiff.mesh import load_mesh, sphere_mesh
from glsldiff.mesh.load import MAX_SIZE_MM, MIN_SIZE_MM
from glsldiff.render.output import check_output, save
from glsldiff.render.grid_check import check_scene, discretisation_error
from glsldiff.render.renderer import Renderer
from glsldiff.physics.exitance import INCIDENCE
from glsldiff.render.scene import (FLUXES, MODELS, TETWILD_EDGES_PER_SIZE, CutSpec, MeshSpec, PolygridSpec, default_scene,
                                   example_names, example_scene, load_scene)
from glsldiff.physics.collision import SOURCES
from glsldiff.validation.validate import validate


def _add_gl(p: argparse.ArgumentParser) -> None:
    p.add_argument("--gl", choices=("egl", "osmesa", "auto"),
                   help="GL backend (default: $GLSLDIFF_GL or egl)")


def _add_repeat(p: argparse.ArgumentParser, default: int) -> None:
    """A bench's ``--repeat N``: timed work runs N times, tables print the median and the minimum."""
    p.add_argument("--repeat", type=A.integer(1, 100), default=default, metavar="N",
                   help="run each timed solve N times; tables show the median and the fastest "
                        "(default %(default)s" + ("; 1 run is printed as such, no median)" if default == 1 else ")"))


def cmd_demo(args: argparse.Namespace) -> int:
    regions = demo.DemoConfig.regions
    if min(args.size[:2]) < regions:
        raise InputError(f"--size: NX and NY must be >= {regions} (the back face is lit in {regions} x {regions} "
                         f"regions), got {args.size[0]} {args.size[1]}")
    cfg = demo.DemoConfig(nx=args.size[0], ny=args.size[1], nz=args.size[2], h=args.h,
                          tol=args.tol, precision=args.precision, out=check_output_folder(args.out), seed=args.seed)
    rows = demo.run(cfg, progress=not args.quiet)
    print_table(f"Back-lit marble slab {cfg.nx}x{cfg.ny}x{cfg.nz}, h = {cfg.h} mm, "
                f"{gl.describe(gl.get_context())}; seconds: 1 run", rows,
                first=("image", "gpu_s", "direct_s", "sweeps", "error_phi", "error_image", "residual"),
                rest=f"all in {cfg.out}/report.csv")
    print(f"gpu_s: {rows[0]['gpu']} (Jacobi-scaled residual); direct_s: {rows[0]['direct']} with the stored factors; "
          "the set-up of both (GPU: textures, shader compilation, the residual checks' CPU system; SuperLU: assembly "
          "and factorisation) is in its own row, in no other. error_phi: relative L2 of the GPU fluence vs the direct "
          "solve of the same system; error_image: same for the front-face radiance image; est_error: the solver's own "
          "estimate.")
    print(f"wrote {cfg.regions ** 2} EXR images, contact_sheet.png and report.csv to {cfg.out}/")
    return 0


def _status(line: str) -> None:
    """Progress of a long step, on stderr (stdout keeps the results)."""
    print(line, file=sys.stderr, flush=True)


def _warn(rep: Any) -> None:
    """A render report's regime warnings, one line each on stderr."""
    for line in rep.warnings:
        print(f"WARNING: {line}", file=sys.stderr, flush=True)


def cmd_render(args: argparse.Namespace) -> int:
    out = check_output(args.out)   # before any work
    if args.scene and args.example:
        raise InputError("give a scene file or --example NAME, not both")
    scene = load_scene(args.scene) if args.scene else example_scene(args.example) if args.example else default_scene()
    if args.check_grid:
        check_scene(scene)
    with Renderer(allow_unconverged=args.allow_unconverged, status=_status) as r:
        img, rep = r.render(scene)
        print(f"scene: {scene.source}")
        print("\n".join(rep.lines() if args.verbose else rep.summary_lines()))
        _warn(rep)
        if args.check_grid:
            err, nodes, seconds = discretisation_error(r, scene)
            print(f"discretisation: exitance within {err.rel_rms:.2%} RMS (max {err.rel_max:.2%} of the largest) of "
                  f"the 1:8 refined grid's ({nodes:,} nodes, green channel, {seconds:.1f} s); the "
                  f"grid's own error is about 4/3 of that; negative surface fluence at {err.negative_surface} nodes "
                  f"({err.negative_surface_refined} refined)")
        for k in range(2, args.frames + 1):   # repeat frames: what a frame costs once set up
            img, again = r.render(scene)
            ran = [p["pass"] for p in again.passes if p["ran"]]
            print(f"frame {k}: ran {', '.join(ran)}; frame {again.frame_seconds * 1e3:.1f} ms "
                  f"= {1.0 / max(again.frame_seconds, 1e-9):.1f} fps-equivalent")
    exr, png, exposure = save(img, out, scene, rep)
    print(f"wrote {exr} (linear radiance), {png} (exposure {exposure:.3g}, gamma 2.2) and "
          f"{exr.with_suffix('.json')} (the full report{'' if args.verbose else '; -v prints it'})")
    return 0


def cmd_cut(args: argparse.Namespace) -> int:
    out = check_output(args.out)   # before any work
    if (args.plane is None) == (args.stroke is None):
        raise InputError("give exactly one of --plane NX NY NZ D or --stroke U,V U,V ...")
    scene = load_scene(args.scene) if args.scene else default_scene()
    if scene.polygrid.discretisation != "tetwild":
        edge = args.edge or scene.mesh.size_mm / TETWILD_EDGES_PER_SIZE
        print(f"cut: the scene's {scene.polygrid.discretisation!r} grid cannot be cut; using an fTetWild mesh "
              f"(discretisation \"tetwild\", edge {edge:g} mm)", file=sys.stderr)
        scene = replace(scene, polygrid=PolygridSpec(discretisation="tetwild", edge_mm=edge))
    elif args.edge:
        scene = replace(scene, polygrid=replace(scene.polygrid, edge_mm=args.edge))
    if args.stroke is not None and scene.camera.position is None:
        raise InputError("--stroke is drawn in the camera's image: the scene needs [camera] position (and target)")
    if args.plane is not None and not any(args.plane[:3]):
        raise InputError("--plane: the normal (the first three numbers) must not be zero")
    scene = replace(scene, cut=CutSpec(tuple(args.plane) if args.plane else None,
                                       tuple(args.stroke) if args.stroke else None, args.iterations))
    with Renderer(allow_unconverged=args.allow_unconverged, status=_status) as r:
        img, rep = r.render(scene)
        print(f"scene: {scene.source}, cut")
        print("\n".join(rep.lines()))
        _warn(rep)
        if not args.no_timing:
            kappa, mu = r.node_material
            pg = r.polygrid
            q = np.zeros(len(pg.positions))
            q[pg.surface_nodes] = r.boundary_source[:, 1]
            rows = update_seconds(pg, r.cut_report, kappa[:, 1], mu[:, 1], q, scene.material.eta, scene.options.tol)
            print_table("TransCut update after the cut on the CPU (green channel; the renderer's own pass 2 "
                        "solves on the GPU, above)", rows)
    exr, png, exposure = save(img, out, scene, rep)
    print(f"wrote {exr} (linear radiance) and {png} (exposure {exposure:.3g}, gamma 2.2)")
    return 0


def _stroke_point(text: str) -> tuple[float, float]:
    try:
        u, v = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a U,V pixel point (two numbers and a comma)") from None
    if not all(np.isfinite([u, v])):
        raise argparse.ArgumentTypeError(f"{text!r}: pixel coordinates must be finite")
    return u, v


def cmd_validate(args: argparse.Namespace) -> int:
    rows = validate(args.cases, check_output_folder(args.out), size=args.size, spp=args.spp, source=args.source,
                    adapt=args.adapt, flux=args.flux, incidence=args.incidence, model=args.model, progress=_status)
    print_table("diffusion renderer vs Mitsuba 3 volpath (subsurface light: multiple and all scattering orders; "
                "eta != 1: surface reflection removed) and the dipole", rows,
                first=("case", "rmse_vs_mc_all_scattering", "mean_ratio_all_scattering", "rel_l2", "power_ratio",
                       "peak_ratio", "mc_noise", "diffusion_s", "mc_s"), rest=f"all in {args.out}/validation.csv")
    print("rmse: relative RMSE over the object's pixels (silhouette excluded); mc_noise: the Monte Carlo "
          "image's own relative standard error; times in seconds (diffusion: t1+t2+t3 of a frame).")
    print(f"wrote validation.csv and validation_<case>.png (diffusion | MC multiple, or subsurface at eta != 1 "
          f"| MC all, with the reflection at eta != 1) to {args.out}/")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    out = check_output_folder(args.out)
    if not args.sizes and not args.throughput:
        raise InputError("give grid --sizes, --throughput, or both")
    if args.sizes:
        rows = forward_bench.forward(sizes=args.sizes, out=out, max_direct_nodes=args.max_direct_nodes,
                                     seconds=args.seconds, precisions=args.precision, schemes=args.schemes,
                                     levels=args.levels, tol=args.tol, repeats=args.repeat)
        print_table(f"bench forward ({gl.describe(gl.get_context())}): seconds, {runs_note(args.repeat)}", rows,
                    first=("grid", "method", "t_median_s", "t_min_s", "final_error", "t(err<1e-4)", "t(err<1e-5)"),
                    rest=f"all in {args.out}/forward.csv")
        print(f"t_median_s / t_min_s: median / fastest of {args.repeat} run(s), set-up included for every method "
              "(CPU: assembly + SuperLU factorisation or pyamg set-up; GPU: texture upload + shader compilation), "
              "the GL context excluded (created once, before any clock); the Jacobi runs (no tol) sweep for "
              f"--seconds {args.seconds:g} (numpy's stops earlier where it stalls at rounding), their repeats redo the "
              "first run's sweeps. t(err<X): the same over the "
              "runs; Mupd/s: per second of solving (measured set-up out); rtol: relative residual passed to pyamg; tol: "
              "Jacobi-scaled residual; residual: Jacobi-scaled residual reached.")
        print(f"wrote forward.csv, forward_curves.csv and forward.png to {args.out}/")
    if args.throughput:
        rows = sweep_throughput(repeats=args.repeat)
        print_table(f"sweep throughput, fp32, conservative stencil ({gl.describe(gl.get_context())}), "
                    f"{runs_note(args.repeat)}", rows,
                    first=("grid", "packing", "ms/sweep", "ms/sweep min", "M upd/s", "cost/node vs regular"),
                    rest=f"all in {args.out}/throughput.csv")
        print("packing primitives: the paper's quads/lines/points with per-primitive offsets (2 passes); texels: "
              "per-texel offset textures, one quad per sweep. Each regular grid has the node count of the polygrid "
              "after it. ms/sweep, M upd/s: the median of the runs of 200 sweeps (GPU finished, no read-back), "
              "ms/sweep min: the fastest; the solver's construction and 5 warm-up sweeps (shader compilation) are "
              "outside the clock (setup_s). cost/node vs regular: the polygrid's time per node update over the "
              "regular grid's, same packing.")
        print(f"wrote {io.write_csv(out / 'throughput.csv', rows)}")
    return 0


def cmd_polygrid(args: argparse.Namespace) -> int:
    out = check_output_folder(args.out)   # before the build
    mesh = load_mesh(args.mesh, size_mm=args.size_mm, component=args.component)
    pg = build_polygrid(mesh, n=args.n, cube_size=args.cube_size,
                        n_cubes=None if args.cube_size else args.cubes, threshold=args.threshold,
                        mapping={"variance_iterations": args.variance_iterations},
                        weights={"fallback": args.fallback})
    stats = pg.stats()
    stats["mesh"] = str(args.mesh)
    stats["polycube_threshold"] = float(pg.polycube.threshold)
    stats["levels"] = " ".join(f"n={lv}:{cnt}" for lv, cnt in polygrid_study.level_counts(pg))
    print_table(f"polygrid of {args.mesh} ({mesh.extents.max():.3g} mm)",
                [{"quantity": k, "value": v} for k, v in stats.items()])
    io.write_csv(out / "polygrid.csv", [{"quantity": k, "value": v} for k, v in stats.items()])
    if not args.no_png:
        polygrid_figure(pg, str(out / "polygrid.png"))
    if args.solve:
        rows = polygrid_study.check_solve(pg, args.tol)
        print_table("GLSL polygrid vs the converged CPU solve (SuperLU, pyamg above 20k nodes; same discrete system)", rows)
        io.write_csv(out / "polygrid_solve.csv", rows)
    print(f"wrote polygrid.csv{'' if args.no_png else ', polygrid.png'}"
          f"{', polygrid_solve.csv' if args.solve else ''} to {out}/")
    return 0


def cmd_tet(args: argparse.Namespace) -> int:
    light = np.asarray(args.light, dtype=np.float64)
    if not (np.all(np.isfinite(light)) and np.linalg.norm(light) > 0):
        raise InputError(f"--light {' '.join(f'{v:g}' for v in args.light)}: give a finite, non-zero direction "
                         "towards the light (e.g. --light 0 0 1)")
    out = check_output_folder(args.out)   # before the meshing
    render_out = check_output(args.render) if args.render else None
    mesh = (sphere_mesh(args.size_mm / 2.0, subdivisions=5) if args.mesh == "sphere"
            else load_mesh(args.mesh, size_mm=args.size_mm, component=args.component))
    tm, rows, summary, solvers = tet_study(mesh, args.edge, args.sigma_a, args.sigma_s, args.eta, args.light, args.tol, out,
                                  status=_status, refine=args.refine, levels=args.levels, coarse_tol=args.coarse_tol,
                                  repeats=args.repeat)
    q = tm.quality.as_dict()
    q.pop("seconds")
    refined = f", 1:8-refined {args.refine}x" if args.refine else ""
    print_table(f"tetrahedral mesh of {args.mesh} ({mesh.extents.max():.3g} mm), fTetWild, edge {args.edge:g} mm{refined}",
                [{"quantity": k, "value": v} for k, v in q.items()])
    print_table("TransCut DE matrix (eqs. 10-14): set-up and reference",
                [{"quantity": k, "value": v} for k, v in summary.items()])
    print_table(f"solved: error = max boundary |phi - phi_ref| / max phi_ref; seconds: {runs_note(args.repeat)}",
                solvers, first=("method", "t(1%)", "t(0.1%)", "solve t(1%)", "solve t(0.1%)", "t_median_s", "t_min_s"),
                rest=f"all in {out}/tet_{mesh.name}_solvers.csv")
    print(f"rtol: ||r|| / ||b|| passed to each solver (the hierarchies' coarse levels: rtol {args.coarse_tol:g}); "
          "t(X): seconds to error X with the set-up (pyamg's, the hierarchy's build; each built once, reused by "
          "the repeats); solve t(X): solve-only seconds to 1 % and 0.1 %, without it; t_median_s / t_min_s: to rtol.")
    print(f"wrote tet_{mesh.name}.csv, tet_{mesh.name}_solvers.csv and tet_{mesh.name}.png (error against time) "
          f"to {out}/")
    if args.render:
        scene = replace(default_scene(), mesh=MeshSpec(args.mesh, args.size_mm),
                        polygrid=PolygridSpec(discretisation="tetwild", edge_mm=args.edge))
        with Renderer(status=_status) as r:
            img, rep = r.render(scene)
            print("\n".join(rep.lines()))
            _warn(rep)
        exr, png, exposure = save(img, render_out, scene, rep)
        print(f"wrote {exr} (the default scene's light and veined marble on this mesh) and {png}")
    return 0


def cmd_bench_edit(args: argparse.Namespace) -> int:
    out = check_output_folder(args.out)
    summary, frames = edit_study(args.models, dabs=args.dabs, frame_sweeps=args.frame_sweeps, size=args.size,
                                 status=_status, repeats=args.repeat)
    print_table(f"editing: {args.dabs}-dab stroke, {args.frame_sweeps} sweeps per frame, {args.size}^2 pixels "
                f"({gl.describe(gl.get_context())}); cold solve {runs_note(args.repeat)}", summary,
                first=("model", "fps editing", "to 0.5 % s", "to tol s", "cold t_median_s", "cold t_min_s"),
                rest=f"all in {args.out}/edit_summary.csv")
    print("fps editing: 1 / (edit + frame) per dab, the median over the dabs; to 0.5 %: seconds from the last dab's "
          "edit to the first frame within 0.5 % (rel. L2) of the converged image (1 stroke); cold t_median_s / "
          f"t_min_s: the peer, the same solver from zero (no frame coherence) to the scene's tol (Jacobi-scaled), "
          f"median / fastest of {args.repeat} run(s); it and the frames reuse the solver the first frame built (set-up "
          "excluded from both, in the first frame's time); paper: Wang et al. 2008 Table III on a GeForce 8800 GTX "
          "(its bunny has 8x our nodes).")
    paths = save_edit_study(summary, frames, out)
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def cmd_bench_frames(args: argparse.Namespace) -> int:
    out = check_output_folder(args.out)
    summary, frames = frames_study(args.modes, size=args.size, orbit=args.orbit, status=_status)
    print_table(f"frames of the default scene, {args.size}^2 pixels ({gl.describe(gl.get_context())})", summary,
                first=("mode", "glsldiff render first frame s", "unchanged ms", "camera ms", "light to 0.5 % s"),
                rest=f"all in {args.out}/frames_summary.csv")
    print("first frame: a fresh renderer after another filled the disk caches (set-up: grid from the cache, render "
          "mesh, surface map; the interactive renderer's also builds the GPU multigrid); unchanged / camera: median "
          "(and fastest) frame with nothing changed / with the eye "
          f"turned {args.orbit} times by 5 degrees about the target; light to 0.5 %: seconds from the light's change "
          "to the first frame within 0.5 % (rel. L2) of a fresh render of the new light to 1e-7, pass 2 "
          "frame-coherent; viewer: closed-form single scattering; render: the 3-D march (glsldiff render).")
    paths = save_frames_study(summary, frames, out)
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def cmd_bench_sphere(args: argparse.Namespace) -> int:
    rows = sphere_study(ns=args.n, radius=args.radius, cube_size=args.cube_size, glsl=not args.no_glsl,
                        out=check_output_folder(args.out), cube_sizes=args.cube_sizes, n_fixed=args.n_fixed,
                        repeats=args.repeat)
    print_table(f"polygrid sphere R = {args.radius} mm vs closed form (relative L2 of phi); solve times "
                f"{runs_note(args.repeat)}", rows,
                first=("series", "n", "h_mm", "err_boundary_blend", "err_interior_blend", "t_median_s",
                       "glsl_t_median_s", "glsl_vs_reference"), rest=f"all in {args.out}/sphere.csv")
    print("series n: fixed polycube, more nodes per cube; series cubes: n fixed, smaller cubes. "
          "err_*_blend: default weights (blend fallback); _axis / _none: the other fallbacks on the same "
          "nodes; reference: the converged solve each row names (SuperLU, or pyamg SA + GMRES to rtol 1e-11 "
          "above 20k nodes); glsl_vs_reference: GPU Jacobi (glsl, to glsl_tol) vs it. t_median_s / t_min_s: the "
          "reference solve, glsl_t_*: the GLSL solve, set-up included in both (assembly, factorisation or AMG "
          "set-up; texture upload, shader compilation).")
    print(f"wrote sphere.csv and sphere.png to {args.out}/")
    return 0


def cmd_bench_sphere_lights(args: argparse.Namespace) -> int:
    out = check_output_folder(args.out)
    rows = sphere_light_study(ns=args.n, polygrid_ns=args.polygrid_n, cube_size=args.cube_size,
                              cube_sizes=args.cube_sizes, n_fixed=args.n_fixed, polygrid_n_fixed=args.polygrid_n_fixed,
                              radius=args.radius, discretisations=args.discretisations, tet_edges=args.tet_edges,
                              out=out, progress=_status, repeats=args.repeat)
    cols = ("discretisation", "series", "n", "h_mm", "light", "rel_rms", "rel_max", "t_median_s", "t_min_s", "solver",
            "cube_mm", "edge_mm", "nodes", "inverted", "adapt_s")
    print_table(f"sphere R = {args.radius} mm under lights: exitant bracket B vs the exact series; solve times "
                f"{runs_note(args.repeat)}", [{k: r[k] for k in cols} for r in rows],
                rest=f"all in {out}/sphere_lights.csv")
    print("rel_rms = ||B - B_series|| / ||B_series||, rel_max = max |B - B_series| / max |B_series| over the "
          "surface (fem) or boundary (paper, conservative) nodes; converged discrete solves (solver: SuperLU, or "
          "pyamg to the rtol it names on large grids), so discretisation error only. series n: fixed polycube, "
          "more nodes per cube; series cubes: n fixed, smaller cubes. t_median_s / t_min_s: the solve, its "
          "set-up (assembly, factorisation or AMG set-up, fem-adapt's refinement) included.")
    print(f"wrote sphere_lights.csv and sphere_lights.png to {out}/")
    return 0


def cmd_bench_meshes(args: argparse.Namespace) -> int:
    out = check_output_folder(args.out)
    rows = mesh_bench(args.meshes, args.cubes, args.n, out, args.size, refined=not args.no_refined,
                      progress=_status)
    print_table("tetrahedral polygrid on meshes (fem discretisation; coverage in lattice spacings h; render "
                "seconds: 1 run)", [{k: v for k, v in r.items() if k != "fine_reason"} for r in rows],
                first=("mesh", "n", "nodes", "front_s", "glsl_vs_oracle", "oracle", "front_status"),
                rest=f"all in {out}/meshes.csv")
    print("glsl_vs_oracle: the GLSL solve (to the scene's tol, glsl_tol, Jacobi-scaled) against the oracle's solve "
          "of the same system (oracle: SuperLU, or pyamg to the rtol it names), over the largest fluence.")
    for r in rows:
        if r.get("fine_reason"):
            print(f"{r['mesh']}, n = {r['n']}: cubes of {r['cube_nodes']} nodes per edge, since with cubes of "
                  f"n nodes {r['fine_reason']}")
    print(f"wrote meshes.csv, meshes.png and the renders to {out}/")
    return 0


def cmd_bench_convergence(args: argparse.Namespace) -> int:
    summary, _, extra = convergence_bench(args.models, check_output_folder(args.out), target=args.target, hole_n=args.hole_n,
                                          bunny_n=args.bunny_n, maxiter=args.max_sweeps, repeats=args.repeat)
    print_table(f"time to error {args.target:g} (figure 15), {runs_note(args.repeat)}", summary,
                first=("model", "method", "t_median_s", "t_min_s", "seconds_to_target", "setup_s"),
                rest=f"all in {args.out}/convergence_summary.csv")
    print("error = sum (L-L0)^2 / sum L0^2 over the boundary nodes, L0 = the peer's converged solve. t_median_s / "
          f"t_min_s: median / fastest of {args.repeat} run(s), set-up included for every method: schemes = setup_s "
          "(hierarchy build, solver construction, shader compilation) + seconds_to_target (GPU time of sweeps and "
          "transfer passes; read-backs and residual checks out); peer = its whole solve (assembly, factorisation or "
          "AMG set-up), to its own convergence. tol: Jacobi-scaled residual; rtol: relative residual passed to "
          "pyamg.")
    print_table("adaptive depth search, frame coherence, precision modes (1 run each; seconds: GPU time)", extra,
                first=("model", "what", "error", "final_error", f"seconds_to_{args.target:g}"),
                rest=f"all in {args.out}/convergence_extra.csv")
    print(f"wrote convergence_summary.csv, convergence_curves.csv, convergence_extra.csv and "
          f"convergence.png to {args.out}/")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    for backend in ("egl", "osmesa"):
        try:
            ctx = gl.create_context(backend)
            print(f"{backend}: {gl.describe(ctx)}; max texture {ctx.info['GL_MAX_TEXTURE_SIZE']}")
            ctx.release()
        except GlsldiffError as exc:
            print(f"{backend}: unavailable ({exc})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = A.CommandParser(prog="glsldiff", description=__doc__)
    sub = parser.add_subparsers(dest="command")

    p = sub.add_parser("demo", help="back-lit marble slab, 4x4 projector regions (GLSL vs scipy on a regular grid)")
    p.add_argument("--size", type=A.integer(3, 4096), nargs=3, default=(64, 64, 12), metavar=("NX", "NY", "NZ"),
                   help="nodes per axis of the slab (default 64 64 12)")
    p.add_argument("--h", type=A.positive, default=0.5, help="node spacing, mm")
    p.add_argument("--tol", type=A.positive, default=5e-7, help="Jacobi residual tolerance")
    p.add_argument("--precision", choices=("fp32", "fp16"), default="fp32", help="float format of the GPU buffers")
    p.add_argument("--seed", type=A.seed, default=0, help="random seed of the veined marble")
    p.add_argument("--out", default="glsldiff-out", help="output folder (EXR images, contact sheet, report.csv)")
    p.add_argument("--quiet", action="store_true", help="no progress line per image")
    _add_gl(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("render", help="render a TOML scene (default: the bunny in veined marble) to OpenEXR + PNG")
    p.add_argument("scene", nargs="?", help="scene file (TOML, see glsldiff.render.scene); none = the built-in default")
    p.add_argument("-o", "--out", default="render.exr", help="output .exr (a tone-mapped .png goes beside it)")
    p.add_argument("--example", metavar="NAME", help=f"render a shipped example scene ({', '.join(example_names())})")
    p.add_argument("--allow-unconverged", action="store_true",
                   help="write the image even when pass 2 runs out of iterations (default: exit 2)")
    p.add_argument("--frames", type=A.integer(1, 10000), default=1, help="render the scene this many times (frame 2+ reuse passes)")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="print the full report (passes, grid, lights, regime); it is always in the .json beside the image")
    p.add_argument("--check-grid", action="store_true",
                   help="also solve the frame on the grid's 1:8 refinement and print how far apart they are "
                        "(tetrahedral grids; ~8x the grid's memory, about a minute for the default scene)")
    _add_gl(p)
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("validate", help="render validation scenes with diffusion and with Mitsuba 3 "
                                        "(pip install glsldiff[validation]); relative RMSE and times")
    p.add_argument("--cases", nargs="+", default=["default"],
                   help="validation cases (glsldiff.validation.validate.CASES) or groups: default (slab, sphere, "
                   "veins, environment spheres), albedo (the front-lit sphere at albedo 0.3-0.99), backlit (slabs of "
                   "2, 4, 8 mean free paths under a touching patch), rgb (skin, ketchup), localized, all")
    p.add_argument("--size", type=A.integer(8, 8192), default=64, help="image side, pixels")
    p.add_argument("--spp", type=A.integer(8), default=256, help="Monte Carlo samples per pixel (a power of two >= 8: "
                   "split into 2-4 renders of 4^k samples, all Mitsuba's low-discrepancy sampler takes)")
    p.add_argument("--model", choices=MODELS, default=None,
                   help="[options].model of every case (default: the scene default, split, but where a case sets it)")
    p.add_argument("--source", choices=("auto",) + SOURCES, default=None,
                   help="[options].source of every case (default: each case's own, mostly the scene default)")
    p.add_argument("--adapt", action=argparse.BooleanOptionalAction, default=None,
                   help="refine the tetrahedra under the light's sharp edges in every case ([polygrid] adapt = true), "
                   "or in none (--no-adapt); default: each case's own (\"auto\": under the spot)")
    p.add_argument("--flux", choices=FLUXES, default=None,
                   help="[options].flux of every case (default smoothed: the exitant bracket's source and fluence "
                   "smoothed along the surface over 1/2 and 1/8 mean free path; boundary: the local ones)")
    p.add_argument("--incidence", choices=INCIDENCE, default=None,
                   help="[options].incidence of every case (default local: the light reflected near where it entered "
                   "follows the half-space's transport per incidence; transport: the load too; marshak: the same "
                   "surface source whatever the incidence)")
    p.add_argument("--out", default="bench-out/validation", help="output folder (CSV, panels, cached Monte Carlo images)")
    _add_gl(p)
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("bench", help="benchmarks")
    bsub = p.add_subparsers(dest="bench", required=True)
    b = bsub.add_parser("forward", help="GLSL Jacobi vs numpy Jacobi vs scipy direct / pyamg, 1e4..1e6 nodes")
    b.add_argument("--sizes", nargs="*", default=["32x32x10", "80x80x16", "200x200x25"],
                   help="grids as NXxNYxNZ (none: skip the slabs, e.g. with --throughput)")
    b.add_argument("--throughput", action="store_true",
                   help="also: sweep throughput of the bunny polygrids against a regular grid of the same node "
                        "count, with both packings (primitives, texels), to throughput.csv")
    b.add_argument("--seconds", type=A.positive, default=20.0, help="time budget per iterative run")
    b.add_argument("--max-direct-nodes", type=A.integer(0), default=200_000,
                   help="largest grid for the scipy direct (SuperLU) solve; above it the "
                        "pyamg solution is the reference")
    b.add_argument("--precision", nargs="+", default=["fp32", "fp16"], choices=("fp32", "fp16"),
                   help="float formats of the GLSL Jacobi runs")
    b.add_argument("--schemes", nargs="*", default=[], choices=("hierarchical", "multigrid", "single"),
                   help="also solve with these multiresolution schedules on the grid's hierarchy (every "
                        "axis needs an odd node count, e.g. 161x161x33), to --tol")
    b.add_argument("--levels", type=A.integer(1, 12), default=4, help="levels of the --schemes hierarchy (at most)")
    b.add_argument("--tol", type=A.positive, default=1e-6,
                   help="--schemes: Jacobi-scaled residual to solve to")
    _add_repeat(b, 3)
    b.add_argument("--out", default="bench-out", help="output folder (CSV + PNG)")
    _add_gl(b)
    b.set_defaults(func=cmd_bench)

    p = sub.add_parser("tet", help="TransCut: tetrahedral mesh of a closed mesh (fTetWild, pip install glsldiff[tet]), "
                                   "its quality, and the DE matrix solved by CG, TransCut's hierarchy and pyamg "
                                   "(error against time)")
    p.add_argument("mesh", help="mesh file (OBJ/PLY/STL/OFF), a built-in sample (bunny, cow, bone) or sphere")
    p.add_argument("--edge", type=A.positive, default=2.5, help="target tetrahedron edge length, mm")
    p.add_argument("--size-mm", type=A.number(MIN_SIZE_MM, MAX_SIZE_MM), default=100.0,
                   help="scale the mesh to this longest extent, mm (default %(default)s)")
    p.add_argument("--component", choices=("error", "largest"), default="error",
                   help="meshes with several components: refuse, or keep the largest")
    p.add_argument("--sigma-a", type=A.number(0.0, 1e4), default=0.0021, help="absorption, mm^-1 (marble)")
    p.add_argument("--sigma-s", type=A.number(0.0, 1e4), default=2.19, help="reduced scattering, mm^-1 (marble)")
    p.add_argument("--eta", type=A.number(1.0, 2.0), default=1.3, help="relative refractive index")
    p.add_argument("--light", type=float, nargs=3, default=[0.0, 0.0, 1.0], help="direction towards the light")
    p.add_argument("--tol", type=A.positive, default=1e-8, help="relative residual of the iterative solves")
    p.add_argument("--refine", type=A.integer(0, 2), default=0,
                   help="1:8-subdivide the mesh this many times (8x the tetrahedra each; for timing at scale)")
    p.add_argument("--levels", type=A.integer(1, 8), default=4, help="levels of TransCut's hierarchy, the fine one "
                   "included (default %(default)s)")
    p.add_argument("--coarse-tol", type=A.positive, default=0.1,
                   help="relative residual of the coarse levels' BiCG (default %(default)s)")
    _add_repeat(p, 3)
    p.add_argument("--render", metavar="OUT.exr", help="also render the mesh (unrefined) with the default scene's "
                   "light and veined marble through pass 3 (a .png goes beside it)")
    p.add_argument("--out", default="tet-out", help="output folder (CSV, error-against-time plot)")
    p.set_defaults(func=cmd_tet)

    p = sub.add_parser("cut", help="TransCut: cut a scene's fTetWild mesh by a plane or a screen stroke, render "
                                   "it and time the update (cut, matrix, hierarchy, re-solve)")
    p.add_argument("scene", nargs="?", help="scene TOML (default: the built-in scene)")
    p.add_argument("--plane", type=float, nargs=4, metavar=("NX", "NY", "NZ", "D"),
                   help="remove the side n . x > D (mm, the scaled mesh's coordinates)")
    p.add_argument("--stroke", type=_stroke_point, nargs="+", metavar="U,V",
                   help="a stroke in output pixels (u right, v down) extruded along the view; removes its left")
    # a point with a negative first coordinate ("-500,-500") is a value, not an option (argparse
    # only knows plain negative numbers)
    p._negative_number_matcher = re.compile(r"^-\d+$|^-\d*\.\d+$|^-?[\d.]+(e[-+]?\d+)?,")
    p.add_argument("--iterations", type=A.integer(0, 10_000), default=40,
                   help="relaxation iterations towards the cut (default %(default)s)")
    p.add_argument("--edge", type=A.positive, help="target tetrahedron edge, mm (default: the scene's, or size / 40)")
    p.add_argument("-o", "--out", required=True, help="output .exr (a tone-mapped .png is written beside it)")
    p.add_argument("--no-timing", action="store_true", help="skip the CPU timing of the update")
    p.add_argument("--allow-unconverged", action="store_true", help="write the image even if pass 2 did not converge")
    _add_gl(p)
    p.set_defaults(func=cmd_cut)

    p = sub.add_parser("polygrid", help="build a polygrid from a closed mesh and print its statistics")
    p.add_argument("mesh", help="mesh file (OBJ/PLY/STL/OFF) or a built-in sample: bunny, cow, bone")
    p.add_argument("--n", type=A.integer(2, 256), default=16, help="nodes per cube edge (paper: 16 for the bunny)")
    p.add_argument("--cubes", type=A.integer(1), default=253, help="target number of cubes (paper's bunny: 253)")
    p.add_argument("--cube-size", type=A.positive, default=None, help="cube edge in mm (overrides --cubes)")
    p.add_argument("--size-mm", type=A.number(MIN_SIZE_MM, MAX_SIZE_MM), default=100.0, help="scale the mesh to this longest extent, mm (default %(default)s)")
    p.add_argument("--threshold", type=A.number(0.0, 1.0, lo_open=True), default=0.5, help="inside-volume fraction a cube needs")
    p.add_argument("--component", choices=("error", "largest"), default="error",
                   help="meshes with several components: refuse, or keep the largest")
    p.add_argument("--fallback", choices=("blend", "axis", "none"), default="blend",
                   help="treatment of nodes with negative or ill-conditioned appendix-B weights")
    p.add_argument("--variance-iterations", type=A.integer(0), default=100,
                   help="L-BFGS iterations of the link-length variance minimisation")
    p.add_argument("--solve", action="store_true", help="also solve a lit marble problem: GLSL vs scipy")
    p.add_argument("--tol", type=A.positive, default=5e-7, help="Jacobi residual tolerance for --solve")
    p.add_argument("--no-png", action="store_true", help="skip the figure")
    p.add_argument("--out", default="polygrid-out", help="output folder (statistics, polygrid.png)")
    _add_gl(p)
    p.set_defaults(func=cmd_polygrid)

    b = bsub.add_parser("edit", help="interactive editing (section 5.4): frame rate while painting, time from an "
                                     "edit to a converged (0.5 %%) image, cold re-solve as the peer; Table III beside")
    b.add_argument("--models", nargs="+", default=list(EDIT_MODELS), choices=EDIT_MODELS, help="models to run")
    b.add_argument("--dabs", type=A.integer(1, 1000), default=8, help="brush dabs in the stroke (one frame each)")
    b.add_argument("--frame-sweeps", type=A.integer(1, 100000), default=10, help="pass-2 sweeps per frame")
    b.add_argument("--size", type=A.integer(16, 8192), default=512, help="image width = height, pixels")
    _add_repeat(b, 1)
    b.add_argument("--out", default="bench-out", help="output folder (CSV + PNG)")
    _add_gl(b)
    b.set_defaults(func=cmd_bench_edit)

    b = bsub.add_parser("frames", help="frames of the default scene: nothing, the camera or a light changed, in the "
                                       "viewer's mode and in glsldiff render's (the 3-D march); time to 0.5 %%")
    b.add_argument("--modes", nargs="+", default=list(FRAME_MODES), choices=FRAME_MODES, help="modes to run")
    b.add_argument("--orbit", type=A.integer(1, 360), default=6, help="camera frames (5 degrees each)")
    b.add_argument("--size", type=A.integer(16, 8192), default=512, help="image width = height, pixels")
    b.add_argument("--out", default="bench-out", help="output folder (CSV + PNG)")
    _add_gl(b)
    b.set_defaults(func=cmd_bench_frames)

    b = bsub.add_parser("sphere", help="polygrid sphere vs the closed form, grid refinement")
    b.add_argument("--n", type=A.integer(2, 64), nargs="+", default=[4, 6, 8, 12], help="nodes per cube edge")
    b.add_argument("--radius", type=A.positive, default=10.0, help="sphere radius, mm")
    b.add_argument("--cube-size", type=A.positive, default=5.0, help="polycube cube edge of series n, mm")
    b.add_argument("--cube-sizes", type=A.positive, nargs="*", default=[5.0, 2.5, 1.667, 1.25],
                   help="cube edges of series cubes (n fixed), mm")
    b.add_argument("--n-fixed", type=A.integer(2, 64), default=4, help="nodes per cube edge of series cubes")
    b.add_argument("--no-glsl", action="store_true", help="skip the GLSL solve (direct solves only)")
    _add_repeat(b, 1)
    b.add_argument("--out", default="bench-out", help="output folder (CSV + PNG)")
    _add_gl(b)
    b.set_defaults(func=cmd_bench_sphere)

    b = bsub.add_parser("sphere-lights", help="sphere under directional lights and a spot vs the exact series: "
                                               "fem (tetrahedra) and the lattice stencils, both refinements")
    b.add_argument("--n", type=A.integer(2, 64), nargs="+", default=[2, 4, 8], help="fem nodes per cube edge")
    b.add_argument("--polygrid-n", type=A.integer(2, 64), nargs="+", default=[4, 6, 8],
                   help="lattice-stencil nodes per cube edge")
    b.add_argument("--cube-size", type=A.positive, default=5.0, help="cube edge of series n, mm")
    b.add_argument("--cube-sizes", type=A.positive, nargs="*", default=[5.0, 3.333, 2.5],
                   help="cube edges of series cubes, mm")
    b.add_argument("--n-fixed", type=A.integer(2, 64), default=2, help="fem nodes per cube edge of series cubes")
    b.add_argument("--polygrid-n-fixed", type=A.integer(2, 64), default=4,
                   help="lattice-stencil nodes per cube edge of series cubes")
    b.add_argument("--radius", type=A.positive, default=10.0, help="sphere radius, mm")
    b.add_argument("--discretisations", nargs="+", default=list(SPHERE_DISCRETISATIONS),
                   choices=SPHERE_ALL_DISCRETISATIONS,
                   help="tetwild (fTetWild meshes, pip install glsldiff[tet]) runs only when named")
    b.add_argument("--tet-edges", type=A.positive, nargs="+", default=[2.5, 1.67, 1.25],
                   help="target edge lengths of the tetwild series, mm")
    _add_repeat(b, 1)
    b.add_argument("--out", default="bench-out", help="output folder (CSV + PNG)")
    b.set_defaults(func=cmd_bench_sphere_lights)

    b = bsub.add_parser("meshes", help="tetrahedral polygrid on sample and generated meshes: quality, coverage, "
                                        "front- and back-lit renders")
    b.add_argument("--meshes", nargs="+", default=list(BENCH_MESHES), choices=BENCH_MESHES, help="meshes to run")
    b.add_argument("--cubes", type=A.integer(1), nargs="+", default=None,
                   help="target cube counts (default: the scene default's for --n)")
    b.add_argument("--n", type=A.integer(2, 16), nargs="+", default=[2],
                   help="nodes per cube edge (several: one row each; cubes of 2 nodes are used where "
                        "larger ones cannot carry the mesh)")
    b.add_argument("--size", type=A.integer(16, 2048), default=256, help="render side, px")
    b.add_argument("--no-refined", action="store_true",
                   help="skip the comparison with each grid's 1:8 refinement (about 8x the grid's memory, "
                        "a minute per default grid)")
    b.add_argument("--out", default="bench-out", help="output folder (CSV + PNG)")
    _add_gl(b)
    b.set_defaults(func=cmd_bench_meshes)

    b = bsub.add_parser("convergence", help="figure 15: single, hierarchical, adaptive, multigrid vs scipy, "
                                             "error against work and time")
    b.add_argument("--models", nargs="+", default=["hole", "bunny"], choices=("hole", "bunny"), help="models to run")
    b.add_argument("--target", type=A.positive, default=0.005, help="figure-15 error to reach")
    b.add_argument("--hole-n", type=A.integer(4, 64), default=12, help="nodes per cube edge of the hole model (paper: 12)")
    b.add_argument("--bunny-n", type=A.integer(4, 64), default=8,
                   help="nodes per cube edge of the bunny (paper: 16; 8 keeps the CPU-only run short)")
    b.add_argument("--max-sweeps", type=A.integer(1), default=20000, help="sweep budget per solve")
    _add_repeat(b, 1)
    b.add_argument("--out", default="bench-out", help="output folder (CSV + PNG)")
    _add_gl(b)
    b.set_defaults(func=cmd_bench_convergence)

    add_parsers(sub, bsub)
    add_capture_parser(sub)
    add_edit_parser(sub)
    add_view_parser(sub)

    p = sub.add_parser("info", help="report the available GL backends and renderers")
    p.set_defaults(func=cmd_info)
    return parser


class _Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``), handled as Ctrl-C is: the clean-up runs, then exit 143."""


def _terminate(signum: int, frame: Any) -> None:
    raise _Terminated


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    on_main = threading.current_thread() is threading.main_thread()
    old_term = signal.signal(signal.SIGTERM, _terminate) if on_main else None
    try:
        args = parser.parse_args(argv)
        if not getattr(args, "command", None):  # bare `glsldiff`: say what it can do, start nothing
            parser.print_help()
            return 0
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
        if getattr(args, "gl", None):
            os.environ["GLSLDIFF_GL"] = args.gl
        env_gl = os.environ.get("GLSLDIFF_GL", "").strip().lower()
        if env_gl and env_gl not in gl.BACKENDS:     # before any work, for every command (info included)
            raise InputError(f"GLSLDIFF_GL={os.environ['GLSLDIFF_GL']!r} is not a GL backend: set it to "
                             f"{', '.join(gl.BACKENDS)} or unset it")
        quiet_ok = args.command in ("view", "info")    # a window waits for the user; info is instant
        with created_folders_removed_on_failure(), (contextlib.nullcontext() if quiet_ok else Heartbeat()):
            return args.func(args)
    except GlsldiffError as exc:   # one line, also where a library's text inside it spans several
        print(f"glsldiff: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        code = 143 if isinstance(exc, _Terminated) else 130
        print(f"glsldiff: {'terminated' if code == 143 else 'interrupted'}; finished output files are kept, none is "
              "half-written", file=sys.stderr)
        if interrupt.abandoned():    # compiled code still running in a worker thread: end now, streams flushed
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
        return code
    finally:
        if on_main:
            signal.signal(signal.SIGTERM, old_term)


def entry() -> None:
    """The ``glsldiff`` program: :func:`main`, then the exit. After Ctrl-C or SIGTERM the process
    ends at once, its streams flushed (``os._exit``), once :func:`main` has cleaned up: the signal
    can land inside compiled code (NLopt's SWIG callback, SuperLU, GL), and the interpreter's own
    shutdown after such an interrupt failed about one run in twenty while flushing stdout
    ("TypeError: an integer is required", exit 120 instead of 130)."""
    code = main()
    if code in (130, 143):
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):   # a closed pipe (``glsldiff ... | head``): nothing to keep
                pass
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    entry()
