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
from glsldiff.core.errors import InputError
from glsldiff.core.io import write_npz
from glsldiff.mesh import (GENERATED_MESHES, SAMPLE_MESHES, cached_load_mesh, generated_mesh, screened_smoothing,
                           subdivide)
from glsldiff.physics.editing import Edit, EditResult, EditView
from glsldiff.physics.exitance import (bracket_smoothing_lengths, deep_irradiance, exitance_coefficients,
                                       exitant_bracket, halfspace_bracket, local_bracket, source_from_irradiance)
from glsldiff.physics.material import coefficients, optical_properties, regime
from glsldiff.physics.regime import regime_warnings
from glsldiff.mesh.raycast import first_hits
from glsldiff.mesh.inside import contains
from glsldiff.physics.optics import boundary_constant, moment_boundary_constant, refracted_cosine
from glsldiff.physics.lights import AreaLight, DirectLight, EnvironmentLight, ProjectorLight, projector_factor
from glsldiff.render.backends import GridBackend, Pass2Inputs, make_backend
from glsldiff.render.camera import scene_camera
from glsldiff.render.editing import MaterialHistory
from glsldiff.render.unscattered import sees_through, unscattered
from glsldiff.render.materials import node_material, surface_reflectance
from glsldiff.render.pass1 import incident_light, visibility
from glsldiff.render.report import RenderReport
from glsldiff.render.scene import TETRAHEDRAL, Scene
from glsldiff.render.shadows import DepthRenderer
from glsldiff.render.single import single_scattering_frame
from glsldiff.render.split_frame import SplitInputs, SplitResult, split_radiance
from glsldiff.render.shading import MAX_SHADER_LIGHTS, shade
from glsldiff.oracle.assembly import LinearSystem
from glsldiff.oracle.refined import RefinedComparison, RefinedError
from glsldiff.system.tet_problem import TetProblem
from glsldiff.system.transcut import paint_blend, paint_weights


