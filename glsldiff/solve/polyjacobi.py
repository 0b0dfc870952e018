"""Polygrid diffusion in GLSL (Wang et al. 2008, section 5.2, figures 6-7).

Textures (all packed like figure 6, see :class:`glsldiff.grids.polygrid.Polygrid`): T_kappa,
T_mu, T_l (= ``u_q``, the source at boundary nodes), T_w1 / T_w2 (the six scaled
Laplacian weights and the row scale at interior nodes; the partner distance ``d`` at
boundary nodes), T_p (node positions, mm; for editing and display, not read by the
sweep), and the ping-pong radiance buffers I_A / I_B of :class:`glsldiff.gl.PingPong`.

Each sweep draws the interior pass (``polygrid_interior.frag``) and then the boundary pass
(``boundary.frag`` with a per-node ``d``), each as quads, lines and points whose vertex
attributes hold the texel offsets to the nodes they read (:func:`polygrid_primitives`).
All vertex data is built once and kept in GPU buffers. The solve loop, the float64
residual checks and the report are those of :class:`glsldiff.solve.jacobi.GlslDiffusion`.
"""
from __future__ import annotations

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff import gl
from glsldiff.solve.jacobi import GlslDiffusion
from glsldiff.core.errors import InputError
from glsldiff.packing import Primitives, decompose, primitive_vertices
from glsldiff.grids.polygrid import Polygrid
from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.report import SolveReport

_MODES = {"triangles": moderngl.TRIANGLES, "lines": moderngl.LINES, "points": moderngl.POINTS}
_FORMAT = "2f 2i 2i 2i 2i 2i 2i"
_ATTRS = ("in_pos", "in_off0", "in_off1", "in_off2", "in_off3", "in_off4", "in_off5")


def polygrid_primitives(pg: Polygrid, update: NDArray[np.bool_] | None = None) -> dict[str, Primitives]:
    """Quad/line/point decomposition of the interior pass and of the boundary pass, over
    the nodes where ``update`` (``(N,)`` flat node mask; default all) is true."""
    lat, mosaic = pg.lattice, pg.mosaic
    si = slice(None) if update is None else update[lat.interior]
    sb = slice(None) if update is None else update[lat.boundary]
    ti = mosaic.texel(lat.interior[si])
    tb = mosaic.texel(lat.boundary[sb])
    off_i = mosaic.texel(lat.neighbours[si]) - ti[:, None, :]
    off_b = (mosaic.texel(lat.link[sb]) - tb)[:, None, :]
    return {"interior": decompose(ti, off_i), "boundary": decompose(tb, off_b)}


def weight_textures(pg: Polygrid) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """T_w1 = (w_x-, w_x+, w_y-, row scale) and T_w2 = (w_y+, w_z-, w_z+, 0) at interior
    nodes (scaled weights), T_w1.r = d at boundary nodes; packed textures."""
    g = pg.graph
    w1 = np.zeros((pg.size, 4))
    w2 = np.zeros((pg.size, 4))
    w1[g.interior, :3] = g.weights[:, :3]
    w1[g.interior, 3] = g.scale
    w2[g.interior, :3] = g.weights[:, 3:]
    w1[g.boundary, 0] = g.d
    return pg.mosaic.pack(w1), pg.mosaic.pack(w2)


