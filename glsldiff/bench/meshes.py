"""``glsldiff bench meshes``: the tetrahedral polygrid on meshes nobody tuned it for.

For each mesh (the pymeshlab samples bunny, cow, bone, airplane; a torus; a 100 x 100 x 2 mm
tile; a 100 mm cube; the public meshes of :mod:`glsldiff.bench.public_meshes`, CGAL's hand,
camel, elk, triceratops, fandisk and couplingdown; all 100 mm long), each n asked for and each target cube count (default:
the scene default's for that n): the cubes actually used (``cube_nodes`` nodes per edge:
:data:`glsldiff.grids.tetrahedral.fem_grid.FINE_CUBE_NODES` where cubes of n nodes cannot carry the
mesh, ``fine_reason`` says why; ``retries`` the rebuilds with other cube sizes,
``size_factor`` the kept one's size over the first's; see
:func:`glsldiff.grids.tetrahedral.fem_grid.build_fem_grid`), the grid's node count, inverted and worst
tetrahedra (quality 1 = regular, <= 0 inverted), coverage (largest and 99th-percentile
distance from a mesh vertex to its nearest surface node, in lattice spacings h), the pass-2
solve (sweeps, status) and the render time, with a front-lit and a back-lit render of each
(veined marble, 256 x 256, the automatic camera) saved as PNG beside ``meshes.csv`` and
on one labelled contact sheet, ``meshes.png``, a row per mesh. Where the default grid found no
polycube and the renderer fell back to the lattice, ``grid`` says so. The grids are measured as built: ``[polygrid] adapt = false`` (no refinement
under the lights' sharp edges, :mod:`glsldiff.grids.tetrahedral.adapt`), so both lights share one grid.

Against the oracle, on the front-lit frame: the GLSL solve's largest surface-fluence
difference from the CPU solve of the same system (:func:`glsldiff.oracle.fem.solve_system_direct`:
SuperLU, or pyamg SA + CG above 20k unknowns; ``oracle`` names which, ``oracle_rtol`` its
tolerance), relative to the largest fluence (``glsl_vs_oracle``; the GPU stops at the scene's
``tol``, ``glsl_tol``, a Jacobi-scaled residual);
the node pairs with a positive off-diagonal entry (``positive_couplings``, red channel: the
discrete maximum principle does not hold there) and the nodes whose exact discrete fluence
is negative in any channel (``negative_nodes``).

Against the converged answer (``refined=True``): the same problem solved on the grid's 1:8
refinement (:class:`glsldiff.oracle.refined.RefinedComparison`, green channel, both lights
on one refined system): ``<light>_vs_refined`` the relative RMS of the exitant bracket ``B``
at the surface nodes, ``<light>_vs_refined_max`` its largest difference over the largest
``|B|``, ``back_negative`` / ``back_negative_refined`` the back-lit surface nodes of negative
fluence on the grid and on its refinement, ``refined_nodes`` and ``refined_s`` (set-up and
both solves). About 8x the grid's memory; roughly a minute for the default bunny grid.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from glsldiff.bench.peers import fem_reference_label
from glsldiff.bench.public_meshes import PUBLIC_MESHES, public_mesh
from glsldiff.core import io
from glsldiff.core.errors import GlsldiffError
from glsldiff.mesh import Mesh, box_mesh, cached_load_mesh, torus_mesh
from glsldiff.oracle.fem import positive_couplings, solve_system_direct
from glsldiff.oracle.refined import RefinedComparison
from glsldiff.render.output import save
from glsldiff.render.camera import Framing, frame_camera
from glsldiff.render.renderer import Renderer
from glsldiff.render.scene import default_cubes, parse_scene

MESHES = ("bunny", "cow", "bone", "airplane", "torus", "tile", "cube", *PUBLIC_MESHES)
_GENERATED: dict[str, Callable[[], Mesh]] = {
    "torus": lambda: torus_mesh(35.0, 15.0),
    "tile": lambda: box_mesh((100.0, 100.0, 2.0), origin=(-50.0, -50.0, -1.0)),
    "cube": lambda: box_mesh((100.0, 100.0, 100.0), origin=(-50.0, -50.0, -50.0)),
}
LIGHTS = {"front": (0.3, 0.5, 1.0), "back": (-0.2, 0.3, -1.0)}   # towards the light, in the camera's frame


def _lights_for(framing: Framing, scene: Any) -> dict[str, list[float]]:
    """:data:`LIGHTS` turned into the frame of the automatic camera on ``framing`` (x right, y
    up, z towards the eye): front-lit from the camera's upper right, back-lit from behind."""
    eye, target, up = frame_camera(scene, framing)
    z = (eye - target) / np.linalg.norm(eye - target)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return {k: [float(c) for c in np.asarray(v) @ np.stack([x, y, z])] for k, v in LIGHTS.items()}


