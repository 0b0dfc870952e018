"""Pass 1 of the renderer: light transmitted into the object at its boundary nodes.

Wang et al. 2008, section 5: before the diffusion pass, the incident light at every boundary
node is computed "using shadow buffers for directional and point lights, and ambient
occlusion or precomputed radiance transfer for environment lighting". :func:`incident_light`
returns, per boundary node x with outward unit normal n, the transmitted irradiance (in the
units of ``DirectionalLight.irradiance``, of ``PointLight.intensity`` per mm^2, or of the
environment's radiance times sr)

    E_t(x) = sum over lights of  L_i(w) (n . w)^+ F_t(eta, n . w) V(x, w)      (dw integrated
                                                                              for environments)

with w the unit direction from x towards the light, F_t = 1 - Fresnel reflectance of the smooth
interface (:func:`glsldiff.physics.optics.fresnel_transmittance`, eta = n_inside / n_outside) and V the
visibility. This is the source q of the boundary condition (Wang et al. eq. 2). The lights are
those of :mod:`glsldiff.physics.lights` (their falloff: :func:`~glsldiff.physics.lights.incidence`);
V comes from the shadow maps of :mod:`glsldiff.render.shadows`.

Environment light
-----------------
The unshadowed term is the spherical-harmonics irradiance with the Fresnel factor folded into
the kernel (:func:`glsldiff.physics.sh.sh_irradiance` of :attr:`EnvironmentLight.sh`).
With ``visibility=True`` (the paper's ambient occlusion), ``directions`` directions w_k on a
Fibonacci sphere each get an orthographic shadow map (at most ``ENV_SHADOW_MAP_MAX`` texels
square), and

    E_t(x) = E_sh(x) * sum_k w_k V(x, w_k) / sum_k w_k,
    w_k = max(L_sh(w_k), 0) (n . w_k)^+ F_t(eta, n . w_k)      (per colour channel),

i.e. the paper's sum ``sum_k L_sh(w_k) (n.w_k)^+ F_t V (4 pi / K)`` normalised by the same sum
with V = 1. The normalisation makes an unoccluded (convex) surface reproduce E_sh exactly
instead of carrying the quadrature error of K directions (several percent for K = 64); the
ratio tends to the plain sum as K grows. Where every weight of a channel vanishes the
cosine-Fresnel weighted visible fraction is used instead.

Area light: :func:`glsldiff.physics.area.area_beams` (exact clipped form factors of its
sub-rectangles, Fresnel per sub-rectangle), not shadowed.

With the surface ``triangles`` over the points (tetrahedral grids), each light but the
environment is averaged over every point's P1 cells rather than sampled at the point
(:func:`_cell_averaged`), so sharp edges (patches, hard spots, projector pixels, shadows) enter
the source with the share of each cell they light.

Beams (for the first-collision volume source, :mod:`glsldiff.physics.collision`): on request
each light is also returned as beams, transmitted irradiance with the refracted cosine it
travels at into the medium. An environment light's beams assume uniform radiance over the
hemisphere (:data:`ENV_BEAMS`); its visibility and spherical-harmonic shape scale them.

GL objects are created per call and released before it returns. Units: mm, radiance and
irradiance in the caller's units.
"""
from __future__ import annotations

import contextlib
import math
import time
from typing import Any, Callable, Sequence

import moderngl
import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff import gl
from glsldiff.core import checks
from glsldiff.core.errors import InputError
from glsldiff.physics.area import area_beams
from glsldiff.physics.lights import (AreaLight, EnvironmentLight, KINDS, Light, casts_shadows, check_light,
                                     incidence, light_kind, to_light)
from glsldiff.physics.optics import refracted_cosine, transmitted_cosine
from glsldiff.physics.sh import fibonacci_directions, sh_evaluate, sh_irradiance
from glsldiff.render.shadows import DepthRenderer

__all__ = ["incident_light", "visibility", "ENV_SHADOW_MAP_MAX", "Beam"]

ENV_SHADOW_MAP_MAX = 512   # shadow maps of environment directions are at most this size
_GAUSS3 = np.polynomial.legendre.leggauss(3)
#: Incidence cosines (3-point Gauss-Legendre on [0, 1]) of an environment light's beams.
ENV_BEAMS = tuple(0.5 * (1.0 + x) for x in _GAUSS3[0])
#: A beam: transmitted irradiance ``(N, 3)`` and the refracted cosine ``(N,)`` it arrives at.
Beam = tuple[NDArray[np.float64], NDArray[np.float64]]