class PolygridDiffusion(GlslDiffusion):
    """Jacobi relaxation of a :class:`DiffusionProblem` on a :class:`Polygrid` in shaders.

    Same interface as :class:`glsldiff.solve.jacobi.GlslDiffusion`: :meth:`solve` returns the
    fluence as a ``(cubes, n, n, n, 3)`` node array and a report whose ``radiance`` is the
    ``(n_boundary, 3)`` exitant radiance.
    """

    method = "glsl-polygrid"

    def __init__(self, problem: DiffusionProblem, ctx: moderngl.Context | None = None,
                 precision: str = "fp32", *, update: NDArray[np.bool_] | None = None,
                 **options: object) -> None:
        """``update``: ``(N,)`` flat node mask of the nodes the sweeps update (default all;
        the adaptive scheme fixes the others); ``options`` go to :class:`GlslDiffusion`
        (``state``, ``damping``, ``interior_rhs``)."""
        if not isinstance(problem.grid, Polygrid):
            raise InputError(f"PolygridDiffusion needs a problem on a Polygrid, got {type(problem.grid).__name__}")
        if update is not None:
            update = np.asarray(update, dtype=bool)
            if update.shape != (problem.grid.size,):
                raise InputError(f"update mask has shape {update.shape}, expected ({problem.grid.size},)")
        self.update = update
        self._extra_arrays: list[moderngl.VertexArray] = []
        super().__init__(problem, ctx, precision, **options)  # type: ignore[arg-type]

    @property
    def updated_nodes(self) -> int:
        """Nodes each sweep updates."""
        return sum(p.texels for p in self.primitives.values())

    def _build_passes(self, defines: dict[str, int]) -> None:
        pg: Polygrid = self.problem.grid
        gl.make_current(self.ctx)
        w1, w2 = weight_textures(pg)
        self._textures["u_w1"] = gl.float_texture(self.ctx, self.size, w1)
        self._textures["u_w2"] = gl.float_texture(self.ctx, self.size, w2)
        self.positions = gl.float_texture(self.ctx, self.size, pg.pack(pg.positions.reshape(pg.shape + (3,))))
        self.primitives = polygrid_primitives(pg, self.update)
        self._defines = defines
        self._vbos: dict[str, list[tuple[moderngl.Buffer, int]]] = {}
        for name, prims in self.primitives.items():
            self._vbos[name] = []
            for mode, verts in primitive_vertices(prims).items():
                if len(verts):
                    vbo = self.ctx.buffer(np.ascontiguousarray(verts).tobytes())
                    self._buffers.append(vbo)
                    self._vbos[name].append((vbo, _MODES[mode]))
        interior = self._program("polygrid.vert", "polygrid_interior.frag", defines)
        boundary = self._program("polygrid.vert", "boundary.frag", {**defines, "PER_NODE_D": 1})
        self._draws += self.pass_arrays(interior, "interior") + self.pass_arrays(boundary, "boundary")

    def pass_arrays(self, prog: moderngl.Program, name: str) -> list[tuple[moderngl.VertexArray, int]]:
        """Vertex arrays drawing ``prog`` over the primitives of pass ``name`` (``"interior"``
        or ``"boundary"``); another program (e.g. a residual) can reuse the same buffers.
        They are released with this solver."""
        attrs = [a for a in _ATTRS if a in prog]
        fmt = " ".join(f if a in prog else "8x" for a, f in zip(_ATTRS, _FORMAT.split()))
        out = [(self.ctx.vertex_array(prog, [(vbo, fmt, *attrs)]), mode) for vbo, mode in self._vbos[name]]
        self._extra_arrays.extend(vao for vao, _ in out)
        return out

    def _uniform_values(self) -> dict[str, object]:
        return {"u_size": tuple(float(s) for s in self.size), "u_C": float(self.problem.C), "u_omega": self.damping,
                **self.material_uniforms}

    def primitive_counts(self) -> dict[str, dict[str, int]]:
        """Quads, lines and points per pass."""
        return {name: prims.kinds for name, prims in self.primitives.items()}

    def release(self) -> None:
        gl.make_current(self.ctx)
        draws = {id(vao) for vao, _ in self._draws}
        for vao in self._extra_arrays:
            if id(vao) not in draws:
                vao.release()
        self._extra_arrays = []
        if getattr(self, "positions", None) is not None:
            self.positions.release()
            self.positions = None
        super().release()


def solve_polygrid(problem: DiffusionProblem, ctx: moderngl.Context | None = None,
                   precision: str = "fp32", **kwargs: object) -> tuple[NDArray, SolveReport]:
    """One-shot GLSL polygrid solve; ``kwargs`` go to :meth:`GlslDiffusion.solve`."""
    with PolygridDiffusion(problem, ctx, precision) as solver:
        return solver.solve(**kwargs)  # type: ignore[arg-type]