def _source(name: str, out: Path) -> str:
    if name in PUBLIC_MESHES:
        return str(public_mesh(name))
    if name not in _GENERATED:
        return name
    m = _GENERATED[name]()
    path = out / f"{name}.obj"
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in m.vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces]
    with io.atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
    return str(path)


def _against_oracle(r: Renderer) -> dict[str, object]:
    """The oracle columns (module docstring) of the renderer's last frame."""
    s = r.fem_system
    if s is None:
        return {}
    x = solve_system_direct(s).reshape(3, s.n).T
    exact = r.surface_values(x)
    scale = float(np.abs(exact).max()) or 1.0
    label, rtol = fem_reference_label(s.n)
    return {"oracle": label, "oracle_rtol": rtol,
            "glsl_vs_oracle": float(np.abs(r.surface_fluence - exact).max()) / scale,
            "positive_couplings": positive_couplings(s.block(0)[0]),
            "negative_nodes": int((x < 0).any(axis=1).sum())}


def _against_refined(r: Renderer, scene: Any, sources: dict[str, np.ndarray]) -> dict[str, object]:
    """The refined-grid columns (module docstring) for the frames' boundary ``sources`` by light
    (none with the first-collision volume source, whose load the comparison does not carry)."""
    if scene.options.source == "volume":
        return {}
    t0 = time.perf_counter()
    rc = RefinedComparison(r.fem_problem(scene))
    errors = dict(zip(sources, rc.compare(list(sources.values()))))
    row: dict[str, object] = {"refined_nodes": rc.nodes[1]}
    for light, e in errors.items():
        row[f"{light}_vs_refined"], row[f"{light}_vs_refined_max"] = e.rel_rms, e.rel_max
        if light == "back":
            row["back_negative"], row["back_negative_refined"] = e.negative_surface, e.negative_surface_refined
    row["refined_s"] = time.perf_counter() - t0
    return row