def _env_beams(eta: float | None) -> list[tuple[float, float]]:
    """``(share, t)`` of the beams an environment light's ``E_t`` is split into: radiance taken
    as uniform over the hemisphere, share ``prop. mu F_t(mu)`` at the Gauss points ``mu`` of
    :data:`ENV_BEAMS` (Gauss weights), ``t`` their refracted cosines."""
    mu = np.asarray(ENV_BEAMS)
    w = _GAUSS3[1] * transmitted_cosine(eta, mu)
    return list(zip(w / w.sum(), refracted_cosine(eta, mu)))


def _mesh_arrays(mesh: Any) -> None:
    v = getattr(mesh, "vertices", None)
    f = getattr(mesh, "faces", None)
    if v is None or f is None:
        raise InputError(f"mesh must be a glsldiff.mesh.Mesh (vertices, faces), got {type(mesh).__name__}")
    v, f = np.asarray(v), np.asarray(f)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise InputError(f"mesh must have (V, 3) vertices and (F, 3) faces, got {v.shape} and {f.shape}")
    if not np.isfinite(v).all():
        raise InputError("mesh.vertices must be finite")


def _size(shadow_map_size: Any) -> int:
    return checks.integer(shadow_map_size, "shadow_map_size", 8, 8192)


def _light_list(lights: Any) -> list[Light]:
    if isinstance(lights, tuple(KINDS.values())):
        lights = [lights]
    try:
        out = list(lights)
    except TypeError:
        raise InputError(f"lights must be a sequence of lights, got {type(lights).__name__}") from None
    return [check_light(light, f"lights[{i}]") for i, light in enumerate(out)]


def _context(ctx: moderngl.Context | None) -> moderngl.Context:
    c = ctx if ctx is not None else gl.get_context()
    gl.make_current(c)
    return c


def visibility(mesh: Any, points: ArrayLike, light: Light, ctx: moderngl.Context | None = None,
               shadow_map_size: int = 1024, normals: ArrayLike | None = None,
               depth: DepthRenderer | None = None) -> NDArray[np.float64]:
    """Shadow-map visibility ``(N,)`` in [0, 1] of ``points`` (N, 3) mm for one light (1 = lit).

    Renders a shadow map whatever the light's ``shadows`` flag says. ``normals`` (N, 3),
    optional, set the slope part of the bias (:mod:`glsldiff.render.shadows`). For an
    :class:`EnvironmentLight` the result is the ambient-occlusion fraction over its
    ``directions`` (weighted by ``(n . w)^+`` when normals are given, else unweighted), with
    shadow maps of at most ``ENV_SHADOW_MAP_MAX`` texels. For a projector it is the shadowing
    alone (points outside the frustum count as lit); its image is
    :func:`glsldiff.physics.lights.projector_factor`. ``depth``: as :func:`incident_light`'s.
    """
    _mesh_arrays(mesh)
    p = checks.points(points)
    n = None if normals is None else checks.unit_rows(normals, "normals", len(p))
    check_light(light)
    size = _size(shadow_map_size)
    if len(p) == 0:
        return np.ones(0)
    with (contextlib.nullcontext(depth) if depth is not None else DepthRenderer(_context(ctx), mesh)) as r:
        q = p - r.centre
        if isinstance(light, EnvironmentLight):
            dirs = fibonacci_directions(light.directions)
            num, den = np.zeros(len(p)), np.zeros(len(p))
            for w in dirs:
                wt = np.ones(len(p)) if n is None else np.maximum(n @ w, 0.0)
                if not wt.any():
                    continue
                sm = r.shadow_map(light, min(size, ENV_SHADOW_MAP_MAX), direction=w)
                num += wt * sm.lookup(q, np.broadcast_to(w, p.shape), n)
                den += wt
            return np.where(den > 0, num / np.maximum(den, 1e-300), 1.0)
        sm = r.shadow_map(light, size)
        return sm.lookup(q, to_light(light, p), n)


