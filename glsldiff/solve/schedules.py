"""Schedules of the multiresolution GLSL solve (Wang et al. 2008, section 5.3, figures 8 and 15):
how a solve runs on a :class:`~glsldiff.solve.levels.LevelStack`. Lengths in mm.

:class:`Single`
    Jacobi on the finest level alone, from zero (the reference of figure 15).
:class:`Hierarchical`
    The paper's coarse-to-fine solve: relax the coarsest level, prolong each level's solution
    as the initial guess of the next finer one, and so on down to the finest.
:class:`Adaptive`
    As hierarchical, but at each finer level only the nodes within ``depths[l]`` mm of the
    surface are updated (figure 8); deeper nodes keep the value prolonged from the coarser
    level. Their sweeps draw primitives over the updated nodes only, and their residual is
    that of the system with the deeper nodes pinned. Texture blocks with no node that the level
    uses are dropped from that level's textures (:func:`used_nodes`); the returned fluence at
    the nodes a level does not hold is the coarser levels' value prolonged.
:class:`Multigrid`
    Beyond the paper (which skipped it): V-cycles of the correction scheme on the same
    pyramids, damped-Jacobi smoothing, the residual restricted into the coarser level's T_q and
    the prolonged correction added back.

Every schedule ends in the one solve loop (:meth:`GlslDiffusion.iterate`, i.e.
:func:`glsldiff.oracle.solvers.relax`) on the finest level and returns the fluence and a
:class:`~glsldiff.system.report.SolveReport` whose ``levels`` say, per level that ran: n, nodes
updated per sweep, sweeps, residual and seconds, and whose ``work`` counts node updates
(figure 15's x axis).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import ClassVar, Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.errors import InputError
from glsldiff.grids.graph import BOUNDARY, INACTIVE
from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.oracle.solvers import Callback
from glsldiff.solve.jacobi import Start
from glsldiff.solve.levels import LevelStack
from glsldiff.solve.stencil import PackedGrid
from glsldiff.system.problem import DiffusionProblem, level_problems
from glsldiff.system.report import CURRENT, SolveReport

Masks = list[NDArray[np.bool_] | None]


@dataclass
class Run:
    """The uniform arguments of one solve (:mod:`glsldiff.system.report`)."""

    tol: float
    maxiter: int
    x0: Start
    callback: Callback | None
    residuals: list[float] | None
    check_every: int


@dataclass
class Schedule:
    """Base schedule: the finest level alone, Jacobi from ``x0``.

    ``work`` is the node updates of the running (or last) solve, current whenever a callback
    runs; ``correction`` and ``damping`` say what level stack the schedule needs.
    """

    name: ClassVar[str] = "single"
    correction: ClassVar[bool] = False
    damping: float = 1.0
    work: int = field(default=0, init=False)

    def levels(self, hierarchy: Hierarchy, problem: DiffusionProblem) -> tuple[list[DiffusionProblem], Masks]:
        """The problems (finest first) and update masks of the levels this schedule uses."""
        return [problem], [None]

    def solve(self, stack: LevelStack, run: Run) -> tuple[NDArray, SolveReport]:
        self.work = 0
        return self.finish(stack, run, run.x0, [], time.perf_counter())

    def finish(self, stack: LevelStack, run: Run, x0: Start, rows: list[dict[str, object]],
               t0: float) -> tuple[NDArray, SolveReport]:
        """Jacobi on the finest level from ``x0`` to ``run.tol``, and the report."""
        fine = stack.finest
        fine.start(x0)
        base, first = self.work, fine.sweeps_run

        def counted(x: NDArray) -> None:
            self.work = base + fine.updated_nodes * (fine.sweeps_run - first)
            run.callback(x)  # type: ignore[misc]

        t1 = time.perf_counter()
        phi, rep = fine.iterate(fine.sweep, tol=run.tol, maxiter=run.maxiter, check_every=run.check_every,
                                callback=counted if run.callback is not None else None,
                                residuals=run.residuals, method=f"glsl-{self.name}-{fine.precision}")
        self.work = base + rep.sweeps * fine.updated_nodes
        rows.append(stack.level_row(0, rep.sweeps, rep.residual, time.perf_counter() - t1))
        rep.seconds, rep.levels, rep.work = time.perf_counter() - t0, rows, self.work
        return phi, rep


Single = Schedule


@dataclass
class Hierarchical(Schedule):
    """Coarse-to-fine start (``x0=None``), then Jacobi on the finest level. Solve options:
    ``level_sweeps`` (coarser level ``l`` gets ``level_sweeps[l - 1]`` sweeps) or ``level_tol``
    (each coarser level relaxed to this residual, checked every ``check_every``)."""

    name: ClassVar[str] = "hierarchical"

    def levels(self, hierarchy: Hierarchy, problem: DiffusionProblem) -> tuple[list[DiffusionProblem], Masks]:
        return level_problems(hierarchy, problem), [None] * hierarchy.levels

    def solve(self, stack: LevelStack, run: Run, level_sweeps: Sequence[int] | None = None,
              level_tol: float = 1e-2) -> tuple[NDArray, SolveReport]:
        t0 = time.perf_counter()
        self.work, rows = 0, []
        if run.x0 is not None:
            return self.finish(stack, run, run.x0, rows, t0)
        L = len(stack.levels)
        for lev in range(L - 1, 0, -1):
            lv = stack.levels[lev]
            t1 = time.perf_counter()
            if lev == L - 1:
                lv.set_initial(None)
            if level_sweeps is not None:
                n, res = int(level_sweeps[lev - 1]), float("nan")
                lv.sweep(n)
            else:
                _, rep = lv.solve(tol=level_tol, maxiter=run.maxiter, x0=CURRENT, check_every=run.check_every)
                n, res = rep.sweeps, rep.residual
            self.work += n * lv.updated_nodes
            self.level_done(stack, lev)
            stack.prolong(lev)
            rows.append(stack.level_row(lev, n, res, time.perf_counter() - t1))
        return self.finish(stack, run, CURRENT, rows, t0)

    def level_done(self, stack: LevelStack, lev: int) -> None:
        """Hook: coarser level ``lev`` is solved (before its prolongation)."""


def update_masks(hierarchy: Hierarchy, depths: Sequence[float | None]) -> Masks:
    """Per level (finest first), the nodes the adaptive schedule updates: those within
    ``depths[l]`` mm of the surface, and every boundary node; ``None`` (all) where
    ``depths[l]`` is ``None``. The coarsest level is always solved whole."""
    if len(depths) != hierarchy.levels:
        raise InputError(f"depths has {len(depths)} entries for {hierarchy.levels} levels "
                         "(finest first; None = all nodes)")
    out: Masks = []
    for lev, d in enumerate(depths):
        if d is None or lev == hierarchy.levels - 1:
            out.append(None)
            continue
        if not (np.isfinite(d) and d >= 0):
            raise InputError(f"depths[{lev}]={d!r} mm must be a finite depth >= 0 or None")
        kind = hierarchy.grids[lev].graph.kind
        out.append(((hierarchy.depth(lev) <= d) & (kind != INACTIVE)) | (kind == BOUNDARY))
    return out


def used_nodes(hierarchy: Hierarchy, masks: Sequence[NDArray[np.bool_] | None]) -> list[NDArray[np.bool_]]:
    """Per level (finest first), the nodes an adaptive solve touches: those it updates, the
    nodes their rows read (interior neighbours, boundary partners) and, below the finest, the
    nodes the prolongation to the finer level's used nodes reads."""
    out: list[NDArray[np.bool_]] = []
    for lev, mask in enumerate(masks):
        g = hierarchy.grids[lev].graph
        upd = (g.kind != INACTIVE) if mask is None else np.asarray(mask, dtype=bool)
        used = upd.copy()
        used[g.neighbours[upd[g.interior]].ravel()] = True
        used[g.link[upd[g.boundary]]] = True
        if lev > 0:
            used[hierarchy.transfers[lev - 1].prolong[out[-1]].indices] = True
        out.append(used & (g.kind != INACTIVE))
    return out


