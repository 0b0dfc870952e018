"""The level stack of the multiresolution solvers (Wang et al. 2008, section 5.3): one
:class:`~glsldiff.solve.jacobi.GlslDiffusion` per level of a
:class:`~glsldiff.grids.hierarchy.Hierarchy` (regular grid or polygrid; each holds its level's
texture pyramid entry T_kappa, T_mu, T_q, T_w1, T_w2 and sweep primitives) and the passes
between levels:

* **prolongation** (``shaders/transfer.frag`` with the hierarchy's ``Transfer.prolong`` as a
  gather, acting on phi): an initial guess for the finer level, written into both of its
  buffers so that nodes no sweep updates keep it; or, in a correction stack, the coarse
  correction times ``alpha`` added to the finer level's state;
* **residual** (the levels' own residual pass) into a per-level residual texture;
* **restriction** (``Transfer.restrict_kind`` as a gather) of that residual into the coarser
  level's T_q.

A plain stack (coarse-to-fine solves) renders all levels into one ping-pong pair as large as
the largest level's textures (the radiance buffers are reused across levels, as in the paper);
a correction stack (multigrid) gives each level its own pair, damped-Jacobi smoothing and an
interior right-hand side on the coarse levels. Lengths in mm.
"""
from __future__ import annotations

import time
from typing import Sequence

import moderngl
import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff import gl
from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.solve.jacobi import GlslDiffusion, buffer_precision
from glsldiff.solve.stencil import transfer_slots
from glsldiff.system.problem import DiffusionProblem



