"""The diffusion's load (pass 1 and the incidence stage, before pass 2) and the options it follows.

* :func:`effective_scene`: the scene's ``"auto"`` options made concrete for the grid and the
  node material (the source: the split takes the first-collision volume source where the grid
  resolves the transport mean free path, :data:`GATHER_MAX_H_SIGMA`; single scattering);
* :func:`light_load` (pass 1): the transmitted irradiance ``E_t`` at the boundary nodes
  (:func:`glsldiff.render.pass1.incident_light`: shadow maps, environment light with per-node
  visibility; on tetrahedral grids every other light averaged over the surface nodes' cells)
  and, by :func:`marshak_source`, the Marshak boundary source ``q`` (``[options].exitant``'s
  convention), refused where no light reaches the object or where it overflows pass 2's float32
  textures (:data:`Q_MAX`). With ``[options].source = "volume"`` the light enters as the
  first-collision load of :mod:`glsldiff.render.collision` instead (``q = 0``);
* :func:`split_incidence`: the surface source following the half-space's transport per
  incidence (``[options].incidence`` ``"local"`` or ``"transport"``,
  :mod:`glsldiff.physics.exitance`): the load (each beam's share ``H(t) / <H>`` under
  ``"transport"``) and what the exitant bracket's local term needs (:class:`Incidence`, used by
  :meth:`glsldiff.render.terms.SurfaceTerms.bracket_q`);
* :func:`boundary_C`: the Robin constant the load and the bracket take.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any, Sequence

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff.core.errors import InputError
from glsldiff.mesh.inside import contains
from glsldiff.physics.exitance import deep_irradiance, halfspace_bracket, source_from_irradiance
from glsldiff.physics.optics import boundary_constant, moment_boundary_constant
from glsldiff.render.backends import GridBackend
from glsldiff.render.pass1 import incident_light
from glsldiff.render.scene import Scene

__all__ = ["GATHER_MAX_H_SIGMA", "Q_MAX", "Incidence", "LightLoad", "boundary_C", "effective_scene", "h_sigma_t",
           "light_load", "marshak_source", "split_incidence", "splits_incidence"]

Array = NDArray[np.float64]

#: Largest boundary source pass 2 accepts: its float32 textures overflow near 3.4e38, and the
#: sweeps multiply sources by stencil weights (mm^-2) before they are divided back.
Q_MAX = 1e30
#: The split takes the first-collision source and gathers the collided fluence where the grid
#: resolves the transport mean free path: node spacing times sigma_t' at most this (a 1-D P1
#: solve of the half-space gathers 0.98 of the converged value at 0.5, 0.93 at 1, 0.85 at 2;
#: in 3-D, blended with the deep field, validate's cases between 0.6 and 1 score as well as or
#: better than with the surface source: slab-spot 0.041 vs 0.214, bunny-veins 0.097 vs 0.131,
#: sphere albedo 0.3 (1.08) 0.031 either way, the 60 mm slab 0.039 vs 0.038).
GATHER_MAX_H_SIGMA = 1.0


def h_sigma_t(h: float, kappa: Array) -> float:
    """Node spacing ``h`` (mm) times the largest sigma_t' = 1 / (3 kappa) (mm^-1) of the node
    material: below :data:`GATHER_MAX_H_SIGMA` the grid resolves the transport mean free path."""
    return h * float(np.max(1.0 / (3.0 * kappa)))


def effective_scene(scene: Scene, volume_source: bool, h_sigma: float, interactive: bool) -> tuple[Scene, str]:
    """``scene`` with its options made concrete for a grid (``volume_source``: it solves the
    first-collision load; ``h_sigma``: :func:`h_sigma_t` of its node material), and the
    report's note why the model differs from the scene's ("" when it does not). The source
    (``"auto"``: the split takes the volume source where the tetrahedral grid resolves the
    transport mean free path, ``h sigma_t' <= GATHER_MAX_H_SIGMA`` at every node and channel,
    else the Marshak surface source; diffusion: surface) and single scattering (``"auto"``: the
    split marches it in 3-D, but takes the half-space's closed form in ``interactive`` frames
    (the viewer); diffusion: off). A split with ``eta < 1`` (no half-space tables) renders
    with the diffusion model."""
    o, note = scene.options, ""
    if o.split and scene.material.eta < 1.0:
        note = f"model: eta = {scene.material.eta:g} < 1 has no half-space tables; rendered with model = \"diffusion\""
        o = replace(o, model="diffusion", source="surface" if o.source == "auto" else o.source)
    if o.source == "auto":
        resolved = volume_source and h_sigma <= GATHER_MAX_H_SIGMA
        o = replace(o, source="volume" if o.split and resolved else "surface")
    if o.single_scattering == "auto":
        o = replace(o, single_scattering=o.split and not interactive)
    return replace(scene, options=o), note


def boundary_C(scene: Scene) -> float:
    """The Robin constant: the exact Fresnel-moment one with the first-collision source
    (:func:`glsldiff.physics.optics.moment_boundary_constant`), the classic ``(1 + F_dr) /
    (1 - F_dr)`` with the Marshak surface source (the calibration of its ``p1`` exitance)."""
    eta = scene.material.eta
    return moment_boundary_constant(eta) if scene.options.source == "volume" else float(boundary_constant(eta))


def marshak_source(scene: Scene, E_t: Array, mesh: Any) -> Array:
    """``(n_boundary, 3)`` the Marshak source of the transmitted irradiance ``E_t`` (W mm^-2 at
    the boundary nodes); :class:`InputError` where it overflows :data:`Q_MAX` or is 0 at every
    node (naming the lights placed inside ``mesh``)."""
    q = source_from_irradiance(E_t, scene.material.eta, scene.options.exitant)
    if not np.all(np.isfinite(q)) or q.max() > Q_MAX:
        raise InputError(f"{scene.source}: [[lights]]: the transmitted irradiance reaches "
                         f"{np.nanmax(E_t):.3g}, beyond what the solver's float32 textures hold "
                         f"(source <= {Q_MAX:.0e}); scale the lights' irradiance or intensity down (the "
                         "image is linear in it)")
    if not q.any():
        placed = [(k, light.position) for k, light in enumerate(scene.lights) if hasattr(light, "position")]
        inside = [(k, p) for (k, p), i in zip(placed, contains(mesh, [p for _, p in placed]) if placed else [])
                  if i]
        where = "".join(f"; light {k + 1} at ({', '.join(f'{c:g}' for c in p)}) mm is inside the object: "
                        "move its position outside the mesh" for k, p in inside)
        hint = "; check the lights' directions, positions, cones and intensities"
        raise InputError(f"{scene.source}: [[lights]]: no light reaches the object (the source is 0 at "
                         f"every boundary node){where or hint}")
    return q


@dataclass(frozen=True)
class LightLoad:
    """Pass 1's result: the transmitted irradiance ``E_t`` ``(n_boundary, 3)``, the Marshak
    source ``q`` (0 with the volume source), the beams (``E`` ``(n_boundary, 3)``, refracted
    cosine ``(n_boundary,)``; empty unless the volume source, the split or the incidence split
    takes them), the first-collision load ``(n, 3)`` of the volume source (else None) and the
    report's line per light."""

    E_t: Array
    q: Array
    beams: list[tuple[Array, Array]]
    load: Array | None
    info: list[dict[str, Any]]


