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

from dataclasses import dataclass, replace
from typing import Any, Callable

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff.core import cache
from glsldiff.core.errors import InputError, SolverError
from glsldiff.mesh import Mesh
from glsldiff.physics.editing import Edit, EditResult, EditView
from glsldiff.grids.polycube import PolycubeNotFound
from glsldiff.render.scene import PolygridSpec, Scene, default_cubes
from glsldiff.system.report import SolveReport

__all__ = ["FALLBACK_POLYGRID", "GridBackend", "Pass2Frame", "Pass2Inputs", "PASS2_HINT", "SOLUTION_CACHE_VERSION",
           "as_built", "make_backend", "set_up_backend"]

#: Part of every cached pass-2 solution's key: bump it when the discrete system changes.
SOLUTION_CACHE_VERSION = 4   # 2: the volume source solves with the Fresnel-moment boundary constant;
#                                   3: the tetrahedra's surface mass is lumped at crease nodes;
#                                   4: and at flat tetrahedra's surface nodes
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


#: The grid of a scene whose mesh has no tetrahedral polygrid (no set of cubes with its topology:
#: spikes, thin sheets): the lattice polygrid's defaults (n = 8, 253 cubes, 3 levels), whose larger
#: cubes step over the parts that break the finer search.
FALLBACK_POLYGRID = PolygridSpec(8, default_cubes("conservative", 8), 3, "conservative", adapt=False)


def as_built(scene: Scene, polygrid: PolygridSpec | None) -> Scene:
    """``scene`` on the grid the renderer built instead of its own (``polygrid``; None: its
    own): the lattice takes the boundary flux (it has no surface triangles to smooth on)."""
    if polygrid is None or scene.polygrid == polygrid:
        return scene
    return replace(scene, polygrid=polygrid, options=replace(scene.options, flux="boundary"))


def set_up_backend(scene: Scene, mesh: Mesh, ctx: moderngl.Context, say: Callable[[str], None],
                   frame_sweeps: int | None, cache_solutions: bool, allow_unconverged: bool
                   ) -> tuple[GridBackend, Mesh, Mesh | None, PolygridSpec | None, str]:
    """The backend of ``scene`` (:func:`make_backend`) set up on ``mesh``: ``(backend, mesh, render
    mesh with creases or None, the polygrid built instead of the scene's or None, why in one
    line)``. A default (``fem``) grid whose mesh has no polycube of its topology falls back to
    :data:`FALLBACK_POLYGRID`, said with the reason and the way back."""
    def make(s: Scene) -> GridBackend:
        return make_backend(s, ctx, say, frame_sweeps, cache_solutions, allow_unconverged)
    backend = make(scene)
    try:
        return (backend, *backend.setup(scene, mesh), None, "")
    except PolycubeNotFound as exc:
        backend.release()
        if scene.polygrid.discretisation != "fem":
            raise
        why = exc.failures[-1] if exc.failures else str(exc)
        fallback = as_built(scene, FALLBACK_POLYGRID)
        note = (f"no tetrahedral polygrid of {scene.mesh.source} with {scene.polygrid.cubes} cubes ({why}): rendered "
                f"on the lattice polygrid instead (n = {FALLBACK_POLYGRID.n}, {FALLBACK_POLYGRID.cubes} cubes); for "
                "the tetrahedral grid give [polygrid] cubes more, or repair the mesh's spikes and thin sheets")
        say("setup: " + note)
        backend = make(fallback)
        try:
            return (backend, *backend.setup(fallback, mesh), FALLBACK_POLYGRID, note)
        except InputError as exc2:
            backend.release()
            other = exc2.failures[-1] if isinstance(exc2, PolycubeNotFound) and exc2.failures else str(exc2)
            raise InputError(f"no polygrid of {scene.mesh.source}: the tetrahedral grid found no set of cubes with "
                             f"its topology ({why}) and the lattice fallback failed too ({other}); parts of the "
                             "mesh come closer than a cube (a bridge of cubes adds a handle) or are thinner than "
                             "one: try [polygrid] cubes = "
                             f"{2 * scene.polygrid.cubes}, or repair the mesh there") from exc2
