"""How far a tetrahedral frame's pass-2 answer is from the converged one (``glsldiff render
--check-grid``): the same problem solved on the grid's 1:8 refinement
(:class:`glsldiff.oracle.refined.RefinedComparison`, exact CPU solves).
"""
from __future__ import annotations

import time
from typing import TYPE_CHECKING

from glsldiff.core.errors import InputError
from glsldiff.oracle.refined import RefinedComparison, RefinedError
from glsldiff.render.scene import TETRAHEDRAL, Scene

if TYPE_CHECKING:
    from glsldiff.render.renderer import Renderer

__all__ = ["check_scene", "discretisation_error"]


def check_scene(scene: Scene) -> None:
    """Refuse (:class:`InputError`, one line) a scene :func:`discretisation_error` cannot check,
    before any work: a lattice grid, or the first-collision volume source."""
    if scene.polygrid.discretisation not in TETRAHEDRAL:
        raise InputError(f"the discretisation check needs a tetrahedral grid; this scene's is "
                         f"{scene.polygrid.discretisation!r} (set [polygrid] discretisation = \"fem\")")
    if scene.options.source == "volume":
        raise InputError("the discretisation check does not carry the first-collision load yet (the split takes "
                         "it where the grid resolves the mean free path); render with [options] source = "
                         "\"surface\" to check the grid")


def discretisation_error(r: "Renderer", scene: Scene, channel: int = 1) -> tuple[RefinedError, int, float]:
    """How far ``r``'s last frame of ``scene`` is from the converged answer: the comparison with
    the 1:8 refinement (one colour ``channel``), the refined grid's node count and the seconds it
    all took. Tetrahedral grids with the surface source only (``source = "auto"``: as the last
    frame resolved it)."""
    scene = r.effective(scene)
    check_scene(scene)
    t0 = time.perf_counter()
    rc = RefinedComparison(r.fem_problem(scene), channel)
    err = rc.compare()[0]
    return err, rc.nodes[1], time.perf_counter() - t0
