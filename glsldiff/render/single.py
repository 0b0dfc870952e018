r"""Single scattering of every light, in reflection and in transmission (the frame's optional term).

:mod:`glsldiff.physics.single` is the planar, front-lit model of Jensen et al. 2001 (light and
view on the same face, a half-space below it). This module follows the object's geometry
instead, so light entering any face and leaving the viewed one is counted (thin parts, back-lit
slabs), for every light kind:

* per shaded vertex x (outward normal n) facing the eye, the view ray refracts in along ``d``
  (Snell, cosine ``t_o``) and runs to its exit at distance ``S`` (:func:`glsldiff.mesh.raycast.
  first_hits`, at most ``REACH`` mean free paths of the least extinguishing channel);
* along it, ``samples`` Gauss-Legendre nodes ``u`` on [0, 1] map to the truncated exponential
  ``s = -ln(1 - u (1 - e^{-lam S})) / lam`` (``lam``: the smallest extinction over RGB at x), the
  view path's attenuation being the integrand's main factor;
* at each sample every light arrives as collimated *beams*: a directional, point, spot or
  projector light as one, an area light as one per sub-rectangle (towards its centre; form factor
  of that sub-rectangle, exact, :func:`glsldiff.physics.area.beam_factors`), an environment light
  as one per direction of ``ENV_DIRECTIONS`` Fibonacci directions (radiance of its band-limited
  spherical harmonics, the one pass 1 uses, times 4 pi / K sr);
* a beam's entry point y is the first surface facing the light on the straight line from the
  sample towards it: a depth map rendered from the light keeps the nearest front-facing depth
  (:meth:`glsldiff.render.shadows.ShadowMap.entry`; translucent shadow maps, Dachsbacher and
  Stamminger 2003). Its normal ``n_y`` is the mesh's corner normals interpolated at the closest
  point on the faces a face buffer rendered with the depth map stores around y
  (:meth:`~glsldiff.render.shadows.ShadowMap.entry_normals`; :func:`glsldiff.mesh.closest_points`
  only where that buffer holds no face, which its coverage, equal to the depth map's, rules
  out). There the irradiance ``E c`` (``c = n_y . w``) crosses with ``F_t(eta, c)`` and refracts
  to cosine ``t_c``: the beam's normal irradiance inside is ``E c F_t / t_c``, its direction the
  refracted one, and its path length Jensen's ``s' = l c / t_c`` (``l`` the straight distance);
* the radiance leaving x towards the eye is

.. math::

    L = \frac{F_t(\eta, \mu_o)}{\eta^2} \sum_k W_k\, \sigma_s(x_k)\, e^{-\tau_o(x_k)}
        \sum_b p(\vec T_b \cdot -\vec d)\, I_b\, e^{-\tau_b},

  ``p`` Henyey-Greenstein with ``sigma_s = sigma_s' / (1 - g)`` (isotropic by default, the
  diffusion medium's). Below a plane lit from the front this is the transport model of
  :func:`glsldiff.physics.single.single_scattering` (tested against its closed form); through a
  slab lit from behind, its closed form (tested).

Heterogeneous media: the material is sampled once on a ``GRID``^3 lattice over the object's box
and interpolated trilinearly; the view path's optical depth is the trapezoid rule over the
samples, a beam's is Simpson's rule over its straight segment times ``c / t_c``.

Limits: the light path is the straight line to the first surface facing the light, so an air
gap behind an occluder (a bunny's ear in front of its body) counts as medium (such points are
in the occluder's shadow, attenuated by its thickness in reality); the refraction at the entry
bends the path only through Jensen's length factor (exact below a plane). Total internal
reflection paths are not followed. The depth maps' texel size (``shadow_map_size``) limits
how finely an entry point is placed.
"""
from __future__ import annotations

import functools
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.jit import kernel, prange
from glsldiff.mesh import closest_points
from glsldiff.mesh.raycast import first_hits
from glsldiff.physics.area import solid_angles, sub_rectangles
from glsldiff.physics.lights import AreaLight, DirectionalLight, EnvironmentLight, Light, incidence, to_light
from glsldiff.physics.optics import fresnel_transmittance, fresnel_transmittance_at, refract
from glsldiff.physics.sh import fibonacci_directions, sh_evaluate
from glsldiff.render.shadows import ON_FACE_TEXELS, DepthRenderer, entry_at, entry_normal_at

