"""One backend per grid family behind the :class:`~glsldiff.render.renderer.Renderer`: the
lattice polygrid (:mod:`.lattice`) and the tetrahedral grids (:mod:`.tetrahedral`, P1 finite
elements on the pillowed polycube or an fTetWild mesh). A backend owns its grid's set-up,
material layout, edits, pass-2 solve and surface values; the renderer orchestrates the passes
and never asks which family it holds.

The interface (:class:`GridBackend`):

* ``setup(scene, mesh)`` builds (or reads from the cache) the grid and returns the mesh the
  scene's surface is (a cut replaces it) and a render mesh with creases, if any;
* ``grid``, ``h`` (node spacing, mm), ``surface_triangles`` (``None`` on the lattice),
  ``interpolation(vertices)`` (boundary nodes -> render-mesh vertices), ``material_shape``,
  ``active`` (the unknowns among the grid's nodes), ``boundary(values)`` (node values at the
  boundary nodes);
* ``set_material()`` (a new material drops the solver), ``edit(...)`` and ``edited(...)``
  (a changed node material: edits, undo, redo);
* ``solve(...)``: one frame's pass 2 as a :class:`Pass2Frame`;
* ``notes(scene)``: the report's grid lines; ``release()``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff.core import cache
from glsldiff.core.errors import InputError, SolverError
from glsldiff.mesh import Mesh
from glsldiff.physics.editing import Edit, EditResult, EditView
from glsldiff.render.scene import Scene
from glsldiff.system.report import SolveReport

__all__ = ["GridBackend", "Pass2Frame", "Pass2Inputs", "PASS2_HINT", "SOLUTION_CACHE_VERSION", "make_backend"]

#: Part of every cached pass-2 solution's key: bump it when the discrete system changes.
SOLUTION_CACHE_VERSION = 2   # 2: the volume source solves with the Fresnel-moment boundary constant
PASS2_HINT = ("the object may be optically too small or thin for its material (size_mm, sigma), or "
              "[options].tol too tight")


@dataclass(frozen=True)
class Pass2Inputs:
    """What one frame's pass 2 solves: the scene (options, eta), the node material ``kappa``
    (mm), ``mu`` (mm^-1), the boundary source ``q`` ``(n_boundary, 3)``, the first-collision
    ``load`` (volume source; ``None`` otherwise), the Robin constant ``C``; ``warm``: start from
    the last frame's fluence; ``painting``: a frame with a new edit (interactive budget)."""

    scene: Scene
    kappa: NDArray[np.float64]
    mu: NDArray[np.float64]
    q: NDArray[np.float64]
    load: NDArray[np.float64] | None
    C: float
    warm: bool
    painting: bool


@dataclass(frozen=True)
class Pass2Frame:
    """One frame's pass 2: the fluence at the boundary nodes ``phi_b`` ``(n_boundary, 3)``, the
    solver's report, whether the frame stopped at its budget before ``tol`` (``partial``) and
    whether the answer came from the disk cache."""

    phi_b: NDArray[np.float64]
    report: SolveReport
    partial: bool
    from_cache: bool


class GridBackend:
    """The common part of the two backends (module docstring). ``ctx`` the GL context,
    ``say`` the renderer's status line, ``frame_sweeps`` the interactive budget (``None``: every
    frame to tol), ``cache_solutions`` whether converged answers go to the disk cache."""

    kind = ""
    surface_triangles: NDArray[np.int64] | None = None
    #: Whether the grid solves the first-collision volume source (``[options].source = "volume"``).
    volume_source = False

    def __init__(self, ctx: moderngl.Context, say: Callable[[str], None], frame_sweeps: int | None,
                 cache_solutions: bool, allow_unconverged: bool) -> None:
        self.ctx, self.say, self.frame_sweeps = ctx, say, frame_sweeps
        self.cache_solutions, self.allow_unconverged = cache_solutions, allow_unconverged
        self.grid: Any = None
        self.h = float("nan")

    # ---- set-up and material ------------------------------------------------------------------
    def setup(self, scene: Scene, mesh: Mesh) -> tuple[Mesh, Mesh | None]:
        raise NotImplementedError

    def interpolation(self, vertices: NDArray[np.float64]) -> Any:
        raise NotImplementedError

    @property
    def material_shape(self) -> tuple[int, ...]:
        raise NotImplementedError

    @property
    def active(self) -> NDArray[np.bool_]:
        """``(N,)`` flat over the grid's nodes: the unknowns."""
        raise NotImplementedError

    def boundary(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """``(n_boundary, 3)``: node values (material-shaped) at the boundary nodes."""
        raise NotImplementedError

    def set_material(self) -> None:
        """A new material: the solver is rebuilt at the next frame."""
        self.release()

    def edit(self, edit: Edit, view: EditView | None, kappa: NDArray, mu: NDArray
             ) -> tuple[NDArray, NDArray, EditResult]:
        raise NotImplementedError

    def edited(self, kappa: NDArray, mu: NDArray) -> None:
        """The node material changed outside :meth:`edit` (undo, redo)."""

    def volume_load(self, kappa: NDArray, mu: NDArray, beams: list) -> NDArray[np.float64]:
        """The first-collision load ``(n, 3)`` of pass 1's ``beams`` (grids with :attr:`volume_source`)."""
        raise InputError("the first-collision source (source = \"volume\") is solved on tetrahedral grids only")

    # ---- pass 2 -------------------------------------------------------------------------------
    @property
    def solver(self) -> Any:
        raise NotImplementedError

    def solve(self, inp: Pass2Inputs) -> Pass2Frame:
        raise NotImplementedError

    def _cache_parts(self) -> tuple[Any, ...]:
        raise NotImplementedError

    def solution_key(self, inp: Pass2Inputs) -> str:
        """The disk cache's key of this frame's converged pass-2 answer."""
        o = inp.scene.options
        return cache.digest(f"pass2 v{SOLUTION_CACHE_VERSION}", inp.scene.polygrid.discretisation,
                            self.grid.positions, *self._cache_parts(), inp.kappa, inp.mu, inp.q, inp.load,
                            inp.scene.material.eta, o.scheme, o.precision, o.tol)

    def check(self, scene: Scene, rep: SolveReport, partial: bool) -> None:
        """:class:`SolverError` for an answer that missed tol (unless allowed, or a partial frame)."""
        if rep.status not in ("converged", "stalled") and not self.allow_unconverged and not partial:
            raise SolverError(f"pass 2 did not converge: residual {rep.residual:.3g} > tol {scene.options.tol:g} "
                              f"after {rep.sweeps} iterations ({rep.status}); {PASS2_HINT}; "
                              "--allow-unconverged writes the unconverged image")

    def notes(self, scene: Scene) -> list[str]:
        """The report's lines on the grid."""
        return []

    def release(self) -> None:
        """Free the solver's GPU objects."""


def make_backend(scene: Scene, ctx: moderngl.Context, say: Callable[[str], None], frame_sweeps: int | None,
                 cache_solutions: bool, allow_unconverged: bool) -> GridBackend:
    """The backend of ``scene``'s ``[polygrid] discretisation``."""
    from glsldiff.render.backends.lattice import LatticeBackend
    from glsldiff.render.backends.tetrahedral import TetBackend
    kind = TetBackend if TetBackend.handles(scene.polygrid.discretisation) else LatticeBackend
    return kind(ctx, say, frame_sweeps, cache_solutions, allow_unconverged)
