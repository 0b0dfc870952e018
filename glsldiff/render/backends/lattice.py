"""The lattice polygrid backend (Wang et al. 2008): the polycube's lattice of nodes, its level
hierarchy and the GLSL multilevel solver (:class:`glsldiff.solve.multilevel.MultilevelDiffusion`);
edits are a GPU pass over the solver's material textures (:class:`glsldiff.render.editing.GpuMaterialEditor`)
in fp32/fp16, their numpy twin with 8-bit material. Under ``frame_sweeps`` (interactive) a frame
with a new edit runs that many sweeps of the finest level and skips the residual check; later
frames run that many sweeps each until ``tol``."""
from __future__ import annotations

import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from glsldiff import gl
from glsldiff.core import cache
from glsldiff.core.errors import SolverError
from glsldiff.grids.cache import cached_polygrid
from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.mesh import Mesh
from glsldiff.physics.editing import KAPPA_MIN, Edit, EditResult, EditView, apply_edit
from glsldiff.render.backends import PASS2_HINT, GridBackend, Pass2Frame, Pass2Inputs
from glsldiff.render.editing import GpuMaterialEditor
from glsldiff.render.scene import Scene
from glsldiff.render.shading import vertex_interpolation
from glsldiff.solve.multilevel import MultilevelDiffusion
from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.report import CURRENT, SolveReport

__all__ = ["LatticeBackend"]


