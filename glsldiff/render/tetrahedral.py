"""Pass 2 on a tetrahedral grid, frame after frame: the P1 system kept across material edits
(:class:`glsldiff.oracle.fem_update.P1System`: an edit re-sums only the entries around the
edited nodes) and the GPU multigrid-preconditioned CG
(:class:`glsldiff.solve.gather_multigrid.GlslSparseMultigrid`) kept with it (an edit re-packs the
finest level's changed texel rows; the aggregation, coarse operators and smoothing damping stay:
a stale preconditioner, still symmetric positive definite, for a local change).

Frame budget while editing (``frame_budget``): a frame with a new edit runs
:data:`PAINT_SWEEPS` damped Jacobi sweeps of the new finest matrix from the last frame's
fluence and skips the residual check (no CPU residual); each later frame runs
:data:`FRAME_ITERATIONS` preconditioned CG iterations and checks the residual, until ``tol``
(the image converges over frames). Without a budget every frame is solved to ``tol``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff.core.errors import InputError, SolverError
from glsldiff.oracle.assembly import LinearSystem
from glsldiff.oracle.fem import TetGeometry
from glsldiff.oracle.fem_update import P1System
from glsldiff.solve.gather_multigrid import GlslSparseMultigrid
from glsldiff.system.report import CURRENT, SolveReport

__all__ = ["FEM_MAXITER", "FRAME_ITERATIONS", "PAINT_SWEEPS", "REBUILD_SHARE", "TetPass2", "TetFrame"]

#: Pass 2's iteration budget on tetrahedra: multigrid-preconditioned CG takes 10-20 iterations
#: on the scenes measured (bunny, cow, spheres, tile); a system it cannot solve in this many is
#: reported as not converged instead of running the relaxations' 20,000-sweep budget.
FEM_MAXITER = 300
#: Damped Jacobi sweeps of the finest level in a frame with a new edit (painting).
PAINT_SWEEPS = 1
#: Preconditioned CG iterations (one V-cycle each) per frame while the image converges after edits.
FRAME_ITERATIONS = 1
#: An edit changing more than this share of the nodes rebuilds the multigrid (the kept one
#: would precondition a different material).
REBUILD_SHARE = 0.25


@dataclass(frozen=True)
class TetFrame:
    """One frame's pass 2: ``phi`` ``(n_active, 3)``, the report, whether the frame stopped at
    its budget before ``tol`` (``partial``) and whether ``phi`` came from the disk cache."""

    phi: NDArray[np.float64]
    report: SolveReport
    partial: bool
    from_cache: bool


class TetPass2:
    """The P1 system and its GPU solver of one tetrahedral grid, kept across frames.

    ``ctx`` the GL context, ``geo`` the grid's :class:`~glsldiff.oracle.fem.TetGeometry`,
    ``active`` ``(n,)`` bool. GPU objects belong to this object (:meth:`release`)."""

    def __init__(self, ctx: moderngl.Context, geo: TetGeometry, active: NDArray[np.bool_]) -> None:
        self.ctx, self.geo, self.active_mask = ctx, geo, np.asarray(active, dtype=bool)
        self.p1: P1System | None = None
        self.solver: GlslSparseMultigrid | None = None
        self.phi: NDArray[np.float64] | None = None        # the last frame's fluence (n_active, 3)
        self.rebuilds = 0                                  # multigrid builds after the first
        self.stale_rows = 0                                # finest rows updated since the last build

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
            self.p1 = P1System(self.geo, self.active_mask, C, kappa, mu)
        else:
            up = self.p1.set_material(kappa, mu)
            if self.solver is not None and up.rows.size:
                if up.nodes.size > REBUILD_SHARE * len(self.active_mask):
                    self.release()
                else:
                    self.solver.update_fine(self.p1.matrices(), up.rows, diagonal_only=up.diagonal_only)
                    self.stale_rows += int(up.rows.size)
        if not np.array_equal(self.p1.system.b, np.asarray(b, dtype=np.float64).T.reshape(-1)):
            self.p1.set_rhs(b)
            if self.solver is not None:     # a new source restarts CG; the same one lets it go on
                self.solver.set_b(b)
        return self.p1.system

    def cached(self, x: NDArray | None, tol: float) -> TetFrame | None:
        """The frame of a cached answer ``x`` of the current :meth:`system` if its residual
        (checked on the CPU) meets ``tol``; else None."""
        if x is None or self.p1 is None:
            return None
        t0 = time.perf_counter()
        s = self.p1.system
        if x.shape != (s.n, 3):
            return None
        res = s.residual(x.T.reshape(-1))
        if not res <= tol:
            return None
        self.phi = np.asarray(x, dtype=np.float64)
        rep = SolveReport("cached (residual checked on the CPU)", nodes=s.n, sweeps=0, residual=res,
                          seconds=time.perf_counter() - t0, converged=True, history=[(0, res)])
        return TetFrame(self.phi, rep, False, True)

    def _build(self, x0: NDArray | None) -> None:
        assert self.p1 is not None
        s = self.p1.system
        if self.solver is None:
            self.rebuilds += self.phi is not None
            self.solver = GlslSparseMultigrid(self.p1.matrices(), s.b.reshape(3, -1).T, ctx=self.ctx)
            self.stale_rows = 0
            if x0 is not None:
                self.solver.set_initial(x0)

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
        budget = FRAME_ITERATIONS if frame_budget and warm else FEM_MAXITER
        try:
            phi, rep = solver.solve(tol=tol, maxiter=budget, x0=CURRENT if (warm or start is not None) else None)
        except SolverError:
            raise
        self.phi = phi
        partial = frame_budget and warm and rep.status not in ("converged", "stalled")
        return TetFrame(phi, rep, partial, False)

    def release(self) -> None:
        if self.solver is not None:
            self.solver.release()
            self.solver = None

    def describe(self) -> dict[str, Any]:
        """The solver's state for reports: rebuilds and finest rows updated since the last build."""
        return {"rebuilds": self.rebuilds, "stale_rows": self.stale_rows}


def check_precision(precision: str, source: str) -> None:
    """The tetrahedral solve runs in fp32 only."""
    if precision != "fp32":
        raise InputError(f"{source}: [options].precision = {precision!r}: the fem discretisation solves in fp32 "
                         "only; use precision = \"fp32\"")
