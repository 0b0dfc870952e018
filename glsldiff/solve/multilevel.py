"""Hierarchical, adaptive and multigrid polygrid diffusion in GLSL (Wang et al. 2008, sec. 5.3).

One :class:`~glsldiff.solve.polyjacobi.PolygridDiffusion` per level of a
:class:`~glsldiff.grids.hierarchy.Hierarchy` holds that level's texture pyramid entry (T_kappa,
T_mu, T_q, T_w1, T_w2) and its sweep primitives. Schemes:

``"single"``
    Jacobi on the finest level alone, from zero (the reference of figure 15).
``"hierarchical"``
    The paper's coarse-to-fine solve: relax the coarsest level, copy each node's value to
    its children (prolongation pass) as the initial guess of the next finer level, and so on
    down to the finest. All levels render into the finest level's ping-pong pair (the
    radiance buffers are reused across levels, as in the paper).
``"adaptive"``
    As hierarchical, but at each finer level only the nodes within ``depths[l]`` mm of the
    surface are updated (figure 8); deeper nodes keep the value copied from the coarser level.
    Their sweeps draw primitives over the updated nodes only, and their residual is that of
    the system with the deeper nodes pinned (:meth:`LinearSystem.pinned`). Texture blocks
    (z-slices of a cube) with no node that the level uses are dropped from that level's
    textures (:func:`used_nodes`); the returned fluence at the nodes a level does not hold
    is the coarser levels' value copied down (parent injection).
``"multigrid"``
    Beyond the paper (which skipped it): V-cycles of the correction scheme on the same
    pyramids. Each level has its own ping-pong pair (as the paper notes, the V-cycle needs
    that extra storage), damped-Jacobi smoothing, a residual pass over the sweep primitives,
    restriction into the coarser level's T_q (:file:`restrict.frag`) and the prolonged
    correction added back (:file:`prolong.frag`).

Every solve returns the fluence and a :class:`~glsldiff.system.report.SolveReport` whose
``levels`` list says, per level that ran: n, nodes updated per sweep, sweeps, residual and
seconds, and whose ``work`` counts node updates (figure 15's x axis).
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from typing import Callable, Sequence

import moderngl
import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff import gl
from glsldiff.core.errors import InputError, SolverError
from glsldiff.grids.graph import BOUNDARY, INACTIVE
from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.solve.jacobi import buffer_precision
from glsldiff.solve.polyjacobi import PolygridDiffusion
from glsldiff.grids.polygrid import Polygrid
from glsldiff.system.problem import DiffusionProblem, level_problems
from glsldiff.oracle.assembly import LinearSystem, assemble, assemble_rhs, diverged_message
from glsldiff.system.report import ConvergenceMonitor

from glsldiff.system.report import SolveReport, contraction_error_estimate

logger = logging.getLogger(__name__)

SCHEMES = ("single", "hierarchical", "adaptive", "multigrid")
_QUAD = np.array([[0, 0], [1, 0], [1, 1], [0, 0], [1, 1], [0, 1]], dtype="f4")


def update_masks(hierarchy: Hierarchy, depths: Sequence[float | None]) -> list[NDArray[np.bool_] | None]:
    """Per level (finest first), the nodes the adaptive scheme updates: those within
    ``depths[l]`` mm of the surface, and every boundary node; ``None`` (all) where
    ``depths[l]`` is ``None``. The coarsest level is always solved whole."""
    if len(depths) != hierarchy.levels:
        raise InputError(f"depths has {len(depths)} entries for {hierarchy.levels} levels "
                         "(finest first; None = all nodes)")
    out: list[NDArray[np.bool_] | None] = []
    for lev, d in enumerate(depths):
        if d is None or lev == hierarchy.levels - 1:
            out.append(None)
            continue
        if not (np.isfinite(d) and d >= 0):
            raise InputError(f"depths[{lev}]={d!r} mm must be a finite depth >= 0 or None")
        g = hierarchy.grids[lev]
        kind = g.lattice.kind
        out.append(((hierarchy.depth(lev) <= d) & (kind != INACTIVE)) | (kind == BOUNDARY))
    return out


def used_nodes(hierarchy: Hierarchy, masks: Sequence[NDArray[np.bool_] | None]) -> list[NDArray[np.bool_]]:
    """Per level (finest first), the nodes an adaptive solve touches: those it updates, the
    nodes their stencils read (interior neighbours, boundary partners) and, below the
    finest, the prolongation sources of the finer level's used nodes."""
    out: list[NDArray[np.bool_]] = []
    for lev, mask in enumerate(masks):
        lat = hierarchy.grids[lev].lattice
        upd = (lat.kind != INACTIVE) if mask is None else np.asarray(mask, dtype=bool)
        used = upd.copy()
        used[lat.neighbours[upd[lat.interior]].ravel()] = True
        used[lat.link[upd[lat.boundary]]] = True
        if lev > 0:
            src = hierarchy.transfers[lev - 1].source[out[-1]]
            used[src[src >= 0]] = True
        out.append(used & (lat.kind != INACTIVE))
    return out


