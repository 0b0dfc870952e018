"""Three-pass rendering of a scene (Wang et al. 2008, section 5; Table III): the stages, in the
one direction data flows (numpy arrays between them), each skipped while the key of the scene
parts it depends on stays (the report says why; e.g. only the camera moved: passes 1 and 2
skipped; only a light moved: setup and material kept, pass 2 warm-started):

* **setup** (per mesh + polygrid, not part of t1..t3): the grid family's backend
  (:mod:`glsldiff.render.backends`) builds the grid; the render mesh, subdivided to its node
  spacing, and the matrix interpolating boundary-node values to its vertices;
* **material**: kappa (mm), mu (mm^-1) per node (:mod:`glsldiff.render.materials`, TransCut's paint);
* **pass 1** (t1, per light set) and the **incidence** split: the diffusion's load
  (:mod:`glsldiff.render.load`);
* **pass 2** (t2): the backend's diffusion solve (lattice: GLSL multilevel sweeps; tetrahedra:
  GPU multigrid-preconditioned CG), warm-started from the previous frame when only the light or
  the material (edits) changed, on a first frame from the converged solution of the same system
  cached on disk (:mod:`glsldiff.core.cache`; the lattice checks its residual, tetrahedra take
  the float64 residual measured when it was stored, with a checksum);
* **pass 3** (t3, every frame): the per-vertex terms (:mod:`glsldiff.render.terms`) shaded from
  the scene's camera (:func:`glsldiff.render.shading.shade`); the report's notes and warnings
  (:mod:`glsldiff.render.frame_report`).
"""
from __future__ import annotations

import time
from dataclasses import replace
from typing import Any, Callable

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff import gl
from glsldiff.core.errors import InputError
from glsldiff.core.io import write_npz
from glsldiff.mesh import GENERATED_MESHES, SAMPLE_MESHES, cached_load_mesh, generated_mesh
from glsldiff.mesh.ops import smooth_subdivide
from glsldiff.physics.editing import Edit, EditResult, EditView
from glsldiff.physics.material import coefficients, optical_properties
from glsldiff.render.backends import GridBackend, Pass2Inputs, as_built, set_up_backend
from glsldiff.render.camera import Framing, frame_camera, scene_camera
from glsldiff.render.editing import MaterialHistory
from glsldiff.render.frame_report import THICKNESS_SAMPLES, FrameNotes
from glsldiff.render.load import (GATHER_MAX_H_SIGMA, Q_MAX, Incidence, boundary_C, effective_scene, h_sigma_t,
                                  light_load, split_incidence)
from glsldiff.render.materials import node_material
from glsldiff.render.report import RenderReport
from glsldiff.render.scene import Scene
from glsldiff.render.shading import Shader
from glsldiff.render.shadows import DepthRenderer
from glsldiff.render.terms import LIT_SHARE, FrameInputs, SurfaceTerms, key as _key, shader_lights
from glsldiff.oracle.assembly import LinearSystem
from glsldiff.system.tet_problem import TetProblem
from glsldiff.system.transcut import paint_blend, paint_weights

