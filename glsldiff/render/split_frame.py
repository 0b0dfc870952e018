"""Pass 3 of the transport split (``[options].model = "split"``, :mod:`glsldiff.physics.split`):
the subsurface radiance per render-mesh vertex towards the eye.

Inputs per boundary node (pass 1 and 2): the beams (transmitted irradiance, refracted cosine),
the material, the fluence; for the gather far field (first-collision source) the collided
fluence at every node. Per vertex (the boundary values interpolated by the renderer's
surface-interpolation matrix):

* ``M``: the exact multiple scattering of the local half-space (adding-doubling tables);
* single scattering: the half-space's closed form, or the 3-D march along the refracted view
  ray (:func:`glsldiff.render.single.scattering_frame`), which with the gather model also
  gathers the collided fluence (:class:`glsldiff.render.fluence.FluenceLattice`);
* the diffusion model's ``X`` and ``X_loc`` and its far-field factor, combined with ``M`` by
  :func:`glsldiff.physics.split.combine`.

The result, without unscattered light, goes to the shader as a view-dependent term (the
tables hold the exit Fresnel factor).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff.physics.adding_doubling import halfspace_tables
from glsldiff.physics.optics import fresnel_transmittance, refracted_cosine
from glsldiff.physics.exitance import halfspace_bracket
from glsldiff.physics.split import (ExternalBeam, collided_halfspace, combine, diffusion_weight, external_beams,
                                    gather_share, gathered_halfspace, local_multiple, local_single, marshak_halfspace)
from glsldiff.render.fluence import FluenceLattice
from glsldiff.render.single import scattering_frame

__all__ = ["SplitInputs", "SplitResult", "SplitStatic", "VertexTerms", "split_again", "split_radiance", "split_repaint",
           "vertex_terms", "FAR_MODELS"]

Array = NDArray[np.float64]
#: The split's far-field models: the gathered collided fluence (first-collision source) or the
#: Marshak fluence's outgoing flux.
FAR_MODELS = ("gather", "surface")


@dataclass
class SplitInputs:
    """What the split needs of a frame. Per boundary node ``(S, ...)``: ``beams`` (transmitted
    irradiance ``(S, 3)``, refracted cosine ``(S,)``), ``kappa`` (mm) and ``mu`` (mm^-1)
    ``(S, 3)``, ``phi`` the fluence ``(S, 3)``, ``q`` the Marshak source ``(S, 3)`` (surface
    far field). ``interp`` ``(V, S)`` maps them to the render vertices."""

    far: str
    march: bool
    eta: float
    C: float
    interp: Any
    vertices: Array
    normals: Array
    beams: Sequence[tuple[Array, Array]]
    kappa: Array
    mu: Array
    phi: Array
    q: Array | None = None
    source_distance_mfp: Array | None = None   # gather: each node's distance to lit surface, mean free paths (S, 3)
    fluence: FluenceLattice | None = None     # gather: the collided fluence at any point
    mesh: Any = None                           # the march: the mesh its rays and depth maps use
    lights: Sequence[Any] = ()
    medium: Any = None
    march_beams: Any = None                    # the march: the lights' beams (single.light_beams; kept across frames)
    at_vertices: "VertexTerms | None" = None   # vertex_terms(this), kept while the material and the lights stay


@dataclass(frozen=True)
class VertexTerms:
    """The view-independent inputs of :func:`split_radiance` at the render vertices: ``kappa``
    (mm), ``mu`` (mm^-1) and albedo ``(V, 3)``, the beams (transmitted irradiance ``(V, 3)``,
    refracted cosine ``(V,)``) and their external form (:func:`~glsldiff.physics.split.external_beams`).
    A camera move keeps them (:func:`vertex_terms`)."""

    kappa: Array
    mu: Array
    albedo: Array
    beams: list[tuple[Array, Array]]
    external: list[ExternalBeam]


def vertex_terms(inp: SplitInputs) -> VertexTerms:
    """``inp``'s boundary material and beams at the render vertices (:class:`VertexTerms`)."""
    kv, mv = np.asarray(inp.interp @ inp.kappa), np.asarray(inp.interp @ inp.mu)
    beams_t = _at_vertices(inp.interp, inp.beams)
    return VertexTerms(kv, mv, _albedo(kv * mv), beams_t, external_beams(beams_t, float(inp.eta)))


@dataclass(frozen=True)
class SplitStatic:
    """The per-vertex terms of the surface far field that do not depend on the fluence: the
    local multiple scattering ``M``, ``single``, the half-space's ``X_loc``, the far field's
    ``c_far``, the diffusion weight ``w`` (each ``(V, 3)``), which vertices face the eye and the
    report line. They stay while the material, the lights and the camera do (the frames that
    converge after an edit change only the fluence)."""

    M: Array
    single: Array
    X_loc: Array
    c_far: Array
    w: Array
    facing: NDArray[np.bool_]
    info: str
    # the closed form's per-vertex inputs (no march), for :func:`split_repaint`: kappa mu at the
    # vertices, albedo, view cosine, external beams, F_t E per vertex, single before the facing mask
    km: Array | None = None
    nu_o: Array | None = None
    ext: Sequence[ExternalBeam] = ()
    B_unit: Array | None = None
    single_raw: Array | None = None