def used_blocks(grid: Polygrid, used: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``(cubes * n,)`` texture blocks (z-slices ``cube * n + z``) holding a used node."""
    return np.asarray(used, dtype=bool).reshape(grid.shape[0] * grid.n, grid.n * grid.n).any(axis=1)


class MultilevelDiffusion:
    """A multiresolution GLSL solver of ``problem`` (on ``hierarchy.grids[0]``).

    Parameters
    ----------
    hierarchy
        The levels (:class:`glsldiff.grids.hierarchy.Hierarchy`).
    problem
        The finest-level problem; coarser levels get the restricted material and source.
    scheme
        One of :data:`SCHEMES` (module docstring).
    depths
        ``"adaptive"`` only: per level, finest first, the depth in mm below which nodes keep
        the coarser level's value (``None``: all nodes; the coarsest is always whole). The
        paper has the user give them; :func:`glsldiff.convergence_bench.choose_depths`
        picks them for a requested error.
    damping
        ``"multigrid"`` only: the damped-Jacobi smoothing factor.
    coarse_correction
        ``"multigrid"`` only: factor on the coarse-grid correction, in (0, 1]. The coarse
        levels are re-discretised and the prolongation is constant, so for smooth errors
        the coarse operator is about half the Galerkin one (R A P) and an undamped
        correction overshoots about 2x; on the distorted cells of the bunny polygrid it
        overshoots more and the V-cycle diverges at 1.0. 0.7 converges on the bench models.
    precision
        ``"fp32"``, ``"fp16"`` (radiance buffers) or ``"paper"`` (fp16 buffers, 8-bit
        kappa/mu), see :class:`~glsldiff.solve.jacobi.GlslDiffusion`.
    drop_blocks
        ``"adaptive"`` only: leave the texture blocks a level does not use out of its
        textures (the paper; default). ``False`` keeps every block (same result, more
        texture memory), for comparison.
    """

    def __init__(self, hierarchy: Hierarchy, problem: DiffusionProblem, scheme: str = "hierarchical",
                 ctx: moderngl.Context | None = None, precision: str = "fp32",
                 depths: Sequence[float | None] | None = None, damping: float = 0.8,
                 coarse_correction: float = 0.7, drop_blocks: bool = True) -> None:
        if scheme not in SCHEMES:
            raise InputError(f"scheme={scheme!r}; choose one of {SCHEMES}")
        if (depths is not None) != (scheme == "adaptive"):
            raise InputError("depths are given with scheme='adaptive' and only then")
        if not (isinstance(coarse_correction, (int, float)) and 0.0 < coarse_correction <= 1.0):
            raise InputError(f"coarse_correction={coarse_correction!r} must be in (0, 1]")
        self.coarse_correction = float(coarse_correction)
        self.hierarchy, self.scheme = hierarchy, scheme
        self.ctx = ctx if ctx is not None else gl.get_context()
        gl.make_current(self.ctx)
        buffers = buffer_precision(precision)
        problems = level_problems(hierarchy, problem) if scheme != "single" else [problem]
        masks = update_masks(hierarchy, depths) if depths is not None else [None] * len(problems)
        self.masks = masks
        self.used = used_nodes(hierarchy, masks) if scheme == "adaptive" else None
        if self.used is not None and drop_blocks:  # drop the texture blocks a level does not use
            problems = [replace(p, grid=p.grid.with_blocks(used_blocks(p.grid, u)))
                        for p, u in zip(problems, self.used)]
        mg = scheme == "multigrid"
        self.levels: list[PolygridDiffusion] = []
        self._objects: list = []
        try:
            shared = None
            if not mg:  # one ping-pong pair for all levels, as large as the largest level's textures
                size = tuple(max(p.grid.texture_size[i] for p in problems) for i in (0, 1))
                shared = self._keep(gl.PingPong.create(self.ctx, size, buffers))
            for lev, p in enumerate(problems):
                self.levels.append(PolygridDiffusion(
                    p, self.ctx, precision, update=masks[lev], state=shared,
                    damping=damping if mg else 1.0, interior_rhs=mg and lev > 0))
            self._build_transfers()
        except Exception:
            self.release()
            raise
        self._full_systems: dict[int, LinearSystem] = {}

    @property
    def finest(self) -> PolygridDiffusion:
        return self.levels[0]

    @property
    def problem(self) -> DiffusionProblem:
        return self.finest.problem

    # ---- GPU set-up of the transfer passes -------------------------------------------------
    def _keep(self, obj):  # noqa: ANN001, ANN202
        self._objects.append(obj)
        return obj

    def _quad(self, prog: moderngl.Program, size: tuple[int, int]) -> moderngl.VertexArray:
        vbo = self._keep(self.ctx.buffer((_QUAD * np.array(size, dtype="f4")).tobytes()))
        return self._keep(self.ctx.vertex_array(prog, [(vbo, "2f", "in_pos")]))

    def _build_transfers(self) -> None:
        ctx, L = self.ctx, len(self.levels)
        defines = {"STENCIL_PAPER": int(self.problem.stencil == "paper"),
                   "MATERIAL_8BIT": int(self.finest.material_bits == 8)}
        self._prolong: list[tuple[moderngl.Program, moderngl.VertexArray, moderngl.Texture]] = []
        self._copy: list[tuple[moderngl.Program, moderngl.VertexArray]] = []
        self._residual: list[tuple[list, moderngl.Texture, moderngl.Framebuffer]] = []
        self._restrict: list[tuple[moderngl.Program, moderngl.VertexArray, moderngl.Framebuffer]] = []
        for lev in range(L - 1):
            fine, coarse = self.levels[lev], self.levels[lev + 1]
            fg, cg = fine.problem.grid, coarse.problem.grid
            t = self.hierarchy.transfers[lev]
            src = np.full((fg.size, 2), -1.0)
            ok = t.source >= 0
            src[ok] = cg.mosaic.texel(t.source[ok])
            src_tex = self._keep(gl.float_texture(ctx, fine.size, fg.mosaic.pack(src)))
            prog = self._keep(gl.program(ctx, "quad.vert", "prolong.frag",
                                         {**defines, "ADD": int(self.scheme == "multigrid")}))
            self._set(prog, {"u_size": tuple(float(s) for s in fine.size)})
            self._prolong.append((prog, self._quad(prog, fine.size), src_tex))
            cprog = self._keep(gl.program(ctx, "quad.vert", "copy.frag"))
            self._set(cprog, {"u_size": tuple(float(s) for s in fine.size)})
            self._copy.append((cprog, self._quad(cprog, fine.size)))
            if self.scheme != "multigrid":
                continue
            res_tex = self._keep(gl.float_texture(ctx, fine.size))
            res_fbo = self._keep(ctx.framebuffer(color_attachments=[res_tex]))
            arrays = []
            for name, row in (("interior", 0), ("boundary", 1)):
                rp = fine._program("polygrid.vert", "polygrid_residual.frag",  # owned by the level
                                   {**fine._defines, "ROW_BOUNDARY": row, "PER_NODE_D": 1})
                arrays += fine.pass_arrays(rp, name)
            self._residual.append((arrays, res_tex, res_fbo))
            rprog = self._keep(gl.program(ctx, "quad.vert", "restrict.frag"))
            self._set(rprog, {"u_size": tuple(float(s) for s in coarse.size), "u_nc": cg.n,
                              "u_txc": cg.mosaic.tiles[0], "u_txf": fg.mosaic.tiles[0]})
            rhs_fbo = self._keep(ctx.framebuffer(color_attachments=[coarse._textures["u_q"]]))
            self._restrict.append((rprog, self._quad(rprog, coarse.size), rhs_fbo))

    @staticmethod
    def _set(prog: moderngl.Program, values: dict[str, object]) -> None:
        for k, v in values.items():
            if k in prog:
                prog[k] = v

    @staticmethod
    def _bind(prog: moderngl.Program, textures: dict[str, moderngl.Texture]) -> None:
        for unit, (name, tex) in enumerate(textures.items()):
            tex.use(unit)
            if name in prog:
                prog[name] = unit

    # ---- the transfer passes ---------------------------------------------------------
    transfer_seconds = 0.0  # wall time of the transfer passes (GPU finished)

    @property
    def compute_seconds(self) -> float:
        """GPU time so far in sweeps and transfer passes (read-backs and CPU checks excluded)."""
        return self.transfer_seconds + sum(lv.sweep_seconds for lv in self.levels)

    def _draw(self, fbo: moderngl.Framebuffer, size: tuple[int, int],
              arrays: Sequence[tuple[moderngl.VertexArray, int]]) -> None:
        """Render ``arrays`` into ``fbo`` over ``size`` texels, then re-bind the caller's framebuffer."""
        t0 = time.perf_counter()
        bound = self.ctx.fbo if self.ctx.fbo is not None else self.ctx.detect_framebuffer(0)
        fbo.use()
        self.ctx.viewport = (0, 0, *size)
        for vao, mode in arrays:
            vao.render(mode)
        bound.use()
        self.ctx.finish()
        self.transfer_seconds += time.perf_counter() - t0

    def prolong(self, lev: int, alpha: float = 1.0) -> None:
        """Level ``lev`` (coarse) -> ``lev - 1``: initial guess (hierarchical, adaptive; both
        buffers of the finer level get it, so that nodes no sweep updates keep it) or added
        correction times ``alpha`` (multigrid)."""
        gl.make_current(self.ctx)
        fine, coarse = self.levels[lev - 1], self.levels[lev]
        prog, vao, src = self._prolong[lev - 1]
        cu = coarse.material_uniforms
        self._set(prog, {**fine.material_uniforms, "u_alpha": float(alpha), **({"u_kappa_c_lo": cu["u_kappa_lo"],
                                                      "u_kappa_c_hi": cu["u_kappa_hi"]} if cu else {})})
        self._bind(prog, {"u_coarse": coarse.state.src, "u_source": src, "u_kappa": fine._textures["u_kappa"],
                          "u_kappa_c": coarse._textures["u_kappa"], "u_state": fine.state.src})
        self._draw(fine.state.dst, fine.size, [(vao, moderngl.TRIANGLES)])
        fine.state.swap()
        if self.scheme != "multigrid":
            # an initial guess goes into both buffers, so that nodes no sweep updates keep it
            # (a copy pass: a framebuffer blit between the float targets is GL_INVALID_ENUM on Mesa)
            cprog, cvao = self._copy[lev - 1]
            self._bind(cprog, {"u_src": fine.state.src})
            self._draw(fine.state.dst, fine.size, [(cvao, moderngl.TRIANGLES)])

    def residual(self, lev: int) -> moderngl.Texture:
        """Residual of level ``lev``'s rows (equation units) into its residual texture."""
        gl.make_current(self.ctx)
        lv = self.levels[lev]
        arrays, tex, fbo = self._residual[lev]
        fbo.clear(0.0, 0.0, 0.0, 0.0)
        lv.bind_textures()
        lv.state.src.use(0)
        self._draw(fbo, lv.size, arrays)
        return tex

    def restrict(self, lev: int) -> None:
        """Residual of level ``lev`` -> right-hand side T_q of level ``lev + 1``."""
        gl.make_current(self.ctx)
        prog, vao, fbo = self._restrict[lev]
        self._bind(prog, {"u_fine": self._residual[lev][1], "u_w1f": self.levels[lev]._textures["u_w1"],
                          "u_w1c": self.levels[lev + 1]._textures["u_w1"]})
        self._draw(fbo, self.levels[lev + 1].size, [(vao, moderngl.TRIANGLES)])

    # ---- solves ----------------------------------------------------------------------
    def set_q(self, q: ArrayLike) -> None:
        """New boundary source on every level (e.g. a moved light), material kept."""
        self.finest.set_q(q)
        if self.scheme in ("hierarchical", "adaptive"):
            full = self.finest.problem.q
            for lev in range(1, len(self.levels)):
                self.levels[lev].set_q(self.hierarchy.restrict_q(full, lev))
        # every level's source changed: keep the cached matrices, renew their right-hand sides
        self._full_systems = {lev: replace(s, b=assemble_rhs(self.levels[lev].problem))
                              for lev, s in self._full_systems.items()}

    def _system(self, lev: int) -> LinearSystem:
        if lev not in self._full_systems:
            self._full_systems[lev] = assemble(self.levels[lev].problem)
        return self._full_systems[lev]

    def solve(self, tol: float = 1e-5, level_sweeps: Sequence[int] | None = None, level_tol: float = 1e-2,
              max_sweeps: int = 20000, check_every: int = 25, keep: bool = False,
              callback: Callable[[int, int, NDArray], None] | None = None,
              **mg: int) -> tuple[NDArray, SolveReport]:
        """Solve to a Jacobi-scaled residual ``tol`` on the finest level.

        Parameters
        ----------
        tol
            Finest-level residual tolerance (adaptive: of the pinned system).
        level_sweeps
            Coarser levels, ``level_sweeps[l - 1]`` sweeps at level ``l``; default: relax
            each coarser level to ``level_tol`` (its own residual, checked every ``check_every``).
        keep
            Frame coherence: continue from the finest level's current solution (the previous
            frame's) instead of the coarse-to-fine start; not with ``"adaptive"``, whose
            pinned deep nodes would keep the previous frame's values.
        callback
            ``callback(level, work, x)`` at each finest-level check with the node updates so
            far and the unknown vector (``SolveReport`` convention, channel-major).
        mg
            ``"multigrid"``: ``pre``, ``post`` (smoothing sweeps, default 3 each),
            ``coarsest`` (sweeps on the coarsest level per cycle, default 30) and ``fmg``
            (default true: a full-multigrid start, the coarse-to-fine nested iteration
            with one V-cycle per level, instead of zero).
        """
        if keep and self.scheme == "adaptive":
            raise InputError("frame coherence (keep=True) is not available with the adaptive scheme: its "
                             "pinned deep nodes would keep the previous frame's values; use 'hierarchical'")
        t0 = time.perf_counter()
        if self.scheme == "multigrid":
            return self._solve_multigrid(tol, max_sweeps, keep, callback, t0, **mg)
        levels: list[dict[str, object]] = []
        work = 0
        L = len(self.levels)
        coarse_phi: dict[int, NDArray[np.float64]] = {}
        if not keep and self.scheme != "single":
            for lev in range(L - 1, 0, -1):
                lv = self.levels[lev]
                t1 = time.perf_counter()
                if lev == L - 1:
                    lv.set_initial(None)
                self._pin(lev)
                if level_sweeps is not None:
                    n = int(level_sweeps[lev - 1])
                    lv.sweep(n)
                    res = float("nan")
                else:
                    _, rep = lv.solve(tol=level_tol, max_sweeps=max_sweeps, check_every=check_every, keep=True)
                    n, res = rep.sweeps, rep.residual
                work += n * lv.updated_nodes
                if self.used is not None:
                    coarse_phi[lev] = lv.fluence()
                self.prolong(lev)
                self.ctx.finish()
                levels.append(self._level_row(lev, n, res, time.perf_counter() - t1))
        fine = self.finest
        if not keep:
            if self.scheme == "single":
                fine.set_initial(None)
            self._pin(0)
        start_work = work
        first = fine.sweeps_run
        cb = None if callback is None else (
            lambda x: callback(0, start_work + fine.updated_nodes * (fine.sweeps_run - first), x))
        t1 = time.perf_counter()
        phi, rep = fine.solve(tol=tol, max_sweeps=max_sweeps, check_every=check_every, keep=True, callback=cb)
        work += rep.sweeps * fine.updated_nodes
        levels.append(self._level_row(0, rep.sweeps, rep.residual, time.perf_counter() - t1))
        if self.used is not None:
            phi = self._fill_unused(phi, coarse_phi)
        rep.method = f"glsl-{self.scheme}-{fine.precision}"
        rep.seconds = time.perf_counter() - t0
        rep.levels, rep.work = levels, work
        return phi, rep

    def _fill_unused(self, phi: NDArray, coarse_phi: dict[int, NDArray]) -> NDArray[np.float64]:
        """Adaptive scheme: the fluence at the nodes the finest level does not use (dropped
        or never read), copied down from the coarsest level that holds them."""
        L = len(self.levels)
        if L == 1:
            return phi
        filled = coarse_phi[L - 1]
        for lev in range(L - 2, -1, -1):
            mine = phi if lev == 0 else coarse_phi[lev]
            used = self.used[lev].reshape(mine.shape[:-1])
            filled = np.where(used[..., None], mine, self.hierarchy.prolong_phi(filled, lev + 1))
        return filled

    def texture_rows(self) -> list[dict[str, object]]:
        """Per level: texture blocks held / in the polygrid and texels per texture (the
        adaptive scheme drops unused blocks)."""
        rows = []
        for lev, lv in enumerate(self.levels):
            m = lv.problem.grid.mosaic
            w, h = lv.size
            full = self.hierarchy.grids[lev].texture_size if self.scheme != "single" else lv.size
            rows.append({"level": lev, "blocks": m.n_slots, "of_blocks": m.n_blocks, "texture": f"{w}x{h}",
                         "texels": w * h, "full_texels": full[0] * full[1]})
        return rows

    def _pin(self, lev: int) -> None:
        """Adaptive scheme: make level ``lev``'s residual checks those of its pinned system."""
        mask = self.masks[lev]
        if mask is None or self.scheme != "adaptive":
            return
        lv = self.levels[lev]
        full = self._system(lev)
        x = full.from_volume(lv.unknown())
        lv.system = full.pinned(~mask[full.active], x)

    def _level_row(self, lev: int, sweeps: int, residual: float, seconds: float) -> dict[str, object]:
        lv = self.levels[lev]
        m = lv.problem.grid.mosaic
        held = "" if m.n_slots == m.n_blocks else f" ({m.n_slots}/{m.n_blocks} blocks)"
        return {"level": lev, "n": lv.problem.grid.n, "updated": lv.updated_nodes,
                "nodes": lv.problem.grid.n_active, "sweeps": sweeps, "residual": residual, "seconds": seconds,
                "texture": "x".join(map(str, lv.size)) + held}

    # ---- multigrid ---------------------------------------------------------------------
    def vcycle(self, lev: int = 0, pre: int = 3, post: int = 3, coarsest: int = 30) -> int:
        """One V-cycle from level ``lev`` down; returns the node updates it cost (smoothing
        sweeps plus one per node for each residual, restriction and prolongation pass)."""
        lv = self.levels[lev]
        t0 = time.perf_counter()
        if lev == len(self.levels) - 1:
            lv.sweep(coarsest)
            self._level_seconds[lev] += time.perf_counter() - t0
            return coarsest * lv.updated_nodes
        lv.sweep(pre)
        self.residual(lev)
        self.restrict(lev)
        coarse = self.levels[lev + 1]
        for fbo in coarse.state.framebuffers:
            fbo.clear(0.0, 0.0, 0.0, 0.0)
        self.ctx.finish()
        self._level_seconds[lev] += time.perf_counter() - t0
        work = self.vcycle(lev + 1, pre, post, coarsest)
        t1 = time.perf_counter()
        self.prolong(lev + 1, self.coarse_correction)
        lv.sweep(post)
        self._level_seconds[lev] += time.perf_counter() - t1
        n = lv.problem.grid.n_active
        return work + (pre + post) * lv.updated_nodes + 2 * n + coarse.problem.grid.n_active

    def _fmg_start(self, pre: int, post: int, coarsest: int) -> int:
        """Full-multigrid start: the restricted source on every coarser level, the coarsest
        relaxed, then prolonged and one V-cycle per finer level; returns the work."""
        L = len(self.levels)
        q = self.problem.q
        work = 0
        for lev in range(L - 1, 0, -1):
            lv = self.levels[lev]
            g = lv.problem.grid
            rhs = np.zeros((g.size, 3))
            rhs[g.lattice.boundary] = self.hierarchy.restrict_q(q, lev)
            lv._textures["u_q"].write(np.ascontiguousarray(g.mosaic.pack(rhs)).tobytes(), alignment=1)
            for fbo in lv.state.framebuffers:
                fbo.clear(0.0, 0.0, 0.0, 0.0)
            if lev < L - 1:
                self.prolong(lev + 1)
            work += self.vcycle(lev, pre, post, coarsest)
        fine = self.finest
        for fbo in fine.state.framebuffers:
            fbo.clear(0.0, 0.0, 0.0, 0.0)
        self.prolong(1)
        return work + fine.problem.grid.n_active

    def _solve_multigrid(self, tol: float, max_sweeps: int, keep: bool,
                         callback: Callable[[int, int, NDArray], None] | None, t0: float,
                         pre: int = 3, post: int = 3, coarsest: int = 30,
                         fmg: bool = True) -> tuple[NDArray, SolveReport]:
        fine = self.finest
        self._level_seconds = [0.0] * len(self.levels)
        work = 0
        if not keep:
            if fmg:
                work = self._fmg_start(pre, post, coarsest)
            else:
                fine.set_initial(None)
        system = fine.system
        monitor = ConvergenceMonitor(tol, max_sweeps, patience=4, floor_max=fine.floor_max)
        x = system.from_volume(fine.unknown())
        r = system.jacobi_step(x)
        status = monitor.update(0, system.residual(x, r))
        if callback is not None:
            callback(0, work, x)
        cycles = 0
        per_level_sweeps = [0] * len(self.levels)
        while status is None:
            work += self.vcycle(0, pre, post, coarsest)
            cycles += 1
            for lev in range(len(self.levels)):
                per_level_sweeps[lev] += coarsest if lev == len(self.levels) - 1 else pre + post
            vol = fine.unknown()
            if fine.buffers == "fp16" and not np.all(np.abs(vol) < gl.FP16_MAX):
                raise SolverError("multigrid overflowed the fp16 buffers; use precision='fp32'")
            x = system.from_volume(vol)
            with np.errstate(over="ignore", invalid="ignore"):
                r = system.jacobi_step(x)
                status = monitor.update(cycles, system.residual(x, r))
            if callback is not None:
                callback(0, work, x)
        history = monitor.history
        if status == "diverged":
            raise SolverError(diverged_message(self.problem, "GLSL multigrid", cycles))
        phi = self.problem.to_phi(system.to_volume(x, self.problem.node_shape))
        seconds = time.perf_counter() - t0
        levels = [self._level_row(lev, per_level_sweeps[lev], history[-1][1] if lev == 0 else float("nan"),
                                  self._level_seconds[lev]) for lev in range(len(self.levels))]
        rep = SolveReport(f"glsl-multigrid-{fine.precision}", nodes=system.n, sweeps=cycles,
                          residual=history[-1][1], seconds=seconds, converged=status == "converged",
                          residuals=history, status=status,
                          error_estimate=contraction_error_estimate(history, float(np.linalg.norm(r)),
                                                                    float(np.linalg.norm(x))),
                          device=gl.describe(self.ctx), radiance=self.problem.exitant_radiance(phi))
        rep.levels, rep.work = levels, work
        return phi, rep

    # ---- lifetime ----------------------------------------------------------------------
    def release(self) -> None:
        gl.make_current(self.ctx)
        for obj in reversed(self._objects):
            obj.release()
        self._objects = []
        for lv in reversed(self.levels):
            lv.release()
        self.levels = []

    def __enter__(self) -> "MultilevelDiffusion":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


__all__ = ["MultilevelDiffusion", "SCHEMES", "update_masks", "used_nodes", "used_blocks"]
