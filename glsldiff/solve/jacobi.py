"""Regular-grid forward diffusion in GLSL (Wang et al. 2008, sections 4.4 and 5.2).

kappa, mu and q are packed into 2D float textures (z-slices tiled as blocks, see
:mod:`glsldiff.grids.regular`); the iterated unknown (``kappa phi`` for the paper's stencil,
``phi`` for the conservative one) lives in a ping-pong pair of float framebuffers.
One Jacobi sweep is two draw calls into the target buffer, both reading the source
buffer: the interior pass (one rectangle per interior z-slice, the offsets to slices
z-1 and z+1 as flat vertex attributes) and the boundary pass (one rectangle per
z-face, one 1-texel strip per side-face edge of each interior slice, the offset to the
linked interior node as attribute). All three colour channels are updated at once.

Convergence is checked by reading the iterate back every ``check_every`` sweeps and
evaluating its Jacobi-scaled residual in float64 with the CPU system of
:mod:`glsldiff.oracle.solvers` (see :func:`glsldiff.oracle.solvers.relax`), so an iterate frozen
by fp16/fp32 rounding reports its true residual and is labelled "stalled".
"""
from __future__ import annotations

import logging
import time
from dataclasses import replace
from functools import cached_property
from typing import Callable, Mapping

import moderngl
import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff import gl

from glsldiff.solve import quantize
from glsldiff.core.errors import InputError, SolverError
from glsldiff.grids.regular import RegularGrid
from glsldiff.system.problem import DiffusionProblem
from glsldiff.oracle.assembly import LinearSystem, assemble, assemble_rhs, diverged_message
from glsldiff.oracle.solvers import relax

from glsldiff.system.report import SolveReport, contraction_error_estimate

logger = logging.getLogger(__name__)

PRECISIONS = ("fp32", "fp16", "paper")


def buffer_precision(precision: str) -> str:
    """The radiance buffers' format (``"fp32"`` or ``"fp16"``) of a solver ``precision``
    (one of :data:`PRECISIONS`; ``"paper"`` = fp16 buffers, 8-bit material)."""
    if precision not in PRECISIONS:
        raise InputError(f"precision={precision!r}; choose one of {PRECISIONS}")
    return "fp32" if precision == "fp32" else "fp16"
_VERTEX = np.dtype([("pos", "f4", 2), ("off0", "i4", 2), ("off1", "i4", 2)])


def _rect_vertices(rects: list[tuple[int, int, int, int, tuple[int, int], tuple[int, int]]]) -> NDArray:
    """Two triangles per texel rectangle ``(x0, y0, x1, y1, off0, off1)`` (x1, y1 exclusive)."""
    out = np.zeros(6 * len(rects), dtype=_VERTEX)
    for i, (x0, y0, x1, y1, o0, o1) in enumerate(rects):
        corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y0), (x1, y1), (x0, y1)]
        out["pos"][6 * i:6 * i + 6] = corners
        out["off0"][6 * i:6 * i + 6] = o0
        out["off1"][6 * i:6 * i + 6] = o1
    return out


def grid_primitives(grid: RegularGrid) -> tuple[NDArray, NDArray]:
    """Vertex arrays of the interior pass and of the boundary pass."""
    nx, ny, nz = grid.nx, grid.ny, grid.nz

    def delta(z_from: int, z_to: int) -> tuple[int, int]:
        (ax, ay), (bx, by) = grid.tile_origin(z_from), grid.tile_origin(z_to)
        return bx - ax, by - ay

    interior, boundary = [], []
    for z in range(nz):
        ox, oy = grid.tile_origin(z)
        inner = (ox + 1, oy + 1, ox + nx - 1, oy + ny - 1)
        if z in (0, nz - 1):  # a z-face: every inner texel is a boundary node
            boundary.append((*inner, delta(z, 1 if z == 0 else nz - 2), (0, 0)))
            continue
        interior.append((*inner, delta(z, z - 1), delta(z, z + 1)))
        boundary += [
            (ox, oy + 1, ox + 1, oy + ny - 1, (1, 0), (0, 0)),                  # x-
            (ox + nx - 1, oy + 1, ox + nx, oy + ny - 1, (-1, 0), (0, 0)),       # x+
            (ox + 1, oy, ox + nx - 1, oy + 1, (0, 1), (0, 0)),                  # y-
            (ox + 1, oy + ny - 1, ox + nx - 1, oy + ny, (0, -1), (0, 0)),       # y+
        ]
    return _rect_vertices(interior), _rect_vertices(boundary)


