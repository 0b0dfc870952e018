"""The tetrahedral backend: P1 finite elements on the pillowed polycube (``[polygrid]
discretisation = "fem"``, :func:`glsldiff.grids.tetrahedral.fem_grid.build_fem_grid`, refined under the
lights' sharp edges with ``adapt``) or on an fTetWild mesh (``"tetwild"``, with TransCut's
``[cut]``), solved on the GPU by multigrid-preconditioned CG.

Pass 2, frame after frame (:class:`TetPass2`): the P1 system kept across material edits
(:class:`glsldiff.oracle.fem_update.P1System`: an edit re-sums only the entries around the
edited nodes) and the GPU multigrid-preconditioned CG
(:class:`glsldiff.solve.gather_multigrid.GlslSparseMultigrid`) kept with it (an edit re-packs the
finest level's changed texel rows; the aggregation, coarse operators and smoothing damping stay:
a stale preconditioner, still symmetric positive definite, for a local change).

Frame budget while editing (``frame_sweeps`` set, the viewer): a frame with a new edit runs
:data:`PAINT_SWEEPS` damped Jacobi sweeps of the new finest matrix from the last frame's
fluence and skips the residual check (no CPU residual); each later frame runs
:data:`FRAME_ITERATIONS` preconditioned CG iterations and measures the residual on the GPU
(fp32, two texels read back), until ``tol`` (the image converges over frames); the frame the
GPU calls converged is confirmed in float64 on the CPU. Where those frames stall (a strong edit
makes the kept coarse levels a poor preconditioner) the coarse levels are remade once from the
edited matrices (:data:`STALL_FRAMES`, :data:`STALL_RATIO`). Without a budget every frame is
solved to ``tol``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff import gl
from glsldiff.core import cache
from glsldiff.core.errors import InputError, SolverError
from glsldiff.grids.tetrahedral.adapt import ADAPT_TOL
from glsldiff.grids.cache import cached_fem_grid, cached_refined_grid, polygrid_key
from glsldiff.grids.tetrahedral.fem_grid import FEM_MAX_NODES, SPLIT_LENGTH
from glsldiff.grids.tetrahedral.shapes import SHAPE_TARGET
from glsldiff.grids.tetrahedral.tetcut import cut as cut_tets, plane_side, stroke_side
from glsldiff.grids.tetrahedral.tetwild import cached_tetrahedralize
from glsldiff.mesh import Mesh
from glsldiff.oracle.assembly import LinearSystem
from glsldiff.oracle.fem import TetGeometry, cached_tet_geometry, tet_geometry, tet_rhs
from glsldiff.oracle.fem_update import P1System, cached_p1_pattern
from glsldiff.physics.editing import Edit, EditResult, EditView, apply_edit
from glsldiff.physics.exitance import source_from_irradiance
from glsldiff.render.backends import PASS2_HINT, GridBackend, Pass2Frame, Pass2Inputs
from glsldiff.render.camera import Framing, scene_camera
from glsldiff.render.collision import first_collision_load, node_columns, surface_columns
from glsldiff.render.fluence import FluenceLattice
from glsldiff.render.pass1 import incident_light
from glsldiff.render.scene import TETRAHEDRAL, Scene
from glsldiff.render.shading import cached_surface_interpolation, surface_interpolation
from glsldiff.solve.gather_multigrid import GlslSparseMultigrid
from glsldiff.system.report import CURRENT, SolveReport
from glsldiff.system.tet_problem import TetProblem

__all__ = ["FEM_MAXITER", "FRAME_ITERATIONS", "PAINT_SWEEPS", "REBUILD_SHARE", "STALL_FRAMES", "STALL_RATIO",
           "TetBackend", "TetPass2", "TetFrame"]

#: Pass 2's iteration budget on tetrahedra: multigrid-preconditioned CG takes 10-20 iterations
#: on the scenes measured (bunny, cow, spheres, tile); a system it cannot solve in this many is
#: reported as not converged instead of running the relaxations' 20,000-sweep budget.
FEM_MAXITER = 300
#: Damped Jacobi sweeps of the finest level in a frame with a new edit (painting).
PAINT_SWEEPS = 1
#: Preconditioned CG iterations (one V-cycle each) per frame while the image converges after edits.
FRAME_ITERATIONS = 1
#: Converging frames after an edit: when the residual after this many still exceeds this share of
#: the first one's, the kept coarse levels are remade from the edited matrices (a strong local
#: edit makes them a poor preconditioner; a mu x2 stroke converges in 2-3 frames and never trips it).
STALL_FRAMES = 6
STALL_RATIO = 0.3
#: Part of the cached aggregation's key: bump it when the hierarchy's construction changes.
HIERARCHY_CACHE_VERSION = 3   # 2: smoothing damping from a Lanczos upper bound (oracle.amg.jacobi_lambda_bound); 3: symmetric strength
#: An edit changing more than this share of the nodes rebuilds the multigrid (the kept one
#: would precondition a different material).
REBUILD_SHARE = 0.25


@dataclass(frozen=True)
class TetFrame:
    """One frame's pass 2: ``phi`` ``(n_active, 3)``, the report, whether the frame stopped at
    its budget before ``tol`` (``partial``) and whether ``phi`` came from the disk cache (or
    the solve started from a cached answer that missed tol)."""

    phi: NDArray[np.float64]
    report: SolveReport
    partial: bool
    from_cache: bool


def _hierarchy(solver: GlslSparseMultigrid) -> dict[str, list]:
    """A multigrid's aggregation and smoothing damping (``P``, ``omega`` per level but the
    coarsest): what a new solver of changed matrices reuses (the disk cache, a remake)."""
    levels = [lv for lv in solver.levels if lv.P is not None]
    return {"P": [lv.P for lv in levels], "omega": [lv.omega for lv in levels]}


class TetPass2:
    """The P1 system and its GPU solver of one tetrahedral grid, kept across frames.

    ``ctx`` the GL context, ``geo`` the grid's :class:`~glsldiff.oracle.fem.TetGeometry`,
    ``active`` ``(n,)`` bool, ``cached_pattern``: the P1 pattern through the disk cache,
    ``cached_hierarchy``: the multigrid's aggregation and damping too. GPU objects belong to
    this object (:meth:`release`)."""

    def __init__(self, ctx: moderngl.Context, geo: TetGeometry, active: NDArray[np.bool_],
                 cached_pattern: bool = False, cached_hierarchy: bool = False) -> None:
        self.ctx, self.geo, self.active_mask = ctx, geo, np.asarray(active, dtype=bool)
        self.cached_pattern = cached_pattern               # the P1 pattern through the disk cache
        self.cached_hierarchy = cached_hierarchy           # the multigrid's aggregation too (per material)
        self.p1: P1System | None = None
        self.solver: GlslSparseMultigrid | None = None
        self.phi: NDArray[np.float64] | None = None        # the last frame's fluence (n_active, 3)
        self._frame_iterations = 0                         # CG iterations of converging frames since the last edit
        self._frame_residuals: list[float] = []            # their residuals
        self.refreshes = 0                                 # coarse levels remade after a stalled convergence

    @property
    def active(self) -> NDArray[np.int64]:
        return np.flatnonzero(self.active_mask)

    def reset(self) -> None:
        """A new material: the system and solver are rebuilt at the next frame."""
        self.release()
        self.p1, self.phi = None, None

    def system(self, kappa: NDArray, mu: NDArray, C: float, b: NDArray[np.float64]) -> LinearSystem:
        """The P1 system of node material ``(kappa, mu)`` ``(n, 3)``, Robin constant ``C`` and
        right-hand side ``b`` ``(n_active, 3)``: assembled once, then updated in place where the
        material changed (and the solver's finest level with it)."""
        if self.p1 is None or self.p1.C != C:
            self.release()
            pattern = cached_p1_pattern(self.geo, self.active_mask) if self.cached_pattern else None
            self.p1 = P1System(self.geo, self.active_mask, C, kappa, mu, pattern=pattern)
        else:
            up = self.p1.set_material(kappa, mu)
            if up.rows.size:
                self._frame_iterations, self._frame_residuals = 0, []
            if self.solver is not None and up.rows.size:
                if up.nodes.size > REBUILD_SHARE * len(self.active_mask):
                    self.release()
                else:
                    self.solver.update_fine(self.p1.matrices(), up.rows, diagonal_only=up.diagonal_only)
        if not np.array_equal(self.p1.system.b, np.asarray(b, dtype=np.float64).T.reshape(-1)):
            self.p1.set_rhs(b)
            self._frame_iterations, self._frame_residuals = 0, []
            if self.solver is not None:     # a new source restarts CG; the same one lets it go on
                self.solver.set_b(b)
        return self.p1.system

    def cached(self, entry: Any, tol: float) -> TetFrame | None:
        """The frame of a converged answer from the disk cache (the entry :meth:`TetBackend.solve`
        stores: ``phi``, ``residual``, ``checksum``) if it is
        intact (its checksum), of this grid's size and its residual, measured in float64 when it
        was stored, meets ``tol``; else None. The entry's key holds every input of the system
        (grid, material, source, eta, C, tol, the discretisation's version), so the system need
        not be assembled again to check it (0.4 s on the bunny): it is assembled when a frame
        changes it."""
        t0 = time.perf_counter()
        if not isinstance(entry, dict):
            return None
        x, res = entry.get("phi"), entry.get("residual")
        n = int(self.active_mask.sum())
        if (not isinstance(x, np.ndarray) or x.shape != (n, 3) or not isinstance(res, float) or not res <= tol
                or entry.get("checksum") != cache.digest(x)):
            return None
        self.phi = np.asarray(x, dtype=np.float64)
        rep = SolveReport("cached (converged when stored, its float64 residual measured then; checksum verified)",
                          nodes=n, sweeps=0, residual=res,
                          seconds=time.perf_counter() - t0, converged=True, history=[(0, res)])
        return TetFrame(self.phi, rep, False, True)

    def _build(self, x0: NDArray | None, hierarchy: dict[str, list] | None = None) -> None:
        """The GPU multigrid of the current system (its aggregation and smoothing damping read
        from the disk cache with the grid's other entries: pyamg and the damping bounds are about
        2 of the 3.7 s set-up on the bunny, quiet cores; or ``hierarchy``'s, :func:`_hierarchy`
        of an earlier solver)."""
        assert self.p1 is not None
        s = self.p1.system
        if self.solver is None:
            key = (cache.digest(f"multigrid v{HIERARCHY_CACHE_VERSION}", self.p1.values, self.p1.indices,
                                self.p1.indptr) if self.cached_hierarchy and hierarchy is None else None)
            kept = cache.load("multigrid", key, dict) if key is not None else hierarchy
            self.solver = GlslSparseMultigrid(self.p1.matrices(), s.b.reshape(3, -1).T, ctx=self.ctx,
                                              prolongations=None if kept is None else kept["P"],
                                              level_omegas=None if kept is None else kept["omega"])
            if key is not None and kept is None:
                cache.store("multigrid", key, _hierarchy(self.solver))
            if x0 is not None:
                self.solver.set_initial(x0)

    def _refresh_coarse(self) -> None:
        """The multigrid of the current matrices with the kept aggregation and smoothing damping
        (Galerkin products, packing and upload again; no pyamg, no eigen-solves: about 1.4 s on the
        bunny), continuing from the current fluence: the kept coarse levels precondition a
        strongly edited material poorly (mu x10 under a stroke: 0.087 -> 0.034 in 36 CG
        iterations)."""
        assert self.solver is not None
        kept, phi = _hierarchy(self.solver), self.solver.unknown()
        self.release()
        self._build(phi, kept)
        self.refreshes += 1

    def prepare(self) -> None:
        """Build the solver now, from the last frame's answer (an interactive first frame served
        from the disk cache: the first edit or light change then costs a frame, not a set-up)."""
        if self.solver is None and self.p1 is not None and self.phi is not None:
            self._build(self.phi)

    def solve(self, tol: float, *, warm: bool, painting: bool = False, frame_budget: bool = False,
              x0: NDArray | None = None) -> TetFrame:
        """Pass 2 of a frame (module docstring): ``warm`` starts from the last frame's fluence,
        ``painting`` (a frame with a new edit, under ``frame_budget``) runs Jacobi sweeps
        only; ``x0`` a start for a cold solve (e.g. the disk cache's answer of another tol)."""
        if self.p1 is None:
            raise RuntimeError("TetPass2.solve before system()")
        start = self.phi if warm and self.phi is not None else x0
        fresh = self.solver is None
        self._build(start)
        solver = self.solver
        assert solver is not None
        if painting and frame_budget and not fresh:
            t0 = time.perf_counter()
            solver.smooth(PAINT_SWEEPS)
            self.phi = solver.unknown()
            rep = SolveReport(f"glsl-frame-coherent Jacobi (painting: {PAINT_SWEEPS} sweeps of the finest level, "
                              "no residual check)", nodes=solver.n, sweeps=PAINT_SWEEPS,
                              seconds=time.perf_counter() - t0, status="budget")
            return TetFrame(self.phi, rep, True, False)
        if frame_budget and warm and not fresh:
            return self._converging_frame(tol)
        budget = FRAME_ITERATIONS if frame_budget and warm else FEM_MAXITER
        phi, rep = solver.solve(tol=tol, maxiter=budget, x0=CURRENT if (warm or start is not None) else None)
        self.phi = phi
        partial = frame_budget and warm and rep.status not in ("converged", "stalled")
        return TetFrame(phi, rep, partial, fresh and not warm and x0 is not None)   # started from the disk cache

    def _converging_frame(self, tol: float) -> TetFrame:
        """A frame of the image converging after an edit or a light change: :data:`FRAME_ITERATIONS`
        CG iterations from where the last frame stopped, the residual measured on the GPU
        (:meth:`~glsldiff.solve.gather_multigrid.GlslSparseMultigrid.residual_gpu`, two texels read
        back); only a frame it calls converged is confirmed in float64 on the CPU. After
        :data:`FEM_MAXITER` iterations without reaching ``tol`` the frame is final, unconverged."""
        solver, p1 = self.solver, self.p1
        assert solver is not None and p1 is not None
        s = p1.system
        t0 = time.perf_counter()
        solver.cycle(FRAME_ITERATIONS)
        self._frame_iterations += FRAME_ITERATIONS
        res, where = solver.residual_gpu(), "GPU fp32"
        self.phi = solver.unknown()
        if not res > tol:          # converged by the GPU's measure (or nan: none): the float64 check decides
            res, where = s.residual(self.phi.T.reshape(-1)), "CPU float64"
        done = res <= tol
        partial = not done and self._frame_iterations < FEM_MAXITER
        self._frame_residuals.append(float(res))
        hist = self._frame_residuals
        if partial and len(hist) == STALL_FRAMES and hist[-1] > STALL_RATIO * hist[0]:
            self._refresh_coarse()
        rep = SolveReport(f"{solver.method}-{solver.precision}(PCG, frame-coherent: {FRAME_ITERATIONS} iteration(s) "
                          f"a frame, residual on the {where})", nodes=solver.n, sweeps=FRAME_ITERATIONS,
                          residual=float(res), seconds=time.perf_counter() - t0, converged=done,
                          history=[(self._frame_iterations, float(res))],
                          status="converged" if done else "budget")
        return TetFrame(self.phi, rep, partial, False)

    def release(self) -> None:
        if self.solver is not None:
            self.solver.release()
            self.solver = None


class TetBackend(GridBackend):
    """The tetrahedral grids behind the renderer (module docstring)."""

    kind = "tetrahedral"
    volume_source = True

    @staticmethod
    def handles(discretisation: str) -> bool:
        return discretisation in TETRAHEDRAL

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.geo: TetGeometry | None = None
        self.pass2: TetPass2 | None = None
        self.adapt_report: Any = None
        self.cut_report: Any = None
        self.cut_seconds = 0.0
        self._b: tuple[Any, ...] | None = None       # (q, load, C, eta, b): the right-hand side of that source
        self._columns: tuple[Any, Any] | None = None
        self._fluence: FluenceLattice | None = None
        self._cached = False
        self._pixels: tuple[Any, Any] | None = None  # (view key, the nodes' (uv, front) in it)
        self._last: Pass2Inputs | None = None        # the last frame's pass-2 inputs

    # ---- set-up -------------------------------------------------------------------------------
    def setup(self, scene: Scene, mesh: Mesh) -> tuple[Mesh, Mesh | None]:
        m, g = scene.mesh, scene.polygrid
        t0 = time.perf_counter()
        if g.discretisation == "tetwild":
            what = "fTetWild tetrahedral mesh"
            self.say(f"setup: {what} of {m.source} (edge {g.edge_mm:g} mm): building it takes seconds to many "
                     "minutes the first time, then it is read from the cache")
            pg, cached = cached_tetrahedralize(mesh, float(g.edge_mm), status=self.say)
        else:
            what = "tetrahedral polygrid"
            self.say(f"setup: {what} of {m.source} (n = {g.n}, about {g.cubes} cubes): building it takes "
                     "seconds to minutes the first time, then it is read from the cache")
            pg, cached = cached_fem_grid(mesh, n=g.n, n_cubes=g.cubes)
        self.say(f"setup: {what} {'read from the cache' if cached else 'built'} in "
                 f"{time.perf_counter() - t0:.1f} s ({pg.n_active:,} nodes)")
        if g.discretisation == "fem" and pg.quality.fine_reason:   # tetwild grids have no polycube
            self.say(f"setup: built from {len(pg.polycube.cubes):,} cubes of {pg.complex.lattice.n} nodes per edge at "
                     f"about the same spacing instead: with n = {g.n}, {pg.quality.fine_reason}")
        if scene.refines:
            pg = self._adapt(scene, mesh, pg)
        crease = None
        if scene.cut is not None:
            pg, mesh, crease = self._cut(scene, pg, Framing.of_mesh(mesh))   # as the renderer frames it
        self.grid, self.h = pg, float(pg.h)
        self._pixels = None
        self.surface_triangles = pg.surface_triangles
        # a grid read from the cache keeps its P1 factors and render-mesh interpolation there too (a
        # refined grid one entry per light set, as its grid); a cut changes with every stroke (no entry)
        self._cached = scene.cut is None
        self.geo = cached_tet_geometry(pg) if self._cached else tet_geometry(pg)
        self.pass2 = TetPass2(self.ctx, self.geo, np.asarray(pg.active, dtype=bool), cached_pattern=self._cached,
                              cached_hierarchy=self._cached and self.cache_solutions)
        return mesh, crease

    def _adapt(self, scene: Scene, mesh: Mesh, pg: Any) -> Any:
        """The fem grid refined under the lights' sharp edges (:mod:`glsldiff.grids.tetrahedral.adapt`),
        marked by pass 1's source sampled at the surface nodes (shadows included)."""
        def source(P: NDArray, N: NDArray) -> NDArray:
            E_t, _ = incident_light(mesh, P, N, scene.lights, scene.material.eta, ctx=self.ctx)
            return source_from_irradiance(np.asarray(E_t, dtype=np.float64), scene.material.eta, scene.options.exitant)
        base = polygrid_key(mesh, "femgrid", n=scene.polygrid.n, n_cubes=scene.polygrid.cubes)
        pg, rep, cached = cached_refined_grid(pg, base, source, max_nodes=FEM_MAX_NODES)
        self.adapt_report = rep
        if rep.edges:
            self.say(f"setup: {rep.line()}{' (read from the cache)' if cached else ''} ({pg.n_active:,} nodes)")
        return pg

    def _cut(self, scene: Scene, tm: Any, frame: Framing) -> tuple[Any, Mesh, Mesh]:
        """TransCut's cut of the fTetWild mesh ``tm`` (``[cut]``), its report kept in
        :attr:`cut_report`: the cut mesh, its boundary as a triangle mesh (shadows, ray casts)
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
        self.say(f"setup: cutting {len(tm.tets):,} tetrahedra by the {what}")
        t0 = time.perf_counter()
        cm, rep = cut_tets(tm, side, iterations=c.iterations)
        self.cut_report = rep
        self.cut_seconds = time.perf_counter() - t0
        V, F = cm.boundary_positions, cm.surface_triangles
        flat = Mesh(V, F, name=f"{scene.mesh.source} (cut)")
        cf = F[cm.cut_faces]
        used = np.unique(cf)
        F2 = np.concatenate([F[~cm.cut_faces], len(V) + np.searchsorted(used, cf)])
        keep, F2 = np.unique(F2, return_inverse=True)             # drop the copies no face uses
        return cm, flat, Mesh(np.concatenate([V, V[used]])[keep], F2.reshape(-1, 3), name=flat.name)

    def interpolation(self, vertices: NDArray[np.float64]) -> Any:
        interp = cached_surface_interpolation if self._cached else surface_interpolation
        return interp(vertices, self.grid.boundary_positions, self.grid.surface_triangles)

    @property
    def material_shape(self) -> tuple[int, ...]:
        return (len(self.grid.positions),)

    @property
    def active(self) -> NDArray[np.bool_]:
        return np.asarray(self.grid.active, dtype=bool).reshape(-1)

    def boundary(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.asarray(values)[self.grid.surface_nodes]

    def set_material(self) -> None:
        assert self.pass2 is not None
        self.pass2.reset()
        self._b = None

    def edit(self, edit: Edit, view: EditView | None, kappa: NDArray, mu: NDArray
             ) -> tuple[NDArray, NDArray, EditResult]:
        """The numpy edit; the P1 system follows the new material at the next pass 2, in place.
        The nodes' pixel coordinates are kept while the view's camera and size stay (a stroke's
        dabs: projecting all 147k nodes of the bunny was 15-20 ms of each painting frame)."""
        pixels = None
        if view is not None:
            key = (view.matrix.tobytes(), view.size)
            if self._pixels is None or self._pixels[0] != key:
                self._pixels = (key, view.pixels(self.grid.positions))
            pixels = self._pixels[1]
        return apply_edit(edit, kappa, mu, self.grid.positions, view, None, pixels)

    # ---- what the tetrahedral models need -----------------------------------------------------
    def volume_load(self, kappa: NDArray, mu: NDArray, beams: list) -> NDArray[np.float64]:
        """The first-collision load ``(n, 3)`` of pass 1's ``beams`` (:mod:`glsldiff.render.collision`)."""
        assert self.geo is not None
        if self._columns is None:      # geometry only: once per grid, not per light
            self.say("pass 1: the surface's columns and each node's place in them (once per grid)")
            cols = surface_columns(self.grid)
            self._columns = (cols, node_columns(self.grid, cols))
        return first_collision_load(self.grid, kappa, mu, beams, self.geo.node_volumes, *self._columns)

    def _at_nodes(self, x: NDArray) -> NDArray[np.float64]:
        """``(n, 3)``: per-active-node values ``(n_active, 3)`` at every node (0 at inactive ones)."""
        assert self.pass2 is not None
        full = np.zeros((len(self.grid.positions), 3))
        full[self.pass2.active] = x
        return full

    def node_fluence(self) -> NDArray[np.float64]:
        """``(n, 3)`` the last frame's fluence at every node (0 at inactive ones)."""
        assert self.pass2 is not None and self.pass2.phi is not None
        return self._at_nodes(self.pass2.phi)

    def fluence_lattice(self) -> FluenceLattice:
        """The last frame's fluence on the sampling lattice of the split's gather."""
        if self._fluence is None:
            self.say("pass 3: sampling lattice of the tetrahedral grid for the gather (once per grid)")
            self._fluence = FluenceLattice(self.grid.positions, self.grid.tets)
        self._fluence.set_values(self.node_fluence())
        return self._fluence

    def normal_gradient(self) -> NDArray[np.float64]:
        """``(n_boundary, 3)`` the recovered gradient of the last fluence along the outward normal."""
        assert self.geo is not None
        grad = self.geo.recovered_gradient(self.node_fluence())[self.grid.surface_nodes]      # (S, 3, 3)
        return np.einsum("sjc,sj->sc", grad, self.grid.normals)

    def problem(self, inp: Pass2Inputs) -> TetProblem:
        """The frame's P1 problem (grid, node material, boundary source, eta, C)."""
        return TetProblem(self.grid, inp.kappa, inp.mu, inp.q, eta=inp.scene.material.eta, C=inp.C)

    def surface_values(self, x: NDArray) -> NDArray[np.float64]:
        """``(n_surface, 3)``: per-active-node values ``(n_active, 3)`` at the surface nodes."""
        return self._at_nodes(x)[self.grid.surface_nodes]

    @property
    def system(self) -> LinearSystem | None:
        """The P1 system of the last frame (``None`` before one). Brought to that frame's
        material and source here: a frame answered from the disk cache assembles nothing, so
        the system could still hold an earlier frame's source (or none)."""
        if self.pass2 is None or self._last is None:
            return None
        return self.linear_system(self._last)

    # ---- pass 2 -------------------------------------------------------------------------------
    @property
    def solver(self) -> GlslSparseMultigrid | None:
        return None if self.pass2 is None else self.pass2.solver

    def _cache_parts(self) -> tuple[Any, ...]:
        return (self.grid.tets,)

    def linear_system(self, inp: Pass2Inputs) -> LinearSystem:
        """The P1 system of the frame's material and source (assembled once per material,
        updated in place after edits; ``b`` recomputed only for a new source)."""
        assert self.pass2 is not None
        # pass 1 makes new arrays for a new source: keep them (an id() could be a freed array's)
        old = self._b
        if old is None or old[0] is not inp.q or old[1] is not inp.load or old[2:4] != (inp.C, inp.scene.material.eta):
            b = tet_rhs(self.problem(inp), self.geo)
            if inp.load is not None:
                b = b + inp.load[self.pass2.active]
            self._b = (inp.q, inp.load, inp.C, inp.scene.material.eta, b)
        return self.pass2.system(inp.kappa, inp.mu, inp.C, self._b[4])

    def solve(self, inp: Pass2Inputs) -> Pass2Frame:
        scene, opts = inp.scene, inp.scene.options
        if opts.precision != "fp32":
            raise InputError(f"{scene.source}: [options].precision = {opts.precision!r}: the fem discretisation "
                             "solves in fp32 only; use precision = \"fp32\"")
        interactive = self.frame_sweeps is not None
        if not (interactive and inp.warm):
            self.say(f"pass 2: multigrid-preconditioned CG (tetrahedra) diffusion solve of {self.grid.n_active:,} "
                     f"nodes to tol {opts.tol:g}")
        gl.make_current(self.ctx)
        tet = self.pass2
        assert tet is not None
        self._last = inp
        key = self.solution_key(inp) if self.cache_solutions and not (interactive and inp.warm) else None
        entry = cache.load("pass2", key, dict) if key is not None and tet.solver is None else None
        frame = tet.cached(entry, opts.tol) if entry is not None else None
        if frame is None or interactive:     # the solve needs the system; the viewer's solver is built now
            self.linear_system(inp)
        if frame is None:
            stored = entry.get("phi") if entry is not None else None
            x0 = stored if isinstance(stored, np.ndarray) and stored.shape == (tet.active.size, 3) else None
            try:
                frame = tet.solve(opts.tol, warm=inp.warm, painting=inp.painting, frame_budget=interactive, x0=x0)
            except SolverError as exc:
                raise SolverError(f"pass 2 did not converge: {exc}; {PASS2_HINT}") from exc
        self.check(scene, frame.report, frame.partial)
        if key is not None and frame.report.status == "converged" and not frame.from_cache:
            phi = np.asarray(frame.phi)
            cache.store("pass2", key, {"phi": phi, "residual": float(frame.report.residual),
                                       "checksum": cache.digest(phi)})
        if interactive:           # the first edit or light change then costs a frame, not a set-up
            tet.prepare()
        return Pass2Frame(self.surface_values(frame.phi), frame.report, frame.partial, frame.from_cache)

    def notes(self, scene: Scene) -> list[str]:
        pg, out = self.grid, []
        if scene.cut is not None:
            cr = self.cut_report
            out.append(f"cut: {cr.tets_removed:,} of {cr.tets_before:,} tetrahedra removed, {cr.nodes_on_cut} of "
                       f"{cr.nodes_to_relax} vertices relaxed onto the cut ({cr.iterations} iterations, "
                       f"{cr.moves_refused} moves refused), at most {cr.max_past_cut:.3g} past it, "
                       f"{self.cut_seconds:.2f} s")
        q = pg.quality
        if scene.polygrid.discretisation == "tetwild":
            out.append(f"grid: tetrahedral (fTetWild), edge {pg.h:.3g} mm, {len(pg.tets):,} tetrahedra, "
                       f"{q.inverted} inverted, worst dihedral angle {q.min_dihedral_deg:.3g} deg, {q.slivers} "
                       f"slivers; boundary within {q.surface_distance_max:.3g} mm of the surface"
                       f"{' (before the cut)' if scene.cut is not None else ''}")
            return out
        out.append(f"grid: tetrahedral (fem), h {pg.h:.3g} mm, {len(pg.polycube.cubes):,} cubes of "
                   f"{pg.complex.lattice.n} nodes per edge"
                   f"{f' (n = {q.requested_n} asked for: {q.fine_reason})' if q.fine_reason else ''}"
                   f"{f', {q.retries} rebuilds with other cube sizes (kept: x{q.size_factor:g})' if q.retries else ''}, "
                   f"{len(pg.tets):,} tetrahedra, {q.inverted} "
                   f"inverted, worst quality {q.worst_quality:.3g} ({q.poor_before:,} -> {q.poor:,} below "
                   f"{SHAPE_TARGET:g} by the shape step), {q.split_edges:,} edges longer than "
                   f"{SPLIT_LENGTH:g} h split ({q.split_poor_before:,} -> {q.split_poor:,} below {SHAPE_TARGET:g} "
                   "after it); coverage: mesh vertices within "
                   f"{q.coverage_max:.2f} h of a surface node (99 %: {q.coverage_p99:.2f} h)")
        ar = self.adapt_report
        out.append("adapt: off ([polygrid] adapt = true refines under the lights' sharp edges; \"auto\", "
                   "the default, only under a spot's or projector's)"
                   if ar is None else f"adapt: {ar.line()}" if ar.edges else
                   f"adapt: the source is linear along every surface edge (to {ADAPT_TOL:.0%} of its "
                   "largest value): grid not refined")
        return out

    def release(self) -> None:
        if self.pass2 is not None:
            self.pass2.release()