def mesh_bench(meshes: Sequence[str] = MESHES, cubes: Sequence[int] | None = None, ns: Sequence[int] = (2,),
               out: Path = Path("bench-out"), size: int = 256, refined: bool = True,
               progress: Callable[[str], None] | None = None) -> list[dict[str, object]]:
    """The table (module docstring); renders and ``meshes.csv`` go to ``out``, one row per
    mesh, n (nodes per cube edge asked for) and cube count. ``cubes`` defaults to the scene
    default's count for each n (:func:`glsldiff.render.scene.default_cubes`); ``refined``:
    also compare each grid's solves with its 1:8 refinement's."""
    out.mkdir(parents=True, exist_ok=True)
    rows: list[dict[str, object]] = []
    tiles: dict[str, list[np.ndarray]] = {}
    runs = [(n, k) for n in ns for k in ([default_cubes("fem", n)] if cubes is None else cubes)]
    with Renderer(allow_unconverged=True) as r:
        for name in meshes:
            src = _source(name, out)
            framing = Framing.of_mesh(cached_load_mesh(src, size_mm=100.0))
            for n, k in runs:
                row: dict[str, object] = {"mesh": name, "cubes_target": k, "n": n, "grid": "tetrahedral"}
                sources: dict[str, np.ndarray] = {}
                spec = {"mesh": {"source": src, "size_mm": 100.0},
                        "polygrid": {"n": n, "cubes": k, "discretisation": "fem", "levels": 1,
                                     "adapt": False},   # one grid for both lights
                        "material": {"preset": "marble", "procedural": "veins"},
                        "output": {"width": size, "height": size}}

                def lit(d: Sequence[float]) -> Any:
                    return parse_scene({**spec, "lights": [{"type": "directional", "direction": list(d)}]},
                                       f"<bench {name}>", out)
                lights = _lights_for(framing, lit(LIGHTS["front"]))
                for light in LIGHTS:
                    if progress:
                        progress(f"meshes: {name}, n = {n}, {k} cubes, {light}-lit")
                    scene = lit(lights[light])
                    t0 = time.perf_counter()
                    try:
                        img, rep = r.render(scene)
                    except GlsldiffError as exc:
                        row[f"{light}_error"] = str(exc)[:120]
                        continue
                    row[f"{light}_s"] = time.perf_counter() - t0
                    row[f"{light}_sweeps"] = rep.solver.sweeps
                    row[f"{light}_status"] = rep.solver.status
                    row[f"{light}_clamped"] = rep.clamped_vertices
                    row[f"{light}_below_1pct"] = rep.clamped_deep
                    if any(w.startswith("no tetrahedral polygrid") for w in rep.warnings):
                        row["grid"] = "lattice (no tetrahedral polycube)"
                    elif light == "front":
                        row["glsl_tol"] = scene.options.tol
                        row.update(_against_oracle(r))
                    if row["grid"] == "tetrahedral":
                        sources[light] = r.boundary_source.copy()
                    _, _, exposure = save(img, out / f"{name}_n{n}_{k}_{light}.exr", scene, rep)
                    tiles.setdefault(f"{name}_n{n}_{k}", []).append(io.tonemap(img, exposure))
                if refined and sources:
                    if progress:
                        progress(f"meshes: {name}, n = {n}, {k} cubes, against the 1:8 refined grid")
                    row.update(_against_refined(r, scene, sources))
                g = r.polygrid if ("front_s" in row or "back_s" in row) and row["grid"] == "tetrahedral" else None
                if g is not None:
                    q = g.quality
                    row.update({"cubes": len(g.polycube.cubes), "cube_nodes": g.complex.lattice.n, "h_mm": g.h,
                                "nodes": g.n_active,
                                "inverted": q.inverted, "worst_quality": q.worst_quality, "split_edges": q.split_edges,
                                "coverage_max_h": q.coverage_max, "coverage_p99_h": q.coverage_p99,
                                "mapping_s": q.seconds.get("total", float("nan")),
                                "retries": q.retries, "size_factor": q.size_factor, "fine_reason": q.fine_reason})
                elif "front_s" in row or "back_s" in row:
                    row["nodes"] = r.polygrid.n_active
                rows.append(row)
    io.write_csv(out / "meshes.csv", rows)
    full = [_label(np.concatenate(t, axis=1), name) for name, t in tiles.items() if len(t) == len(LIGHTS)]
    if full:
        io.write_png(out / "meshes.png", np.concatenate(full, axis=0))
    return rows


def _label(row: np.ndarray, text: str) -> np.ndarray:
    """A contact sheet's row (front | back, 8-bit RGB) with its name and the lights written on it."""
    import cv2
    out = np.ascontiguousarray(row)
    w = out.shape[1] // len(LIGHTS)
    for i, light in enumerate(LIGHTS):
        cv2.putText(out, f"{text}: {light}-lit" if i == 0 else f"{light}-lit", (i * w + 6, 18),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 0), 1, cv2.LINE_AA)
    return out