def incident_light(mesh: Any, points: ArrayLike, normals: ArrayLike, lights: Sequence[Light],
                   eta: float | None, ctx: moderngl.Context | None = None,
                   shadow_map_size: int = 1024, beams: list[Beam] | None = None,
                   triangles: ArrayLike | None = None,
                   depth: DepthRenderer | None = None) -> tuple[NDArray[np.float64], list[dict[str, Any]]]:
    """Transmitted irradiance at boundary nodes (pass 1; formulas in the module docstring).

    Parameters
    ----------
    mesh
        The closed :class:`glsldiff.mesh.Mesh` that casts the shadows (mm).
    points
        ``(N, 3)`` node positions on or slightly inside the surface, mm.
    normals
        ``(N, 3)`` outward normals (normalised here; zero rows are refused).
    lights
        Lights of :mod:`glsldiff.physics.lights` (a single light is accepted too).
    eta
        Relative refractive index n_inside / n_outside, > 0; ``None``: the incident
        irradiance (no Fresnel factor), e.g. for a diffuse surface reflectance.
    ctx
        GL context for the shadow maps; default :func:`glsldiff.gl.get_context` (only
        created when some light needs a shadow map).
    shadow_map_size
        Texels per side of each shadow-map view (environment directions: at most
        ``ENV_SHADOW_MAP_MAX``).
    triangles
        ``(F, 3)`` surface triangles over ``points`` (optional): every light but the
        environment is then averaged over each point's P1 support (:func:`_cell_averaged`)
        instead of sampled at it.
    beams
        If a list, the light is also appended to it as beams ``(E (N, 3), t (N,))`` whose
        ``E`` sum to ``E_t``, ``t`` the refracted cosine each arrives at (module docstring):
        one per directional, point, spot or projector light, one per sub-rectangle of an
        area light, ``len(ENV_BEAMS)`` per environment light.
    depth
        A :class:`~glsldiff.render.shadows.DepthRenderer` of ``mesh`` to render the shadow maps
        with (one that keeps its maps shares them with later passes; the caller releases it);
        default: one made and released here.

    Returns
    -------
    E_t
        ``(N, 3)`` float64 transmitted irradiance, RGB.
    info
        One dict per light: ``light`` (kind), ``shadow_map`` (e.g. ``"1024x1024"``,
        ``"6 x 1024x1024 (cube)"``, ``"64 x 512x512"`` or ``"none (shadows off)"``),
        ``seconds``, ``facing`` (points with n . w > 0, or with any lit direction; for a
        projector also inside its frustum on a non-black pixel),
        ``shadowed`` (facing points with visibility < 0.5), ``max`` (largest E_t of the
        light, per channel), and for environments ``sh_order``, ``directions`` and (with
        visibility) ``mean_visibility``, the cosine-Fresnel weighted visible fraction.
    """
    _mesh_arrays(mesh)
    p = checks.points(points)
    n = checks.unit_rows(normals, "normals", len(p))
    eta_v = None if eta is None else checks.real(eta, "eta", 0.0, math.inf, lo_open=True, hi_open=True)
    light_list = _light_list(lights)
    size = _size(shadow_map_size)
    total = np.zeros((len(p), 3))
    infos: list[dict[str, Any]] = []
    renderer: DepthRenderer | None = depth
    try:
        for light in light_list:
            t0 = time.perf_counter()
            info: dict[str, Any] = {"light": light_kind(light)}
            needs_map = casts_shadows(light) and len(p) > 0
            if needs_map and renderer is None:
                renderer = DepthRenderer(_context(ctx), mesh)
            if isinstance(light, EnvironmentLight):
                e = _environment(light, p, n, eta_v, renderer if needs_map else None, size, info)
                if beams is not None:
                    beams.extend((e * w, np.full(len(p), t)) for w, t in _env_beams(eta_v))
            elif isinstance(light, AreaLight):
                g, t = _cell_averaged(lambda q, nq: area_beams(light, q, nq, eta_v), p, n, triangles, info,
                                      area_beams(light, p, n, eta_v))
                rad = np.asarray(light.radiance)
                e = g.sum(axis=1)[:, None] * rad
                if beams is not None:
                    beams.extend((g[:, k, None] * rad, t[:, k]) for k in range(g.shape[1]))
                info.update(shadow_map="none (area lights are not shadowed)", shadowed=0,
                            facing=int((g.sum(axis=1) > 0).sum()), samples=light.samples ** 2)
            else:
                sm = renderer.shadow_map(light, size) if needs_map and renderer is not None else None
                info["shadow_map"] = sm.label if sm is not None else "none (shadows off)"
                e, t3, facing, vis = _direct_light(light, p, n, eta_v, sm, renderer)
                info["facing"] = int(facing.sum())
                info["shadowed"] = int((vis[facing] < 0.5).sum())
                e, t3 = _cell_averaged(lambda q, nq: _direct_light(light, q, nq, eta_v, sm, renderer)[:2],
                                       p, n, triangles, info, (e, t3))
                if beams is not None:
                    beams.append((e, t3[:, 0]))
            total += e
            info["max"] = [float(x) for x in (e.max(axis=0) if len(e) else np.zeros(3))]
            info["seconds"] = time.perf_counter() - t0
            infos.append(info)
    finally:
        if renderer is not None and renderer is not depth:
            renderer.release()
    return total, infos