@dataclass
class SplitResult:
    """``radiance`` ``(V, 3)`` and its parts (single, multiple), seconds and a report line;
    ``static``: the fluence-independent terms of a surface far field (``None`` for the gather)."""

    radiance: Array
    single: Array
    multiple: Array
    seconds: float
    info: str = ""
    parts: dict[str, float] = field(default_factory=dict)
    static: SplitStatic | None = None
    clamped: tuple[int, float, int] = (0, 0.0, 0)   # negative fluence at the vertices: fluence_clamped


def _at_vertices(interp: Any, beams: Sequence[tuple[Array, Array]]) -> list[tuple[Array, Array]]:
    """Beams at the vertices: irradiance interpolated, refracted cosine irradiance-weighted."""
    out = []
    for E, t in beams:
        Ev = np.asarray(interp @ E)
        w = np.asarray(interp @ E.sum(axis=1))
        tw = np.asarray(interp @ (E.sum(axis=1) * t))
        out.append((Ev, np.where(w > 0, tw / np.maximum(w, 1e-300), 0.0)))
    return out


def fluence_clamped(interp: Any, phi: Array, facing: NDArray[np.bool_]) -> tuple[int, float, int]:
    """The vertices facing the eye whose interpolated fluence ``interp @ phi`` is negative (the
    split clamps it to 0; a P1 undershoot, e.g. at a crease): how many, how deep (over the
    largest value) and how many below -1 % of the largest (``RenderReport.clamped_*``)."""
    raw = np.asarray(interp @ phi)[facing]
    if raw.size == 0:
        return 0, 0.0, 0
    top = max(float(raw.max()), 1e-300)
    return (int(np.any(raw < 0.0, axis=1).sum()), float(max(-raw.min(), 0.0) / top),
            int(np.any(raw < -0.01 * top, axis=1).sum()))


def split_again(static: SplitStatic, interp: Any, phi: Array) -> SplitResult:
    """:func:`split_radiance` of a frame whose fluence ``phi`` ``(S, 3)`` alone changed since the
    result that kept ``static`` (surface far field): only the fluence's terms are recomputed."""
    t0 = time.perf_counter()
    X = np.asarray(interp @ np.maximum(phi, 0.0))
    multiple = combine(static.M, X, static.X_loc, static.c_far, static.w) * static.facing[:, None]
    return SplitResult(static.single + multiple, static.single, multiple, time.perf_counter() - t0, static.info,
                       static=static, clamped=fluence_clamped(interp, phi, static.facing))


def split_repaint(previous: SplitStatic, inp: SplitInputs) -> SplitResult | None:
    """:func:`split_radiance` of a frame whose material changed at a few vertices (painting) with
    the same lights, camera and options as the frame that kept ``previous`` (surface far field,
    closed-form single scattering): the half-space terms are recomputed at the vertices whose
    ``kappa mu`` changed only (a brush touches a few hundred of the bunny's 32k). None where it
    cannot (a march, or more than a quarter of the vertices changed): call :func:`split_radiance`."""
    t0 = time.perf_counter()
    if inp.march or inp.far != "surface" or previous.km is None or previous.nu_o is None or previous.B_unit is None \
            or previous.single_raw is None:
        return None
    kv, mv = np.asarray(inp.interp @ inp.kappa), np.asarray(inp.interp @ inp.mu)
    km = kv * mv
    rows = np.flatnonzero(np.any(km != previous.km, axis=1))
    if rows.size > 0.25 * len(km):
        return None
    eta, C = float(inp.eta), inp.C
    tables = halfspace_tables(eta)
    a = _albedo(km[rows])
    ext = [(E[rows], nu[rows]) for E, nu in previous.ext]
    nu_o = previous.nu_o[rows]
    M, single_raw, c_far, w = (x.copy() for x in (previous.M, previous.single_raw, previous.c_far, previous.w))
    M[rows] = local_multiple(tables, a, ext, nu_o)
    single_raw[rows] = local_single(eta, a, ext, nu_o)
    c_far[rows] = a * tables.escape(a, nu_o[:, None]) / (2.0 * C)
    w[rows] = diffusion_weight(M[rows], single_raw[rows],
                               halfspace_bracket(kv[rows], mv[rows], eta, "p1", C) * previous.B_unit[rows])
    X_loc = np.asarray(inp.interp @ marshak_halfspace(inp.q, inp.kappa, inp.mu, C))
    facing = previous.facing
    kept = replace(previous, M=M, single=np.maximum(single_raw, 0.0) * facing[:, None], X_loc=X_loc, c_far=c_far, w=w,
                   info=_info(inp, eta, X_loc, len(km)), km=km, single_raw=single_raw)
    out = split_again(kept, inp.interp, inp.phi)
    out.seconds = time.perf_counter() - t0
    return out


