"""Three-pass rendering of a scene (Wang et al. 2008, section 5; Table III).

Stages, in the one direction data flows (numpy arrays between them):

* **setup** (per mesh + polygrid): mesh, polygrid, hierarchy, and the sparse matrix that
  interpolates boundary-node values to the mesh vertices (inverse-distance weights of the
  4 nearest boundary nodes). Not part of t1..t3 (the paper precomputes it too).
* **material** (per material): kappa (mm), mu (mm^-1) per node (:mod:`glsldiff.render.materials`),
  and the GLSL solver that holds them as textures.
* **pass 1** (t1, per light set): transmitted irradiance ``E_t`` at the boundary nodes
  (:func:`glsldiff.render.pass1.incident_light`: shadow maps, environment light with per-node
  visibility; on tetrahedral grids every other light averaged over the surface nodes' cells),
  and the solver's source:
  with ``[options].source = "surface"`` (default) the Marshak boundary source ``q``; with
  ``"volume"`` the first-collision load of :mod:`glsldiff.render.collision` (light as reduced
  intensity below the surface, ``q = 0``; tetrahedral grids only).
* **pass 2** (t2): the polygrid diffusion solve (:class:`glsldiff.solve.multilevel.MultilevelDiffusion`;
  on tetrahedra, ``[polygrid] discretisation = "fem"`` (pillowed polycube) or ``"tetwild"`` (an
  fTetWild mesh of the surface, :mod:`glsldiff.grids.tetwild`), GPU algebraic-multigrid-preconditioned
  CG, :class:`glsldiff.solve.gather_multigrid.GlslSparseMultigrid`),
  warm-started from the previous frame's solution when only the light changed, and on a
  first frame from the converged solution of the same system cached on disk
  (:mod:`glsldiff.core.cache`) by an earlier run: the solver still checks the residual
  against ``tol`` before it stops (0 sweeps when the cached answer meets it).
* **pass 3** (t3, every frame): :func:`glsldiff.render.shading.shade`, the mesh rasterised with
  moderngl from the scene's camera (:mod:`glsldiff.render.camera`); per vertex, the
  multiple-scattering term interpolated from the boundary nodes times ``F_t(eta, n.w_o)``,
  plus Ward specular per light (per-vertex shadow visibility; a projector's image factor,
  :func:`glsldiff.physics.lights.projector_factor`, is folded into it as its channel mean, so the
  highlight takes the intensity's colour), plus optional single scattering of every light in
  reflection and transmission (:mod:`glsldiff.render.single`, ``[options].single_scattering``),
  plus the
  unscattered light of area and environment lights seen through the object
  (:mod:`glsldiff.render.unscattered`, ``[options].unscattered``, default on), plus an optional
  measured diffuse surface reflectance ``rho_d / pi * E`` (``[material].reflectance``,
  :mod:`glsldiff.inverse.reflectance`; ``E`` the incident irradiance with shadows).

Exitant radiance (``[options].exitant``): the conventions of :mod:`glsldiff.physics.exitance`.

On lit surfaces the bracket of ``p1``/``arbree`` can dip below zero where the diffusion
solution undershoots (low albedo); such vertices are clamped to 0 and counted in the report.

Skipping: every stage keeps the key of the scene parts it depends on; a stage whose key
did not change is skipped and the report says why (e.g. only the camera moved: passes 1
and 2 skipped; only a light moved: setup and material kept, pass 2 warm-started).
"""
from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any, Callable

import moderngl
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from glsldiff import gl
from glsldiff.core import cache
from glsldiff.core.errors import InputError, SolverError
from glsldiff.core.io import write_npz
from glsldiff.grids.adapt import ADAPT_TOL, refine_for_source
from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.grids.cache import cached_fem_grid, cached_polygrid
from glsldiff.grids.tetcut import cut as cut_tets, plane_side, stroke_side
from glsldiff.grids.fem_grid import FEM_MAX_NODES, SPLIT_LENGTH
from glsldiff.grids.shapes import SHAPE_TARGET
from glsldiff.grids.tetwild import cached_tetrahedralize
from glsldiff.mesh import (GENERATED_MESHES, SAMPLE_MESHES, Mesh, generated_mesh, load_mesh, screened_smoothing,
                           subdivide)
from glsldiff.physics.editing import KAPPA_MIN, Edit, EditResult, EditView, apply_edit
from glsldiff.physics.exitance import (bracket_smoothing_lengths, deep_irradiance, exitance_coefficients,
                                       exitant_bracket, halfspace_bracket, local_bracket, source_from_irradiance)
from glsldiff.physics.material import coefficients, optical_properties, regime
from glsldiff.physics.regime import regime_warnings
from glsldiff.mesh.raycast import first_hits
from glsldiff.mesh.inside import contains
from glsldiff.physics.optics import boundary_constant, moment_boundary_constant, refracted_cosine
from glsldiff.physics.lights import AreaLight, DirectLight, EnvironmentLight, ProjectorLight, projector_factor
from glsldiff.render.camera import scene_camera
from glsldiff.render.collision import first_collision_load, node_columns, surface_columns
from glsldiff.render.unscattered import sees_through, unscattered
from glsldiff.render.editing import GpuMaterialEditor, MaterialHistory
from glsldiff.render.materials import node_material, surface_reflectance
from glsldiff.render.pass1 import incident_light, visibility
from glsldiff.render.report import RenderReport
from glsldiff.render.scene import TETRAHEDRAL, Scene
from glsldiff.render.shadows import DepthRenderer
from glsldiff.render.single import single_scattering_frame
from glsldiff.render.fluence import FluenceLattice
from glsldiff.render.split_frame import SplitInputs, SplitResult, split_radiance
from glsldiff.render.tetrahedral import TetPass2, check_precision
from glsldiff.render.shading import MAX_SHADER_LIGHTS, shade, surface_interpolation, vertex_interpolation
from glsldiff.solve.multilevel import MultilevelDiffusion
from glsldiff.oracle.assembly import LinearSystem
from glsldiff.oracle.fem import tet_geometry, tet_rhs
from glsldiff.oracle.refined import RefinedComparison, RefinedError
from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.tet_problem import TetProblem
from glsldiff.system.transcut import paint_blend, paint_weights
from glsldiff.system.report import CURRENT, SolveReport


#: Largest boundary source pass 2 accepts: its float32 textures overflow near 3.4e38, and the
#: sweeps multiply sources by stencil weights (mm^-2) before they are divided back.
Q_MAX = 1e30
#: Part of every cached pass-2 solution's key: bump it when the discrete system changes.
SOLUTION_CACHE_VERSION = 2   # 2: the volume source solves with the Fresnel-moment boundary constant


# ---------------------------------------------------------------- the renderer
#: The split takes the first-collision source and gathers the collided fluence where the grid
#: resolves the transport mean free path: node spacing times sigma_t' at most this (a 1-D P1
#: solve of the half-space gathers 0.98 of the converged value at 0.5, 0.93 at 1, 0.85 at 2;
#: in 3-D, blended with the deep field, validate's cases between 0.6 and 1 score as well as or
#: better than with the surface source: slab-spot 0.041 vs 0.214, bunny-veins 0.097 vs 0.131,
#: sphere albedo 0.3 (1.08) 0.031 either way, the 60 mm slab 0.039 vs 0.038).
GATHER_MAX_H_SIGMA = 1.0
#: Surface nodes with more than this share of the largest transmitted irradiance count as lit (the
#: split's gather far field measures each node's distance to them).
LIT_SHARE = 1e-3
#: Surface nodes whose thickness the regime check measures (a ray cast each, once per grid).
THICKNESS_SAMPLES = 4000


def _key(*parts: Any) -> str:
    return repr(parts)