#: Triangles whose corners' values of a light differ by more than this share of the light's
#: largest are integrated on REFINE x REFINE sub-triangles (:func:`_cell_averaged`) ...
REFINE_REL = 0.05
#: ... and whose centroid's value differs from the mean of the corners' by more than this share.
REFINE_CENTROID = 0.01
REFINE = 4


def _sub_barycentrics(m: int) -> NDArray[np.float64]:
    """``(m^2, 3)`` barycentric centroids of the m^2 congruent sub-triangles of a triangle."""
    out = []
    for i in range(m):
        for j in range(m - i):
            out.append(((i + 1 / 3) / m, (j + 1 / 3) / m))          # upward sub-triangle
            if i + j < m - 1:
                out.append(((i + 2 / 3) / m, (j + 2 / 3) / m))      # downward one
    a = np.array(out)
    return np.column_stack([1.0 - a.sum(axis=1), a[:, 0], a[:, 1]])


Evaluate = Callable[[NDArray[np.float64], NDArray[np.float64]], tuple[NDArray[np.float64], NDArray[np.float64]]]


def _cell_averaged(evaluate: Evaluate, p: NDArray[np.float64], n: NDArray[np.float64],
                   triangles: ArrayLike | None, info: dict[str, Any],
                   at_points: tuple[NDArray[np.float64], NDArray[np.float64]]
                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The light values ``at_points`` ``(g (N, K), t (N, K))`` (``evaluate(points, normals)``
    gives them anywhere: K beams or colour channels with their refracted cosines), each the
    average over the point's
    P1 support on ``triangles``: ``g_i = sum_T int_T g v_i / sum_T int_T v_i``. A sharp light
    edge (a patch, a hard spot, a projector pixel, a shadow) crossing a node's cells then puts
    into the source the share of the cells it lights, not all or nothing (which, sampled at the
    nodes, moved the edge by up to half a spacing: +9 % power for a 4 mm patch on a 0.42 mm
    grid). Triangles whose corners differ by less than ``REFINE_REL`` of the light's largest
    value, or whose centroid's value the corners' mean matches within ``REFINE_CENTROID`` of
    it (smooth light), use the corner values (lumped); the others are integrated at the
    centroids of ``REFINE^2`` sub-triangles. ``t`` is averaged with the weights ``g v_i``."""
    g, t = at_points
    if triangles is None or len(p) == 0 or not g.any():
        return g, t
    tri = np.asarray(triangles, dtype=np.int64)
    P = p[tri]
    area = 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1)
    G = g.sum(axis=1)[tri]
    refine = (G.max(axis=1) - G.min(axis=1)) > REFINE_REL * G.max()
    if refine.any():   # keep only those the linear interpolant misses at the centroid: an edge crosses them
        cand = np.flatnonzero(refine)
        nc = n[tri[cand]].sum(axis=1)
        gc, _ = evaluate(P[cand].mean(axis=1), nc / np.linalg.norm(nc, axis=1, keepdims=True).clip(1e-300))
        refine[cand] = np.abs(gc.sum(axis=1) - G[cand].mean(axis=1)) > REFINE_CENTROID * G.max()
    info["refined_triangles"] = int(refine.sum())
    w = np.repeat(area / 3.0, 3)
    num = np.zeros_like(g)
    num_t = np.zeros_like(g)
    den = np.bincount(tri.ravel(), w, minlength=len(p))
    keep = ~refine
    corner = tri[keep].ravel()
    wk = np.repeat(area[keep] / 3.0, 3)[:, None]
    np.add.at(num, corner, wk * g[corner])
    np.add.at(num_t, corner, wk * g[corner] * t[corner])
    if refine.any():
        bary = _sub_barycentrics(REFINE)                                        # (m, 3)
        rt = tri[refine]
        pts = np.einsum("mk,fkj->fmj", bary, p[rt]).reshape(-1, 3)
        nrm = np.einsum("mk,fkj->fmj", bary, n[rt]).reshape(-1, 3)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True).clip(1e-300)
        gs, ts = evaluate(pts, nrm)
        m = len(bary)
        gs, ts = gs.reshape(len(rt), m, -1), ts.reshape(len(rt), m, -1)
        wa = (area[refine] / m)[:, None, None] * bary[None, :, :]               # (f, m, 3) int of v_i per point
        for k in range(3):
            np.add.at(num, rt[:, k], np.einsum("fm,fmq->fq", wa[:, :, k], gs))
            np.add.at(num_t, rt[:, k], np.einsum("fm,fmq->fq", wa[:, :, k], gs * ts))
    has = den > 0
    g_avg = np.where(has[:, None], num / np.where(has, den, 1.0)[:, None], g)
    t_avg = np.where(has[:, None] & (num > 0), num_t / np.where(num > 0, num, 1.0), t)
    return g_avg, t_avg


def _direct_light(light: Light, q: NDArray[np.float64], nq: NDArray[np.float64], eta: float | None,
                  sm: Any, renderer: DepthRenderer | None
                  ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]:
    """A directional, point, spot or projector light at points ``q`` with normals ``nq``: its
    transmitted irradiance ``(M, 3)`` with shadows (shadow map ``sm``, or none), the refracted
    cosine repeated per channel ``(M, 3)``, the facing points (lit but for shadows) and the
    visibility ``(M,)``."""
    w = to_light(light, q)
    cos = np.einsum("ij,ij->i", nq, w)
    scale, colour = incidence(light, q, transmitted_cosine(eta, cos))
    facing = scale > 0
    vis = np.ones(len(q))
    if sm is not None:
        assert renderer is not None
        idx = np.flatnonzero(facing)
        vis[idx] = sm.lookup(q[idx] - renderer.centre, w[idx], nq[idx])
    e = (scale * vis)[:, None] * np.atleast_2d(colour) * np.ones((len(q), 3))
    return e, np.repeat(refracted_cosine(eta, cos)[:, None], 3, axis=1), facing, vis


def _environment(light: EnvironmentLight, p: NDArray[np.float64], n: NDArray[np.float64], eta: float | None,
                 renderer: DepthRenderer | None, size: int, info: dict[str, Any]) -> NDArray[np.float64]:
    coeffs = light.sh
    info["sh_order"] = light.order
    info["directions"] = light.directions if renderer is not None else 0
    e_sh = sh_irradiance(coeffs, n, eta) if len(n) else np.zeros((0, 3))
    if renderer is None:
        info["shadow_map"] = "none (visibility off)"
        info["facing"] = len(p)
        info["shadowed"] = 0
        return e_sh
    dirs = fibonacci_directions(light.directions)
    radiance = np.maximum(sh_evaluate(coeffs, dirs), 0.0)          # (K, 3)
    num = np.zeros((len(p), 3))
    den = np.zeros((len(p), 3))
    num_g = np.zeros(len(p))
    den_g = np.zeros(len(p))
    env_size = min(size, ENV_SHADOW_MAP_MAX)
    q = p - renderer.centre
    for k, w in enumerate(dirs):
        cos = n @ w
        g = transmitted_cosine(eta, cos)
        idx = np.flatnonzero(g > 0)
        if idx.size == 0:
            continue
        sm = renderer.shadow_map(light, env_size, direction=w)
        v = sm.lookup(q[idx], np.broadcast_to(w, (idx.size, 3)), n[idx])
        wk = g[idx, None] * radiance[k][None, :]
        num[idx] += wk * v[:, None]
        den[idx] += wk
        num_g[idx] += g[idx] * v
        den_g[idx] += g[idx]
    frac_g = np.where(den_g > 0, num_g / np.maximum(den_g, 1e-300), 1.0)
    frac = np.where(den > 0, num / np.maximum(den, 1e-300), frac_g[:, None])
    info["shadow_map"] = f"{light.directions} x {env_size}x{env_size}"
    info["facing"] = int((den_g > 0).sum())
    info["shadowed"] = int((frac_g < 0.5).sum())
    info["mean_visibility"] = float(frac_g.mean()) if len(frac_g) else 1.0
    return e_sh * frac