def _albedo(km: Array) -> Array:
    """The vertices' albedo from ``kappa mu``; a pure absorber (round-off of ``1 - 3 kappa mu``): 0."""
    albedo = np.clip(1.0 - 3.0 * km, 0.0, 1.0)
    albedo[albedo < 1e-12] = 0.0
    return albedo


def _info(inp: SplitInputs, eta: float, X_loc: Array, n_vertices: int) -> str:
    lit = X_loc.sum(axis=1) > 0
    return (f"model split: single scattering {'3-D march' if inp.march else 'half-space closed form'}; multiple "
            f"scattering exact for the local half-space (adding-doubling, eta {eta:g}) with the far field of the "
            f"{'first-collision diffusion gathered along the view rays' if inp.far == 'gather' else 'Marshak diffusion'}"
            f" ({int(lit.sum()):,} of {n_vertices:,} vertices lit)")


def split_radiance(inp: SplitInputs, eye: Array) -> SplitResult:
    """The split's subsurface radiance per vertex (module docstring), for the camera at ``eye``."""
    t0 = time.perf_counter()
    v, n = inp.vertices, inp.normals
    w_o = np.asarray(eye, dtype=np.float64)[None, :] - v
    nu_o = np.clip(np.einsum("ij,ij->i", w_o, n) / np.maximum(np.linalg.norm(w_o, axis=1), 1e-300), 0.0, 1.0)
    facing = nu_o > 0.0
    eta = float(inp.eta)
    tables = halfspace_tables(eta)
    at = inp.at_vertices if inp.at_vertices is not None else vertex_terms(inp)
    kv, mv, albedo, beams_t, ext = at.kappa, at.mu, at.albedo, at.beams, at.external
    M = local_multiple(tables, albedo, ext, nu_o)
    gathered = None
    if inp.march:
        single, gathered = scattering_frame(inp.mesh, v, n, eye, eta, inp.lights, inp.medium, None,
                                            fluence=inp.fluence if inp.far == "gather" else None,
                                            beams=inp.march_beams)
    else:
        single = local_single(eta, albedo, ext, nu_o)
    if inp.far == "gather":
        if gathered is None:
            raise ValueError("the gather far field needs the 3-D march (march=True)")
        t_o = refracted_cosine(eta, nu_o)
        f_o = np.asarray(fresnel_transmittance(eta, nu_o)) / (eta * eta) * facing
        X_g, X_g_loc = gathered, gathered_halfspace(beams_t, kv, mv, t_o, f_o, eta, inp.C)
        dist = (np.asarray(inp.interp @ inp.source_distance_mfp) if inp.source_distance_mfp is not None
                else None)
        # the deep field's exitance of the same collided fluence: the Robin condition's flux phi / (2C)
        # over the exit angles of light that entered that far away (better where the light comes from
        # several mean free paths away: the unlit face of a thick slab lit from behind)
        esc = tables.escape(albedo, nu_o[:, None], dist) / (2.0 * inp.C)
        # (it counts the once-scattered light too, which the march has: taken out, never below 0)
        X_p = np.maximum(np.asarray(inp.interp @ np.maximum(inp.phi, 0.0)) * esc - single, 0.0)
        X_p_loc = np.maximum(collided_halfspace(beams_t, kv, mv, inp.C) * esc - local_single(eta, albedo, ext, nu_o),
                             0.0)
        g = gather_share(dist, X_g.shape)
        X, X_loc = g * X_g + (1.0 - g) * X_p, g * X_g_loc + (1.0 - g) * X_p_loc
        c_far: Any = 1.0
    else:
        X = np.asarray(inp.interp @ np.maximum(inp.phi, 0.0))
        X_loc = np.asarray(inp.interp @ marshak_halfspace(inp.q, inp.kappa, inp.mu, inp.C))
        c_far = albedo * tables.escape(albedo, nu_o[:, None]) / (2.0 * inp.C)
    w: Any = 0.0
    B_unit = None
    single_raw = single
    if inp.far == "surface":       # departures of the Marshak fluence count as the diffusion's exitance does
        Et = sum((E for E, _ in beams_t), np.zeros_like(kv))
        B_unit = Et * np.asarray(fresnel_transmittance(eta, nu_o))[:, None]
        w = diffusion_weight(M, single, halfspace_bracket(kv, mv, eta, "p1", inp.C) * B_unit)
    multiple = combine(M, X, X_loc, c_far, w) * facing[:, None]
    single = np.maximum(single, 0.0) * facing[:, None]       # (round-off of the march's sums)
    info = _info(inp, eta, X_loc, len(v))
    kept = None
    if inp.far == "surface":
        closed = {} if inp.march else {"km": kv * mv, "nu_o": nu_o, "ext": ext, "B_unit": B_unit, "single_raw": single_raw}
        kept = SplitStatic(M, single, X_loc, np.broadcast_to(c_far, M.shape), np.broadcast_to(w, M.shape), facing, info,
                           **closed)
    return SplitResult(single + multiple, single, multiple, time.perf_counter() - t0, info, static=kept,
                       clamped=fluence_clamped(inp.interp, inp.phi, facing))
