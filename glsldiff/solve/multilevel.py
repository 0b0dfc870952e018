"""Multiresolution GLSL diffusion (Wang et al. 2008, section 5.3): a
:class:`~glsldiff.solve.levels.LevelStack` on a :class:`~glsldiff.grids.hierarchy.Hierarchy`
(regular grid or polygrid) run by one of the schedules of :mod:`glsldiff.solve.schedules`
(``"single"``, ``"hierarchical"``, ``"adaptive"``, ``"multigrid"``), behind the uniform solver
interface of :mod:`glsldiff.system.report`.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import moderngl
from numpy.typing import ArrayLike, NDArray

from glsldiff import gl
from glsldiff.core.errors import InputError
from glsldiff.grids.hierarchy import Hierarchy
from glsldiff.oracle.solvers import Callback
from glsldiff.solve.jacobi import GlslDiffusion, Start
from glsldiff.solve.levels import LevelStack
from glsldiff.solve.schedules import SCHEDULES, SCHEMES, Adaptive, Multigrid, Run, Schedule
from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.report import MAXITER, RELAX_TOL, SolveReport


def make_schedule(scheme: str, depths: Sequence[float | None] | None = None, damping: float = 0.8,
                  coarse_correction: float = 0.7, drop_blocks: bool = True) -> Schedule:
    """The schedule named ``scheme`` (one of :data:`SCHEMES`) with its options: ``depths`` and
    ``drop_blocks`` (``"adaptive"``, :class:`~glsldiff.solve.schedules.Adaptive`), ``damping``
    and ``coarse_correction`` (``"multigrid"``, :class:`~glsldiff.solve.schedules.Multigrid`)."""
    if scheme not in SCHEDULES:
        raise InputError(f"scheme={scheme!r}; choose one of {SCHEMES}")
    if (depths is not None) != (scheme == "adaptive"):
        raise InputError("depths are given with scheme='adaptive' and only then")
    if scheme == "adaptive":
        return Adaptive(depths=depths, drop_blocks=drop_blocks)  # type: ignore[arg-type]
    if scheme == "multigrid":
        return Multigrid(damping=damping, coarse_correction=coarse_correction)
    return SCHEDULES[scheme]()


class MultilevelDiffusion:
    """A multiresolution GLSL solver of ``problem`` (on ``hierarchy.grids[0]``).

    Parameters
    ----------
    hierarchy
        The levels (:class:`glsldiff.grids.hierarchy.Hierarchy`, of a regular grid or a polygrid).
    problem
        The finest-level problem; coarser levels get the restricted material and source.
    scheme
        One of :data:`SCHEMES`; ``depths``, ``damping``, ``coarse_correction`` and
        ``drop_blocks`` are its options (:func:`make_schedule`).
    precision
        ``"fp32"``, ``"fp16"`` (radiance buffers) or ``"paper"`` (fp16 buffers, 8-bit
        kappa/mu), see :class:`~glsldiff.solve.jacobi.GlslDiffusion`.
    """

    def __init__(self, hierarchy: Hierarchy, problem: DiffusionProblem, scheme: str = "hierarchical",
                 ctx: moderngl.Context | None = None, precision: str = "fp32",
                 depths: Sequence[float | None] | None = None, damping: float = 0.8,
                 coarse_correction: float = 0.7, drop_blocks: bool = True) -> None:
        self.schedule = make_schedule(scheme, depths, damping, coarse_correction, drop_blocks)
        self.hierarchy, self.scheme = hierarchy, scheme
        if problem.grid is not hierarchy.grids[0]:
            raise InputError("the problem is not on this hierarchy's finest grid")
        problems, masks = self.schedule.levels(hierarchy, problem)
        self.stack = LevelStack(hierarchy, problems, ctx if ctx is not None else gl.get_context(), precision,
                                masks=masks, correction=self.schedule.correction, damping=self.schedule.damping)

    @property
    def levels(self) -> list[GlslDiffusion]:
        return self.stack.levels

    @property
    def finest(self) -> GlslDiffusion:
        return self.stack.finest

    @property
    def problem(self) -> DiffusionProblem:
        return self.stack.problem

    @property
    def compute_seconds(self) -> float:
        """GPU time so far in sweeps and transfer passes (read-backs and CPU checks excluded)."""
        return self.stack.compute_seconds

    @property
    def work(self) -> int:
        """Node updates of the running (or last) solve, current whenever its callback runs."""
        return self.schedule.work

    def set_q(self, q: ArrayLike) -> None:
        """New boundary source on every level (e.g. a moved light), material kept."""
        self.stack.set_q(q)

    def set_material(self, kappa: ArrayLike, mu: ArrayLike, finest_uploaded: bool = False) -> None:
        """New kappa (mm) and mu (mm^-1) on the finest level and, restricted as at set-up, on
        the coarser ones. ``finest_uploaded``: the finest level's textures already hold them
        (a GPU edit, :mod:`glsldiff.render.editing`)."""
        problems, _ = self.schedule.levels(self.hierarchy, replace(self.problem, kappa=kappa, mu=mu))
        for lev, p in zip(self.levels, problems):
            lev.set_material(p.kappa, p.mu, upload=not (finest_uploaded and lev is self.finest))

    def texture_rows(self) -> list[dict[str, object]]:
        """Per level: texture blocks held / in the grid and texels per texture."""
        return self.stack.texture_rows()

    def solve(self, tol: float = RELAX_TOL, maxiter: int = MAXITER, x0: Start = None,
              callback: Callback | None = None, residuals: list[float] | None = None, *,
              check_every: int = 25, **options: object) -> tuple[NDArray, SolveReport]:
        """Solve to a Jacobi-scaled residual ``tol`` on the finest level (adaptive: of its
        pinned system).

        Parameters
        ----------
        tol, maxiter, x0, callback, residuals
            The uniform solver arguments (:mod:`glsldiff.system.report`). ``maxiter`` counts
            finest-level sweeps (V-cycles for multigrid; it also bounds each coarser level's
            relaxation). ``x0=None`` is the schedule's cold start (zero, coarse-to-fine, or the
            full-multigrid start); a fluence array or :data:`~glsldiff.system.report.CURRENT`
            (frame coherence: the previous frame's solution still in the buffers) starts the
            finest level there instead (not with ``"adaptive"``, whose pinned deep nodes
            need the coarse-to-fine start). ``callback(x)`` runs at each finest-level check;
            :attr:`work` then holds the node updates so far.
        check_every
            Sweeps between residual checks (not multigrid: every cycle is checked).
        options
            The schedule's own (:mod:`glsldiff.solve.schedules`): ``level_sweeps``,
            ``level_tol`` (hierarchical, adaptive); ``pre``, ``post``, ``coarsest``, ``fmg``
            (multigrid).
        """
        run = Run(tol, maxiter, x0, callback, residuals, check_every)
        return self.schedule.solve(self.stack, run, **options)  # type: ignore[arg-type]

    def release(self) -> None:
        self.stack.release()

    def __enter__(self) -> "MultilevelDiffusion":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


__all__ = ["MultilevelDiffusion", "SCHEMES", "make_schedule"]