def light_load(scene: Scene, mesh: Any, backend: GridBackend, kappa: Array, mu: Array,
               ctx: moderngl.Context, depth: Any = None) -> LightLoad:
    """Pass 1 of ``scene`` on ``backend``'s grid: the light reaching the boundary nodes through
    ``mesh`` and the load it makes (the node material ``kappa``, ``mu``, material-shaped, for the
    first-collision load); ``depth``: the renderer's map-keeping ``DepthRenderer`` of ``mesh``."""
    pg = backend.grid
    volume = scene.options.source == "volume"
    beams: list | None = [] if volume or scene.options.split or splits_incidence(scene) else None
    E_t, info = incident_light(mesh, pg.boundary_positions, pg.normals, scene.lights, scene.material.eta, ctx=ctx,
                               beams=beams, triangles=backend.surface_triangles, depth=depth)
    E_t = np.asarray(E_t, dtype=np.float64)
    q = marshak_source(scene, E_t, mesh)
    load = None
    if volume:   # the light enters as the first-collision source; no diffuse light crosses the boundary
        t0 = time.perf_counter()
        load = backend.volume_load(kappa, mu, beams or [])
        info.append({"light": "first-collision source", "beams": len(beams or ()),
                     "nodes": int(load.any(axis=1).sum()), "seconds": time.perf_counter() - t0})
    return LightLoad(E_t, np.zeros_like(q) if volume else q, beams or [], load, info)


def splits_incidence(scene: Scene) -> bool:
    """Whether the surface source follows the half-space's transport per incidence
    (:mod:`glsldiff.physics.exitance`, ``[options].incidence`` "local" or "transport")."""
    o = scene.options
    return not o.split and o.incidence != "marshak" and o.source == "surface" and o.exitant != "paper"


@dataclass(frozen=True)
class Incidence:
    """The incidence stage's result: the diffusion's load ``q`` ``(n_boundary, 3)``, the report's
    line, and (``"local"``, ``"transport"``) what the bracket's local term needs: the
    half-space's bracket ``beta``, the boundary material ``kappa`` (mm), ``mu`` (mm^-1) and
    whether the load is the deep share of each beam."""

    q: Array
    note: str
    beta: Array | None = None
    kappa: Array | None = None
    mu: Array | None = None
    deep: bool = False


def split_incidence(scene: Scene, backend: GridBackend, kappa: Array, mu: Array, E_t: Array, q_marshak: Array,
                    beams: Sequence[tuple[Array, Array]]) -> Incidence:
    """The diffusion's load from pass 1's ``beams`` (``E`` ``(n_boundary, 3)``, refracted cosine
    ``(n_boundary,)``) and the node material ``kappa``, ``mu`` (material-shaped): each beam's
    share ``H(t) / <H>`` under ``incidence = "transport"``, pass 1's Marshak source ``q_marshak``
    otherwise."""
    o = scene.options
    if not splits_incidence(scene):
        return Incidence(q_marshak, "- (model split: exact local transport per beam)" if o.split else
                         "marshak (the paper's convention)" if o.exitant == "paper" and o.source == "surface"
                         else "marshak" if o.source == "surface" else "- (volume source)")
    kappa_b, mu_b = backend.boundary(kappa), backend.boundary(mu)
    eta = scene.material.eta
    deep = o.incidence == "transport"
    E = deep_irradiance(beams, kappa_b, mu_b) if deep else E_t
    lit = E_t.sum(axis=1) > 0
    share = E.sum(axis=1)[lit] / E_t.sum(axis=1)[lit] if lit.any() else np.ones(1)
    note = (f"transport (the load's share of each beam H(t) / <H>: {share.min():.2f}-{share.max():.2f}; the "
            "bracket's local term follows the view)" if deep else
            "local (the Marshak load; the bracket's local term follows the half-space's transport per incidence "
            "and view)")
    return Incidence(source_from_irradiance(E, eta, o.exitant), note,
                     halfspace_bracket(kappa_b, mu_b, eta, o.exitant, boundary_C(scene)), kappa_b, mu_b, deep)