def used_blocks(grid: PackedGrid, used: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``(n_blocks,)`` texture blocks (x-y slices) holding a used node."""
    m = grid.mosaic
    return np.asarray(used, dtype=bool).reshape(m.n_blocks, m.bw * m.bh).any(axis=1)


@dataclass
class Adaptive(Hierarchical):
    """Hierarchical with the deep nodes of the finer levels pinned (module docstring).

    ``depths``: per level, finest first, the depth in mm below which nodes keep the coarser
    level's value (``None``: all nodes; the coarsest is always whole); the paper has the user
    give them, :func:`glsldiff.bench.convergence.choose_depths` picks them for a requested
    error. ``drop_blocks``: leave the texture blocks a level does not use out of its textures
    (the paper; default); ``False`` keeps every block (same result, more texture memory)."""

    name: ClassVar[str] = "adaptive"
    depths: Sequence[float | None] = ()
    drop_blocks: bool = True

    def levels(self, hierarchy: Hierarchy, problem: DiffusionProblem) -> tuple[list[DiffusionProblem], Masks]:
        problems, _ = super().levels(hierarchy, problem)
        masks = update_masks(hierarchy, self.depths)
        self.hierarchy = hierarchy
        self.used = used_nodes(hierarchy, masks)
        if self.drop_blocks:
            problems = [replace(p, grid=p.grid.with_blocks(used_blocks(p.grid, u)))
                        for p, u in zip(problems, self.used)]
        return problems, masks

    def solve(self, stack: LevelStack, run: Run, **options: object) -> tuple[NDArray, SolveReport]:
        if run.x0 is not None:
            raise InputError("frame coherence and warm starts (x0) are not available with the adaptive scheme: "
                             "its pinned deep nodes take the coarse-to-fine start's values; use 'hierarchical'")
        self._coarse_phi: dict[int, NDArray[np.float64]] = {}
        phi, rep = super().solve(stack, run, **options)  # type: ignore[arg-type]
        return self._fill_unused(phi), rep

    def level_done(self, stack: LevelStack, lev: int) -> None:
        self._coarse_phi[lev] = stack.levels[lev].fluence()

    def _fill_unused(self, phi: NDArray) -> NDArray[np.float64]:
        """The fluence at the nodes the finest level does not use (dropped or never read),
        prolonged from the coarsest level that holds them."""
        L = len(self.used)
        if L == 1:
            return phi
        filled = self._coarse_phi[L - 1]
        for lev in range(L - 2, -1, -1):
            mine = phi if lev == 0 else self._coarse_phi[lev]
            used = self.used[lev].reshape(mine.shape[:-1])
            filled = np.where(used[..., None], mine, self.hierarchy.prolong_phi(filled, lev + 1))
        return filled


@dataclass
class Multigrid(Schedule):
    """V-cycles of the correction scheme (module docstring). ``damping``: the damped-Jacobi
    smoothing factor; ``coarse_correction``: factor on the coarse-grid correction, in (0, 1].
    The coarse levels are re-discretised, so for smooth errors the coarse operator differs from
    the Galerkin one (R A P); with the polygrid's constant prolongation an undamped correction
    overshoots about 2x, and on the distorted cells of the bunny polygrid more (the V-cycle
    diverges at 1.0; 0.7 converges on the bench models).

    Solve options: ``pre``, ``post`` (smoothing sweeps, default 3 each), ``coarsest`` (sweeps on
    the coarsest level per cycle, default 30) and ``fmg`` (default true: a full-multigrid start,
    the coarse-to-fine nested iteration with one V-cycle per level, instead of zero). The
    callback also sees the start. ``maxiter`` counts V-cycles; the residual is checked after
    each.
    """

    name: ClassVar[str] = "multigrid"
    correction: ClassVar[bool] = True
    damping: float = 0.8
    coarse_correction: float = 0.7

    def __post_init__(self) -> None:
        if not (isinstance(self.coarse_correction, (int, float)) and 0.0 < self.coarse_correction <= 1.0):
            raise InputError(f"coarse_correction={self.coarse_correction!r} must be in (0, 1]")

    def levels(self, hierarchy: Hierarchy, problem: DiffusionProblem) -> tuple[list[DiffusionProblem], Masks]:
        return level_problems(hierarchy, problem), [None] * hierarchy.levels

    def vcycle(self, stack: LevelStack, lev: int = 0, pre: int = 3, post: int = 3, coarsest: int = 30) -> int:
        """One V-cycle from level ``lev`` down; returns the node updates it cost (smoothing
        sweeps plus one per node for each residual, restriction and prolongation pass)."""
        lv = stack.levels[lev]
        t0 = time.perf_counter()
        if lev == len(stack.levels) - 1:
            lv.sweep(coarsest)
            self.level_seconds[lev] += time.perf_counter() - t0
            return coarsest * lv.updated_nodes
        lv.sweep(pre)
        stack.residual(lev)
        stack.restrict(lev)
        stack.clear(lev + 1)
        self.level_seconds[lev] += time.perf_counter() - t0
        work = self.vcycle(stack, lev + 1, pre, post, coarsest)
        t1 = time.perf_counter()
        stack.prolong(lev + 1, self.coarse_correction)
        lv.sweep(post)
        self.level_seconds[lev] += time.perf_counter() - t1
        coarse = stack.levels[lev + 1].problem.grid
        return work + (pre + post) * lv.updated_nodes + 2 * lv.problem.grid.n_active + coarse.n_active

    def _fmg_start(self, stack: LevelStack, pre: int, post: int, coarsest: int) -> int:
        """Full-multigrid start: each coarser level's own (restricted) source, the coarsest
        relaxed, then prolonged and one V-cycle per finer level; returns the work."""
        L = len(stack.levels)
        work = 0
        for lev in range(L - 1, 0, -1):
            stack.levels[lev].reset_rhs()
            stack.clear(lev)
            if lev < L - 1:
                stack.prolong(lev + 1)
            work += self.vcycle(stack, lev, pre, post, coarsest)
        stack.clear(0)
        stack.prolong(1)
        return work + stack.finest.problem.grid.n_active

    def solve(self, stack: LevelStack, run: Run, pre: int = 3, post: int = 3, coarsest: int = 30,
              fmg: bool = True) -> tuple[NDArray, SolveReport]:
        t0 = time.perf_counter()
        fine, L = stack.finest, len(stack.levels)
        self.level_seconds = [0.0] * L
        self.work = 0
        if run.x0 is None and fmg and L > 1:
            self.work = self._fmg_start(stack, pre, post, coarsest)
        else:
            fine.start(run.x0)
        if run.callback is not None:  # the start is an iteration of its own
            run.callback(fine.system.from_volume(fine.unknown()))
        cycles = [0]

        def step(n: int) -> None:
            for _ in range(n):
                self.work += self.vcycle(stack, 0, pre, post, coarsest)
                cycles[0] += 1

        phi, rep = fine.iterate(step, tol=run.tol, maxiter=run.maxiter, check_every=1, callback=run.callback,
                                residuals=run.residuals, name="GLSL multigrid", patience=4,
                                method=f"glsl-multigrid-{fine.precision}", t0=t0)
        sweeps = [cycles[0] * (coarsest if lev == L - 1 else pre + post) for lev in range(L)]
        rep.levels = [stack.level_row(lev, sweeps[lev], rep.residual if lev == 0 else float("nan"),
                                      self.level_seconds[lev]) for lev in range(L)]
        rep.work = self.work
        return phi, rep


SCHEDULES: dict[str, type[Schedule]] = {"single": Single, "hierarchical": Hierarchical, "adaptive": Adaptive,
                                        "multigrid": Multigrid}
SCHEMES = tuple(SCHEDULES)
