"""Forward diffusion in GLSL by Jacobi relaxation, on any grid (Wang et al. 2008, sections 4.4
and 5.2, figures 6-7): the regular block grid and the polygrid, which on a box is the same
system (``tests/test_polygrid.py``).

Textures (packed by the grid's :class:`~glsldiff.packing.Mosaic`, lengths in mm, coefficients
in mm^-1): T_kappa, T_mu, T_q (the source at boundary nodes), T_w1 / T_w2 (scaled Laplacian
weights and the row scale at interior nodes, the partner distance d at boundary nodes; see
:func:`glsldiff.solve.stencil.weight_textures`) and the ping-pong radiance buffers I_A / I_B of
:class:`glsldiff.gl.PingPong` holding the unknown (``kappa phi`` for the paper's stencil,
``phi`` for the conservative one). All three colour channels are updated at once.

A sweep draws the interior pass and then the boundary pass of ``shaders/stencil.frag``, each
as the quads, lines and points of :func:`glsldiff.solve.stencil.pass_primitives`, whose vertex
attributes hold the texel offsets to the nodes a row reads (packing ``"primitives"``, the
paper's); or, packing ``"texels"``, one quad whose texels read their row kind and offsets from
two integer textures (:func:`glsldiff.solve.stencil.offset_textures`), bit-identical results,
the default on polygrids (:func:`default_packing`); :meth:`GlslDiffusion.residual`
draws the same primitives with the residual variant of the shader (multigrid). The rows are
those of ``shaders/diffusion.glsl``, the CPU oracle's (:mod:`glsldiff.oracle.assembly`).

Convergence is checked by reading the iterate back every ``check_every`` sweeps and
evaluating its Jacobi-scaled residual in float64 with the CPU system
(:func:`glsldiff.oracle.solvers.relax`, the solve loop of every relaxation), so an iterate
frozen by fp16/fp32 rounding reports its true residual and is labelled "stalled".
"""
from __future__ import annotations

import os
import time
from dataclasses import replace
from functools import cached_property
from types import MappingProxyType
from typing import Callable, Mapping

import moderngl
import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff import gl
from glsldiff.core.errors import InputError, SolverError
from glsldiff.oracle.assembly import LinearSystem, assemble, assemble_rhs
from glsldiff.oracle.solvers import Callback, relax
from glsldiff.packing import primitive_vertices
from glsldiff.solve import quantize
from glsldiff.solve.stencil import (PACKINGS, PASSES, offset_textures, pass_primitives, primitive_count,
                                    uniform_weights, weight_textures)
from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.report import CURRENT, MAXITER, RELAX_TOL, SolveReport

PRECISIONS = ("fp32", "fp16", "paper")
Start = ArrayLike | str | None  # x0 of a GLSL solve: a fluence node array, CURRENT, or None

_MODES = {"triangles": moderngl.TRIANGLES, "lines": moderngl.LINES, "points": moderngl.POINTS}
_FORMAT = ("2f", "2i", "2i", "2i", "2i", "2i", "2i")
_ATTRS = ("in_pos", "in_off0", "in_off1", "in_off2", "in_off3", "in_off4", "in_off5")


#: Primitives per updated node above which the "texels" packing is the default. From
#: ``glsldiff bench forward --throughput`` (llvmpipe, 2 cores, best of 3): a primitives sweep costs
#: about 2.7e-8 s per node + 4.5e-7 s per primitive (regular 50^3: 242 primitives, 3.3-3.4 ms;
#: bunny 8^3 per cube: 14 k, 11.5 ms; 4^3: 62 k, 30 ms), a texels sweep 3.1-3.4e-8 s per node
#: whatever the layout (3.7-3.9 ms on the regular grid, 4.4-4.5 ms on both bunnies, 1.86 ms on
#: the 54 k-node torus); they break even near 0.01 primitives per node.
TEXELS_ABOVE = 0.01


def default_packing(draws_per_node: float) -> str:
    """The sweeps' packing when none is given: ``$GLSLDIFF_PACKING``, else ``"texels"`` when the
    paper's primitives would draw more than :data:`TEXELS_ABOVE` primitives per node (polygrids of
    small cubes), ``"primitives"`` otherwise (regular grids, polygrids of large cubes). Not
    measured on a discrete GPU."""
    name = os.environ.get("GLSLDIFF_PACKING", "").strip().lower()
    if not name:
        return "texels" if draws_per_node > TEXELS_ABOVE else "primitives"
    if name not in PACKINGS:
        raise InputError(f"GLSLDIFF_PACKING={name!r}; choose one of {PACKINGS}")
    return name