class Renderer:
    """Renders scenes, keeping each stage's result while its inputs stay the same.

    >>> r = Renderer()                       # doctest: +SKIP
    >>> img, rep = r.render(default_scene())  # doctest: +SKIP
    """

    def __init__(self, ctx: moderngl.Context | None = None, allow_unconverged: bool = False,
                 status: Callable[[str], None] | None = None, frame_sweeps: int | None = None,
                 cache_solutions: bool = True) -> None:
        """``allow_unconverged``: keep a pass-2 solve that ran out of iterations (the image is
        then not the converged answer) instead of raising :class:`SolverError`. ``status``
        receives a line before each step that can take seconds (the command prints them).
        ``frame_sweeps``: interactive frame coherence on the lattice (the viewer): a warm-started
        pass 2 runs at most this many sweeps per frame and the next frames go on from there
        until ``tol`` is met (:attr:`converged`); cold starts still solve to ``tol``.
        ``cache_solutions=False``: pass 2 neither reads nor writes converged solutions on disk
        (benchmarks that time cold solves; built grids are still cached)."""
        self.ctx = ctx if ctx is not None else gl.get_context()
        self.allow_unconverged = allow_unconverged
        if frame_sweeps is not None and frame_sweeps < 1:
            raise InputError(f"frame_sweeps={frame_sweeps!r} must be >= 1 (or None: solve every frame to tol)")
        self.frame_sweeps = frame_sweeps
        self.cache_solutions = cache_solutions
        self._partial = False
        self._status = status
        self._keys: dict[str, str] = {}
        self._geo: dict[str, Any] = {}
        self._solver: Any = None
        self._mat: dict[str, Any] = {}
        self._E_t: NDArray | None = None
        self._q: NDArray | None = None
        self._q_marshak: NDArray | None = None    # pass 1's load before the incidence split
        self._beams: list = []                    # pass 1's beams (E (N, 3), refracted cosine (N,))
        self._incidence: dict[str, Any] | None = None   # incidence "local"/"transport": what the local term needs
        self._incidence_used = ""                 # the report's incidence line
        self._local_key: Any = None
        self._phi_b: NDArray | None = None
        self._solve_report: Any = None
        self._from_cache = False
        self._tet: TetPass2 | None = None          # tetrahedral grids: the P1 system and solver across frames
        self._load: NDArray | None = None
        self._flux_fields: tuple[NDArray, NDArray] | None = None   # (phi, q) of the exitant bracket
        self._flux_kind: str | None = None        # the [options].flux that _flux_fields were made for
        self._smoothers: Any = None                # flux = "smoothed": (phi, q) smoothing along the surface
        self._smoother_info = ""                  # the smoothers' lengths and set-up time, for the report
        self._flux_used = ""                      # what the last frame's bracket took its flux from (report)
        self._editor: GpuMaterialEditor | None = None
        self._history = MaterialHistory()
        self._edit_version = 0
        self._surface: tuple[Any, NDArray] | None = None
        self._model_note = ""
        #: validation: shade only the split's "single" or "multiple" scattering part (None: all of it)
        self.split_part: str | None = None

    @property
    def mesh(self) -> Any:
        """The render mesh (subdivided to the node spacing), after the first frame."""
        return self._geo["render_mesh"]

    @property
    def pass2_solver(self) -> Any:
        """The pass-2 solver of the last frame (lattice: :class:`MultilevelDiffusion`; tetrahedra:
        :class:`~glsldiff.solve.gather_multigrid.GlslSparseMultigrid`; None before a solve or when a cached answer served it)."""
        return self._tet.solver if self._tet is not None else self._solver

    @property
    def converged(self) -> bool:
        """Whether the last frame's pass 2 met ``tol`` (False while ``frame_sweeps`` frames
        are still converging)."""
        return not self._partial

    @property
    def frame_vertices(self) -> NDArray[np.float64]:
        """The vertices the camera frames (the uncut mesh, mm), after the first frame."""
        return self._geo["frame"]

    @property
    def polygrid(self) -> Any:
        return self._geo["pg"]

    @property
    def fem_system(self) -> LinearSystem | None:
        """The P1 system (over the active nodes, with the last frame's source) a tetrahedral
        grid solved in pass 2; ``None`` on the lattice or before the first frame."""
        return None if self._tet is None or self._tet.p1 is None else self._tet.p1.system

    def surface_values(self, x: NDArray) -> NDArray[np.float64]:
        """``(n_surface, 3)``: per-active-node values ``(n_active, 3)`` of a tetrahedral grid
        (e.g. a solution of :attr:`fem_system`) at its surface nodes."""
        pg = self._geo["pg"]
        full = np.zeros((len(pg.positions), 3))
        full[self._fem_active] = x
        return full[pg.surface_nodes]

    @property
    def _fem_active(self) -> NDArray[np.int64]:
        assert self._tet is not None
        return self._tet.active

    @property
    def node_material(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The last frame's ``(kappa, mu)`` per node (mm, mm^-1), ``(n, 3)`` each on a tetrahedral grid."""
        return self._mat["kappa"], self._mat["mu"]

    @property
    def boundary_source(self) -> NDArray[np.float64]:
        """``(n_boundary, 3)`` the last frame's boundary source ``q`` (0 with the volume source)."""
        if self._q is None:
            raise RuntimeError("no frame rendered yet")
        return self._q

    @property
    def cut_report(self) -> Any:
        """The :class:`~glsldiff.grids.tetcut.CutReport` of a scene's ``[cut]`` (None without one)."""
        return getattr(self, "_cut_report", None)

    @property
    def surface_fluence(self) -> NDArray[np.float64]:
        """``(n_boundary, 3)`` the last frame's pass-2 fluence at the boundary nodes."""
        if self._phi_b is None:
            raise RuntimeError("no frame rendered yet")
        return self._phi_b

    # -- stages --------------------------------------------------------------------
    def _setup(self, scene: Scene) -> None:
        m, g = scene.mesh, scene.polygrid
        if m.source in GENERATED_MESHES:
            mesh = generated_mesh(m.source, m.size_mm)
        else:
            src = m.source if m.source in SAMPLE_MESHES else str(scene.resolve(m.source))
            mesh = load_mesh(src, size_mm=m.size_mm)
        fem = g.discretisation in TETRAHEDRAL
        t0 = time.perf_counter()
        if g.discretisation == "tetwild":
            what = "fTetWild tetrahedral mesh"
            self._say(f"setup: {what} of {m.source} (edge {g.edge_mm:g} mm): building it takes seconds to many "
                      "minutes the first time, then it is read from the cache")
            pg, cached = cached_tetrahedralize(mesh, float(g.edge_mm), status=self._say)
        else:
            what = "tetrahedral polygrid" if fem else "polygrid"
            self._say(f"setup: {what} of {m.source} (n = {g.n}, about {g.cubes} cubes): building it takes "
                      "seconds to minutes the first time, then it is read from the cache")
            pg, cached = (cached_fem_grid if fem else cached_polygrid)(mesh, n=g.n, n_cubes=g.cubes)
        self._say(f"setup: {what} {'read from the cache' if cached else 'built'} in "
                  f"{time.perf_counter() - t0:.1f} s ({pg.n_active:,} nodes)")
        if g.discretisation == "fem" and pg.quality.fine_reason:   # tetwild grids have no polycube
            self._say(f"setup: built from {len(pg.polycube.cubes):,} cubes of {pg.complex.lattice.n} nodes per edge at "
                      f"about the same spacing instead: with n = {g.n}, {pg.quality.fine_reason}")
        self._adapt_report = None
        if scene.refines:
            pg = self._adapt(scene, mesh, pg)
        frame = np.asarray(mesh.vertices)           # the uncut surface frames the camera
        crease, self._cut_report = None, None
        if scene.cut is not None:
            pg, mesh, crease = self._cut(scene, pg, frame)
        hier = None if fem else Hierarchy.build(pg, g.levels)   # levels = 1: the polygrid alone
        h = pg.h if fem else pg.lattice.h
        render_mesh = subdivide(mesh if crease is None else crease, h)
        v, f = np.asarray(render_mesh.vertices), np.asarray(render_mesh.faces)
        interp = (surface_interpolation(v, pg.boundary_positions, pg.surface_triangles) if fem
                  else vertex_interpolation(v, pg.boundary_positions))
        self._geo = {"mesh": mesh, "render_mesh": render_mesh, "pg": pg, "hier": hier, "vertices": v, "faces": f,
                     "normals": render_mesh.vertex_normals, "interp": interp, "fem": fem,
                     "tetgeo": tet_geometry(pg) if fem else None, "frame": frame}

    def _adapt(self, scene: Scene, mesh: Mesh, pg: Any) -> Any:
        """The fem grid refined under the lights' sharp edges (:mod:`glsldiff.grids.adapt`),
        marked by pass 1's source sampled at the surface nodes (shadows included)."""
        def source(P: NDArray, N: NDArray) -> NDArray:
            E_t, _ = incident_light(mesh, P, N, scene.lights, scene.material.eta, ctx=self.ctx)
            return source_from_irradiance(np.asarray(E_t, dtype=np.float64), scene.material.eta, scene.options.exitant)
        pg, rep = refine_for_source(pg, source, max_nodes=FEM_MAX_NODES)
        self._adapt_report = rep
        if rep.edges:
            self._say(f"setup: {rep.line()} ({pg.n_active:,} nodes)")
        return pg

    def _cut(self, scene: Scene, tm: Any, frame: NDArray) -> tuple[Any, Mesh, Mesh]:
        """TransCut's cut of the fTetWild mesh ``tm`` (``[cut]``), its report kept in
        ``self._cut_report``: the cut mesh, its boundary as a triangle mesh (shadows, ray casts)
        and as a render mesh whose cut faces have their own vertices (a crease: the cut face and
        the old surface are shaded with their own normals)."""
        c = scene.cut
        assert c is not None
        if c.plane is not None:
            side = plane_side(c.plane[:3], c.plane[3] / float(np.linalg.norm(c.plane[:3])))   # n . x > d
            what = f"plane {list(c.plane)}"
        else:
            _, mvp = scene_camera(scene, frame)
            W, H = scene.output.width, scene.output.height

            def project(X: NDArray) -> NDArray:
                clip = np.concatenate([X, np.ones((len(X), 1))], axis=1) @ mvp.T
                ndc = clip[:, :2] / clip[:, 3:4]
                return np.stack([(ndc[:, 0] + 1.0) * 0.5 * W, (1.0 - ndc[:, 1]) * 0.5 * H], axis=1)
            side = stroke_side(project, c.stroke)
            what = f"stroke of {len(c.stroke or ())} points"
        self._say(f"setup: cutting {len(tm.tets):,} tetrahedra by the {what}")
        t0 = time.perf_counter()
        cm, rep = cut_tets(tm, side, iterations=c.iterations)
        self._cut_report = rep
        self._cut_seconds = time.perf_counter() - t0
        V, F = cm.boundary_positions, cm.surface_triangles
        flat = Mesh(V, F, name=f"{scene.mesh.source} (cut)")
        cf = F[cm.cut_faces]
        used = np.unique(cf)
        F2 = np.concatenate([F[~cm.cut_faces], len(V) + np.searchsorted(used, cf)])
        keep, F2 = np.unique(F2, return_inverse=True)             # drop the copies no face uses
        return cm, flat, Mesh(np.concatenate([V, V[used]])[keep], F2.reshape(-1, 3), name=flat.name)

    def _material(self, scene: Scene) -> None:
        pg = self._geo["pg"]
        kappa, mu, info = node_material(scene, pg.positions, pg)
        for p in scene.paint:      # TransCut's paint, at the nodes (the P1 system's material lives there)
            w = paint_weights(pg.positions, p.points, p.radius_mm)
            sa, ss = optical_properties(kappa, mu)
            if p.sigma_a is not None:
                sa = paint_blend(sa, p.sigma_a, w, p.strength)
            if p.sigma_s_prime is not None:
                ss = paint_blend(ss, p.sigma_s_prime, w, p.strength)
            if np.any(sa + ss <= 0):
                raise InputError(f"{scene.source}: [[paint]]: the paint leaves sigma_a + sigma_s_prime = 0 at some "
                                 "nodes; paint positive values")
            kappa, mu = coefficients(sa, ss)
            info = {**info, "material": f"{info.get('material')} + {len(scene.paint)} paint stroke(s)"}
        shape = (len(pg.positions),) if self._geo["fem"] else pg.shape
        self._mat = {"kappa": kappa.reshape(shape + (3,)), "mu": mu.reshape(shape + (3,)), "info": info}
        self._drop_solver()
        if self._tet is not None:
            self._tet.reset()
        self._history = MaterialHistory()     # a new material starts a new edit history
        self._edited = False                  # the node material differs from the scene's (edits)

    def _drop_solver(self) -> None:
        if self._editor is not None:
            self._editor.release()
            self._editor = None
        if self._solver is not None:
            self._solver.release()
            self._solver = None
        if self._tet is not None:
            self._tet.release()

    def _effective(self, scene: Scene) -> Scene:
        """``scene`` with its options made concrete for the current grid and material: the source
        (``"auto"``: the split takes the first-collision volume source where the tetrahedral grid
        resolves the transport mean free path, ``h sigma_t' <= GATHER_MAX_H_SIGMA`` at every node
        and channel, else the Marshak surface source; diffusion: surface) and single scattering
        (``"auto"``: the split marches it in 3-D with the volume source, takes the half-space's
        closed form with the surface source; diffusion: off). A split with ``eta < 1`` (no
        half-space tables) renders with the diffusion model, and the report says so."""
        o = scene.options
        self._model_note = ""
        if o.split and scene.material.eta < 1.0:
            self._model_note = (f"model: eta = {scene.material.eta:g} < 1 has no half-space tables; rendered with "
                                "model = \"diffusion\"")
            o = replace(o, model="diffusion", source="surface" if o.source == "auto" else o.source)
        fem = bool(self._geo.get("fem"))
        if o.source == "auto":
            resolved = fem and self._h_sigma_t() <= GATHER_MAX_H_SIGMA
            o = replace(o, source="volume" if o.split and resolved else "surface")
        if o.single_scattering == "auto":      # interactive frames (the viewer) take the split's closed form
            o = replace(o, single_scattering=o.split and self.frame_sweeps is None)
        return replace(scene, options=o)

    def _h_sigma_t(self) -> float:
        """The grid's node spacing (mm) times the largest sigma_t' (mm^-1) of the node material:
        below :data:`GATHER_MAX_H_SIGMA` the grid resolves the transport mean free path."""
        pg = self._geo["pg"]
        h = pg.h if self._geo["fem"] else pg.lattice.h
        return h * float(np.max(1.0 / (3.0 * self._mat["kappa"])))

    def _pass1(self, scene: Scene) -> None:
        pg = self._geo["pg"]
        volume = scene.options.source == "volume"
        beams: list | None = [] if volume or scene.options.split or self._splits_incidence(scene) else None
        E_t, info = incident_light(self._geo["mesh"], pg.boundary_positions, pg.normals, scene.lights,
                                   scene.material.eta, ctx=self.ctx, beams=beams,
                                   triangles=pg.surface_triangles if self._geo["fem"] else None)
        self._E_t = np.asarray(E_t, dtype=np.float64)
        q = source_from_irradiance(self._E_t, scene.material.eta, scene.options.exitant)
        if not np.all(np.isfinite(q)) or q.max() > Q_MAX:
            raise InputError(f"{scene.source}: [[lights]]: the transmitted irradiance reaches "
                             f"{np.nanmax(self._E_t):.3g}, beyond what the solver's float32 textures hold "
                             f"(source <= {Q_MAX:.0e}); scale the lights' irradiance or intensity down (the "
                             "image is linear in it)")
        if not q.any():
            placed = [(k, light.position) for k, light in enumerate(scene.lights) if hasattr(light, "position")]
            inside = [(k, p) for (k, p), i in zip(placed, contains(self._geo["mesh"], [p for _, p in placed])
                                                  if placed else []) if i]
            where = "".join(f"; light {k + 1} at ({', '.join(f'{c:g}' for c in p)}) mm is inside the object: "
                            "move its position outside the mesh" for k, p in inside)
            hint = "; check the lights' directions, positions, cones and intensities"
            raise InputError(f"{scene.source}: [[lights]]: no light reaches the object (the source is 0 at "
                             f"every boundary node){where or hint}")
        self._q = self._q_marshak = np.zeros_like(q) if volume else q
        self._beams = beams or []
        self._load = None
        if volume:   # the light enters as the first-collision source; no diffuse light crosses the boundary
            t0 = time.perf_counter()
            if "columns" not in self._geo:      # geometry only: once per grid, not per light
                self._say("pass 1: the surface's columns and each node's place in them (once per grid)")
                self._geo["columns"] = surface_columns(pg)
                self._geo["node_columns"] = node_columns(pg, self._geo["columns"])
            self._load = first_collision_load(pg, self._mat["kappa"], self._mat["mu"], beams,
                                              self._geo["tetgeo"].node_volumes, self._geo["columns"],
                                              self._geo["node_columns"])
            info.append({"light": "first-collision source", "beams": len(beams or ()),
                         "nodes": int(self._load.any(axis=1).sum()), "seconds": time.perf_counter() - t0})
        self._light_info = info

    @staticmethod
    def _splits_incidence(scene: Scene) -> bool:
        """Whether the surface source follows the half-space's transport per incidence
        (:mod:`glsldiff.physics.exitance`, ``[options].incidence`` "local" or "transport")."""
        o = scene.options
        return not o.split and o.incidence != "marshak" and o.source == "surface" and o.exitant != "paper"

    def _boundary_material(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(kappa, mu)`` ``(n_boundary, 3)`` at the surface (boundary) nodes."""
        pg = self._geo["pg"]
        if self._geo["fem"]:
            return self._mat["kappa"][pg.surface_nodes], self._mat["mu"][pg.surface_nodes]
        return (self._mat["kappa"].reshape(-1, 3)[pg.lattice.boundary],
                self._mat["mu"].reshape(-1, 3)[pg.lattice.boundary])

    def _split_incidence(self, scene: Scene) -> None:
        """The diffusion's load from pass 1's beams and the node material (each beam's share
        ``H(t) / <H>`` under ``incidence = "transport"``, pass 1's Marshak source otherwise) and
        what the bracket's local term needs (``"local"`` and ``"transport"``)."""
        self._q, self._incidence = self._q_marshak, None
        o = scene.options
        if not self._splits_incidence(scene):
            self._incidence_used = ("- (model split: exact local transport per beam)" if o.split else
                                    "marshak (the paper's convention)" if o.exitant == "paper" and o.source == "surface"
                                    else "marshak" if o.source == "surface" else "- (volume source)")
            return
        kappa, mu = self._boundary_material()
        eta = scene.material.eta
        deep = o.incidence == "transport"
        E = deep_irradiance(self._beams, kappa, mu) if deep else self._E_t
        self._q = source_from_irradiance(E, eta, o.exitant)
        self._incidence = {"beta": halfspace_bracket(kappa, mu, eta, o.exitant, self._boundary_C(scene)),
                           "kappa": kappa, "mu": mu, "deep": deep}
        self._local_key = None
        lit = self._E_t.sum(axis=1) > 0
        share = E.sum(axis=1)[lit] / self._E_t.sum(axis=1)[lit] if lit.any() else np.ones(1)
        self._incidence_used = (f"transport (the load's share of each beam H(t) / <H>: {share.min():.2f}-"
                                f"{share.max():.2f}; the bracket's local term follows the view)" if deep else
                                "local (the Marshak load; the bracket's local term follows the half-space's "
                                "transport per incidence and view)")

    def _bracket_q(self, scene: Scene, eye: NDArray[np.float64]) -> NDArray[np.float64]:
        """The ``q`` of the exitant bracket: the load, less the local term of ``incidence =
        "local"`` or ``"transport"`` over ``b`` (it depends on the view: recomputed when the
        camera moves)."""
        if self._incidence is None:
            return self._q
        pg = self._geo["pg"]
        key = tuple(np.round(np.asarray(eye, dtype=np.float64), 9))
        if self._local_key != key:
            d = np.asarray(eye, dtype=np.float64)[None, :] - pg.boundary_positions
            cos = np.einsum("ij,ij->i", d, pg.normals) / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
            view = np.where(cos > 0.0, refracted_cosine(scene.material.eta, np.clip(cos, 0.0, 1.0)), 1.0)
            inc = self._incidence
            local = local_bracket(self._beams, inc["kappa"], inc["mu"], view, inc["beta"], inc["deep"])
            b = exitance_coefficients(scene.material.eta, scene.options.exitant, self._boundary_C(scene))[1]
            self._q_bracket, self._local_key, self._flux_fields = self._q - local / b, key, None
        return self._q_bracket

    def _say(self, line: str) -> None:
        if self._status is not None:
            self._status(line)

    def _paint_sweeps(self, pg: Any) -> None:
        """Pass 2 of a frame with a new edit while painting (``frame_sweeps``): the sweeps alone,
        from the previous frame's solution, and no residual check (it needs the CPU system of the
        new material); frames without a new edit check it again."""
        t0 = time.perf_counter()
        fine = self._solver.finest
        fine.sweep(self.frame_sweeps)
        phi = fine.fluence()
        self._partial = True
        self._finish_pass2(pg, phi, SolveReport(f"glsl-frame-coherent-{fine.precision} (painting: no residual check)",
                                                nodes=int(pg.n_active), sweeps=int(self.frame_sweeps),
                                                seconds=time.perf_counter() - t0, status="budget"), False)

    def _pass2(self, scene: Scene, warm: bool, painting: bool = False) -> None:
        pg, opts, fem = self._geo["pg"], scene.options, self._geo["fem"]
        if fem:
            self._tet_pass2(scene, warm, painting)
            return
        if painting and self.frame_sweeps is not None and self._solver is not None:
            self._paint_sweeps(pg)
            return
        self._say(f"pass 2: {opts.scheme} diffusion solve of {pg.n_active:,} nodes to tol {opts.tol:g}")
        gl.make_current(self.ctx)
        x0: Any = CURRENT if warm and opts.scheme != "multigrid" else None
        key = self._solution_key(scene)
        warm_from_disk = opts.scheme != "adaptive" and (x0 is None or self._solver is None)   # (adaptive: below)
        stored = cache.load("pass2", key, np.ndarray) if self.cache_solutions and warm_from_disk else None
        if self._solver is None:
            self._solver = self._lattice_solver(scene)
            x0 = None
        else:
            self._solver.set_q(self._q)
        self._from_cache = False
        if x0 is None and opts.scheme != "adaptive":   # adaptive needs its coarse-to-fine start
            x0 = stored
            self._from_cache = x0 is not None
        budget: dict[str, Any] = {}
        partial = self.frame_sweeps is not None and isinstance(x0, str)   # x0 = CURRENT
        if partial:      # frame coherence: a few sweeps now, more next frame
            budget = {"maxiter": self.frame_sweeps, "check_every": self.frame_sweeps}
        try:
            phi, rep = self._solver.solve(tol=opts.tol, x0=x0, **budget)
        except SolverError as exc:   # diverged: no image to keep, whatever allow_unconverged says
            raise SolverError(f"pass 2 did not converge: {exc}; {self._PASS2_HINT}") from exc
        self._partial = partial and rep.status not in ("converged", "stalled")
        self._check_converged(scene, rep)
        if rep.status == "converged" and not self._from_cache and self.cache_solutions:
            cache.store("pass2", key, np.asarray(phi))
        self._finish_pass2(pg, phi, rep, fem)

    _PASS2_HINT = ("the object may be optically too small or thin for its material (size_mm, sigma), or "
                   "[options].tol too tight")

    def _solution_key(self, scene: Scene) -> str:
        """The disk cache's key of this frame's converged pass-2 answer."""
        pg, opts, fem = self._geo["pg"], scene.options, self._geo["fem"]
        return cache.digest(f"pass2 v{SOLUTION_CACHE_VERSION}", scene.polygrid.discretisation, pg.positions,
                            pg.tets if fem else pg.weights, self._mat["kappa"], self._mat["mu"], self._q, self._load,
                            scene.material.eta, opts.scheme, opts.precision, opts.tol)

    def _check_converged(self, scene: Scene, rep: SolveReport) -> None:
        if rep.status not in ("converged", "stalled") and not self.allow_unconverged and not self._partial:
            raise SolverError(f"pass 2 did not converge: residual {rep.residual:.3g} > tol {scene.options.tol:g} "
                              f"after {rep.sweeps} iterations ({rep.status}); {self._PASS2_HINT}; "
                              "--allow-unconverged writes the unconverged image")

    def _tet_pass2(self, scene: Scene, warm: bool, painting: bool) -> None:
        """Pass 2 on tetrahedra (:mod:`glsldiff.render.tetrahedral`): the P1 system updated in
        place after edits, the GPU solver kept; under ``frame_sweeps`` (interactive) a frame
        with a new edit runs a few Jacobi sweeps and the next ones a CG iteration each."""
        pg, opts = self._geo["pg"], scene.options
        check_precision(opts.precision, str(scene.source))
        gl.make_current(self.ctx)
        self._fem_linear_system(scene)
        tet = self._tet
        assert tet is not None
        interactive = self.frame_sweeps is not None
        if not (interactive and warm):
            self._say(f"pass 2: multigrid-preconditioned CG (tetrahedra) diffusion solve of {pg.n_active:,} nodes "
                      f"to tol {opts.tol:g}")
        key = self._solution_key(scene) if self.cache_solutions and not (interactive and warm) else None
        stored = cache.load("pass2", key, np.ndarray) if key is not None and tet.solver is None else None
        frame = tet.cached(stored, opts.tol) if tet.solver is None else None
        if frame is None:
            try:
                frame = tet.solve(opts.tol, warm=warm, painting=painting, frame_budget=interactive, x0=stored)
            except SolverError as exc:
                raise SolverError(f"pass 2 did not converge: {exc}; {self._PASS2_HINT}") from exc
        self._from_cache = frame.from_cache
        self._partial = frame.partial
        self._check_converged(scene, frame.report)
        if key is not None and frame.report.status == "converged" and not frame.from_cache:
            cache.store("pass2", key, np.asarray(frame.phi))
        self._finish_pass2(pg, frame.phi, frame.report, True)

    def _finish_pass2(self, pg: Any, phi: NDArray, rep: SolveReport, fem: bool) -> None:
        self._flux_fields = None
        self._solutions = getattr(self, "_solutions", 0) + 1     # pass 3's caches follow every new phi
        if fem:
            self._phi_b = self.surface_values(phi)
            self._phi_active = np.asarray(phi, dtype=np.float64)
        else:
            self._phi_b = np.asarray(phi, dtype=np.float64).reshape(-1, 3)[pg.lattice.boundary]
        self._solve_report = rep

    def _lattice_solver(self, scene: Scene) -> MultilevelDiffusion:
        opts = scene.options
        problem = DiffusionProblem(self._geo["pg"], self._mat["kappa"], self._mat["mu"], self._q,
                                   eta=scene.material.eta, stencil=scene.polygrid.discretisation)
        return MultilevelDiffusion(self._geo["hier"], problem, opts.scheme, ctx=self.ctx, precision=opts.precision)

    @staticmethod
    def _boundary_C(scene: Scene) -> float:
        """The Robin constant: the exact Fresnel-moment one with the first-collision source
        (:func:`glsldiff.physics.optics.moment_boundary_constant`), the classic ``(1 + F_dr) /
        (1 - F_dr)`` with the Marshak surface source (the calibration of its ``p1`` exitance)."""
        eta = scene.material.eta
        return (moment_boundary_constant(eta) if scene.options.source == "volume"
                else float(boundary_constant(eta)))

    def fem_problem(self, scene: Scene) -> TetProblem:
        """The last frame's P1 problem of ``scene`` (grid, node material, boundary source, eta
        and the Robin constant C) on a tetrahedral grid; without the first-collision load of
        ``source = "volume"``."""
        if not self._geo.get("fem") or self._q is None:
            raise RuntimeError("no frame of a tetrahedral grid rendered yet")
        return self._fem_problem(scene)

    @staticmethod
    def check_discretisation_scene(scene: Scene) -> None:
        """Refuse (:class:`InputError`, one line) a scene :meth:`discretisation_error` cannot
        check, before any work: a lattice grid, or the first-collision volume source."""
        if scene.polygrid.discretisation not in ("fem", "tetwild"):
            raise InputError(f"the discretisation check needs a tetrahedral grid; this scene's is "
                             f"{scene.polygrid.discretisation!r} (set [polygrid] discretisation = \"fem\")")
        if scene.options.source == "volume":
            raise InputError("the discretisation check does not carry the first-collision load yet (the split takes "
                             "it where the grid resolves the mean free path); render with [options] source = "
                             "\"surface\" to check the grid")

    def discretisation_error(self, scene: Scene, channel: int = 1) -> tuple[RefinedError, int, float]:
        """How far the last frame's pass-2 answer is from the converged one: the same problem
        solved on the grid's 1:8 refinement (:class:`glsldiff.oracle.refined.RefinedComparison`;
        one colour ``channel``, exact CPU solves). Returns the comparison, the refined grid's
        node count and the seconds it all took. Tetrahedral grids with the surface source only
        (``source = "auto"``: as the last frame resolved it)."""
        if self._geo and self._mat:
            scene = self._effective(scene)
        self.check_discretisation_scene(scene)
        t0 = time.perf_counter()
        rc = RefinedComparison(self.fem_problem(scene), channel)
        err = rc.compare()[0]
        return err, rc.nodes[1], time.perf_counter() - t0

    def _fem_problem(self, scene: Scene) -> TetProblem:
        return TetProblem(self._geo["pg"], self._mat["kappa"], self._mat["mu"], self._q, eta=scene.material.eta,
                          C=self._boundary_C(scene))

    def _fem_linear_system(self, scene: Scene) -> LinearSystem:
        """The P1 system of the current material and source (:class:`TetPass2`: assembled once
        per material, updated in place after edits)."""
        pg = self._geo["pg"]
        if self._tet is None or self._tet.geo is not self._geo["tetgeo"]:
            if self._tet is not None:
                self._tet.release()
            self._tet = TetPass2(self.ctx, self._geo["tetgeo"], np.asarray(pg.active, dtype=bool))
        C = self._boundary_C(scene)
        key = (id(self._q), id(self._load), C, scene.material.eta)    # pass 1 makes new arrays for a new source
        if getattr(self, "_fem_b", (None,))[0] != key:
            b = tet_rhs(self._fem_problem(scene), self._geo["tetgeo"])
            if self._load is not None:
                b = b + self._load[self._tet.active]
            self._fem_b = (key, b)
        return self._tet.system(self._mat["kappa"], self._mat["mu"], C, self._fem_b[1])

    @staticmethod
    def _shader_lights(scene: Scene) -> list[DirectLight]:
        """The lights pass 3 shades per light (all but environment and area lights, at most
        MAX_SHADER_LIGHTS)."""
        return [lt for lt in scene.lights if not isinstance(lt, (EnvironmentLight, AreaLight))][:MAX_SHADER_LIGHTS]

    def _pass3(self, scene: Scene) -> NDArray[np.float32]:
        geo, opts = self._geo, scene.options
        v, f, nrm = geo["vertices"], geo["faces"], geo["normals"]
        eta = scene.material.eta
        eye, mvp = self._camera(scene)
        if opts.split:      # the subsurface radiance is view-dependent and >= 0 by construction
            ms = np.zeros_like(v)
            self._clamped, self._clamped_depth, self._clamped_deep = 0, 0.0, 0
        else:
            B = exitant_bracket(*self._bracket_fields(scene, eye), eta, opts.exitant, self._boundary_C(scene))
            ms = geo["interp"] @ B
            neg = ms < 0.0
            self._clamped = int(np.any(neg, axis=1).sum())
            top = max(float(ms.max()), 1e-300)
            self._clamped_depth = float(max(-ms.min(), 0.0) / top)
            self._clamped_deep = int(np.any(ms < -0.01 * top, axis=1).sum())
            ms = np.maximum(ms, 0.0)
        shader_lights = self._shader_lights(scene)
        vis_key = _key(self._keys.get("geometry"), scene.lights)     # the geometry key holds the cut too
        if self._keys.get("vis") != vis_key:
            # per shader light: shadow visibility (V,) and RGB image factor (V, 3), 1 but for projectors
            vis, tint = np.ones((len(v), 4)), np.ones((len(v), 4, 3))
            for i, light in enumerate(shader_lights):
                if light.shadows:
                    vis[:, i] = visibility(geo["mesh"], v, light, ctx=self.ctx, normals=nrm)
                if isinstance(light, ProjectorLight):
                    tint[:, i] = projector_factor(light, v)
            self._vis, self._tint, self._keys["vis"] = vis, tint, vis_key
        ss = np.zeros_like(v)
        if opts.split:
            sr = self._split_frame(scene, eye)
            ss = {"single": sr.single, "multiple": sr.multiple}.get(self.split_part or "", sr.radiance)
        elif opts.single_scattering:
            ss = self._single(scene, eye)
        if scene.material.reflectance is not None:
            ss = ss + self._surface_diffuse(scene)
        if opts.unscattered and sees_through(scene.lights):
            ss = ss + self._unscattered(scene, eye)
        vis = self._vis * self._tint.mean(axis=2)   # the shader's visibility is one number per light
        return shade(self.ctx, v, f, nrm, ms, vis, ss, shader_lights, eye, mvp, eta,
                     scene.specular.rho_s, scene.specular.alpha, (scene.output.width, scene.output.height))

    def _bracket_fields(self, scene: Scene, eye: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The ``(phi, q)`` of the exitant bracket ``a phi - b q`` per surface node. ``[options].flux =
        "smoothed"`` (tetrahedral grids, the default): both smoothed along the surface, ``q`` over
        half a transport mean free path and ``phi`` over an eighth
        (:func:`glsldiff.physics.exitance.bracket_smoothing_lengths`): a hard light edge then leaves
        no ring and no mottle; the local fields where no light enters through the surface (the
        volume source). ``"boundary"``: the local fields (the boundary condition's flux ``(phi -
        q) / (2C)``). ``"gradient"``: ``q`` such that that expression equals the outward flux
        ``-kappa dphi/dn`` of the solution's recovered gradient (volume-weighted mean of the
        tetrahedra's gradients at each surface node)."""
        flux = scene.options.flux
        if flux == "boundary" or not self._geo["fem"] or (flux == "smoothed" and not self._q.any()):
            self._flux_used = (flux if flux != "smoothed" else
                               "boundary (the lattice has no surface triangles to smooth on)" if not self._geo["fem"]
                               else "smoothed: no light enters through the surface here (volume source), so the "
                                    "local bracket")
            return self._phi_b, self._bracket_q(scene, eye)
        q_bracket = self._bracket_q(scene, eye)        # before the cache check: a new view drops the cache
        if self._flux_kind != flux:          # the kept fields are the other option's
            self._flux_fields, self._flux_kind = None, flux
        if self._flux_fields is None and flux == "smoothed":
            pg = self._geo["pg"]
            key = _key(self._keys.get("geometry"), self._keys.get("material"))
            if self._keys.get("smoother") != key:
                t0 = time.perf_counter()
                lam_phi, lam_q = bracket_smoothing_lengths(self._boundary_material()[0])
                self._smoothers = tuple(screened_smoothing(pg.boundary_positions, pg.surface_triangles, lam)
                                        for lam in (lam_phi, lam_q))
                self._smoother_info = (f"smoothed along the surface, q over {lam_q.min():.3g}-{lam_q.max():.3g} mm "
                                       "(half a mean free path), phi over a quarter of that; set-up "
                                       f"{time.perf_counter() - t0:.2f} s")
                self._keys["smoother"] = key
            self._flux_fields = (self._smoothers[0](self._phi_b), self._smoothers[1](q_bracket))
        elif self._flux_fields is None:
            pg, geo = self._geo["pg"], self._geo["tetgeo"]
            full = np.zeros((len(pg.positions), 3))
            full[self._fem_active] = self._phi_active
            grad = geo.recovered_gradient(full)[pg.surface_nodes]                    # (S, 3, 3)
            normal_flux = -self._boundary_material()[0] * np.einsum("sjc,sj->sc", grad, pg.normals)
            self._flux_fields = (self._phi_b, self._phi_b - 2.0 * self._boundary_C(scene) * normal_flux
                                 - (self._q - q_bracket))
        self._flux_used = self._smoother_info if flux == "smoothed" else flux
        return self._flux_fields

    def _surface_diffuse(self, scene: Scene) -> NDArray[np.float64]:
        """Per-vertex measured diffuse surface reflection ``rho_d / pi * E`` (Lambertian), with
        ``E`` the incident irradiance of all lights (shadows, environment visibility);
        cached until the lights, the geometry or the reflectance change (a change of the
        reflectance alone re-runs neither the material stage nor pass 1-2)."""
        geo = self._geo
        rho_key = _key(self._keys.get("geometry"), scene.material.reflectance, scene.material.volume)
        if self._keys.get("rho") != rho_key:
            self._rho, self._keys["rho"] = geo["interp"] @ surface_reflectance(scene, geo["pg"]), rho_key
        key = _key(rho_key, self._keys.get("light"))
        if self._keys.get("diffuse") != key:
            E, _ = incident_light(geo["mesh"], geo["vertices"], geo["normals"], scene.lights, None,
                                  ctx=self.ctx)
            self._diffuse, self._keys["diffuse"] = self._rho * E / math.pi, key
        return self._diffuse

    def _medium(self, scene: Scene) -> Any:
        """The material for path integrals through the object: ``(sigma_a, sigma_s')`` RGB
        arrays (mm^-1) when homogeneous, else a function of points ``(M, 3)`` returning both
        ``(M, 3)``, evaluated in the nodes' unit box; after edits, the edited node material at
        the nearest node (and so for a block volume or a node material: their values exist at the
        nodes only)."""
        pg = self._geo["pg"]
        lo, hi = pg.positions.min(axis=0), pg.positions.max(axis=0)
        if getattr(self, "_edited", False) or scene.material.volume or scene.material.nodes:
            nodes = np.flatnonzero(np.ones(len(pg.positions), bool) if self._geo["fem"]
                                   else np.asarray(pg.active).reshape(-1))
            if "node_tree" not in self._geo:      # once per grid, not per edit
                self._geo["node_tree"] = cKDTree(np.asarray(pg.positions).reshape(-1, 3)[nodes])
            tree = self._geo["node_tree"]
            k_all, m_all = (self._mat[n].reshape(-1, 3)[nodes] for n in ("kappa", "mu"))

            def edited(p: NDArray) -> tuple[NDArray, NDArray]:
                _, i = tree.query(p)
                return m_all[i], np.maximum(1.0 / (3.0 * k_all[i]) - m_all[i], 0.0)
            return edited

        def material(p: NDArray) -> tuple[NDArray, NDArray]:
            kappa, mu, _ = node_material(scene, np.vstack([lo, hi, p]), pg)   # same unit box as the nodes
            kappa, mu = kappa[2:], mu[2:]
            return mu, np.maximum(1.0 / (3.0 * kappa) - mu, 0.0)

        if scene.material.procedural:
            return material
        sa, ss = material(self._geo["vertices"][:1])
        return sa[0], ss[0]

    def _unscattered(self, scene: Scene, eye: NDArray) -> NDArray[np.float64]:
        """Per-vertex unscattered light seen through the object (:mod:`glsldiff.render.unscattered`),
        kept while the camera, lights, material and geometry stay the same."""
        key = _key(self._keys.get("material"), self._keys.get("light"), self._edit_version, tuple(np.round(eye, 9)))
        if self._keys.get("unscattered") != key:
            t0 = time.perf_counter()
            geo, medium = self._geo, self._medium(scene)
            sigma_t: Any = (lambda p: np.add(*medium(p))) if callable(medium) else medium[0] + medium[1]
            self._unsc = unscattered(geo["mesh"], geo["vertices"], geo["normals"], eye, scene.material.eta,
                                     scene.lights, sigma_t, float((1.0 / (3.0 * self._mat["kappa"])).min()))
            self._keys["unscattered"] = key
            self._unsc_seconds = time.perf_counter() - t0
        return self._unsc

    def _regime_warnings(self, scene: Scene) -> list[str]:
        """The scene's ways out of what its model was validated on (:mod:`glsldiff.physics.regime`):
        albedo, eta and thin parts, the object's thickness along the inward normal at up to
        :data:`THICKNESS_SAMPLES` surface nodes (ray cast once per grid) over the transport mean
        free path of their most transparent channel."""
        geo, pg = self._geo, self._geo["pg"]
        if "thickness" not in geo:
            S = len(pg.boundary_positions)
            pick = np.unique(np.linspace(0, S - 1, min(S, THICKNESS_SAMPLES)).astype(np.int64))
            h = pg.h if geo["fem"] else pg.lattice.h
            T, _ = first_hits(geo["mesh"], pg.boundary_positions[pick], -np.asarray(pg.normals)[pick], t_min=0.5 * h)
            geo["thickness"] = (pick, T)
        pick, T = geo["thickness"]
        kappa, mu = self._boundary_material()
        st_min = (1.0 / (3.0 * kappa[pick])).min(axis=1)
        albedo = np.clip(1.0 - 3.0 * kappa * mu, 0.0, 1.0)
        out = regime_warnings("split" if scene.options.split else "diffusion", albedo, scene.material.eta,
                              T * st_min)
        hs = self._h_sigma_t()
        if scene.options.split and scene.options.source == "volume" and hs > GATHER_MAX_H_SIGMA:
            out.append(f"source = \"volume\" on a grid coarser than the mean free path (node spacing x sigma_t' up "
                       f"to {hs:.2g}, resolved below {GATHER_MAX_H_SIGMA:g}): the gathered far field reads low there "
                       "(1-D: 0.93 of the converged value at 1, 0.85 at 2); leave [options].source to \"auto\" or "
                       "give [polygrid] cubes more")
        return out

    def _split_frame(self, scene: Scene, eye: NDArray) -> SplitResult:
        """The transport split's subsurface radiance per vertex (:mod:`glsldiff.render.split_frame`),
        kept while the solution, the lights, the material and the camera stay the same."""
        key = _key(self._keys.get("solve"), getattr(self, "_solutions", 0), self._keys.get("light"), self._edit_version,
                   tuple(np.round(eye, 9)))
        if self._keys.get("split") == key:
            return self._split_result
        geo, o = self._geo, scene.options
        far = "gather" if o.source == "volume" else "surface"
        fluence = None
        if far == "gather":
            pg = geo["pg"]
            if "lattice" not in geo:
                self._say("pass 3: sampling lattice of the tetrahedral grid for the gather (once per grid)")
                geo["lattice"] = FluenceLattice(pg.positions, pg.tets)
            full = np.zeros((len(pg.positions), 3))
            full[self._fem_active] = self._phi_active
            geo["lattice"].set_values(full)
            fluence = geo["lattice"]
            light = self._keys.get("light")
            if getattr(self, "_lit_distance", (None,))[0] != light:   # mm, once per lighting, not per camera
                Et = self._E_t.sum(axis=1)
                lit = Et > LIT_SHARE * max(float(Et.max()), 1e-300)
                d = (cKDTree(pg.boundary_positions[lit]).query(pg.boundary_positions)[0] if lit.any()
                     else np.full(len(Et), 1e30))
                self._lit_distance = (light, d)
        kappa, mu = self._boundary_material()
        # gather: each surface node's distance to where light enters, in mean free paths
        thick = self._lit_distance[1][:, None] / (3.0 * kappa) if far == "gather" else None
        inp = SplitInputs(far=far, march=bool(o.single_scattering) or far == "gather", eta=scene.material.eta,
                          C=self._boundary_C(scene), interp=geo["interp"], vertices=geo["vertices"],
                          normals=geo["normals"], beams=self._beams, kappa=kappa, mu=mu, phi=self._phi_b,
                          q=self._q, source_distance_mfp=thick, fluence=fluence, mesh=geo["mesh"], lights=scene.lights,
                          medium=self._medium(scene))
        self._split_result = split_radiance(inp, eye, self.ctx)
        self._keys["split"] = key
        return self._split_result

    def _single(self, scene: Scene, eye: NDArray) -> NDArray[np.float64]:
        """Per-vertex single scattering of every light, reflection and transmission
        (:mod:`glsldiff.render.single`), kept while the camera, lights, material and geometry
        stay the same; its time is the report's ``single`` seconds."""
        key = _key(self._keys.get("material"), self._keys.get("light"), self._edit_version, tuple(np.round(eye, 9)))
        if self._keys.get("single") != key:
            t0 = time.perf_counter()
            geo = self._geo
            with DepthRenderer(self.ctx, geo["mesh"]) as depth:
                self._ss = single_scattering_frame(geo["mesh"], geo["vertices"], geo["normals"], eye,
                                                   scene.material.eta, scene.lights, self._medium(scene), depth)
            self._keys["single"] = key
            self._ss_seconds = time.perf_counter() - t0
        return self._ss

    # -- the frame -----------------------------------------------------------------
    def render(self, scene: Scene) -> tuple[NDArray[np.float32], RenderReport]:
        """One frame: ``(h, w, 3)`` linear radiance (row 0 = top) and the report."""
        rep = RenderReport(renderer=gl.describe(self.ctx), image_size=(scene.output.width, scene.output.height))
        geo_key = _key(scene.mesh, scene.polygrid, str(scene.base_dir), scene.cut,
                       (scene.camera, scene.output) if scene.cut is not None and scene.cut.stroke else None,
                       (scene.lights, scene.material.eta, scene.options.exitant) if scene.refines
                       else None)                                          # the refined grid follows the lights
        mat_key = _key(geo_key, replace(scene.material, reflectance=None), scene.paint,  # pass 3 alone: reflectance
                       scene.options.scheme, scene.options.precision, str(scene.base_dir))
        edited = self._keys.get("edits", 0) != self._edit_version and "solve" in self._keys
        going_on = self._partial       # the last frame's pass 2 stopped at its sweep budget
        if going_on:
            self._keys.pop("solve", None)

        def stage(name: str, key_name: str, key: str, fn: Any, why_skip: str, timer: str | None) -> bool:
            if self._keys.get(key_name) == key:
                rep.passes.append({"pass": name, "ran": False, "seconds": 0.0, "why": why_skip})
                return False
            t0 = time.perf_counter()
            reason = "first frame" if key_name not in self._keys else f"{key_name} changed"
            fn()
            dt = time.perf_counter() - t0
            self._keys[key_name] = key
            rep.passes.append({"pass": name, "ran": True, "seconds": dt, "why": reason})
            if timer:
                rep.seconds[timer] = dt
            return True

        new_geo = stage("setup", "geometry", geo_key, lambda: self._setup(scene),
                        "mesh and polygrid unchanged (no re-packing)", "setup")
        if new_geo:
            self._keys.pop("material", None)
            self._keys.pop("light", None)
            self._keys.pop("solve", None)
        new_mat = stage("material", "material", mat_key, lambda: self._material(scene), "material unchanged", None)
        scene = self._effective(scene)       # the model's concrete source and single scattering
        volume = scene.options.source == "volume"
        light_key = _key(geo_key, scene.lights, scene.material.eta, scene.options.exitant, str(scene.base_dir),
                         scene.options.source, scene.options.incidence, scene.options.model,
                         (mat_key, self._edit_version) if volume else None)   # the volume load follows the material
        solve_key = _key(mat_key, light_key, scene.options.tol, self._edit_version)
        new_light = stage("pass1", "light", light_key, lambda: self._pass1(scene),
                          "lights unchanged: incident light kept", "t1")
        stage("incidence", "incidence", _key(light_key, mat_key, self._edit_version),   # edits change the albedo
              lambda: self._split_incidence(scene), "lights and material unchanged: load kept", None)
        warm = not (new_geo or new_mat) and (new_light or edited or going_on)
        if new_geo or new_mat:
            self._partial = False
        self._keys["edits"] = self._edit_version
        painting = warm and edited and not new_light
        stage("pass2", "solve", solve_key, lambda: self._pass2(scene, warm, painting),
              "material and incident light unchanged: solution kept", "t2")
        if rep.ran("pass2") and self._from_cache:
            rep.passes[-1]["why"] += ": warm start from the cached solution of this system (residual checked)"
        elif rep.ran("pass2") and warm:
            what = "light changed" if new_light else "material edited" if edited else "converging"
            rep.passes[-1]["why"] = f"{what}: warm start from the previous frame (frame coherence)"
            if self._partial:
                rep.passes[-1]["why"] += f"; {self.frame_sweeps} sweeps this frame, not yet at tol"
        t0 = time.perf_counter()
        img = self._pass3(scene)
        rep.seconds["t3"] = time.perf_counter() - t0
        rep.passes.append({"pass": "pass3", "ran": True, "seconds": rep.seconds["t3"], "why": "every frame"})
        pg = self._geo["pg"]
        rep.nodes, rep.boundary_nodes = int(pg.n_active), int(len(pg.boundary_positions))
        rep.solver = self._solve_report
        rep.clamped_vertices, rep.clamped_depth, rep.clamped_deep = self._clamped, self._clamped_depth, self._clamped_deep
        if scene.cut is not None:
            cr = self._cut_report
            rep.notes.append(f"cut: {cr.tets_removed:,} of {cr.tets_before:,} tetrahedra removed, {cr.nodes_on_cut} of "
                             f"{cr.nodes_to_relax} vertices relaxed onto the cut ({cr.iterations} iterations, "
                             f"{cr.moves_refused} moves refused), at most {cr.max_past_cut:.3g} past it, "
                             f"{self._cut_seconds:.2f} s")
        if scene.polygrid.discretisation == "tetwild":
            q = pg.quality
            rep.notes.append(f"grid: tetrahedral (fTetWild), edge {pg.h:.3g} mm, {len(pg.tets):,} tetrahedra, "
                             f"{q.inverted} inverted, worst dihedral angle {q.min_dihedral_deg:.3g} deg, {q.slivers} "
                             f"slivers; boundary within {q.surface_distance_max:.3g} mm of the surface"
                             f"{' (before the cut)' if scene.cut is not None else ''}")
        elif self._geo["fem"]:
            q = pg.quality
            rep.notes.append(f"grid: tetrahedral (fem), h {pg.h:.3g} mm, {len(pg.polycube.cubes):,} cubes of "
                             f"{pg.complex.lattice.n} nodes per edge"
                             f"{f' (n = {q.requested_n} asked for: {q.fine_reason})' if q.fine_reason else ''}"
                             f"{f', {q.retries} rebuilds with other cube sizes (kept: x{q.size_factor:g})' if q.retries else ''}, "
                             f"{len(pg.tets):,} tetrahedra, {q.inverted} "
                             f"inverted, worst quality {q.worst_quality:.3g} ({q.poor_before:,} -> {q.poor:,} below "
                             f"{SHAPE_TARGET:g} by the shape step), {q.split_edges:,} edges longer than "
                             f"{SPLIT_LENGTH:g} h split; coverage: mesh vertices within "
                             f"{q.coverage_max:.2f} h of a surface node (99 %: {q.coverage_p99:.2f} h)")
            ar = self._adapt_report
            rep.notes.append("adapt: off ([polygrid] adapt = true refines under the lights' sharp edges; \"auto\", "
                             "the default, only under a spot's or projector's)"
                             if ar is None else f"adapt: {ar.line()}" if ar.edges else
                             f"adapt: the source is linear along every surface edge (to {ADAPT_TOL:.0%} of its "
                             "largest value): grid not refined")
        through = scene.options.unscattered and sees_through(scene.lights)
        if scene.options.split:
            sr = self._split_result
            rep.notes.append(f"{sr.info}; {sr.seconds:.2f} s")
            model = f"model: split; source: {scene.options.source}; "
            rep.model = (f"split ({'gather' if scene.options.source == 'volume' else 'surface'} far field, single "
                         f"scattering {'3-D march' if scene.options.single_scattering else 'closed form'})")
        else:
            rep.model = f"diffusion ({scene.options.source} source, {scene.options.exitant})"
            model = (f"model: diffusion; exitant: {scene.options.exitant}; source: {scene.options.source}; incidence: "
                     f"{self._incidence_used}; flux: {self._flux_used}; single scattering: "
                     f"{f'{self._ss_seconds:.2f} s' if scene.options.single_scattering else 'off'}; ")
        if self._model_note:
            rep.notes.append(self._model_note)
        rep.notes.append(f"material: {self._mat['info'].get('material')}; {model}"
                         f"unscattered light: {f'{self._unsc_seconds:.2f} s' if through else 'off'}; "
                         f"diffuse surface reflectance: "
                         f"{'off' if scene.material.reflectance is None else scene.material.reflectance}")
        rep.notes.append(regime(self._mat["kappa"], self._mat["mu"], pg.h if self._geo["fem"] else pg.lattice.h,
                                scene.options.model))
        rep.warnings = self._regime_warnings(scene)
        eye = self._camera(scene)[0]
        inside_key = _key(self._keys.get("geometry"), tuple(np.round(eye, 9)))
        if self._keys.get("inside") != inside_key:     # a ray cast: once per camera, not per frame
            self._inside = bool(contains(self._geo["mesh"], eye[None, :])[0])
            self._keys["inside"] = inside_key
        if self._inside:
            rep.warnings.append(f"the camera at ({eye[0]:.4g}, {eye[1]:.4g}, {eye[2]:.4g}) mm is inside the object: "
                                "the image shows the inside of its surface, which no validated case covers (light "
                                "reaching a camera inside the medium is not modelled); move [camera].position out")
        for info in getattr(self, "_light_info", []):
            rep.notes.append("light: " + ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                                                   for k, v in info.items()))
        return img, rep

    def _camera(self, scene: Scene) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """:func:`~glsldiff.render.camera.scene_camera` of the framed mesh, kept while the
        camera, the image size and the geometry stay."""
        key = _key(self._keys.get("geometry"), scene.camera, scene.output.width, scene.output.height)
        if self._keys.get("camera") != key:
            self._eye_mvp = scene_camera(scene, self._geo["frame"])
            self._keys["camera"] = key
        return self._eye_mvp

    # -- editing (Wang et al. 2008, section 5.4) --------------------------------------
    def edit_view(self, scene: Scene) -> EditView:
        """The scene camera as an edit plane (``[output]`` pixels), with the distance of the
        visible surface per pixel (a depth render, kept while the camera and geometry stay)."""
        if not self._geo:
            raise RuntimeError("render a frame before editing")
        eye, mvp = self._camera(scene)
        size = (scene.output.width, scene.output.height)
        key = _key(self._keys.get("geometry"), tuple(np.round(mvp.ravel(), 9)), size)
        if self._surface is None or self._surface[0] != key:
            with DepthRenderer(self.ctx, self._geo["mesh"]) as depth:
                self._surface = (key, depth.camera_distance(mvp, eye, size))
        return EditView(mvp, size, eye, surface=self._surface[1])

    @property
    def edit_counts(self) -> tuple[int, int]:
        """(undo steps, redo steps) available."""
        return self._history.counts

    def edit(self, edit: Edit, view: EditView | None = None, history: bool = True) -> EditResult:
        """Apply ``edit`` (seen in ``view``, e.g. :meth:`edit_view`) to the node material of
        the last frame; the next :meth:`render` re-solves pass 2 from that frame's solution
        (frame coherence). On a lattice polygrid in fp32/fp16 the edit is a GPU pass over the
        solver's material textures (:class:`GpuMaterialEditor`); on tetrahedra (and with 8-bit
        material) it is the numpy twin, and the P1 system is re-assembled next frame (its
        multigrid keeps the old prolongations and starts from the last frame's solution).
        ``history=False`` joins the previous undo step (the dabs of one brush stroke)."""
        if not self._mat:
            raise RuntimeError("render a frame before editing")
        t0 = time.perf_counter()
        pg = self._geo["pg"]
        before = (self._mat["kappa"], self._mat["mu"])
        gpu = (not self._geo["fem"] and self._solver is not None
               and self._solver.finest.material_bits == 32)
        if gpu:
            if self._editor is None:
                self._editor = GpuMaterialEditor(self._solver.finest, pg.positions)
            self._editor.apply(edit, view)
            kappa, mu = self._editor.read()
            self._solver.set_material(kappa, mu, finest_uploaded=True)
            self._mat = {**self._mat, "kappa": kappa, "mu": mu}
            x, x0 = (kappa, before[0]) if edit.prop == "kappa" else (mu, before[1])
            act = np.asarray(pg.active)
            changed = np.any(x != x0, axis=-1) & act
            floor = KAPPA_MIN if edit.prop == "kappa" else 0.0
            result = EditResult(int(changed.sum()), int((np.any(x <= floor, axis=-1) & changed).sum()),
                                int((np.any(3.0 * kappa * mu > 1.0 + 1e-6, axis=-1) & changed).sum()))
        else:
            active = None if self._geo["fem"] else np.asarray(pg.active).reshape(-1)
            kappa, mu, result = apply_edit(edit, before[0], before[1], pg.positions, view, active)
            self._set_edited_material(kappa, mu)
        if history or self._history.counts[0] == 0:
            self._history.push(*before)
        self._edit_version += 1
        self._edited = True
        return replace(result, seconds=time.perf_counter() - t0)

    def _set_edited_material(self, kappa: NDArray, mu: NDArray) -> None:
        """Hand a CPU-side material to pass 2: the lattice solver's textures (every level), or
        a re-assembly of the P1 system next frame."""
        self._mat = {**self._mat, "kappa": kappa, "mu": mu}
        if self._geo["fem"]:
            pass    # the P1 system follows the node material at the next pass 2, in place (TetPass2.system)
        elif self._solver is not None:
            self._solver.set_material(kappa, mu)

    def undo(self) -> bool:
        """Return to the material before the last edit; False when there is none."""
        return self._step(self._history.undo)

    def redo(self) -> bool:
        """Re-apply the last undone edit; False when there is none."""
        return self._step(self._history.redo)

    def _step(self, fn: Callable[[tuple[NDArray, NDArray]], tuple[NDArray, NDArray] | None]) -> bool:
        if not self._mat:
            return False
        got = fn((self._mat["kappa"], self._mat["mu"]))
        if got is None:
            return False
        self._set_edited_material(*got)
        self._edit_version += 1
        self._edited = True
        return True

    def save_material(self, path: str | Any) -> Any:
        """Write the current (edited) node material to ``path`` (``.npz``: ``kappa`` mm, ``mu``
        mm^-1, ``positions_mm``, ``(N, 3)`` over the active nodes), the ``[material].nodes``
        file a scene renders (``glsldiff render``) and ``glsldiff edit`` edits."""
        if not self._mat:
            raise RuntimeError("render a frame before saving its material")
        pg = self._geo["pg"]
        act = np.ones(len(pg.positions), bool) if self._geo["fem"] else np.asarray(pg.active).reshape(-1)
        k, m = (self._mat[n].reshape(-1, 3)[act] for n in ("kappa", "mu"))
        return write_npz(path, kappa=k, mu=m, positions_mm=np.asarray(pg.positions)[act],
                         source=str(self._mat["info"].get("material")))

    def release(self) -> None:
        self._drop_solver()

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