__all__ = ["scattering_frame", "single_scattering_frame", "light_beams", "medium_lattice", "SAMPLES",
           "ENV_DIRECTIONS", "GRID", "REACH"]

Array = NDArray[np.float64]
SAMPLES = 8           # nodes along each refracted view ray (docs/guide/single-scattering.md: the error budget)
ENV_DIRECTIONS = 32   # beams of an environment light
GRID = 48             # heterogeneous material lattice per axis
REACH = 16.0          # view rays followed this many mean free paths at most
_CHUNK = 8192         # vertices per batch (times SAMPLES sample points)
_BLOCK = 256          # sample points per task of a parallel kernel


class _Medium:
    """``(sigma_s, sigma_t)`` at points: constants, or a callable ``p -> (sigma_a, sigma_s')``
    sampled on a lattice over ``[lo, hi]`` and interpolated trilinearly (:func:`_trilinear`)."""

    def __init__(self, medium: Any, lo: Array, hi: Array, g: float) -> None:
        if callable(medium):
            pad = 1e-3 * float(np.max(hi - lo))
            self.lo, self.hi = lo - pad, hi + pad
            axes = [np.linspace(self.lo[i], self.hi[i], GRID) for i in range(3)]
            X, Y, Z = np.meshgrid(*axes, indexing="ij")
            sa, ss = medium(np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1))
            sa, ss = np.broadcast_to(sa, (X.size, 3)), np.broadcast_to(ss, (X.size, 3))
            sig_s = ss / (1.0 - g)
            # (G, G, G, 6): sigma_s RGB then sigma_t RGB per lattice point
            self.grid = np.ascontiguousarray(np.concatenate([sig_s, sa + sig_s], axis=1).reshape(GRID, GRID, GRID, 6))
            self.const = None
        else:
            sa, ss = (np.asarray(x, dtype=np.float64) for x in medium)
            self.const = (ss / (1.0 - g), sa + ss / (1.0 - g))
            self.lo, self.hi = lo, hi
            self.grid = np.ascontiguousarray(np.broadcast_to(np.concatenate(self.const), (2, 2, 2, 6)))

    @property
    def homogeneous(self) -> bool:
        return self.const is not None

    def __call__(self, p: Array) -> tuple[Array, Array]:
        if self.const is not None:
            return np.broadcast_to(self.const[0], p.shape), np.broadcast_to(self.const[1], p.shape)
        out = _trilinear(self.grid, self.lo, self.hi, np.ascontiguousarray(p, dtype=np.float64))
        return out[:, :3], out[:, 3:]


@kernel
def _cell(v: float, lo: float, hi: float, G: int) -> tuple[int, float]:
    """Lattice cell and fraction of coordinate ``v`` on ``G`` points over ``[lo, hi]``, clamped
    to the lattice (``map_coordinates``' ``nearest``)."""
    c = min(max((v - lo) / (hi - lo) * (G - 1), 0.0), G - 1.0)
    i = min(int(np.floor(c)), G - 2)
    return i, c - i


@kernel(inline=True)
def _lookup(grid: Array, lo: Array, hi: Array, x: float, y: float, z: float, out: Array, first: int = 0) -> None:
    """Trilinear value ``(6,)`` of ``grid`` ``(G, G, G, 6)`` spanning ``[lo, hi]`` at one point,
    into ``out``: channels ``first`` to 5 (3: sigma_t alone)."""
    G = grid.shape[0]
    i, fx = _cell(x, lo[0], hi[0], G)
    j, fy = _cell(y, lo[1], hi[1], G)
    k, fz = _cell(z, lo[2], hi[2], G)
    for c in range(first, 6):
        out[c] = ((1.0 - fx) * ((1.0 - fy) * ((1.0 - fz) * grid[i, j, k, c] + fz * grid[i, j, k + 1, c])
                                + fy * ((1.0 - fz) * grid[i, j + 1, k, c] + fz * grid[i, j + 1, k + 1, c]))
                  + fx * ((1.0 - fy) * ((1.0 - fz) * grid[i + 1, j, k, c] + fz * grid[i + 1, j, k + 1, c])
                          + fy * ((1.0 - fz) * grid[i + 1, j + 1, k, c] + fz * grid[i + 1, j + 1, k + 1, c])))