class LatticeBackend(GridBackend):
    """The lattice polygrid behind the renderer (module docstring)."""

    kind = "lattice"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._solver: MultilevelDiffusion | None = None
        self._editor: GpuMaterialEditor | None = None
        self.hierarchy: Hierarchy | None = None

    def setup(self, scene: Scene, mesh: Mesh) -> tuple[Mesh, Mesh | None]:
        g = scene.polygrid
        t0 = time.perf_counter()
        self.say(f"setup: polygrid of {scene.mesh.source} (n = {g.n}, about {g.cubes} cubes): building it takes "
                 "seconds to minutes the first time, then it is read from the cache")
        pg, cached = cached_polygrid(mesh, n=g.n, n_cubes=g.cubes)
        self.say(f"setup: polygrid {'read from the cache' if cached else 'built'} in "
                 f"{time.perf_counter() - t0:.1f} s ({pg.n_active:,} nodes)")
        self.grid, self.h = pg, float(pg.lattice.h)
        self.hierarchy = Hierarchy.build(pg, g.levels)   # levels = 1: the polygrid alone
        return mesh, None

    def interpolation(self, vertices: NDArray[np.float64]) -> Any:
        return vertex_interpolation(vertices, self.grid.boundary_positions)

    @property
    def material_shape(self) -> tuple[int, ...]:
        return tuple(self.grid.shape)

    @property
    def active(self) -> NDArray[np.bool_]:
        return np.asarray(self.grid.active).reshape(-1)

    def boundary(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(values).reshape(-1, 3)[self.grid.lattice.boundary]

    # ---- edits --------------------------------------------------------------------------------
    def edit(self, edit: Edit, view: EditView | None, kappa: NDArray, mu: NDArray
             ) -> tuple[NDArray, NDArray, EditResult]:
        """On the GPU when the solver holds 32-bit material textures, else in numpy."""
        s = self._solver
        if s is None or s.finest.material_bits != 32:
            k2, m2, result = apply_edit(edit, kappa, mu, self.grid.positions, view, self.active)
            self.edited(k2, m2)
            return k2, m2, result
        if self._editor is None:
            self._editor = GpuMaterialEditor(s.finest, self.grid.positions)
        self._editor.apply(edit, view)
        k2, m2 = self._editor.read()
        s.set_material(k2, m2, finest_uploaded=True)
        x, x0 = (k2, kappa) if edit.prop == "kappa" else (m2, mu)
        changed = np.any(x != x0, axis=-1) & np.asarray(self.grid.active)
        floor = KAPPA_MIN if edit.prop == "kappa" else 0.0
        result = EditResult(int(changed.sum()), int((np.any(x <= floor, axis=-1) & changed).sum()),
                            int((np.any(3.0 * k2 * m2 > 1.0 + 1e-6, axis=-1) & changed).sum()))
        return k2, m2, result

    def edited(self, kappa: NDArray, mu: NDArray) -> None:
        if self._solver is not None:       # every level's material textures
            self._solver.set_material(kappa, mu)

    # ---- pass 2 -------------------------------------------------------------------------------
    @property
    def solver(self) -> MultilevelDiffusion | None:
        return self._solver

    def _cache_parts(self) -> tuple[Any, ...]:
        return (self.grid.weights,)

    def solve(self, inp: Pass2Inputs) -> Pass2Frame:
        scene, opts = inp.scene, inp.scene.options
        if inp.painting and self.frame_sweeps is not None and self._solver is not None:
            return self._paint_sweeps()
        self.say(f"pass 2: {opts.scheme} diffusion solve of {self.grid.n_active:,} nodes to tol {opts.tol:g}")
        gl.make_current(self.ctx)
        x0: Any = CURRENT if inp.warm and opts.scheme != "multigrid" else None
        key = self.solution_key(inp)
        from_disk = opts.scheme != "adaptive" and (x0 is None or self._solver is None)   # (adaptive: below)
        stored = cache.load("pass2", key, np.ndarray) if self.cache_solutions and from_disk else None
        if self._solver is None:
            problem = DiffusionProblem(self.grid, inp.kappa, inp.mu, inp.q, eta=scene.material.eta,
                                       stencil=scene.polygrid.discretisation)
            self._solver = MultilevelDiffusion(self.hierarchy, problem, opts.scheme, ctx=self.ctx,
                                               precision=opts.precision)
            x0 = None
        else:
            self._solver.set_q(inp.q)
        from_cache = False
        if x0 is None and opts.scheme != "adaptive":   # adaptive needs its coarse-to-fine start
            x0 = stored
            from_cache = x0 is not None
        budget: dict[str, Any] = {}
        partial = self.frame_sweeps is not None and isinstance(x0, str)   # x0 = CURRENT
        if partial:      # frame coherence: a few sweeps now, more next frame
            budget = {"maxiter": self.frame_sweeps, "check_every": self.frame_sweeps}
        try:
            phi, rep = self._solver.solve(tol=opts.tol, x0=x0, **budget)
        except SolverError as exc:   # diverged: no image to keep, whatever allow_unconverged says
            raise SolverError(f"pass 2 did not converge: {exc}; {PASS2_HINT}") from exc
        partial = partial and rep.status not in ("converged", "stalled")
        self.check(scene, rep, partial)
        if rep.status == "converged" and not from_cache and self.cache_solutions:
            cache.store("pass2", key, np.asarray(phi))
        return Pass2Frame(self.boundary(phi), rep, partial, from_cache)

    def _paint_sweeps(self) -> Pass2Frame:
        """Pass 2 of a frame with a new edit while painting (``frame_sweeps``): the sweeps alone,
        from the previous frame's solution, and no residual check (it needs the CPU system of the
        new material); frames without a new edit check it again."""
        assert self._solver is not None and self.frame_sweeps is not None
        t0 = time.perf_counter()
        fine = self._solver.finest
        fine.sweep(self.frame_sweeps)
        phi = fine.fluence()
        rep = SolveReport(f"glsl-frame-coherent-{fine.precision} (painting: no residual check)",
                          nodes=int(self.grid.n_active), sweeps=int(self.frame_sweeps),
                          seconds=time.perf_counter() - t0, status="budget")
        return Pass2Frame(self.boundary(phi), rep, True, False)

    def release(self) -> None:
        if self._editor is not None:
            self._editor.release()
            self._editor = None
        if self._solver is not None:
            self._solver.release()
            self._solver = None