class GlslDiffusion:
    """Jacobi relaxation of a :class:`DiffusionProblem` in fragment shaders.

    GPU objects (textures, framebuffers, programs, buffers) belong to this object;
    call :meth:`release` (or use it as a context manager) to free them.

    Parameters
    ----------
    problem
        The validated problem (grid, kappa, mu, q, C, stencil).
    ctx
        A moderngl context; default :func:`glsldiff.gl.get_context`.
    precision
        ``"fp32"`` (fp32 buffers and material), ``"fp16"`` (fp16 ping-pong buffers) or
        ``"paper"`` (the paper's rendering precision: fp16 buffers and 8-bit kappa/mu,
        :mod:`glsldiff.solve.quantize`).
    """

    method = "glsl-jacobi"  # report name (before the precision suffix)

    def __init__(self, problem: DiffusionProblem, ctx: moderngl.Context | None = None,
                 precision: str = "fp32", *, state: gl.PingPong | None = None, damping: float = 1.0,
                 interior_rhs: bool = False) -> None:
        buffers = buffer_precision(precision)
        if not 0.0 < damping <= 1.0:
            raise InputError(f"damping={damping!r} must be in (0, 1] (1 = plain Jacobi)")
        self.problem = problem
        self.precision = precision
        self.buffers = buffers
        self.material_bits = 8 if precision == "paper" else 32
        self.damping = float(damping)
        self.ctx = ctx if ctx is not None else gl.get_context()
        gl.make_current(self.ctx)
        g = problem.grid
        self.size = g.texture_size
        self.material_uniforms: dict[str, tuple[float, float, float]] = {}
        self._textures: dict[str, moderngl.Texture] = {
            "u_kappa": self._material_texture(), "u_mu": self._material_texture(),
            "u_q": gl.float_texture(self.ctx, self.size, g.pack(problem.q)),
        }
        self._write_material()
        if state is None:
            self.state = gl.PingPong.create(self.ctx, self.size, self.buffers)
        else:  # borrowed (radiance buffers shared across the levels of a hierarchy)
            if state.dtype != gl.DTYPES[self.buffers] or state.size[0] < self.size[0] or state.size[1] < self.size[1]:
                raise InputError(f"a shared state of {state.size} ({state.dtype}) cannot hold a "
                                 f"{self.size} {precision} level")
            self.state = state
        self._owns_state = state is None
        self._progs: list[moderngl.Program] = []
        self._buffers: list[moderngl.Buffer] = []
        self._draws: list[tuple[moderngl.VertexArray, int]] = []
        self._build_passes({"STENCIL_PAPER": int(problem.stencil == "paper"),
                            "FACE_HARMONIC": int(problem.face_mean == "harmonic"),
                            "DAMPED": int(self.damping < 1.0), "HAS_RHS": int(interior_rhs),
                            "MATERIAL_8BIT": int(self.material_bits == 8)})
        self._mask = g.active
        self.sweeps_run = 0  # sweeps since creation (work counters of multilevel solves)
        self.sweep_seconds = 0.0  # wall time inside sweep(), GPU finished (no read-backs)

    # ---- setup ----------------------------------------------------------------
    def _material_texture(self) -> moderngl.Texture:
        if self.material_bits == 8:
            tex = self.ctx.texture(self.size, 4, dtype="f1")
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            return tex
        return gl.float_texture(self.ctx, self.size)

    def _write_material(self) -> None:
        """Upload kappa and mu (8-bit codes and their decode uniforms in ``"paper"`` precision)."""
        p, g = self.problem, self.problem.grid
        if self.material_bits == 8:
            act = np.asarray(g.active).reshape(-1)
            ck, cm, self.material_uniforms = quantize.encode(p.kappa.reshape(-1, 3), p.mu.reshape(-1, 3), act)
            shape = tuple(g.shape) + (3,)
            data = {"u_kappa": g.pack(ck.reshape(shape)), "u_mu": g.pack(cm.reshape(shape))}
            for name, arr in data.items():
                self._textures[name].write(np.ascontiguousarray(arr, dtype=np.uint8).tobytes(), alignment=1)
            for prog in getattr(self, "_progs", []):
                self._set_uniforms(prog)
            return
        for name, vol in (("u_kappa", p.kappa), ("u_mu", p.mu)):
            self._textures[name].write(np.ascontiguousarray(g.pack(vol)).tobytes(), alignment=1)

    def _build_passes(self, defines: dict[str, int]) -> None:
        """Programs and vertex arrays of the interior pass and the boundary pass."""
        for frag, verts in zip(("interior.frag", "boundary.frag"), grid_primitives(self.problem.grid)):
            prog = self._program("grid.vert", frag, {**defines, "PER_NODE_D": 0})
            layout = ((prog, "2f 2i 2i", "in_pos", "in_off0", "in_off1") if "in_off1" in prog
                      else (prog, "2f 2i 8x", "in_pos", "in_off0"))
            self._add_draw(layout, verts, moderngl.TRIANGLES)

    def _program(self, vert: str, frag: str, defines: dict[str, int]) -> moderngl.Program:
        prog = gl.program(self.ctx, vert, frag, defines)
        self._progs.append(prog)
        self._set_uniforms(prog)
        return prog

    def _add_draw(self, layout: tuple, verts: NDArray, mode: int) -> None:
        """One vertex array (``layout = (program, format, *attributes)``) drawn with ``mode``."""
        if len(verts) == 0:
            return
        prog, fmt, *attrs = layout
        vbo = self.ctx.buffer(np.ascontiguousarray(verts).tobytes())
        self._buffers.append(vbo)
        self._draws.append((self.ctx.vertex_array(prog, [(vbo, fmt, *attrs)]), mode))

    def _uniform_values(self) -> dict[str, object]:
        g, p = self.problem.grid, self.problem
        return {"u_size": tuple(float(s) for s in self.size), "u_h2": g.h * g.h,
                "u_C": float(p.C), "u_d": g.h, "u_omega": self.damping, **self.material_uniforms}

    def _set_uniforms(self, prog: moderngl.Program) -> None:
        units = {name: i + 1 for i, name in enumerate(self._textures)}
        for name, value in {**self._uniform_values(), "u_state": 0, **units}.items():
            if name in prog:
                prog[name] = value

    @cached_property
    def system(self) -> LinearSystem:
        """The CPU system (assembled on first use) that checks the residual of read-backs."""
        return assemble(self.problem)

    def set_q(self, q: ArrayLike | Mapping[str, ArrayLike]) -> None:
        """Replace the boundary source (the material textures stay on the GPU)."""
        gl.make_current(self.ctx)
        self.problem = self.problem.with_q(q)
        self._textures["u_q"].write(np.ascontiguousarray(self.problem.grid.pack(self.problem.q)).tobytes(),
                                    alignment=1)
        if "system" in self.__dict__:
            self.system = replace(self.system, b=assemble_rhs(self.problem))

    def set_material(self, kappa: ArrayLike, mu: ArrayLike) -> None:
        """Replace kappa (mm) and mu (mm^-1) in place (same grid, source and options): an
        edit or an optimiser step re-uses the textures, programs and vertex buffers."""
        gl.make_current(self.ctx)
        self.problem = replace(self.problem, kappa=kappa, mu=mu)
        self._write_material()
        self.__dict__.pop("system", None)

    def set_initial(self, phi: ArrayLike | None) -> None:
        """Start the next solve from fluence ``phi`` (volume) or from zero."""
        gl.make_current(self.ctx)
        g = self.problem.grid
        if phi is None:
            x = np.zeros(tuple(g.shape) + (3,))
        else:
            phi = np.asarray(phi, dtype=np.float64)
            if phi.shape != tuple(g.shape) + (3,):
                raise InputError(f"initial phi has shape {phi.shape}, expected {tuple(g.shape) + (3,)}")
            x = self.problem.from_phi(phi) * self._mask[..., None]
        self.state.write(g.pack(x))

    @property
    def floor_max(self) -> float:
        """Largest residual taken for the rounding floor of the buffers (fp16 stalls near
        1e-2 on slowly converging grids: an increment below half an fp16 ulp is lost)."""
        return 1e-2 if self.buffers == "fp32" else 5e-2

    def bind_textures(self) -> None:
        """Bind the material, source and weight textures to the units the programs read."""
        for unit, tex in enumerate(self._textures.values(), start=1):
            tex.use(unit)

    # ---- iteration --------------------------------------------------------------
    def sweep(self, n: int = 1) -> None:
        """Run ``n`` Jacobi sweeps (interior pass + boundary pass each)."""
        gl.make_current(self.ctx)
        t0 = time.perf_counter()
        bound = self.ctx.fbo if self.ctx.fbo is not None else self.ctx.detect_framebuffer(0)
        self.bind_textures()
        for _ in range(n):
            self.state.dst.use()
            self.ctx.viewport = (0, 0, *self.size)  # this level's texels of a (maybe shared) state
            self.state.src.use(0)
            for vao, mode in self._draws:
                vao.render(mode)
            self.state.swap()
        self.sweeps_run += n
        self.ctx.finish()  # sweeps are timed: wait for the GPU
        bound.use()  # leave the caller's framebuffer bound, never ours
        self.sweep_seconds += time.perf_counter() - t0

    def unknown(self) -> NDArray[np.float64]:
        """Current iterate (``kappa phi`` or ``phi``) as a ``(nz, ny, nx, 3)`` float64 volume."""
        gl.make_current(self.ctx)
        return self.problem.grid.unpack(self.state.read(size=self.size)).astype(np.float64)

    def fluence(self) -> NDArray[np.float64]:
        """Current fluence phi as a ``(nz, ny, nx, 3)`` volume (0 at inactive nodes)."""
        return self.problem.to_phi(self.unknown())

    def solve(self, tol: float = 1e-6, max_sweeps: int = 20000, check_every: int = 50,
              x0: ArrayLike | None = None, keep: bool = False,
              callback: Callable[[NDArray], None] | None = None) -> tuple[NDArray, SolveReport]:
        """Relax until the Jacobi-scaled residual is <= ``tol`` or ``max_sweeps`` ran.

        Parameters
        ----------
        tol
            Residual tolerance (see :class:`SolveReport`).
        max_sweeps
            Sweep budget.
        check_every
            Sweeps between residual checks (each costs two read-backs).
        x0
            Initial fluence volume; default zero. Ignored when ``keep`` is true.
        keep
            Continue from the current buffer contents (frame coherence / restarts).
        callback
            Called with the unknown vector (channel-major, float64) after each check.

        Returns
        -------
        phi, report
            Fluence ``(nz, ny, nx, 3)`` and the :class:`SolveReport`.

        Raises
        ------
        SolverError
            The iteration diverged (spectral radius >= 1) or overflowed the fp16 buffers.
        """
        t0 = time.perf_counter()
        if not keep:
            self.set_initial(x0)
        system = self.system

        def advance(n: int) -> NDArray:
            self.sweep(n)
            vol = self.unknown()
            if self.buffers == "fp16" and not np.all(np.abs(vol) < gl.FP16_MAX):
                raise SolverError(
                    f"GLSL Jacobi overflowed the fp16 buffers (|value| reached {gl.FP16_MAX:g}); "
                    "scale q down or use precision='fp32'")
            return system.from_volume(vol)

        x, status, history, step = relax(system, advance, system.from_volume(self.unknown()), tol,
                                         max_sweeps, check_every, callback, floor_max=self.floor_max)
        sweeps, res = history[-1]
        if status == "diverged":
            raise SolverError(diverged_message(self.problem, "GLSL Jacobi", sweeps))
        phi = self.problem.to_phi(system.to_volume(x, self.problem.node_shape))
        converged = status == "converged"
        if not converged:
            logger.warning("GLSL Jacobi did not converge (%s): residual %.3e after %d sweeps",
                           status, res, sweeps)
        report = SolveReport(
            f"{self.method}-{self.precision}", nodes=system.n, sweeps=sweeps, residual=res,
            seconds=time.perf_counter() - t0, converged=converged, residuals=history, status=status,
            error_estimate=contraction_error_estimate(history, step, float(np.linalg.norm(x))),
            device=gl.describe(self.ctx), radiance=self.problem.exitant_radiance(phi))
        return phi, report

    # ---- lifetime ---------------------------------------------------------------
    def release(self) -> None:
        """Free every GPU object this solver created."""
        gl.make_current(self.ctx)
        for obj in (*(vao for vao, _ in self._draws), *self._buffers, *self._progs, *self._textures.values()):
            obj.release()
        if self._owns_state:
            self.state.release()
        self._draws, self._buffers, self._progs, self._textures = [], [], [], {}

    def __enter__(self) -> "GlslDiffusion":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def solve_glsl(problem: DiffusionProblem, ctx: moderngl.Context | None = None,
               precision: str = "fp32", **kwargs: object) -> tuple[NDArray, SolveReport]:
    """One-shot GLSL solve; ``kwargs`` go to :meth:`GlslDiffusion.solve`."""
    with GlslDiffusion(problem, ctx, precision) as solver:
        return solver.solve(**kwargs)  # type: ignore[arg-type]