#: Largest boundary source pass 2 accepts: its float32 textures overflow near 3.4e38, and the
#: sweeps multiply sources by stencil weights (mm^-2) before they are divided back.
Q_MAX = 1e30


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
        self._backend: GridBackend | None = None   # the grid family's set-up, material, edits and pass 2
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
        self._load: NDArray | None = None
        self._flux_fields: tuple[NDArray, NDArray] | None = None   # (phi, q) of the exitant bracket
        self._flux_kind: str | None = None        # the [options].flux that _flux_fields were made for
        self._smoothers: Any = None                # flux = "smoothed": (phi, q) smoothing along the surface
        self._smoother_info = ""                  # the smoothers' lengths and set-up time, for the report
        self._flux_used = ""                      # what the last frame's bracket took its flux from (report)
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
        :class:`~glsldiff.solve.gather_multigrid.GlslSparseMultigrid`; None before a solve or when a
        cached answer served it)."""
        return None if self._backend is None else self._backend.solver

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
        return self._grid

    @property
    def _be(self) -> GridBackend:
        """The grid's backend (after the first frame's set-up)."""
        assert self._backend is not None
        return self._backend

    @property
    def _grid(self) -> Any:
        return self._be.grid

    @property
    def fem_system(self) -> LinearSystem | None:
        """The P1 system (over the active nodes, with the last frame's source) a tetrahedral
        grid solved in pass 2; ``None`` on the lattice or before the first frame."""
        return getattr(self._backend, "system", None)

    def surface_values(self, x: NDArray) -> NDArray[np.float64]:
        """``(n_surface, 3)``: per-active-node values ``(n_active, 3)`` of a tetrahedral grid
        (e.g. a solution of :attr:`fem_system`) at its surface nodes."""
        return self._be.surface_values(x)

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
        return getattr(self._backend, "cut_report", None)

    @property
    def surface_fluence(self) -> NDArray[np.float64]:
        """``(n_boundary, 3)`` the last frame's pass-2 fluence at the boundary nodes."""
        if self._phi_b is None:
            raise RuntimeError("no frame rendered yet")
        return self._phi_b

    # -- stages --------------------------------------------------------------------
    def _setup(self, scene: Scene) -> None:
        m = scene.mesh
        if m.source in GENERATED_MESHES:
            mesh = generated_mesh(m.source, m.size_mm)
        else:
            src = m.source if m.source in SAMPLE_MESHES else str(scene.resolve(m.source))
            mesh = cached_load_mesh(src, size_mm=m.size_mm)
        if self._backend is not None:
            self._backend.release()
        self._backend = make_backend(scene, self.ctx, self._say, self.frame_sweeps, self.cache_solutions,
                                     self.allow_unconverged)
        frame = np.asarray(mesh.vertices)           # the uncut surface frames the camera
        mesh, crease = self._backend.setup(scene, mesh)
        render_mesh = subdivide(mesh if crease is None else crease, self._backend.h)
        v, f = np.asarray(render_mesh.vertices), np.asarray(render_mesh.faces)
        self._geo = {"mesh": mesh, "render_mesh": render_mesh, "vertices": v, "faces": f,
                     "normals": render_mesh.vertex_normals, "interp": self._backend.interpolation(v), "frame": frame}

    def _material(self, scene: Scene) -> None:
        pg = self._grid
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
        shape = self._be.material_shape
        self._mat = {"kappa": kappa.reshape(shape + (3,)), "mu": mu.reshape(shape + (3,)), "info": info}
        self._be.set_material()
        self._history = MaterialHistory()     # a new material starts a new edit history
        self._edited = False                  # the node material differs from the scene's (edits)

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
        if o.source == "auto":
            resolved = self._be.volume_source and self._h_sigma_t() <= GATHER_MAX_H_SIGMA
            o = replace(o, source="volume" if o.split and resolved else "surface")
        if o.single_scattering == "auto":      # interactive frames (the viewer) take the split's closed form
            o = replace(o, single_scattering=o.split and self.frame_sweeps is None)
        return replace(scene, options=o)

    def _h_sigma_t(self) -> float:
        """The grid's node spacing (mm) times the largest sigma_t' (mm^-1) of the node material:
        below :data:`GATHER_MAX_H_SIGMA` the grid resolves the transport mean free path."""
        return self._be.h * float(np.max(1.0 / (3.0 * self._mat["kappa"])))

    def _pass1(self, scene: Scene) -> None:
        pg = self._grid
        volume = scene.options.source == "volume"
        beams: list | None = [] if volume or scene.options.split or self._splits_incidence(scene) else None
        E_t, info = incident_light(self._geo["mesh"], pg.boundary_positions, pg.normals, scene.lights,
                                   scene.material.eta, ctx=self.ctx, beams=beams,
                                   triangles=self._be.surface_triangles)
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
            self._load = self._be.volume_load(self._mat["kappa"], self._mat["mu"], beams or [])
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
        return self._be.boundary(self._mat["kappa"]), self._be.boundary(self._mat["mu"])

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
        pg = self._grid
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

    def _pass2(self, scene: Scene, warm: bool, painting: bool = False) -> None:
        """One frame's pass 2 by the grid's backend (:mod:`glsldiff.render.backends`)."""
        frame = self._be.solve(self._pass2_inputs(scene, warm, painting))
        self._partial, self._from_cache = frame.partial, frame.from_cache
        self._flux_fields = None
        self._solutions = getattr(self, "_solutions", 0) + 1     # pass 3's caches follow every new phi
        self._phi_b = frame.phi_b
        self._solve_report = frame.report

    def _pass2_inputs(self, scene: Scene, warm: bool = False, painting: bool = False) -> Pass2Inputs:
        return Pass2Inputs(scene, self._mat["kappa"], self._mat["mu"], self._q, self._load, self._boundary_C(scene),
                           warm, painting)

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
        if not hasattr(self._backend, "problem") or self._q is None:
            raise RuntimeError("no frame of a tetrahedral grid rendered yet")
        return self._be.problem(self._pass2_inputs(scene))

    @staticmethod
    def check_discretisation_scene(scene: Scene) -> None:
        """Refuse (:class:`InputError`, one line) a scene :meth:`discretisation_error` cannot
        check, before any work: a lattice grid, or the first-collision volume source."""
        if scene.polygrid.discretisation not in TETRAHEDRAL:
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
            self._vis_shader = vis * tint.mean(axis=2)   # the shader's visibility is one number per light
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
        return shade(self.ctx, v, f, nrm, ms, self._vis_shader, ss, shader_lights, eye, mvp, eta,
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
        flat = self._be.surface_triangles is None
        if flux == "boundary" or flat or (flux == "smoothed" and not self._q.any()):
            self._flux_used = (flux if flux != "smoothed" else
                               "boundary (the lattice has no surface triangles to smooth on)" if flat
                               else "smoothed: no light enters through the surface here (volume source), so the "
                                    "local bracket")
            return self._phi_b, self._bracket_q(scene, eye)
        q_bracket = self._bracket_q(scene, eye)        # before the cache check: a new view drops the cache
        if self._flux_kind != flux:          # the kept fields are the other option's
            self._flux_fields, self._flux_kind = None, flux
        if self._flux_fields is None and flux == "smoothed":
            pg = self._grid
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
            normal_flux = -self._boundary_material()[0] * self._be.normal_gradient()
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
            self._rho, self._keys["rho"] = geo["interp"] @ surface_reflectance(scene, self._grid), rho_key
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
        pg = self._grid
        lo, hi = pg.positions.min(axis=0), pg.positions.max(axis=0)
        if getattr(self, "_edited", False) or scene.material.volume or scene.material.nodes:
            nodes = np.flatnonzero(self._be.active)
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
        geo, pg = self._geo, self._grid
        if "thickness" not in geo:     # ray casts: once per grid, kept in the disk cache with it
            S = len(pg.boundary_positions)
            pick = np.unique(np.linspace(0, S - 1, min(S, THICKNESS_SAMPLES)).astype(np.int64))
            p, n, h = pg.boundary_positions[pick], -np.asarray(pg.normals)[pick], self._be.h
            key = cache.digest("thickness v1", geo["mesh"].vertices, geo["mesh"].faces, p, n, h)
            T = cache.memo("thickness", key, np.ndarray, lambda: first_hits(geo["mesh"], p, n, t_min=0.5 * h)[0])
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
            pg = self._grid
            fluence = self._be.fluence_lattice()
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
        pg = self._grid
        rep.nodes, rep.boundary_nodes = int(pg.n_active), int(len(pg.boundary_positions))
        rep.solver = self._solve_report
        rep.clamped_vertices, rep.clamped_depth, rep.clamped_deep = self._clamped, self._clamped_depth, self._clamped_deep
        rep.notes.extend(self._be.notes(scene))
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
        rep.notes.append(regime(self._mat["kappa"], self._mat["mu"], self._be.h,
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
        before = (self._mat["kappa"], self._mat["mu"])
        kappa, mu, result = self._be.edit(edit, view, *before)
        self._mat = {**self._mat, "kappa": kappa, "mu": mu}
        if history or self._history.counts[0] == 0:
            self._history.push(*before)
        self._edit_version += 1
        self._edited = True
        return replace(result, seconds=time.perf_counter() - t0)

    def _set_edited_material(self, kappa: NDArray, mu: NDArray) -> None:
        """Hand a changed node material (undo, redo) to the backend."""
        self._mat = {**self._mat, "kappa": kappa, "mu": mu}
        self._be.edited(kappa, mu)

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
        pg = self._grid
        act = self._be.active
        k, m = (self._mat[n].reshape(-1, 3)[act] for n in ("kappa", "mu"))
        return write_npz(path, kappa=k, mu=m, positions_mm=np.asarray(pg.positions)[act],
                         source=str(self._mat["info"].get("material")))

    def release(self) -> None:
        if self._backend is not None:
            self._backend.release()

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