@kernel(parallel=True)
def _trilinear(grid: Array, lo: Array, hi: Array, p: Array) -> Array:
    """``(M, 6)`` :func:`_lookup` at points ``p`` ``(M, 3)``."""
    out = np.empty((p.shape[0], 6))
    for m in prange(p.shape[0]):
        _lookup(grid, lo, hi, p[m, 0], p[m, 1], p[m, 2], out[m])
    return out


class _Beams:
    """The beams of one light: depth maps, and per beam the direction and the normal
    irradiance inside at entry points."""

    def __init__(self, light: Light, renderer: DepthRenderer, size: int) -> None:
        self.light = light
        self.centre = renderer.centre
        if isinstance(light, AreaLight):
            corners = sub_rectangles(light)
            self.points = corners.mean(axis=1)                               # sub-rectangle centres
            cube = max(64, size // 2)                                        # six views each
            self.maps = [renderer.render(renderer.perspective_views(c, cube), cube, normals=True)
                         for c in self.points]
        elif isinstance(light, EnvironmentLight):
            self.dirs = fibonacci_directions(min(ENV_DIRECTIONS, light.directions))
            self.radiance = np.maximum(sh_evaluate(light.sh, self.dirs), 0.0) * (4.0 * np.pi / len(self.dirs))
            self.maps = [renderer.shadow_map(light, size, direction=w, normals=True) for w in self.dirs]
        else:
            self.maps = [renderer.shadow_map(light, size, normals=True)]

    def __len__(self) -> int:
        return len(self.maps)

    def towards(self, b: int, x: Array) -> Array:
        """Unit directions from points ``x`` towards beam ``b``'s source."""
        if isinstance(self.light, AreaLight):
            d = self.points[b] - x
            return d / np.linalg.norm(d, axis=1, keepdims=True).clip(1e-300)
        if isinstance(self.light, EnvironmentLight):
            return np.broadcast_to(self.dirs[b], x.shape)
        return to_light(self.light, x)

    def entry(self, b: int, x: Array) -> Array:
        """Straight distance (mm) from points ``x`` back to beam ``b``'s entry point (NaN: none)."""
        return self.maps[b].entry(x - self.centre)

    def entry_normals(self, b: int, y: Array) -> Array:
        """``(M, 3)`` unit outward normal at beam ``b``'s entry points ``y`` (NaN: no face stored)."""
        return self.maps[b].entry_normals(y - self.centre)

    def constant(self, b: int) -> tuple[Array, Array] | None:
        """``(w, E)`` ``(3,)`` each of a beam with one direction towards its source and one normal
        irradiance at every point (directional and environment lights; W/mm^2), else None."""
        if isinstance(self.light, DirectionalLight):
            return (np.ascontiguousarray(self.light.direction, dtype=np.float64),
                    np.ascontiguousarray(self.light.irradiance, dtype=np.float64))
        if isinstance(self.light, EnvironmentLight):
            return np.ascontiguousarray(self.dirs[b]), np.ascontiguousarray(self.radiance[b])
        return None

    def irradiance(self, b: int, y: Array, ell: Array, eta: float) -> tuple[Array, Array]:
        """At entry points ``y`` of samples a straight distance ``ell`` inside: beam ``b``'s normal
        irradiance outside ``(M, 3)`` (on a surface facing it; W/mm^2) and the unit direction
        towards its source ``(M, 3)``."""
        w = self.towards(b, y)
        if isinstance(self.light, AreaLight):
            # the solid angle seen from the sample, its inside leg shortened by eta (a flat interface
            # makes what lies outside look eta times farther; paraxial)
            virtual = y - (ell / eta)[:, None] * w
            E_n = solid_angles(self.light, np.full(len(y), b), virtual)[:, None] * np.asarray(self.light.radiance)
        elif isinstance(self.light, EnvironmentLight):
            E_n = np.broadcast_to(self.radiance[b], (len(y), 3))
        else:
            scale, colour = incidence(self.light, y)
            E_n = scale[:, None] * np.atleast_2d(colour)
        return E_n, w


def single_scattering_frame(mesh: Any, vertices: Array, normals: Array, eye: Array, eta: float,
                            lights: Sequence[Light], medium: Any, renderer: DepthRenderer,
                            shadow_map_size: int = 1024, samples: int = SAMPLES, g: float = 0.0) -> Array:
    """``(V, 3)`` single-scattered radiance towards ``eye`` at ``vertices`` (module docstring).

    ``medium``: ``(sigma_a, sigma_s')`` RGB arrays (mm^-1) or a callable of points ``(M, 3)``
    returning both ``(M, 3)``; ``renderer`` renders the lights' depth maps of ``mesh``."""
    return scattering_frame(mesh, vertices, normals, eye, eta, lights, medium, renderer, shadow_map_size,
                            samples, g)[0]


def light_beams(lights: Sequence[Light], renderer: DepthRenderer, shadow_map_size: int = 1024) -> list[_Beams]:
    """The lights' beams with their depth maps (read back: no GL objects), for
    :func:`scattering_frame`'s ``beams`` while the lights and the mesh stay."""
    return [_Beams(lt, renderer, shadow_map_size) for lt in lights]


def medium_lattice(medium: Any, mesh: Any, g: float = 0.0) -> _Medium:
    """``medium`` sampled for the march over ``mesh``'s box, for :func:`scattering_frame`'s
    ``medium`` while the material stays."""
    mv = np.asarray(mesh.vertices, dtype=np.float64)
    return _Medium(medium, mv.min(axis=0), mv.max(axis=0), g)


def scattering_frame(mesh: Any, vertices: Array, normals: Array, eye: Array, eta: float,
                     lights: Sequence[Light], medium: Any, renderer: DepthRenderer | None,
                     shadow_map_size: int = 1024, samples: int = SAMPLES, g: float = 0.0,
                     fluence: Callable[[Array], Array] | None = None,
                     beams: Sequence[_Beams] | None = None) -> tuple[Array, Array]:
    """``(single, gathered)``, each ``(V, 3)``: :func:`single_scattering_frame`, and with
    ``fluence`` (a callable of points ``(M, 3)`` returning the collided fluence ``(M, 3)``) the
    light it scatters once more towards the eye along the same refracted view rays, ``F_t(mu_o) /
    eta^2 sum_k W_k sigma_s(x_k) e^{-tau_o(x_k)} phi(x_k) / (4 pi)`` (isotropic: the transport
    split's gather, :mod:`glsldiff.physics.split`); zeros without it. A frame whose lights or
    material did not change passes the last frame's ``beams`` (:func:`light_beams`; ``renderer``
    may then be None) and ``medium`` (:func:`medium_lattice`, made with the same ``g``)."""
    v = np.asarray(vertices, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    out = np.zeros((len(v), 3))
    gathered = np.zeros((len(v), 3))
    if len(v) == 0 or (not lights and fluence is None):
        return out, gathered
    med = medium if isinstance(medium, _Medium) else medium_lattice(medium, mesh, g)
    w_o = np.asarray(eye, dtype=np.float64) - v
    w_o /= np.linalg.norm(w_o, axis=1, keepdims=True).clip(1e-300)
    mu_o = np.einsum("ij,ij->i", n, w_o)
    idx = np.flatnonzero(mu_o > 0.0)
    if idx.size == 0:
        return out, gathered
    if beams is None:
        if renderer is None:
            raise ValueError("scattering_frame needs a DepthRenderer or the lights' beams")
        beams = light_beams(lights, renderer, shadow_map_size)
    d, _ = refract(-w_o[idx], n[idx], 1.0 / eta)                             # view ray, propagating in
    _, st0 = med(v[idx])
    lam = np.maximum(st0.min(axis=1), 1e-12)                                 # mm^-1; a clear channel: uniform
    h = 1e-6 * float(np.max(mesh.extents))                                  # off the surface (mm)
    S, _ = first_hits(mesh, v[idx] + h * d, d, t_max=float(REACH / lam.min()))
    S = np.minimum(S + h, REACH / lam)                                       # no hit: the reach
    u, wu = _nodes(samples)
    f_o = np.asarray(fresnel_transmittance(eta, mu_o[idx])) / eta**2
    for a in range(0, len(idx), _CHUNK):
        sl = slice(a, a + _CHUNK)
        m = len(idx[sl])
        x, weight, sig_t = _view_samples(np.ascontiguousarray(v[idx[sl]]), np.ascontiguousarray(d[sl]), S[sl],
                                         lam[sl], np.ascontiguousarray(st0[sl]), u, wu, med.grid, med.lo, med.hi,
                                         med.homogeneous)
        x, sig_t = x.reshape(-1, 3), sig_t.reshape(-1, 3)
        up = -np.repeat(d[sl], samples, axis=0)                               # view propagation, to the surface
        incoming = np.zeros((m * samples, 3))
        for bl in beams:
            for b in range(len(bl)):
                _beam(bl, b, x, sig_t, up, mesh, med, eta, g, incoming)
        out[idx[sl]] = f_o[sl, None] * np.einsum("mkc,mkc->mc", weight, incoming.reshape(m, samples, 3))
        if fluence is not None:
            phi = np.maximum(fluence(x), 0.0).reshape(m, samples, 3)
            gathered[idx[sl]] = f_o[sl, None] * np.einsum("mkc,mkc->mc", weight, phi) / (4.0 * np.pi)
    return out, gathered


@functools.lru_cache(maxsize=4)
def _nodes(samples: int) -> tuple[Array, Array]:
    """Gauss-Legendre nodes and weights of ``samples`` points on [0, 1]."""
    x, w = np.polynomial.legendre.leggauss(samples)
    return 0.5 * (x + 1.0), 0.5 * w


@kernel(parallel=True)
def _view_samples(v: Array, d: Array, S: Array, lam: Array, st0: Array, u: Array, wu: Array, grid: Array,
                  lo: Array, hi: Array, homogeneous: bool) -> tuple[Array, Array, Array]:
    """Along each refracted view ray ``v + s d`` (``S``: its length, ``lam``: its sampling
    extinction, ``st0``: sigma_t at ``v``): the sample points ``s_k = -ln(1 - u_k (1 - e^{-lam
    S})) / lam`` ``(m, K, 3)``, their weights ``W_k sigma_s e^{-tau_o}`` ``(m, K, 3)`` (the
    view path's optical depth: exact when homogeneous, else the trapezoid rule from ``v``) and
    sigma_t there ``(m, K, 3)``."""
    m, K = v.shape[0], u.shape[0]
    x = np.empty((m, K, 3))
    weight = np.empty((m, K, 3))
    sig_t = np.empty((m, K, 3))
    for i in prange(m):
        val = np.empty(6)
        span = -np.expm1(-lam[i] * S[i])                                    # 1 - e^{-lam S}
        tau = np.zeros(3)
        s_prev = 0.0
        for k in range(K):
            s = -np.log1p(-u[k] * span) / lam[i]
            W = wu[k] * span / (lam[i] * (1.0 - u[k] * span))
            for c in range(3):
                x[i, k, c] = v[i, c] + s * d[i, c]
            if homogeneous:
                for c in range(6):
                    val[c] = grid[0, 0, 0, c]
            else:
                _lookup(grid, lo, hi, x[i, k, 0], x[i, k, 1], x[i, k, 2], val)
            for c in range(3):
                if homogeneous:
                    tau[c] = s * val[3 + c]
                else:
                    before = st0[i, c] if k == 0 else sig_t[i, k - 1, c]
                    tau[c] += 0.5 * (before + val[3 + c]) * (s - s_prev)
                sig_t[i, k, c] = val[3 + c]
                weight[i, k, c] = W * val[c] * np.exp(-tau[c])
            s_prev = s
    return x, weight, sig_t


def _beam(bl: _Beams, b: int, x: Array, st_x: Array, up: Array, mesh: Any, med: _Medium, eta: float,
          g: float, out: Array) -> None:
    """Adds beam ``b``'s phase-weighted, attenuated normal irradiance inside at sample points
    ``x`` (``st_x``: the extinction there, ``up``: the view ray's propagation) to ``out`` ``(M, 3)``:
    in one kernel for a beam of one direction and irradiance, else its entry points in numpy
    between kernels."""
    sel: Any = slice(None)
    const = bl.constant(b)
    if const is not None:
        sm = bl.maps[b]
        tri, cn = sm.surface
        miss = np.zeros(len(x), dtype=np.bool_)
        _constant_beam(x, st_x, up, const[0], const[1], bl.centre, sm.views_packed, sm.size, sm.front, sm.face,
                       tri, cn, ON_FACE_TEXELS, float(eta), float(g), med.grid, med.lo, med.hi, med.homogeneous,
                       out, miss)
        sel = np.flatnonzero(miss)          # no face stored there (not expected: same coverage)
        if sel.size == 0:
            return
    ell = bl.entry(b, x[sel])
    ok = np.flatnonzero(np.isfinite(ell))
    if ok.size == 0:
        return
    idx = np.arange(len(x))[sel][ok]
    xo, ell = x[idx], ell[ok]
    y = xo + ell[:, None] * bl.towards(b, xo)
    n_y = bl.entry_normals(b, y)
    miss_n = np.flatnonzero(~np.isfinite(n_y[:, 0]))
    if miss_n.size:
        n_y[miss_n] = closest_points(mesh, y[miss_n], exact=False)[3]
    E_n, w_y = bl.irradiance(b, y, ell, eta)
    res = _beam_terms(xo, y, ell, np.ascontiguousarray(w_y), n_y, np.ascontiguousarray(E_n),
                      np.ascontiguousarray(up[idx]), np.ascontiguousarray(st_x[idx]), float(eta), float(g),
                      med.grid, med.lo, med.hi, med.homogeneous)
    out[idx] += res


@kernel(parallel=True)
def _beam_terms(x: Array, y: Array, ell: Array, w: Array, n_y: Array, E_n: Array, up: Array, st_x: Array,
                eta: float, g: float, grid: Array, lo: Array, hi: Array, homogeneous: bool) -> Array:
    """``(M, 3)`` one beam's :func:`_add_term` at samples ``x``: entering at ``y`` (normal
    ``n_y``, towards the source ``w``, irradiance ``E_n``) a straight distance ``ell`` away."""
    M = x.shape[0]
    res = np.zeros((M, 3))
    blocks = (M + _BLOCK - 1) // _BLOCK
    for blk in prange(blocks):
        mid = np.empty(6)
        end = np.empty(6)
        for i in range(blk * _BLOCK, min(M, (blk + 1) * _BLOCK)):
            _add_term(i, x, y[i, 0], y[i, 1], y[i, 2], ell[i], w[i, 0], w[i, 1], w[i, 2], n_y[i, 0], n_y[i, 1],
                      n_y[i, 2], E_n[i, 0], E_n[i, 1], E_n[i, 2], up, st_x, eta, g, grid, lo, hi, homogeneous,
                      mid, end, res)
    return res


@kernel(parallel=True)
def _constant_beam(x: Array, st_x: Array, up: Array, w: Array, E: Array, centre: Array, views: Any, size: int,
                   front: Any, face: Any, tri: Array, cn: Array, on_face: float, eta: float, g: float,
                   grid: Array, lo: Array, hi: Array, homogeneous: bool, out: Array, miss: Any) -> None:
    """Adds to ``out`` ``(M, 3)`` a beam of one direction ``w`` and one irradiance ``E``
    (directional and environment lights) at samples ``x``: its entry points and normals from the
    light's depth and face maps (:func:`~glsldiff.render.shadows.entry_at`,
    :func:`~glsldiff.render.shadows.entry_normal_at`) and :func:`_add_term`, in one pass;
    ``miss[i]``: an entry point with no face stored (left for the caller)."""
    M = x.shape[0]
    blocks = (M + _BLOCK - 1) // _BLOCK
    for blk in prange(blocks):
        mid = np.empty(6)
        end = np.empty(6)
        for i in range(blk * _BLOCK, min(M, (blk + 1) * _BLOCK)):
            ell = entry_at(x[i, 0] - centre[0], x[i, 1] - centre[1], x[i, 2] - centre[2], views, size, front)
            if not ell == ell:                  # no surface towards the light stored
                continue
            y0, y1, y2 = x[i, 0] + ell * w[0], x[i, 1] + ell * w[1], x[i, 2] + ell * w[2]
            n0, n1, n2 = entry_normal_at(y0 - centre[0], y1 - centre[1], y2 - centre[2], views, size, face, tri, cn,
                                         on_face)
            if not n0 == n0:
                miss[i] = True
                continue
            _add_term(i, x, y0, y1, y2, ell, w[0], w[1], w[2], n0, n1, n2, E[0], E[1], E[2], up, st_x, eta, g,
                      grid, lo, hi, homogeneous, mid, end, out)


@kernel(inline=True)
def _add_term(i: int, x: Array, y0: float, y1: float, y2: float, ell: float, w0: float, w1: float, w2: float,
              n0: float, n1: float, n2: float, E0: float, E1: float, E2: float, up: Array, st_x: Array, eta: float,
              g: float, grid: Array, lo: Array, hi: Array, homogeneous: bool, mid: Array, end: Array,
              out: Array) -> None:
    """Adds to ``out[i]`` a beam's ``p(T . up) E c F_t / t e^{-tau}`` at sample ``x[i]`` (module
    docstring): entering at ``y`` (normal ``n``, towards the source ``w``, normal irradiance
    ``E``) a straight distance ``ell`` away; ``tau``: Jensen's path ``ell c / t`` times sigma_t by
    Simpson's rule over the segment (exact when homogeneous); ``mid``, ``end``: scratch ``(6,)``."""
    c = n0 * w0 + n1 * w1 + n2 * w2
    if not c > 0.0:                     # facing away, or no normal (NaN)
        return
    c = min(c, 1.0)
    e = 1.0 / eta
    sin2 = e * e * (1.0 - c * c)
    cos_t = np.sqrt(min(max(1.0 - sin2, 0.0), 1.0))      # the refracted cosine
    t = max(cos_t, 1e-6)
    share = c * fresnel_transmittance_at(eta, c) / t
    path = ell * c / t
    # refracted propagation: Snell for -w crossing the surface (normal n) from outside
    k = e * c - cos_t
    T0, T1, T2 = -e * w0 + k * n0, -e * w1 + k * n1, -e * w2 + k * n2
    norm = max(np.sqrt(T0 * T0 + T1 * T1 + T2 * T2), 1e-300)
    mu = (T0 * up[i, 0] + T1 * up[i, 1] + T2 * up[i, 2]) / norm
    den = 1.0 + g * g - 2.0 * g * mu
    f = share * (1.0 - g * g) / (4.0 * np.pi * den * np.sqrt(den))       # Henyey-Greenstein
    if homogeneous:
        out[i, 0] += f * E0 * np.exp(-path * grid[0, 0, 0, 3])
        out[i, 1] += f * E1 * np.exp(-path * grid[0, 0, 0, 4])
        out[i, 2] += f * E2 * np.exp(-path * grid[0, 0, 0, 5])
        return
    _lookup(grid, lo, hi, 0.5 * (x[i, 0] + y0), 0.5 * (x[i, 1] + y1), 0.5 * (x[i, 2] + y2), mid, 3)
    _lookup(grid, lo, hi, y0, y1, y2, end, 3)
    out[i, 0] += f * E0 * np.exp(-path * (st_x[i, 0] + 4.0 * mid[3] + end[3]) / 6.0)
    out[i, 1] += f * E1 * np.exp(-path * (st_x[i, 1] + 4.0 * mid[4] + end[4]) / 6.0)
    out[i, 2] += f * E2 * np.exp(-path * (st_x[i, 2] + 4.0 * mid[5] + end[5]) / 6.0)