def buffer_precision(precision: str) -> str:
    """The radiance buffers' format (``"fp32"`` or ``"fp16"``) of a solver ``precision``
    (one of :data:`PRECISIONS`; ``"paper"`` = fp16 buffers, 8-bit material)."""
    if precision not in PRECISIONS:
        raise InputError(f"precision={precision!r}; choose one of {PRECISIONS}")
    return "fp32" if precision == "fp32" else "fp16"


class GlslDiffusion:
    """Jacobi relaxation of a :class:`DiffusionProblem` (regular grid or polygrid) in shaders.

    GPU objects (textures, programs, buffers, vertex arrays; the ping-pong pair unless
    borrowed) belong to this object; call :meth:`release` (or use it as a context manager).

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
    packing
        ``"primitives"`` or ``"texels"`` (module docstring); default :func:`default_packing`.
    update
        ``(N,)`` flat node mask of the nodes the sweeps update (default all; the adaptive
        schedule fixes the others). The residual checks are then those of the system with the
        other nodes held at their values when a solve starts (:meth:`LinearSystem.pinned`).
    state
        A ping-pong pair to borrow (levels of a hierarchy sharing their radiance buffers).
    damping
        Jacobi damping in (0, 1] (1 = plain Jacobi; multigrid smoothing).
    interior_rhs
        T_q also holds a right-hand side at interior nodes (a multigrid coarse level).
    """

    method = "glsl-jacobi"  # report name (before the precision suffix)

    def __init__(self, problem: DiffusionProblem, ctx: moderngl.Context | None = None,
                 precision: str = "fp32", *, update: NDArray[np.bool_] | None = None,
                 state: gl.PingPong | None = None, damping: float = 1.0, interior_rhs: bool = False,
                 packing: str | None = None) -> None:
        self.buffers = buffer_precision(precision)
        g = problem.grid
        if packing is not None and packing not in PACKINGS:
            raise InputError(f"packing={packing!r}; choose one of {PACKINGS}")
        if not 0.0 < damping <= 1.0:
            raise InputError(f"damping={damping!r} must be in (0, 1] (1 = plain Jacobi)")
        if update is not None:
            update = np.asarray(update, dtype=bool)
            if update.shape != (g.size,):
                raise InputError(f"update mask has shape {update.shape}, expected ({g.size},)")
        self.problem, self.precision, self.update = problem, precision, update
        self.material_bits = 8 if precision == "paper" else 32
        self.damping = float(damping)
        self.ctx = ctx if ctx is not None else gl.get_context()
        gl.make_current(self.ctx)
        self.size: tuple[int, int] = g.texture_size
        if state is not None and (state.dtype != gl.DTYPES[self.buffers] or state.size[0] < self.size[0]
                                  or state.size[1] < self.size[1]):
            raise InputError(f"a shared state of {state.size} ({state.dtype}) cannot hold a "
                             f"{self.size} {precision} level")
        self._gpu = gl.Resources()
        self._sweep_draws: list[tuple[moderngl.VertexArray, int]] = []
        self._residual_draws: list[tuple[moderngl.VertexArray, int]] | None = None  # built on first use
        self.material_uniforms: dict[str, tuple[float, float, float]] = {}
        self.stencil_uniforms = uniform_weights(g.graph)
        self.defines = {"STENCIL_PAPER": int(problem.stencil == "paper"),
                        "FACE_HARMONIC": int(problem.face_mean == "harmonic"),
                        "DAMPED": int(self.damping < 1.0), "HAS_RHS": int(interior_rhs),
                        "MATERIAL_8BIT": int(self.material_bits == 8), "UNIFORM_WEIGHTS": int(bool(self.stencil_uniforms))}
        try:
            w1, w2 = weight_textures(g)
            self._textures: dict[str, moderngl.Texture] = {
                "u_kappa": self._material_texture(), "u_mu": self._material_texture(),
                "u_q": self._gpu.add(gl.float_texture(self.ctx, self.size, g.pack(problem.q))),
                "u_w1": self._gpu.add(gl.float_texture(self.ctx, self.size, w1)),
                "u_w2": self._gpu.add(gl.float_texture(self.ctx, self.size, w2))}
            self._write_material()
            self.state = state if state is not None else self._gpu.add(
                gl.PingPong.create(self.ctx, self.size, self.buffers))
            self.primitives = pass_primitives(g, update)
            self.packing = packing or default_packing(primitive_count(self.primitives) / max(1, self.updated_nodes))
            if self.packing == "texels":
                for name, arr in zip(("u_offa", "u_offb"), offset_textures(g, update)):
                    tex = self.ctx.texture(self.size, 4, np.ascontiguousarray(arr).tobytes(), dtype="u4", alignment=1)
                    tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
                    self._textures[name] = self._gpu.add(tex)
                quad = self._gpu.add(self.ctx.buffer(gl.quad_vertices(self.size).tobytes()))
                self._vbos = {"texels": [(quad, moderngl.TRIANGLES)]}
            else:
                self._vbos = {name: [(self._gpu.add(self.ctx.buffer(np.ascontiguousarray(v).tobytes())),
                                      _MODES[mode]) for mode, v in primitive_vertices(prims).items() if len(v)]
                              for name, prims in self.primitives.items()}
            self._sweep_draws = self._pass_draws(residual=False)
        except Exception:
            self._gpu.release()
            raise
        self.sweeps_run = 0  # sweeps since creation (work counters of multilevel solves)
        self.sweep_seconds = 0.0  # wall time inside sweep(), GPU finished (no read-backs)
        self._pinned: LinearSystem | None = None

    # ---- set-up -----------------------------------------------------------------------------
    def _material_texture(self) -> moderngl.Texture:
        if self.material_bits == 8:
            tex = self.ctx.texture(self.size, 4, dtype="f1")
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            return self._gpu.add(tex)
        return self._gpu.add(gl.float_texture(self.ctx, self.size))

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
            for prog in self._gpu_programs():
                gl.set_uniforms(prog, self.material_uniforms)
            return
        for name, vol in (("u_kappa", p.kappa), ("u_mu", p.mu)):
            self._textures[name].write(np.ascontiguousarray(g.pack(vol)).tobytes(), alignment=1)

    def _gpu_programs(self) -> list[moderngl.Program]:
        draws = self._sweep_draws + (self._residual_draws or [])
        return list({id(vao.program): vao.program for vao, _ in draws}.values())

    def _program(self, row: str, residual: bool) -> moderngl.Program:
        texels = row == "texels"
        prog = self._gpu.add(gl.program(self.ctx, "quad.vert" if texels else "stencil.vert", "stencil.frag",
                                        {**self.defines, "ROW_BOUNDARY": int(row == "boundary"),
                                         "RESIDUAL": int(residual), "TEXEL_OFFSETS": int(texels)}))
        units = {name: unit for unit, name in enumerate(self._textures, start=1)}
        gl.set_uniforms(prog, {"u_size": tuple(float(s) for s in self.size), "u_C": float(self.problem.C),
                               "u_omega": self.damping, "u_state": 0, **units, **self.stencil_uniforms,
                               **self.material_uniforms})
        return prog

    def _pass_draws(self, residual: bool) -> list[tuple[moderngl.VertexArray, int]]:
        """Vertex arrays of the interior and boundary passes (sweep or residual variant), over
        the primitive buffers built once."""
        if self.packing == "texels":   # one quad: every texel reads its row kind and offsets
            prog = self._program("texels", residual)
            return [(self._gpu.add(self.ctx.vertex_array(prog, [(vbo, "2f", "in_pos")])), mode)
                    for vbo, mode in self._vbos["texels"]]
        out = []
        for name in PASSES:
            prog = self._program(name, residual)
            attrs = [a for a in _ATTRS if a in prog]
            fmt = " ".join(f if a in prog else "8x" for a, f in zip(_ATTRS, _FORMAT))
            out += [(self._gpu.add(self.ctx.vertex_array(prog, [(vbo, fmt, *attrs)])), mode)
                    for vbo, mode in self._vbos[name]]
        return out

    # ---- the problem ------------------------------------------------------------------------
    @property
    def textures(self) -> Mapping[str, moderngl.Texture]:
        """T_kappa, T_mu, T_q, T_w1, T_w2 by uniform name (read-only view; a transfer pass may
        render into ``"u_q"`` or read the material)."""
        return MappingProxyType(self._textures)

    @property
    def updated_nodes(self) -> int:
        """Nodes each sweep updates."""
        return sum(p.texels for p in self.primitives.values())

    def primitive_counts(self) -> dict[str, dict[str, int]]:
        """Quads, lines and points per pass."""
        return {name: prims.kinds for name, prims in self.primitives.items()}

    @cached_property
    def full_system(self) -> LinearSystem:
        """The CPU system of the problem (assembled on first use)."""
        return assemble(self.problem)

    @property
    def system(self) -> LinearSystem:
        """The CPU system that checks the residual of read-backs: the full system, or with an
        ``update`` mask the one pinned at the start of the last solve."""
        return self._pinned if self._pinned is not None else self.full_system

    def set_q(self, q: ArrayLike | Mapping[str, ArrayLike]) -> None:
        """Replace the boundary source (the material textures stay on the GPU)."""
        gl.make_current(self.ctx)
        self.problem = self.problem.with_q(q)
        self.reset_rhs()
        if "full_system" in self.__dict__:
            self.full_system = replace(self.full_system, b=assemble_rhs(self.problem))
        self._pinned = None

    def reset_rhs(self) -> None:
        """Write the problem's source into T_q (after a pass rendered something else there)."""
        gl.make_current(self.ctx)
        self._textures["u_q"].write(np.ascontiguousarray(self.problem.grid.pack(self.problem.q)).tobytes(),
                                    alignment=1)

    def set_material(self, kappa: ArrayLike, mu: ArrayLike, upload: bool = True) -> None:
        """Replace kappa (mm) and mu (mm^-1) in place (same grid, source and options): an
        edit or an optimiser step re-uses the textures, programs and vertex buffers.
        ``upload=False``: the textures already hold them (a GPU edit wrote them); only the
        CPU side (residual checks) is updated."""
        gl.make_current(self.ctx)
        self.problem = replace(self.problem, kappa=kappa, mu=mu)
        if upload:
            self._write_material()
        self.__dict__.pop("full_system", None)
        self._pinned = None

    def set_initial(self, phi: ArrayLike | None) -> None:
        """Start the next solve from fluence ``phi`` (node array) or from zero."""
        gl.make_current(self.ctx)
        g = self.problem.grid
        if phi is None:
            x = np.zeros(tuple(g.shape) + (3,))
        else:
            phi = np.asarray(phi, dtype=np.float64)
            if phi.shape != tuple(g.shape) + (3,):
                raise InputError(f"initial phi has shape {phi.shape}, expected {tuple(g.shape) + (3,)}")
            x = self.problem.from_phi(phi) * g.active[..., None]
        self.state.write(g.pack(x))

    @property
    def floor_max(self) -> float:
        """Largest residual taken for the rounding floor of the buffers (fp16 stalls near
        1e-2 on slowly converging grids: an increment below half an fp16 ulp is lost)."""
        return 1e-2 if self.buffers == "fp32" else 5e-2

    def bind_textures(self) -> None:
        """Bind the state (unit 0) and the material, source and weight textures."""
        self.state.src.use(0)
        for unit, tex in enumerate(self._textures.values(), start=1):
            tex.use(unit)

    # ---- passes -----------------------------------------------------------------------------
    def sweep(self, n: int = 1) -> None:
        """Run ``n`` Jacobi sweeps (interior pass + boundary pass each)."""
        gl.make_current(self.ctx)
        t0 = time.perf_counter()
        with gl.keep_framebuffer(self.ctx):
            for unit, tex in enumerate(self._textures.values(), start=1):
                tex.use(unit)
            for _ in range(n):
                self.state.dst.use()
                self.ctx.viewport = (0, 0, *self.size)  # this level's texels of a (maybe shared) state
                self.state.src.use(0)
                for vao, mode in self._sweep_draws:
                    vao.render(mode)
                self.state.swap()
            self.sweeps_run += n
            self.ctx.finish()  # sweeps are timed: wait for the GPU
        self.sweep_seconds += time.perf_counter() - t0

    def residual(self, target: moderngl.Framebuffer) -> None:
        """Draw ``rhs - A x`` of every updated row, in the units of the equation (not
        row-scaled), into ``target`` (a float framebuffer of at least :attr:`size`; other
        texels untouched). The residual programs are built on first use."""
        gl.make_current(self.ctx)
        if self._residual_draws is None:
            self._residual_draws = self._pass_draws(residual=True)
        with gl.keep_framebuffer(self.ctx):
            target.use()
            self.ctx.viewport = (0, 0, *self.size)
            self.bind_textures()
            for vao, mode in self._residual_draws:
                vao.render(mode)

    def unknown(self) -> NDArray[np.float64]:
        """Current iterate (``kappa phi`` or ``phi``) as a float64 node array ``shape + (3,)``."""
        gl.make_current(self.ctx)
        return self.problem.grid.unpack(self.state.read(size=self.size)).astype(np.float64)

    def fluence(self) -> NDArray[np.float64]:
        """Current fluence phi as a node array ``shape + (3,)`` (0 at inactive nodes)."""
        return self.problem.to_phi(self.unknown())

    # ---- solves -----------------------------------------------------------------------------
    def start(self, x0: Start) -> None:
        """Initial iterate of a solve: zero (``None``), fluence ``x0``, or :data:`CURRENT`."""
        if isinstance(x0, str):
            if x0 != CURRENT:
                raise InputError(f"x0={x0!r}: give a fluence array, None (zero) or {CURRENT!r}")
            return
        self.set_initial(x0)

    def solve(self, tol: float = RELAX_TOL, maxiter: int = MAXITER, x0: Start = None,
              callback: Callback | None = None, residuals: list[float] | None = None, *,
              check_every: int = 50) -> tuple[NDArray, SolveReport]:
        """Relax until the Jacobi-scaled residual is <= ``tol`` or ``maxiter`` sweeps ran.

        Parameters
        ----------
        tol, maxiter, x0, callback, residuals
            The uniform solver arguments (:mod:`glsldiff.system.report`): residual tolerance,
            sweep budget, initial fluence (``None``: zero; :data:`CURRENT`: continue from the
            buffers, for restarts and frame coherence), ``callback(x)`` after each check with
            the unknown vector (channel-major, float64), a list for the residual history.
        check_every
            Sweeps between residual checks (each costs a read-back).

        Returns
        -------
        phi, report
            Fluence (node array ``shape + (3,)``) and the :class:`SolveReport`; its
            ``radiance`` is the exitant radiance (face arrays on a regular grid, ``(n_boundary,
            3)`` on a polygrid).

        Raises
        ------
        SolverError
            The iteration diverged (spectral radius >= 1) or overflowed the fp16 buffers.
        """
        t0 = time.perf_counter()
        self.start(x0)
        return self.iterate(self.sweep, tol=tol, maxiter=maxiter, check_every=check_every, callback=callback,
                            residuals=residuals, name="GLSL Jacobi", t0=t0)

    def iterate(self, step: Callable[[int], None], *, tol: float, maxiter: int, check_every: int,
                callback: Callback | None = None, residuals: list[float] | None = None,
                name: str = "GLSL Jacobi", patience: int = 8, method: str | None = None,
                t0: float | None = None) -> tuple[NDArray, SolveReport]:
        """The solve loop of the GLSL solvers (:func:`glsldiff.oracle.solvers.relax`) on this
        level's iterate, from its current buffers: ``step(n)`` advances ``n`` iterations (Jacobi
        sweeps, or a schedule's V-cycles); the residual is checked after every ``check_every``."""
        t0 = time.perf_counter() if t0 is None else t0
        if self.update is not None:  # the nodes no sweep updates keep their current values
            full = self.full_system
            self._pinned = full.pinned(~self.update[full.active], full.from_volume(self.unknown()))
        system = self.system

        def advance(n: int) -> NDArray:
            step(n)
            vol = self.unknown()
            if self.buffers == "fp16" and not np.all(np.abs(vol) < gl.FP16_MAX):
                raise SolverError(
                    f"{name} overflowed the fp16 buffers (|value| reached {gl.FP16_MAX:g}); "
                    "scale q down or use precision='fp32'")
            return system.from_volume(vol)

        result = relax(system, advance, system.from_volume(self.unknown()), tol=tol, maxiter=maxiter,
                       check_every=check_every, callback=callback, residuals=residuals,
                       floor_max=self.floor_max, patience=patience, name=name, problem=self.problem)
        return result.report(method or f"{self.method}-{self.precision}", self.problem, system,
                             time.perf_counter() - t0)

    # ---- lifetime ---------------------------------------------------------------------------
    def release(self) -> None:
        """Free every GPU object this solver created (not a borrowed state)."""
        gl.make_current(self.ctx)
        self._gpu.release()
        self._textures, self._vbos, self._sweep_draws, self._residual_draws = {}, {}, [], None

    def __enter__(self) -> "GlslDiffusion":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def solve_glsl(problem: DiffusionProblem, ctx: moderngl.Context | None = None, precision: str = "fp32",
               **kwargs: object) -> tuple[NDArray, SolveReport]:
    """One-shot GLSL solve (regular grid or polygrid); ``kwargs`` go to :meth:`GlslDiffusion.solve`."""
    with GlslDiffusion(problem, ctx, precision) as solver:
        return solver.solve(**kwargs)  # type: ignore[arg-type]