class LevelStack:
    """The levels of ``problems`` (finest first, on ``hierarchy.grids``) on the GPU and the
    transfer passes between them (module docstring).

    Parameters
    ----------
    hierarchy
        The grids and transfers.
    problems
        One problem per level used (finest first): the finest alone for a single-level solve.
    masks
        Per level, the ``(N,)`` nodes its sweeps update (``None``: all).
    correction
        Multigrid: coarse levels solve for corrections (own ping-pong pairs, interior
        right-hand sides, residual and restriction passes; prolongation adds).
    damping
        Jacobi damping of every level of a correction stack.
    """

    def __init__(self, hierarchy: Hierarchy, problems: Sequence[DiffusionProblem], ctx: moderngl.Context,
                 precision: str = "fp32", *, masks: Sequence[NDArray[np.bool_] | None] | None = None,
                 correction: bool = False, damping: float = 1.0) -> None:
        self.hierarchy, self.ctx, self.correction = hierarchy, ctx, correction
        self.masks = list(masks) if masks is not None else [None] * len(problems)
        self.levels: list[GlslDiffusion] = []
        self.transfer_seconds = 0.0  # wall time of the transfer passes (GPU finished)
        self._gpu = gl.Resources()
        gl.make_current(ctx)
        try:
            shared = None
            if not correction:  # one ping-pong pair for all levels, as large as the largest level's textures
                size = tuple(max(p.grid.texture_size[i] for p in problems) for i in (0, 1))
                shared = self._gpu.add(gl.PingPong.create(ctx, size, buffer_precision(precision)))
            for lev, p in enumerate(problems):
                self.levels.append(GlslDiffusion(p, ctx, precision, update=self.masks[lev], state=shared,
                                                 damping=damping if correction else 1.0,
                                                 interior_rhs=correction and lev > 0))
            self._build_transfers()
        except Exception:
            self.release()
            raise

    @property
    def finest(self) -> GlslDiffusion:
        return self.levels[0]

    @property
    def problem(self) -> DiffusionProblem:
        return self.finest.problem

    @property
    def compute_seconds(self) -> float:
        """GPU time so far in sweeps and transfer passes (read-backs and CPU checks excluded)."""
        return self.transfer_seconds + sum(lv.sweep_seconds for lv in self.levels)

    # ---- GPU set-up ----------------------------------------------------------------------
    def _quad(self, prog: moderngl.Program, size: tuple[int, int]) -> moderngl.VertexArray:
        vbo = self._gpu.add(self.ctx.buffer(gl.quad_vertices(size).tobytes()))
        return self._gpu.add(self.ctx.vertex_array(prog, [(vbo, "2f", "in_pos")]))

    def _gather(self, matrix: object, target: GlslDiffusion, source: GlslDiffusion, defines: dict[str, int]
                ) -> tuple[moderngl.Program, moderngl.VertexArray, moderngl.TextureArray]:
        """Program, quad and slot layers of a transfer pass from ``source`` onto ``target``."""
        slots = transfer_slots(matrix, target.problem.grid.mosaic, source.problem.grid.mosaic)
        k, h, w, _ = slots.shape
        tex = self._gpu.add(self.ctx.texture_array((w, h, k), 4, np.ascontiguousarray(slots).tobytes(), dtype="f4"))
        tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        prog = self._gpu.add(gl.program(self.ctx, "quad.vert", "transfer.frag", {**target.defines, **defines,
                                                                                 "SLOTS": k}))
        src = source.material_uniforms  # the source level's 8-bit decode range of kappa, if any
        gl.set_uniforms(prog, {"u_size": tuple(float(s) for s in target.size), **target.material_uniforms,
                               **({"u_kappa_src_lo": src["u_kappa_lo"], "u_kappa_src_hi": src["u_kappa_hi"]}
                                  if src else {})})
        return prog, self._quad(prog, target.size), tex

    def _build_transfers(self) -> None:
        self._prolong: list[tuple[moderngl.Program, moderngl.VertexArray, moderngl.TextureArray]] = []
        self._copy: list[tuple[moderngl.Program, moderngl.VertexArray]] = []
        self._residual: list[tuple[moderngl.Texture, moderngl.Framebuffer]] = []
        self._restrict: list[tuple[moderngl.Program, moderngl.VertexArray, moderngl.TextureArray,
                                   moderngl.Framebuffer]] = []
        for lev in range(len(self.levels) - 1):
            fine, coarse = self.levels[lev], self.levels[lev + 1]
            t = self.hierarchy.transfers[lev]
            self._prolong.append(self._gather(t.prolong, fine, coarse, {"PHI": 1, "ADD": int(self.correction)}))
            if not self.correction:
                cprog = self._gpu.add(gl.program(self.ctx, "quad.vert", "copy.frag"))
                gl.set_uniforms(cprog, {"u_size": tuple(float(s) for s in fine.size)})
                self._copy.append((cprog, self._quad(cprog, fine.size)))
                continue
            res_tex = self._gpu.add(gl.float_texture(self.ctx, fine.size))
            self._residual.append((res_tex, self._gpu.add(self.ctx.framebuffer(color_attachments=[res_tex]))))
            rhs_fbo = self._gpu.add(self.ctx.framebuffer(color_attachments=[coarse.textures["u_q"]]))
            self._restrict.append((*self._gather(t.restrict_kind, coarse, fine, {"PHI": 0, "ADD": 0}), rhs_fbo))

    # ---- the passes ----------------------------------------------------------------------
    def _draw(self, fbo: moderngl.Framebuffer, size: tuple[int, int], vao: moderngl.VertexArray,
              textures: dict[str, moderngl.Texture | moderngl.TextureArray]) -> None:
        """Render the quad ``vao`` into ``fbo`` over ``size`` texels with ``textures`` bound."""
        t0 = time.perf_counter()
        with gl.keep_framebuffer(self.ctx):
            for unit, (name, tex) in enumerate(textures.items()):
                tex.use(unit)
                gl.set_uniforms(vao.program, {name: unit})
            fbo.use()
            self.ctx.viewport = (0, 0, *size)
            vao.render(moderngl.TRIANGLES)
            self.ctx.finish()
        self.transfer_seconds += time.perf_counter() - t0

    def prolong(self, lev: int, alpha: float = 1.0) -> None:
        """Level ``lev`` (coarse) -> ``lev - 1``: the initial guess of the finer level (both of
        its buffers), or in a correction stack ``alpha`` times the correction added to it."""
        gl.make_current(self.ctx)
        fine, coarse = self.levels[lev - 1], self.levels[lev]
        prog, vao, slots = self._prolong[lev - 1]
        gl.set_uniforms(prog, {"u_alpha": float(alpha)})
        self._draw(fine.state.dst, fine.size, vao, {
            "u_slots": slots, "u_src": coarse.state.src, "u_kappa_src": coarse.textures["u_kappa"],
            "u_kappa": fine.textures["u_kappa"], "u_state": fine.state.src})
        fine.state.swap()
        if not self.correction:
            # an initial guess goes into both buffers, so that nodes no sweep updates keep it
            # (a copy pass: a framebuffer blit between the float targets is GL_INVALID_ENUM on Mesa)
            cprog, cvao = self._copy[lev - 1]
            self._draw(fine.state.dst, fine.size, cvao, {"u_src": fine.state.src})

    def residual(self, lev: int) -> moderngl.Texture:
        """Residual of level ``lev``'s rows (equation units) into its residual texture."""
        gl.make_current(self.ctx)
        tex, fbo = self._residual[lev]
        t0 = time.perf_counter()
        fbo.clear(0.0, 0.0, 0.0, 0.0)
        self.levels[lev].residual(fbo)
        self.ctx.finish()
        self.transfer_seconds += time.perf_counter() - t0
        return tex

    def restrict(self, lev: int) -> None:
        """Residual of level ``lev`` -> right-hand side T_q of level ``lev + 1``."""
        gl.make_current(self.ctx)
        prog, vao, slots, fbo = self._restrict[lev]
        self._draw(fbo, self.levels[lev + 1].size, vao, {"u_slots": slots, "u_src": self._residual[lev][0]})

    def clear(self, lev: int) -> None:
        """Zero both buffers of level ``lev``."""
        for fbo in self.levels[lev].state.framebuffers:
            fbo.clear(0.0, 0.0, 0.0, 0.0)

    # ---- sources and bookkeeping ---------------------------------------------------------
    def set_q(self, q: ArrayLike) -> None:
        """New boundary source on the finest level (e.g. a moved light), material kept; a plain
        stack also restricts it to every coarser level."""
        self.finest.set_q(q)
        if not self.correction:
            full = self.finest.problem.q
            for lev in range(1, len(self.levels)):
                self.levels[lev].set_q(self.hierarchy.restrict_q(full, lev))

    def level_row(self, lev: int, sweeps: int, residual: float, seconds: float) -> dict[str, object]:
        """A :attr:`SolveReport.levels` entry of level ``lev``."""
        lv = self.levels[lev]
        g = lv.problem.grid
        m = g.mosaic
        held = "" if m.n_slots == m.n_blocks else f" ({m.n_slots}/{m.n_blocks} blocks)"
        n = getattr(g, "n", None) or "x".join(map(str, (g.nx, g.ny, g.nz)))
        return {"level": lev, "n": n, "updated": lv.updated_nodes, "nodes": g.n_active, "sweeps": sweeps,
                "residual": residual, "seconds": seconds, "texture": "x".join(map(str, lv.size)) + held}

    def texture_rows(self) -> list[dict[str, object]]:
        """Per level: texture blocks held / in the grid and texels per texture (an adaptive
        schedule drops unused blocks)."""
        rows = []
        for lev, lv in enumerate(self.levels):
            m = lv.problem.grid.mosaic
            w, h = lv.size
            fw, fh = self.hierarchy.grids[lev].texture_size
            rows.append({"level": lev, "blocks": m.n_slots, "of_blocks": m.n_blocks, "texture": f"{w}x{h}",
                         "texels": w * h, "full_texels": fw * fh})
        return rows

    def release(self) -> None:
        gl.make_current(self.ctx)
        for lv in reversed(self.levels):
            lv.release()
        self.levels = []
        self._gpu.release()