__all__ = ["Renderer", "GATHER_MAX_H_SIGMA", "LIT_SHARE", "THICKNESS_SAMPLES", "Q_MAX"]


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
        self._inc: Incidence | None = None        # the incidence stage's load (and the bracket's local term)
        self._q_marshak: NDArray | None = None    # pass 1's load before the incidence split
        self._beams: list = []                    # pass 1's beams (E (N, 3), refracted cosine (N,))
        self._phi_b: NDArray | None = None
        self._solve_report: Any = None
        self._from_cache = False
        self._load: NDArray | None = None
        self._history = MaterialHistory()
        self._edit_version = 0
        self._surface: tuple[Any, NDArray] | None = None
        self._model_note = ""
        self._built_grid: Any = None              # the polygrid built instead of the scene's (no polycube of it)
        self._grid_note = ""                      # and why, in one line
        self._edited = False                      # the node material differs from the scene's (edits)
        self._solutions = 0                       # pass-2 solutions so far (pass 3's caches follow each)
        self._depth: DepthRenderer | None = None  # the lights' maps of the grid's mesh, shared by passes 1 and 3
        self._light_info: list[dict[str, Any]] = []
        self._terms = SurfaceTerms(self.ctx)      # pass 3's per-vertex terms and their caches
        self._shader = Shader(self.ctx)           # pass 3's program, buffers and target, kept across frames
        self._notes = FrameNotes()
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
    def mesh_framing(self) -> Framing:
        """How the automatic camera frames the (uncut) mesh, after the first frame."""
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
        """The :class:`~glsldiff.grids.tetrahedral.tetcut.CutReport` of a scene's ``[cut]`` (None without one)."""
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
            self._backend = None
        frame = Framing.of_mesh(mesh)                # the uncut surface frames the camera
        self._backend, mesh, crease, self._built_grid, self._grid_note = set_up_backend(
            scene, mesh, self.ctx, self._say, self.frame_sweeps, self.cache_solutions, self.allow_unconverged)
        render_mesh, normals = smooth_subdivide(mesh if crease is None else crease, self._backend.h)
        v, f = np.asarray(render_mesh.vertices), np.asarray(render_mesh.faces)
        self._geo = {"mesh": mesh, "render_mesh": render_mesh, "vertices": v, "faces": f,
                     "normals": normals, "interp": self._backend.interpolation(v), "frame": frame}

    def _material(self, scene: Scene) -> None:
        pg = self._grid
        kappa, mu, info = node_material(scene, pg.positions, pg)
        for p in scene.paint:      # TransCut's paint, at the nodes (the P1 system's material lives there)
            w = paint_weights(pg.positions, p.points, p.radius_mm)
            sa, ss = optical_properties(kappa, mu)
            sa = sa if p.sigma_a is None else paint_blend(sa, p.sigma_a, w, p.strength)
            ss = ss if p.sigma_s_prime is None else paint_blend(ss, p.sigma_s_prime, w, p.strength)
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

    def effective(self, scene: Scene) -> Scene:
        """``scene`` as the last frame rendered it: on the grid built (:func:`~glsldiff.render.backends.as_built`),
        its options made concrete for the grid and material (:func:`~glsldiff.render.load.effective_scene`;
        the reason the model differs goes to the report); ``scene`` itself before a frame."""
        if not (self._geo and self._mat):
            return scene
        scene = as_built(scene, self._built_grid)
        h_sigma = h_sigma_t(self._be.h, self._mat["kappa"])
        scene, self._model_note = effective_scene(scene, self._be.volume_source, h_sigma, self.frame_sweeps is not None)
        return scene

    def _pass1(self, scene: Scene) -> None:
        """Pass 1: the light reaching the boundary nodes and its load (:func:`~glsldiff.render.load.light_load`)."""
        lit = light_load(scene, self._geo["mesh"], self._be, self._mat["kappa"], self._mat["mu"], self.ctx,
                         self._light_maps(scene))
        self._E_t, self._q_marshak, self._beams, self._load = lit.E_t, lit.q, lit.beams, lit.load
        self._light_info = lit.info

    def _light_maps(self, scene: Scene) -> DepthRenderer:
        """The grid mesh's :class:`~glsldiff.render.shadows.DepthRenderer` that keeps each light's
        shadow map: pass 1, the shading visibility and the 3-D march render a light's map once
        (the march adds its faces); maps of lights no longer in ``scene`` are dropped."""
        mesh = self._geo["mesh"]
        if self._depth is None or self._depth.mesh is not mesh:
            if self._depth is not None:
                self._depth.release()
            self._depth = None
            self._depth = DepthRenderer(self.ctx, mesh, keep_maps=True)
        self._depth.keep_lights(scene.lights)
        return self._depth

    def _incidence(self, scene: Scene) -> None:
        """The incidence stage: the diffusion's load from pass 1 (:func:`~glsldiff.render.load.split_incidence`)."""
        assert self._E_t is not None and self._q_marshak is not None
        self._inc = split_incidence(scene, self._be, self._mat["kappa"], self._mat["mu"], self._E_t, self._q_marshak,
                                    self._beams)

    @property
    def _q(self) -> NDArray[np.float64] | None:
        """``(n_boundary, 3)`` the diffusion's load (after the incidence stage; 0 with the volume source)."""
        return None if self._inc is None else self._inc.q

    def _say(self, line: str) -> None:
        if self._status is not None:
            self._status(line)

    def _pass2(self, scene: Scene, warm: bool, painting: bool = False) -> None:
        """One frame's pass 2 by the grid's backend (:mod:`glsldiff.render.backends`)."""
        frame = self._be.solve(self._pass2_inputs(scene, warm, painting))
        self._partial, self._from_cache = frame.partial, frame.from_cache
        self._solutions += 1     # pass 3's caches follow every new phi
        self._phi_b = frame.phi_b
        self._solve_report = frame.report

    def _pass2_inputs(self, scene: Scene, warm: bool = False, painting: bool = False) -> Pass2Inputs:
        return Pass2Inputs(scene, self._mat["kappa"], self._mat["mu"], self._q, self._load, boundary_C(scene),
                           warm, painting)

    def fem_problem(self, scene: Scene) -> TetProblem:
        """The last frame's P1 problem of ``scene`` (grid, node material, boundary source, eta
        and the Robin constant C) on a tetrahedral grid; without the first-collision load of
        ``source = "volume"``."""
        if not hasattr(self._backend, "problem") or self._q is None:
            raise RuntimeError("no frame of a tetrahedral grid rendered yet")
        return self._be.problem(self._pass2_inputs(scene))

    def _pass3(self, scene: Scene) -> tuple[NDArray[np.float32], FrameInputs]:
        """Shade the frame from the camera: the per-vertex terms of :class:`SurfaceTerms` and Ward
        specular; also what the terms took (:class:`~glsldiff.render.terms.FrameInputs`)."""
        assert self._E_t is not None and self._inc is not None and self._phi_b is not None
        (eye, mvp), k, geo = self._camera(scene), self._keys, self._geo
        f = FrameInputs(scene, self._be, geo, self._mat["kappa"], self._mat["mu"], self._edited, self._E_t, self._inc,
                        self._beams, self._phi_b, k.get("geometry"), k.get("material"), k.get("light"), k.get("solve"),
                        self._solutions, self._edit_version, eye, self._light_maps(scene))
        ms, vis, ss = self._terms.multiple(f), self._terms.visibility(f), self._terms.added(f, self.split_part)
        return self._shader.shade(geo["vertices"], geo["faces"], geo["normals"], ms, vis, ss, shader_lights(scene), eye,
                                  mvp, scene.material.eta, scene.specular.rho_s, scene.specular.alpha,
                                  (scene.output.width, scene.output.height)), f

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
        scene = as_built(scene, self._built_grid)      # the lattice where the mesh has no tetrahedral grid
        new_mat = stage("material", "material", mat_key, lambda: self._material(scene), "material unchanged", None)
        scene = self.effective(scene)       # the model's concrete source and single scattering
        volume = scene.options.source == "volume"
        light_key = _key(geo_key, scene.lights, scene.material.eta, scene.options.exitant, str(scene.base_dir),
                         scene.options.source, scene.options.incidence, scene.options.model,
                         (mat_key, self._edit_version) if volume else None)   # the volume load follows the material
        solve_key = _key(mat_key, light_key, scene.options.tol, self._edit_version)
        new_light = stage("pass1", "light", light_key, lambda: self._pass1(scene),
                          "lights unchanged: incident light kept", "t1")
        stage("incidence", "incidence", _key(light_key, mat_key, self._edit_version),   # edits change the albedo
              lambda: self._incidence(scene), "lights and material unchanged: load kept", None)
        warm = not (new_geo or new_mat) and (new_light or edited or going_on)
        if new_geo or new_mat:
            self._partial = False
        self._keys["edits"] = self._edit_version
        painting = warm and edited and not new_light
        stage("pass2", "solve", solve_key, lambda: self._pass2(scene, warm, painting),
              "material and incident light unchanged: solution kept", "t2")
        if rep.ran("pass2") and self._from_cache:
            rep.passes[-1]["why"] += f": from the cached solution of this system ({self._solve_report.sweeps} iterations)"
        elif rep.ran("pass2") and warm:
            what = "light changed" if new_light else "material edited" if edited else "converging"
            rep.passes[-1]["why"] = f"{what}: warm start from the previous frame (frame coherence)"
            if self._partial:
                rep.passes[-1]["why"] += f"; {self.frame_sweeps} sweeps this frame, not yet at tol"
        t0 = time.perf_counter()
        img, f = self._pass3(scene)
        rep.seconds["t3"] = time.perf_counter() - t0
        rep.passes.append({"pass": "pass3", "ran": True, "seconds": rep.seconds["t3"], "why": "every frame"})
        pg = self._grid
        rep.nodes, rep.boundary_nodes = int(pg.n_active), int(len(pg.boundary_positions))
        rep.solver = self._solve_report
        self._notes.fill(rep, f, self._terms, self._mat["info"].get("material"), self._model_note, self._light_info)
        rep.warnings[:0] = [self._grid_note] if self._grid_note else []
        return img, rep

    def _camera(self, scene: Scene) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """:func:`~glsldiff.render.camera.scene_camera` of the framed mesh, kept while the
        camera, the image size and the geometry stay."""
        key = _key(self._keys.get("geometry"), scene.camera, scene.output.width, scene.output.height)
        if self._keys.get("camera") != key:
            self._eye_mvp = scene_camera(scene, self._geo["frame"])
            self._keys["camera"] = key
        return self._eye_mvp

    def framing(self, scene: Scene) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """``(eye, target, up)`` (mm) of ``scene``'s camera on the mesh the last frame rendered
        (:func:`~glsldiff.render.camera.frame_camera`; the automatic framing when ``[camera]`` has
        no position)."""
        return frame_camera(scene, self.mesh_framing)

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
        if history or self._history.counts[0] == 0:
            self._history.push(*before)
        self._set_edited_material(kappa, mu)
        return replace(result, seconds=time.perf_counter() - t0)

    def _set_edited_material(self, kappa: NDArray, mu: NDArray) -> None:
        """The node material after an edit, undo or redo (the next frame re-solves pass 2)."""
        self._mat = {**self._mat, "kappa": kappa, "mu": mu}
        self._edit_version += 1
        self._edited = True

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
        self._be.edited(*got)
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
        self._shader.release()
        if self._backend is not None:
            self._backend.release()
        if self._depth is not None:
            self._depth.release()
            self._depth = None

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
