"""Algebraic multigrid in GLSL for a general sparse symmetric system with RGB channels (the
systems of :class:`glsldiff.solve.gather.GlslSparse`, e.g. the P1 finite elements of
:func:`glsldiff.oracle.fem.assemble_tet`): V-cycles, by default as the preconditioner of
conjugate gradients, every pass a gather fragment shader of :mod:`glsldiff.solve.gather`.

Hierarchy (CPU, once per matrix)
    Smoothed aggregation (pyamg) on the channel-mean matrix ``(A_R + A_G + A_B) / 3`` gives the
    prolongations ``P_l`` (``n_l x n_{l+1}``), shared by the three channels (one pattern,
    similar values); the coarse operators are Galerkin per channel, ``A_{l+1} = P_l^T A_l P_l``.
    Options (:data:`glsldiff.oracle.amg.AMG_DEFAULTS`): the ``"symmetric"`` strength of
    connection with theta 0 and energy-minimising prolongation smoothing (degree 1). pyamg's
    own default (the same strength, Jacobi-smoothed P) aggregates ~27 fine nodes of a P1 matrix
    per coarse node, and its iteration counts grow with the grid (10 mm sphere, 5 mm cubes,
    n = 3, 6, 8 nodes per cube edge, iterations to 1e-4: plain V(2,2) 11, 22, 27 against 7,
    10, 12 with the ``"evolution"`` strength; PCG 6, 9, 10 against 5, 6, 6). The energy
    smoothing takes 6, 8, 10 PCG iterations there. The evolution strength (the default until
    the first-render work of issue 45; ``amg={"strength": "evolution"}``) converges in fewer
    cycles but sets up slower: on the default bunny (147k nodes, fresh cache, 2 cores) pyamg
    1.7-2.0 s against 0.96 s, 4 levels against 3, 6 PCG cycles (1.04-1.11 s) against 8
    (1.2-1.4 s), pass 2 5.1 s against 3.6 s; an edit to 0.5 % 0.21 s (bench edit), a light
    change to 0.5 % 0.62-0.71 s (bench frames) with this default.
    The coarsening stops at ``max_coarse`` unknowns (default 300). pyamg and the damping estimates
    run on one BLAS thread (OpenBLAS's threads on 2 busy cores made them 2-4x slower).
Coarsest level
    Solved exactly, on the GPU, by one pass: ``x_c = A_c^-1 b_c`` with the dense inverse of
    each channel's ``A_c`` (float64 LAPACK, stored in fp32) as an ``n_c``-slot gather (``n_c^2``
    multiply-adds: under 0.1 M for 300 unknowns, well under a fine sweep's cost; 0.4 ms of a
    ~100 ms cycle on 125k nodes). No read-back per cycle and no coarse iteration to tune:
    damped Jacobi on the coarsest operator (condition number ~10^2 - 10^3) would need hundreds
    of sweeps per cycle, one draw each; a CPU solve a read-back and an upload per cycle.
    ``max_coarse`` is capped by the texture-array layers (``GL_MAX_ARRAY_TEXTURE_LAYERS``, 2048
    on llvmpipe).
GPU storage, per level ``l`` (node ``i`` at texel ``(i % W_l, i // W_l)``, ``W_l`` a power of two)
    ``x`` (ping-pong pair), ``b``, ``r`` and ``a_ii`` (RGBA32F textures; ``b``, ``r`` render
    targets), the off-diagonal slots of ``A_l`` (the three channels in rgb), and for
    ``l < L-1`` the slots of ``P_l`` (rows: level ``l``'s nodes), of ``R_l = P_l^T`` (rows:
    level ``l+1``'s nodes), both with the shared value in all three channels, and of
    ``omega_l D_l^-1`` (one slot: the first pre-smoothing sweep from ``x = 0``); at the
    coarsest the dense inverse. All are :class:`~glsldiff.solve.gather.EllPack` layers, the few
    longest rows (at most :data:`~glsldiff.solve.gather.SPILL_SHARE`) spilled to a small texture
    of their own instead of padding every row to them (the bunny's finest matrix: 19 layers, not
    31: 73 -> 45 MB; all gathers 122 -> 85 MB), packed
    and written level by level, matrix by matrix, a band of texel rows at a time
    (:func:`~glsldiff.solve.gather.upload_packed`: the packs are never all in memory at once,
    215 MB on the 147k-node bunny) and drawn by :class:`~glsldiff.solve.gather.GatherProgram`
    (``shaders/gather.frag``, the operation by its ``u_mode``). On the CPU the finest level is
    the caller's matrices where they are in the compact form of
    :func:`~glsldiff.oracle.assembly.channel_values` (a P1 system's: not copied), and the CPU
    system whose residual the solve checks is those matrices too
    (:class:`~glsldiff.oracle.assembly.ChannelSystem`, no block-diagonal copy).
V-cycle (``pre``/``post`` damped Jacobi sweeps, default 2/2), every step one full-screen pass
    down, ``l = 0 .. L-2``: ``pre`` sweeps on ``A_l x_l = b_l`` (from ``x_l = 0`` on the coarse
    levels, and on level 0 as a preconditioner: the first sweep is then ``x_l = omega_l D_l^-1
    b_l``, an ``APPLY``); ``r_l = b_l - A_l x_l`` (``RESIDUAL``); ``b_{l+1} = P_l^T r_l``
    (``APPLY`` of ``R_l``); coarsest: ``x = A^-1 b`` (``APPLY``); up, ``l = L-2 .. 0``:
    ``x_l += P_l x_{l+1}`` (``ADD``), ``post`` sweeps. With one level (``n <= max_coarse``) a
    cycle is the dense solve.
Acceleration (``accel``)
    ``"cg"`` (default): conjugate gradients per channel, preconditioned by one V-cycle from
    zero (symmetric positive definite when ``pre == post``), entirely on the GPU: ``q = A p``
    (``MATVEC``), the dot products ``r.z``, ``p.q`` reduced to one texel in two passes
    (``shaders/gather_reduce.frag``) and read by the vector updates
    (``shaders/gather_axpy.frag``): no read-back per iteration. An iteration costs a V-cycle
    plus 4 fine passes of 2-3 fetches per node and 4 reduction passes (~10 % of a cycle). An
    iteration ends at its new iterate: the next direction's V-cycle opens the next iteration, so
    ``x_k`` is there after k V-cycles, not k + 1 (a frame after an edit: 1 V-cycle, not 2).
    ``None``: plain V-cycles ``x <- x + V(b - A x)``. CG matters on grids whose P1 matrix is far
    from an M-matrix: on the 125k-node bunny grid (``lambda_max(D^-1 A)`` 3.7) plain V-cycles
    contract by 0.93 per cycle (pyamg's own Gauss-Seidel V-cycles by 0.92) and need 42 cycles
    to 1e-4, PCG 17; on the sphere 12 and 6.
Smoothing damping
    ``omega="auto"`` takes, per level, ``omega_l = 1.6 / lambda_max(D_l^-1 A_l)``, the largest
    over the channels, ``lambda_max`` from above: a Lanczos Ritz value plus its residual, to 0.2 %
    (:func:`~glsldiff.oracle.amg.jacobi_lambda_bound`; +0.15 to +0.2 % on the bunny's levels:
    0.4 s CPU for its 9 matrices against 1.5 s for ARPACK to 1e-3 on one BLAS thread, 5-6 s on
    OpenBLAS's threads; the same PCG iterations, errors within 0.5 %). A smoother
    must damp the upper part of the spectrum (what the coarse grid cannot represent); the
    classic ``4/3 / lambda_max`` balances ``|1 - omega lambda|`` over ``[lambda_max / 2,
    lambda_max]``; 1.6 trades some of that for the middle of the spectrum, which these
    aggregation hierarchies represent poorly (measured, sphere n = 8, plain V(2,2): 15, 13, 12
    cycles to 1e-4 with 4/3, 1.6, 1.8; bunny PCG: 19, 17, 16). 1.6 keeps a 20 % margin to
    the divergence of Jacobi (and so of the V-cycle's positive definiteness) at 2.

Convergence is checked by :func:`glsldiff.oracle.solvers.relax` as for every relaxation: the
fine iterate is read back every ``check_every`` iterations (default 1: a check, a read-back
and a float64 residual on the CPU, costs ~7 % of a cycle on llvmpipe, less than the half cycle
that checking every second cycle overshoots on average) and its Jacobi-scaled residual
evaluated; ``maxiter`` and the report's ``sweeps`` count iterations (V-cycles; CG
iterations, one V-cycle each). The fp32 floor of that residual is ~1e-6 (the monitor reports
``"stalled"`` there).

Measured on llvmpipe (2 shared cores), time to a 1e-4 residual, three channels: see
:class:`GlslSparseMultigrid`.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import moderngl
import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from glsldiff import gl
from glsldiff.core.errors import InputError, SolverError
from glsldiff.oracle.amg import build_prolongations, galerkin, jacobi_lambda_bound
from glsldiff.oracle.assembly import ChannelSystem, row_entries
from glsldiff.oracle.solvers import Callback
from glsldiff.solve.gather import (ADD, APPLY, JACOBI, MATVEC, PRECISIONS, RESIDUAL, GatherMatrix, GatherProgram,
                                   GatherSolver, Matrices, Start, channel_matrices, check_symmetric, compact_channels,
                                   distinct, node_rhs, pack_nodes, parse_omega, texture_width, upload_packed,
                                   write_band)
from glsldiff.system.report import CURRENT, MAXITER, RELAX_TOL, SolveReport

__all__ = ["GlslSparseMultigrid", "MultigridLevel", "smoother_omega", "SMOOTH_TARGET", "MAX_COARSE", "ACCELERATIONS"]

SMOOTH_TARGET = 1.6       # omega_l = SMOOTH_TARGET / lambda_max(D_l^-1 A_l) for omega="auto"
MAX_COARSE = 300          # coarsest level: at most this many unknowns (a dense inverse on the GPU)
ACCELERATIONS = ("cg", None)   # conjugate gradients preconditioned by one V-cycle, or plain V-cycles


# ---- the hierarchy (CPU) --------------------------------------------------------------------
def smoother_omega(mats: Sequence[sp.csr_matrix], target: float = SMOOTH_TARGET) -> tuple[float, float]:
    """``(omega, lambda_max)``: ``target / lambda_max(D^-1 A)``, the largest over the distinct
    channel matrices (the ``omega="auto"`` smoothing damping, module docstring)."""
    lam = max(jacobi_lambda_bound(M) for M in distinct(list(mats)))
    return target / lam, lam


def _one_pattern(mats: list[sp.csr_matrix]) -> list[sp.csr_matrix]:
    """Galerkin channel matrices of a level on one ``indices``/``indptr`` pair with their values in
    one ``(3, nnz)`` array (:func:`~glsldiff.solve.gather.compact_channels`) where their stored
    patterns agree (every level of the bunny: 2 of 3 index arrays, 10 MB, not kept); else as
    they are."""
    M0 = mats[0]
    if not all(np.array_equal(M.indptr, M0.indptr) and np.array_equal(M.indices, M0.indices) for M in mats[1:]):
        return mats
    return compact_channels(np.stack([M.data for M in mats]), M0.indices, M0.indptr, M0.shape)


@dataclass
class MultigridLevel:
    """One level of the hierarchy (CPU side).

    Attributes
    ----------
    n
        Unknowns per channel.
    A
        The three channel matrices (level 0: the system's; else Galerkin).
    P
        Prolongation to this level from the next coarser one (``n x n_next``, shared by the
        channels); ``None`` at the coarsest.
    omega, lambda_max
        Smoothing damping and the ``lambda_max(D^-1 A)`` upper estimate behind it (``None`` for a
        given omega; both ``nan`` at the coarsest, which is solved exactly).
    slots
        ``K`` of the level's gather: off-diagonals of ``A`` per row; at the coarsest, ``n``
        (the dense inverse's rows).
    p_slots, r_slots
        ``K`` of ``P`` (its longest row) and of ``R = P^T`` (its longest column); 0 at the coarsest.
    size
        ``(W, H)`` of the level's textures.
    inverse
        At the coarsest: ``A^-1`` per channel (dense, float64); else ``None``.
    """

    n: int
    A: list[sp.csr_matrix]
    P: sp.csr_matrix | None
    omega: float
    lambda_max: float | None
    slots: int = 0
    p_slots: int = 0
    r_slots: int = 0
    size: tuple[int, int] = (0, 0)
    inverse: list[NDArray[np.float64]] | None = field(default=None, repr=False)

    @property
    def coarsest(self) -> bool:
        return self.P is None

    def as_dict(self, level: int) -> dict[str, object]:
        """The report's view of the level."""
        return {"level": level, "n": self.n, "nodes": self.n, "slots": self.slots,
                "omega": self.omega, "lambda_max": self.lambda_max, "p_slots": self.p_slots,
                "r_slots": self.r_slots, "texture": f"{self.size[0]}x{self.size[1]}",
                "smoother": "dense inverse" if self.coarsest else "damped Jacobi"}


@dataclass
class _GpuLevel:
    """A level's textures, framebuffers and gathers."""

    size: tuple[int, int]
    x: gl.PingPong
    b: moderngl.Texture
    b_fbo: moderngl.Framebuffer
    diag: moderngl.Texture
    A: GatherMatrix | None                 # off-diagonals (None at a coarsest level below 0)
    r: moderngl.Texture | None = None
    r_fbo: moderngl.Framebuffer | None = None
    P: GatherMatrix | None = None          # rows here, columns on the next level
    R: GatherMatrix | None = None          # rows on the next level, columns here
    first: GatherMatrix | None = None      # omega D^-1: the first sweep from x = 0
    inverse: GatherMatrix | None = None    # the coarsest level's dense inverse


class _Quad:
    """A fragment shader of ``shaders/`` on a full-viewport unit quad (``quad.vert``)."""

    def __init__(self, ctx: moderngl.Context, resources: gl.Resources, fragment: str,
                 units: dict[str, int]) -> None:
        self.ctx = ctx
        self.prog = resources.add(gl.program(ctx, "quad.vert", fragment))
        gl.set_uniforms(self.prog, {"u_size": (1.0, 1.0), **units})
        vbo = resources.add(ctx.buffer(np.array([0, 0, 1, 0, 0, 1, 1, 1], dtype="f4").tobytes()))
        self.vao = resources.add(ctx.vertex_array(self.prog, [(vbo, "2f", "in_pos")]))

    def draw(self, target: moderngl.Framebuffer, size: tuple[int, int], textures: Sequence[moderngl.Texture],
             uniforms: dict[str, Any]) -> None:
        target.use()
        self.ctx.viewport = (0, 0, *size)
        for unit, tex in enumerate(textures):
            tex.use(unit)
        for name, value in uniforms.items():
            if name in self.prog:
                self.prog[name].value = value
        self.vao.render(moderngl.TRIANGLE_STRIP)


@dataclass
class _Target:
    """A texture with its framebuffer."""

    tex: moderngl.Texture
    fbo: moderngl.Framebuffer

    @classmethod
    def create(cls, ctx: moderngl.Context, res: gl.Resources, size: tuple[int, int]) -> "_Target":
        tex = res.add(gl.float_texture(ctx, size))
        fbo = res.add(ctx.framebuffer(color_attachments=[tex]))
        fbo.clear(0.0, 0.0, 0.0, 0.0)
        return cls(tex, fbo)


class _ConjugateGradients:
    """Preconditioned conjugate gradients on the GPU, per channel: the iterate ``x``, residual
    ``r``, direction ``p`` (ping-pong pairs), ``q = A p``, and the dot products ``rho = r.z``
    (two one-texel targets: this and the previous iteration's) and ``p.q``, reduced by
    ``gather_reduce.frag`` in two passes (chunks of ``c = ceil(sqrt(n))``, then the
    ``ceil(n / c)`` partial sums) and used by ``gather_axpy.frag`` without a read-back."""

    def __init__(self, ctx: moderngl.Context, res: gl.Resources, n: int, size: tuple[int, int]) -> None:
        self.n, self.size = n, size
        self.x = res.add(gl.PingPong.create(ctx, size, "fp32"))
        self.r = res.add(gl.PingPong.create(ctx, size, "fp32"))
        self.p = res.add(gl.PingPong.create(ctx, size, "fp32"))
        self.q = _Target.create(ctx, res, size)
        self.chunk = max(1, math.isqrt(n - 1) + 1)
        self.partials = -(-n // self.chunk)
        self.partial = _Target.create(ctx, res, (1 << max(0, (self.partials - 1).bit_length()), 1))
        self.rho = [_Target.create(ctx, res, (1, 1)), _Target.create(ctx, res, (1, 1))]
        self.pq = _Target.create(ctx, res, (1, 1))
        self.norms = [_Target.create(ctx, res, (1, 1)), _Target.create(ctx, res, (1, 1))]   # residual_gpu's
        self.pending = False     # the iterate updated, the next direction not yet made
        self.reduce = _Quad(ctx, res, "gather_reduce.frag", {"u_a": 0, "u_b": 1})
        self.axpy = _Quad(ctx, res, "gather_axpy.frag", {"u_a": 0, "u_b": 1, "u_num": 2, "u_den": 3})
        self.started = False

    def dot(self, a: moderngl.Texture, b: moderngl.Texture, out: _Target) -> None:
        """``out`` = per-channel ``a . b`` over the ``n`` nodes (two passes)."""
        W = self.size[0]
        self.reduce.draw(self.partial.fbo, (self.partials, 1), [a, b],
                         {"u_product": 1, "u_count": self.n, "u_chunk": self.chunk,
                          "u_src_shift": W.bit_length() - 1})
        pw = self.partial.tex.size[0]
        self.reduce.draw(out.fbo, (1, 1), [self.partial.tex, self.partial.tex],
                         {"u_product": 0, "u_count": self.partials, "u_chunk": self.partials,
                          "u_src_shift": pw.bit_length() - 1})

    def update(self, pair: gl.PingPong, a: moderngl.Texture, b: moderngl.Texture, num: _Target, den: _Target,
               scale: float) -> None:
        """``pair`` <- ``a + scale (num / den) b`` (``a`` may be ``pair.src``)."""
        self.axpy.draw(pair.dst, self.size, [a, b, num.tex, den.tex], {"u_scale": float(scale)})
        pair.swap()


# ---- the solver -----------------------------------------------------------------------------
class GlslSparseMultigrid(GatherSolver):
    """Algebraic multigrid for ``A_c x_c = b_c`` (c = R, G, B): V-cycles, by default
    preconditioning conjugate gradients, every pass a gather fragment shader (module
    docstring: hierarchy, storage, cycle, coarsest solve, acceleration, damping). The interface
    is :class:`~glsldiff.solve.gather.GlslSparse`'s (a drop-in replacement), counting V-cycles.

    GPU objects belong to this object; call :meth:`release` (or use it as a context manager).

    Parameters
    ----------
    matrices
        One ``n x n`` sparse matrix (all channels) or three (R, G, B) with the same stored
        pattern; real, finite, symmetric, positive diagonal (positive definite for convergence).
    b
        ``(n, 3)`` right-hand side (``(n,)``: the same for all channels).
    ctx
        A moderngl context; default :func:`glsldiff.gl.get_context`.
    precision
        ``"fp32"`` only.
    omega
        Smoothing damping: ``"auto"`` (per level, ``1.6 / lambda_max(D_l^-1 A_l)``) or one float
        in (0, 2) for every level.
    pre, post
        Damped Jacobi sweeps before and after the coarse correction on every level but the
        coarsest (defaults 2, 2; ``pre + post >= 1``).
    max_coarse, max_levels
        Coarsening stops at ``max_coarse`` unknowns (the dense coarsest solve; at most the
        context's texture-array layers) or ``max_levels`` levels.
    amg
        Further options of ``pyamg.smoothed_aggregation_solver`` (default :data:`glsldiff.oracle.amg.AMG_DEFAULTS`).
    prolongations
        The ``P_l`` to use instead of pyamg's (``n_l x n_{l+1}`` each, finest first).
    level_omegas
        With ``prolongations``: the smoothing damping of every level but the coarsest (e.g. an
        earlier solver's :attr:`omegas` of the same matrices, kept on disk), instead of the
        ``omega="auto"`` estimates.
    accel
        ``"cg"`` (conjugate gradients preconditioned by one V-cycle per iteration; needs
        ``pre == post``) or ``None`` (plain V-cycles).

    Attributes
    ----------
    n, levels
        Unknowns per channel; the :class:`MultigridLevel` list (finest first).
    pre, post, accel
        The V-cycle's sweeps; the acceleration.
    system
        The CPU :class:`~glsldiff.oracle.assembly.ChannelSystem` (the finest level's channel
        matrices) whose residual the solve checks.
    setup_seconds
        CPU hierarchy time per stage (``"pyamg"``, ``"galerkin"``, ``"omega"``, ``"inverse"``,
        and ``"upload"`` (GPU objects, the slots packed band by band as they are written);
        :attr:`hierarchy_seconds` sums the CPU ones.
    cycles_run, cycle_seconds
        V-cycles since creation and the wall time inside :meth:`cycle` (GPU finished).
    level_seconds
        Per level, the time of its passes when :attr:`profile` is true (a ``finish`` after each
        level's down and up phase; off by default).
    """

    method = "glsl-gather-multigrid"

    def __init__(self, matrices: Matrices, b: ArrayLike, ctx: moderngl.Context | None = None,
                 precision: str = "fp32", omega: float | str = "auto", pre: int = 2, post: int = 2,
                 max_coarse: int = MAX_COARSE, max_levels: int = 10, amg: dict[str, Any] | None = None,
                 prolongations: Sequence[sp.spmatrix | sp.sparray] | None = None, accel: str | None = "cg",
                 level_omegas: Sequence[float] | None = None) -> None:
        if precision not in PRECISIONS:
            raise InputError(f"precision={precision!r}: GlslSparseMultigrid supports only {PRECISIONS}")
        for name, v in (("pre", pre), ("post", post)):
            if not isinstance(v, (int, np.integer)) or v < 0:
                raise InputError(f"{name}={v!r} must be an integer >= 0")
        if pre + post < 1:
            raise InputError("pre + post must be >= 1 (a V-cycle without smoothing does not converge)")
        if not isinstance(max_levels, (int, np.integer)) or max_levels < 1:
            raise InputError(f"max_levels={max_levels!r} must be an integer >= 1")
        if accel not in ACCELERATIONS:
            raise InputError(f"accel={accel!r}: give 'cg' (conjugate gradients, one V-cycle per iteration) or None "
                             "(plain V-cycles)")
        if accel == "cg" and pre != post:
            raise InputError(f"accel='cg' needs a symmetric V-cycle (pre == post), not pre={pre}, post={post}")
        mats = channel_matrices(matrices, "GlslSparseMultigrid")
        check_symmetric(mats, "GlslSparseMultigrid needs symmetric matrices (Galerkin coarse operators "
                        "and a symmetric smoother)", "symmetrise the system")
        n = mats[0].shape[0]
        bb = node_rhs(b, n)
        fixed = parse_omega(omega)
        self.precision, self.n, self.pre, self.post, self.accel = precision, n, int(pre), int(post), accel
        self.ctx = ctx if ctx is not None else gl.get_context()
        gl.make_current(self.ctx)
        max_layers = int(self.ctx.info.get("GL_MAX_ARRAY_TEXTURE_LAYERS", 256))
        if not 1 <= max_coarse <= max_layers:
            raise InputError(f"max_coarse={max_coarse!r} must be in 1 .. {max_layers} (the coarsest level's "
                             "dense inverse is a gather of max_coarse slots: texture-array layers)")
        max_size = int(self.ctx.info["GL_MAX_TEXTURE_SIZE"])
        self.setup_seconds: dict[str, float] = {}

        # hierarchy
        t0 = time.perf_counter()
        if prolongations is None:
            mean = mats[0].copy()
            mean.data = (mats[0].data + mats[1].data + mats[2].data) / 3.0
            Ps = build_prolongations(mean, max_coarse, max_levels, amg) if n > max_coarse else []
        else:
            Ps = [sp.csr_matrix(P, dtype=np.float64) for P in prolongations]
            rows = n
            for l, P in enumerate(Ps):
                if P.shape[0] != rows or P.shape[1] < 1:
                    raise InputError(f"prolongations[{l}] is {P.shape}; it must be {rows} x n_coarse")
                if not np.isfinite(P.data).all():
                    raise InputError(f"prolongations[{l}] has non-finite entries")
                rows = P.shape[1]
            if rows > max_coarse:
                raise InputError(f"the coarsest level of the given prolongations has {rows} unknowns; "
                                 f"at most max_coarse = {max_coarse} (a dense inverse)")
        self.setup_seconds["pyamg"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        As = [mats]
        for P in Ps:
            R = sp.csr_matrix(P.T)
            As.append(_one_pattern([galerkin(A, P, R) for A in As[-1]]))
        self.setup_seconds["galerkin"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if level_omegas is not None and (prolongations is None or len(level_omegas) != len(Ps)
                                         or not all(0.0 < w < 2.0 for w in level_omegas)):
            raise InputError(f"level_omegas: give one omega in (0, 2) per level but the coarsest ({len(Ps)}) "
                             "with the prolongations they were estimated for")
        self.levels: list[MultigridLevel] = []
        for l, A in enumerate(As):
            P = Ps[l] if l < len(Ps) else None
            if P is None:
                w, lam = math.nan, math.nan
            elif level_omegas is not None:
                w, lam = float(level_omegas[l]), SMOOTH_TARGET / float(level_omegas[l])
            elif fixed is None:
                w, lam = smoother_omega(A)
            else:
                w, lam = fixed, None
            self.levels.append(MultigridLevel(A[0].shape[0], A, P, w, lam,
                                              size=texture_width(A[0].shape[0], max_size)))
        self.setup_seconds["omega"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        last = self.levels[-1]
        try:
            last.inverse = [np.linalg.inv(A.toarray()) for A in last.A]
        except np.linalg.LinAlgError as exc:
            raise SolverError(f"the coarsest operator ({last.n} unknowns) is singular: {exc}") from exc
        self.setup_seconds["inverse"] = time.perf_counter() - t0

        self.system = ChannelSystem(mats, b=bb.T.reshape(-1), diag=self._diagonal(0).T.reshape(-1),
                                    active=np.arange(n))
        t0 = time.perf_counter()
        self._gpu = gl.Resources()
        try:
            with gl.keep_framebuffer(self.ctx):
                self._upload(bb)
            self.ctx.finish()
        except Exception:
            self._gpu.release()
            raise
        self.setup_seconds["upload"] = time.perf_counter() - t0
        self.cycles_run = 0
        self.cycle_seconds = 0.0
        self.profile = False
        self.level_seconds = np.zeros(len(self.levels))

    def _diagonal(self, level: int) -> NDArray[np.float64]:
        """``(n_l, 3)``: the diagonal of level ``level``'s channel matrices."""
        return np.stack([A.diagonal() for A in self.levels[level].A], axis=1)

    def _upload(self, bb: NDArray[np.float64]) -> None:
        """Create the GPU objects of every level (owned by ``self._gpu``), level by level and
        matrix by matrix, each packed in bands while it is written
        (:func:`~glsldiff.solve.gather.upload_packed`: no level's packed slots are held, 215 MB
        on the bunny)."""
        self._pass = GatherProgram(self.ctx, self._gpu)
        self._levels: list[_GpuLevel] = []
        for l in range(len(self.levels)):
            self._levels.append(self._upload_level(l, bb if l == 0 else None))
        self._cg = _ConjugateGradients(self.ctx, self._gpu, self.n, self.levels[0].size) if self.accel else None
        self._b_norm_stale = True

    def _upload_level(self, l: int, bb: NDArray[np.float64] | None) -> _GpuLevel:
        """Level ``l``'s textures, framebuffers and gathers (``bb`` its right-hand side, level 0's);
        its :class:`MultigridLevel` gets the slot counts."""
        lv, ctx, res = self.levels[l], self.ctx, self._gpu
        size, diag = lv.size, self._diagonal(l)

        def gather(mats: Sequence[sp.spmatrix], at: tuple[int, int], **kw: bool) -> GatherMatrix:
            return upload_packed(ctx, mats, at, res, **kw, spill=True,
                                 hint=f" (a level of {lv.n} unknowns: lower max_coarse or change amg)")[0]

        btex = res.add(gl.float_texture(ctx, size, None if bb is None else pack_nodes(bb, size)))
        g = _GpuLevel(size=size, x=res.add(gl.PingPong.create(ctx, size, "fp32")), b=btex,
                      b_fbo=res.add(ctx.framebuffer(color_attachments=[btex])),
                      diag=res.add(gl.float_texture(ctx, size, pack_nodes(diag, size, pad=1.0))), A=None)
        if l > 0:
            g.b_fbo.clear(0.0, 0.0, 0.0, 0.0)
        if l == 0 or not lv.coarsest:    # the finest keeps its zeros: update_fine re-packs it in place
            g.A = gather(lv.A, size, diagonal=False, keep_zeros=l == 0)
        if lv.coarsest:
            g.inverse = gather([sp.csr_matrix(M) for M in lv.inverse], size, diagonal=True)
            lv.slots = g.inverse.slots
            return g
        nxt = self.levels[l + 1]
        g.r = res.add(gl.float_texture(ctx, size))
        g.r_fbo = res.add(ctx.framebuffer(color_attachments=[g.r]))
        g.P = gather([lv.P] * 3, size, diagonal=True)
        g.R = gather([sp.csr_matrix(lv.P.T)] * 3, nxt.size, diagonal=True)
        assert g.A is not None
        lv.slots, lv.p_slots, lv.r_slots = g.A.slots, g.P.slots, g.R.slots
        if self.pre > 0:
            inv_d = lv.omega / diag
            g.first = gather([sp.diags(inv_d[:, c]).tocsr() for c in range(3)], size, diagonal=True)
        return g

    # ---- state ------------------------------------------------------------------------------
    @property
    def hierarchy_seconds(self) -> float:
        """CPU time of the hierarchy: pyamg, Galerkin products, omega estimates and the dense
        inverse (not the packing, done band by band with the upload)."""
        return sum(v for k, v in self.setup_seconds.items() if k != "upload")

    @property
    def omegas(self) -> list[float]:
        """Smoothing damping per level (``nan`` at the coarsest)."""
        return [lv.omega for lv in self.levels]

    @property
    def operator_complexity(self) -> float:
        """Stored entries of all levels' ``A`` over the finest's (one channel)."""
        return sum(lv.A[0].nnz for lv in self.levels) / self.levels[0].A[0].nnz

    @property
    def state(self) -> gl.PingPong:
        """The iterate (ping-pong pair): the conjugate gradients' ``x``, or the finest level's."""
        return self._levels[0].x if self._cg is None else self._cg.x

    def describe(self) -> str:
        """One line per level: unknowns, slots, omega, transfer slots."""
        out = [f"V({self.pre},{self.post}), {len(self.levels)} levels, operator complexity "
               f"{self.operator_complexity:.2f}, hierarchy {self.hierarchy_seconds:.2f} s"]
        for l, lv in enumerate(self.levels):
            if lv.coarsest:
                out.append(f"  level {l}: n={lv.n}, dense inverse ({lv.slots} slots)")
            else:
                out.append(f"  level {l}: n={lv.n}, K={lv.slots}, omega={lv.omega:.4g}, P slots {lv.p_slots}, "
                           f"P^T slots {lv.r_slots}")
        return "\n".join(out)

    @property
    def _rhs(self) -> moderngl.Texture:
        return self._levels[0].b

    @property
    def _fine_size(self) -> tuple[int, int]:
        return self.levels[0].size

    def _restart(self) -> None:
        self._b_norm_stale = True        # residual_gpu's ||D^-1 b|| (b or the diagonal may have changed)
        if self._cg is not None:
            self._cg.started = False     # conjugate gradients restart from the current x

    # ---- in-place changes (interactive editing) ---------------------------------------------
    def update_fine(self, matrices: Matrices, rows: ArrayLike, diagonal_only: bool = False) -> None:
        """The finest matrix changed in ``rows`` only (same stored pattern as before): its
        values, diagonal and first-sweep factors are re-packed for the texel rows those rows
        sit in and written there (``diagonal_only``: only diagonal entries changed, the
        off-diagonal slots are not rewritten); the coarse levels, the prolongations and the smoothing
        damping are kept (a stale but still symmetric positive definite preconditioner for
        a local change: conjugate gradients converge with it, the iteration count tells how
        stale it is; a new solver with ``prolongations`` and ``level_omegas`` of this one remakes
        the coarse operators without pyamg or eigen-solves). The next iteration restarts
        conjugate gradients from the current iterate."""
        fast = (isinstance(matrices, (list, tuple)) and len(matrices) == 3
                and all(sp.issparse(M) and M.format == "csr" and M.dtype == np.float64 and M.has_sorted_indices
                        for M in matrices))      # P1System.matrices(): checked below for the rows that changed
        mats = list(matrices) if fast else channel_matrices(matrices, "GlslSparseMultigrid.update_fine")
        lv = self.levels[0]
        if (mats[0].shape != lv.A[0].shape or any(M.nnz != A.nnz for M, A in zip(mats, lv.A))
                or any(not np.array_equal(M.indptr, mats[0].indptr) for M in mats[1:])):
            raise InputError(f"update_fine needs the finest matrix's pattern ({lv.A[0].shape}, {lv.A[0].nnz} "
                             "entries, one for all channels); build a new solver for a new pattern")
        rows = np.unique(np.asarray(rows, dtype=np.int64))
        if rows.size and (rows[0] < 0 or rows[-1] >= self.n):
            raise InputError(f"rows must be in 0 .. {self.n - 1}")
        lv.A = mats
        self.system.set_blocks(mats)
        n = self.n
        pos = row_entries(mats[0].indptr, rows)
        counts = np.diff(mats[0].indptr)[rows]
        if fast and not all(np.isfinite(M.data[pos]).all() for M in mats):
            raise InputError("update_fine: the updated rows have non-finite (NaN/inf) entries")
        on_diag = mats[0].indices[pos] == np.repeat(rows, counts)
        diag = np.stack([M.data[pos[on_diag]] for M in mats], axis=1)        # (rows, 3), rows ascending
        if not np.all(diag > 0):
            raise InputError("update_fine: the updated matrix has a non-positive diagonal entry")
        for c in range(3):
            self.system.diag[c * n + rows] = diag[:, c]
        if rows.size:
            self._write_rows(mats, rows, diagonal_only)
        self._restart()

    def _write_rows(self, mats: list[sp.csr_matrix], rows: NDArray[np.int64], diagonal_only: bool) -> None:
        """Re-pack and upload the finest level's texel rows that hold ``rows`` (runs of texel
        rows written as one band each)."""
        g, lv = self._levels[0], self.levels[0]
        W, _ = lv.size
        y = np.unique(rows // W)
        breaks = np.flatnonzero(np.diff(y) > 1)
        gl.make_current(self.ctx)
        for y0, y1 in zip(np.concatenate([[y[0]], y[breaks + 1]]), np.concatenate([y[breaks], [y[-1]]])):
            r0, r1 = int(y0) * W, min(self.n, (int(y1) + 1) * W)
            size = (W, int(y1 - y0) + 1)
            if not diagonal_only:
                write_band(g.A, [M[r0:r1] for M in mats], int(y0), size, diagonal=False, keep_zeros=True)
            d = self.system.diag.reshape(3, self.n)[:, r0:r1].T                  # (rows, 3), just updated
            g.diag.write(pack_nodes(d, size, pad=1.0).tobytes(), viewport=(0, int(y0), W, size[1]), alignment=1)
            if g.first is not None:      # omega D^-1 as a one-slot gather: (values, own column), -1 past n
                fc = np.zeros((1, size[1] * W, 4), dtype=np.float32)
                fc[0, :, 3] = -1.0
                fc[0, : r1 - r0, :3] = lv.omega / d
                fc[0, : r1 - r0, 3] = np.arange(r0, r1)
                g.first.texture.write(fc.tobytes(), viewport=(0, int(y0), 0, W, size[1], 1), alignment=1)

    def residual_gpu(self) -> float:
        """The Jacobi-scaled residual ``max_c ||D^-1 (b - A x)|| / ||D^-1 b||`` of the current
        iterate (the measure of :func:`glsldiff.oracle.solvers.relax`), evaluated on the GPU in
        fp32: a residual pass, the first-sweep scaling ``omega D^-1`` (omega cancels), two
        reductions, 2 texels read back instead of the iterate and a float64 product on the CPU.
        Right after a conjugate-gradient iteration the residual is the one the iteration updated
        (no matrix product), and ``||D^-1 b||`` is kept until the right-hand side, the iterate or
        the matrix is replaced.
        ``nan`` where it cannot (plain V-cycles, a zero right-hand side): check on the CPU then.
        Its fp32 floor is about 1e-6 (the float64 check's too: the iterate is fp32)."""
        g, cg = self._levels[0], self._cg
        if cg is None or g.first is None or g.r is None:
            return math.nan
        gl.make_current(self.ctx)
        with gl.keep_framebuffer(self.ctx):
            if cg.started and cg.pending:     # an iteration just ended: conjugate gradients' own r = b - A x
                r_tex = cg.r.src
            else:
                self._pass.draw(RESIDUAL, g.r_fbo, g.size, g.A, self.state.src, g.size, diag=g.diag, b=g.b)
                r_tex = g.r
            todo = [(r_tex, cg.norms[0])] + ([(g.b, cg.norms[1])] if self._b_norm_stale else [])
            for vec, out in todo:
                self._pass.draw(APPLY, cg.q.fbo, g.size, g.first, vec, g.size)
                cg.dot(cg.q.tex, cg.q.tex, out)
            self._b_norm_stale = False
            r, b = (np.frombuffer(t.tex.read(), dtype=np.float32)[:3].astype(np.float64) for t in cg.norms)
        ok = b > 0                       # channels without a source do not count (as channel_ratio)
        return float(np.sqrt(np.max(r[ok] / b[ok]))) if ok.any() else math.nan

    def smooth(self, sweeps: int) -> None:
        """``sweeps`` damped Jacobi sweeps of the finest level on the iterate (no coarse
        correction, no read-back): the cheap part of a frame while the matrix keeps changing
        (painting); conjugate gradients restart from the result."""
        gl.make_current(self.ctx)
        t0 = time.perf_counter()
        g, st = self._levels[0], self.state
        with gl.keep_framebuffer(self.ctx):
            for _ in range(sweeps):
                self._pass.draw(JACOBI, st.dst, g.size, g.A, st.src, g.size, diag=g.diag, b=g.b,
                                omega=self.levels[0].omega)
                st.swap()
            self.ctx.finish()
        self.cycle_seconds += time.perf_counter() - t0
        self._restart()

    # ---- cycles -----------------------------------------------------------------------------
    def _smooth(self, g: _GpuLevel, b: moderngl.Texture, omega: float, sweeps: int) -> None:
        for _ in range(sweeps):
            self._pass.draw(JACOBI, g.x.dst, g.size, g.A, g.x.src, g.size, diag=g.diag, b=b, omega=omega)
            g.x.swap()

    def _mark(self, level: int, t: float) -> float:
        if not self.profile:
            return t
        self.ctx.finish()
        now = time.perf_counter()
        self.level_seconds[level] += now - t
        return now

    def _vcycle(self, b0: moderngl.Texture, zero: bool) -> None:
        """One V-cycle on the finest level's ``x`` with right-hand side ``b0`` (level 0's ``b``,
        or the conjugate gradients' residual), from ``x = 0`` when ``zero``."""
        draw, levels, L = self._pass.draw, self._levels, len(self._levels)
        t = time.perf_counter()
        for l in range(L - 1):
            g, nxt, lv = levels[l], levels[l + 1], self.levels[l]
            b = b0 if l == 0 else g.b
            sweeps = self.pre
            if l > 0 or zero:      # x_l = 0: the first sweep is x = omega D^-1 b
                if sweeps > 0:
                    draw(APPLY, g.x.dst, g.size, g.first, b, g.size)
                    g.x.swap()
                    sweeps -= 1
                else:
                    g.x.framebuffers[g.x.index].clear(0.0, 0.0, 0.0, 0.0)
            self._smooth(g, b, lv.omega, sweeps)
            draw(RESIDUAL, g.r_fbo, g.size, g.A, g.x.src, g.size, diag=g.diag, b=b)
            draw(APPLY, nxt.b_fbo, nxt.size, g.R, g.r, g.size)
            t = self._mark(l, t)
        c = levels[-1]
        draw(APPLY, c.x.dst, c.size, c.inverse, b0 if L == 1 else c.b, c.size)
        c.x.swap()
        t = self._mark(L - 1, t)
        for l in range(L - 2, -1, -1):
            g, nxt = levels[l], levels[l + 1]
            draw(ADD, g.x.dst, g.size, g.P, nxt.x.src, nxt.size, own=g.x.src)
            g.x.swap()
            self._smooth(g, b0 if l == 0 else g.b, self.levels[l].omega, self.post)
            t = self._mark(l, t)

    def _cg_start(self) -> None:
        """``r = b - A x``, ``z = M r`` (a V-cycle from 0), ``p = z``, ``rho = r.z``."""
        cg, g = self._cg, self._levels[0]
        self._pass.draw(RESIDUAL, cg.r.dst, g.size, g.A, cg.x.src, g.size, diag=g.diag, b=g.b)
        cg.r.swap()
        self._vcycle(cg.r.src, zero=True)
        z = g.x.src
        cg.update(cg.p, z, z, cg.pq, cg.pq, 0.0)           # p = z
        cg.dot(cg.r.src, z, cg.rho[0])
        cg.started, cg.pending = True, False

    def _cg_update(self) -> None:
        """The iterate's half of an iteration: ``q = A p``, ``alpha = rho / p.q``, ``x += alpha
        p``, ``r -= alpha q``; the next direction waits for the next iteration (:meth:`_cg_direction`),
        so an iteration ends at its new iterate (a frame shows ``x_k`` after k V-cycles, not k + 1)."""
        cg, g = self._cg, self._levels[0]
        self._pass.draw(MATVEC, cg.q.fbo, g.size, g.A, cg.p.src, g.size, diag=g.diag)
        cg.dot(cg.p.src, cg.q.tex, cg.pq)
        cg.update(cg.x, cg.x.src, cg.p.src, cg.rho[0], cg.pq, 1.0)
        cg.update(cg.r, cg.r.src, cg.q.tex, cg.rho[0], cg.pq, -1.0)
        cg.pending = True

    def _cg_direction(self) -> None:
        """The direction's half: ``z = M r``, ``rho' = r.z``, ``p = z + (rho' / rho) p``."""
        cg, g = self._cg, self._levels[0]
        self._vcycle(cg.r.src, zero=True)
        z = g.x.src
        cg.dot(cg.r.src, z, cg.rho[1])
        cg.update(cg.p, z, cg.p.src, cg.rho[1], cg.rho[0], 1.0)
        cg.rho.reverse()
        cg.pending = False

    def cycle(self, n: int = 1) -> None:
        """Run ``n`` iterations on the GPU (no read-back): V-cycles, or conjugate-gradient
        iterations (one V-cycle each; the first after :meth:`set_initial`, :meth:`set_b` or a
        solve's start also computes the residual and the first direction)."""
        gl.make_current(self.ctx)
        t0 = time.perf_counter()
        with gl.keep_framebuffer(self.ctx):
            for _ in range(n):
                if self._cg is None:
                    self._vcycle(self._levels[0].b, zero=False)
                else:
                    if not self._cg.started:
                        self._cg_start()
                    elif self._cg.pending:
                        self._cg_direction()
                    self._cg_update()
            self.cycles_run += n
            self.ctx.finish()  # cycles are timed: wait for the GPU
        self.cycle_seconds += time.perf_counter() - t0

    def solve(self, tol: float = RELAX_TOL, maxiter: int = MAXITER, x0: Start = None,
              callback: Callback | None = None, residuals: list[float] | None = None, *,
              check_every: int = 1) -> tuple[NDArray[np.float64], SolveReport]:
        """V-cycles until the Jacobi-scaled residual is <= ``tol`` or ``maxiter`` cycles ran
        (:func:`glsldiff.oracle.solvers.relax`; the arguments as :meth:`GlslSparse.solve`'s,
        counting V-cycles). Returns ``x`` ``(n, 3)`` and the report: ``method``
        ``"glsl-gather-multigrid-fp32(V(2,2),levels=L)"``, ``sweeps`` = cycles, ``levels`` one
        dict per level (``n``/``nodes``, ``slots``, ``omega``, ``sweeps`` run, ...), ``work`` =
        node updates (smoothing sweeps times unknowns summed over levels, plus one per coarsest
        unknown and cycle).

        Raises
        ------
        SolverError
            The iteration diverged (not positive definite, or omega too large).
        """
        t0 = time.perf_counter()
        if not (isinstance(x0, str) and x0 == CURRENT):
            self._restart()       # CURRENT goes on with the conjugate gradients' directions (frame coherence)
        kind = f"V({self.pre},{self.post})" if self._cg is None else f"PCG,V({self.pre},{self.post})"
        seconds0 = self.level_seconds.copy()
        result = self._relax(self.cycle, x0, tol=tol, maxiter=maxiter, check_every=check_every, callback=callback,
                             residuals=residuals, name=f"GLSL gather multigrid {kind}",
                             hint=lambda: ("the V-cycle needs symmetric positive definite matrices and a smoothing "
                                           f"omega below 2 / lambda_max(D^-1 A) (omegas {self.omegas})"))
        cycles = result.iterations
        levels = []
        for l, lv in enumerate(self.levels):
            d = lv.as_dict(l)
            sweeps = cycles * (1 if lv.coarsest else self.pre + self.post)
            d.update(updated=lv.n, sweeps=sweeps, residual=math.nan,
                     seconds=float(self.level_seconds[l] - seconds0[l]) if self.profile else math.nan)
            levels.append(d)
        return self._finish(f"{self.method}-{self.precision}({kind},levels={len(self.levels)})", result, t0,
                            levels=levels, work=int(sum(int(d["sweeps"]) * int(d["n"]) for d in levels)))
