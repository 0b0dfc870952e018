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

from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates

from glsldiff.mesh import closest_points
from glsldiff.mesh.raycast import first_hits
from glsldiff.physics.area import solid_angles, sub_rectangles
from glsldiff.physics.lights import AreaLight, EnvironmentLight, Light, incidence, to_light
from glsldiff.physics.optics import fresnel_transmittance, refract, refracted_cosine, transmitted_cosine
from glsldiff.physics.sh import fibonacci_directions, sh_evaluate
from glsldiff.physics.single import henyey_greenstein
from glsldiff.render.shadows import DepthRenderer

__all__ = ["scattering_frame", "single_scattering_frame", "SAMPLES", "ENV_DIRECTIONS", "GRID", "REACH"]

Array = NDArray[np.float64]
SAMPLES = 16          # nodes along each refracted view ray
ENV_DIRECTIONS = 32   # beams of an environment light
GRID = 48             # heterogeneous material lattice per axis
REACH = 16.0          # view rays followed this many mean free paths at most
_CHUNK = 2048         # vertices per batch (times SAMPLES sample points)


class _Medium:
    """``(sigma_s, sigma_t)`` at points: constants, or a callable ``p -> (sigma_a, sigma_s')``
    sampled on a lattice over ``[lo, hi]`` and interpolated trilinearly."""

    def __init__(self, medium: Any, lo: Array, hi: Array, g: float) -> None:
        if callable(medium):
            pad = 1e-3 * float(np.max(hi - lo))
            self.lo, self.hi = lo - pad, hi + pad
            axes = [np.linspace(self.lo[i], self.hi[i], GRID) for i in range(3)]
            X, Y, Z = np.meshgrid(*axes, indexing="ij")
            sa, ss = medium(np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1))
            sa, ss = np.broadcast_to(sa, (X.size, 3)), np.broadcast_to(ss, (X.size, 3))
            sig_s = ss / (1.0 - g)
            self.grid = np.stack([sig_s, sa + sig_s]).reshape(2, GRID, GRID, GRID, 3)
            self.const = None
        else:
            sa, ss = (np.asarray(x, dtype=np.float64) for x in medium)
            self.const = (ss / (1.0 - g), sa + ss / (1.0 - g))

    @property
    def homogeneous(self) -> bool:
        return self.const is not None

    def __call__(self, p: Array) -> tuple[Array, Array]:
        if self.const is not None:
            return np.broadcast_to(self.const[0], p.shape), np.broadcast_to(self.const[1], p.shape)
        c = ((p - self.lo) / (self.hi - self.lo) * (GRID - 1)).T.clip(0, GRID - 1)
        out = np.empty((2, len(p), 3))
        for a in range(2):
            for ch in range(3):
                out[a, :, ch] = map_coordinates(self.grid[a, ..., ch], c, order=1, mode="nearest")
        return out[0], out[1]


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

    def inside(self, b: int, y: Array, n_y: Array, ell: Array, eta: float
               ) -> tuple[Array, Array, Array, Array]:
        """At entry points ``y`` (normals ``n_y``) of samples a straight distance ``ell``
        inside: the beam's normal irradiance inside ``(M, 3)``, the incidence cosine and the
        refracted cosine ``(M,)``, and the direction towards the source at ``y``."""
        w = self.towards(b, y)
        c = np.maximum(np.einsum("ij,ij->i", n_y, w), 0.0)
        t = np.maximum(refracted_cosine(eta, c), 1e-6)
        share = transmitted_cosine(eta, c) / t                                # F_t c / t
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
        return share[:, None] * E_n, c, t, w


def single_scattering_frame(mesh: Any, vertices: Array, normals: Array, eye: Array, eta: float,
                            lights: Sequence[Light], medium: Any, renderer: DepthRenderer,
                            shadow_map_size: int = 1024, samples: int = SAMPLES, g: float = 0.0) -> Array:
    """``(V, 3)`` single-scattered radiance towards ``eye`` at ``vertices`` (module docstring).

    ``medium``: ``(sigma_a, sigma_s')`` RGB arrays (mm^-1) or a callable of points ``(M, 3)``
    returning both ``(M, 3)``; ``renderer`` renders the lights' depth maps of ``mesh``."""
    return scattering_frame(mesh, vertices, normals, eye, eta, lights, medium, renderer, shadow_map_size,
                            samples, g)[0]


def scattering_frame(mesh: Any, vertices: Array, normals: Array, eye: Array, eta: float,
                     lights: Sequence[Light], medium: Any, renderer: DepthRenderer,
                     shadow_map_size: int = 1024, samples: int = SAMPLES, g: float = 0.0,
                     fluence: Callable[[Array], Array] | None = None) -> tuple[Array, Array]:
    """``(single, gathered)``, each ``(V, 3)``: :func:`single_scattering_frame`, and with
    ``fluence`` (a callable of points ``(M, 3)`` returning the collided fluence ``(M, 3)``) the
    light it scatters once more towards the eye along the same refracted view rays, ``F_t(mu_o) /
    eta^2 sum_k W_k sigma_s(x_k) e^{-tau_o(x_k)} phi(x_k) / (4 pi)`` (isotropic: the transport
    split's gather, :mod:`glsldiff.physics.split`); zeros without it."""
    v = np.asarray(vertices, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    out = np.zeros((len(v), 3))
    gathered = np.zeros((len(v), 3))
    if len(v) == 0 or (not lights and fluence is None):
        return out, gathered
    mv = np.asarray(mesh.vertices, dtype=np.float64)
    med = _Medium(medium, mv.min(axis=0), mv.max(axis=0), g)
    w_o = np.asarray(eye, dtype=np.float64) - v
    w_o /= np.linalg.norm(w_o, axis=1, keepdims=True).clip(1e-300)
    mu_o = np.einsum("ij,ij->i", n, w_o)
    idx = np.flatnonzero(mu_o > 0.0)
    if idx.size == 0:
        return out, gathered
    beams = [_Beams(lt, renderer, shadow_map_size) for lt in lights]
    d, _ = refract(-w_o[idx], n[idx], 1.0 / eta)                             # view ray, propagating in
    _, st0 = med(v[idx])
    lam = np.maximum(st0.min(axis=1), 1e-12)                                 # mm^-1; a clear channel: uniform
    h = 1e-6 * float(np.ptp(v, axis=0).max())
    S, _ = first_hits(mesh, v[idx] + h * d, d, t_max=float(REACH / lam.min()))
    S = np.minimum(S + h, REACH / lam)                                       # no hit: the reach
    x_gl, w_gl = np.polynomial.legendre.leggauss(samples)
    u, wu = 0.5 * (x_gl + 1.0), 0.5 * w_gl
    f_o = np.asarray(fresnel_transmittance(eta, mu_o[idx])) / eta**2
    for a in range(0, len(idx), _CHUNK):
        sl = slice(a, a + _CHUNK)
        m = len(idx[sl])
        span = -np.expm1(-lam[sl] * S[sl])                                   # 1 - e^{-lam S}
        s = -np.log1p(-u[None, :] * span[:, None]) / lam[sl, None]            # (m, K)
        W = wu[None, :] * span[:, None] / (lam[sl, None] * (1.0 - u[None, :] * span[:, None]))
        x = (v[idx[sl]][:, None, :] + s[..., None] * d[sl][:, None, :]).reshape(-1, 3)
        sig_s, sig_t = med(x)
        sig_s, sig_t = sig_s.reshape(m, samples, 3), sig_t.reshape(m, samples, 3)
        if med.homogeneous:
            tau_o = s[..., None] * sig_t
        else:
            st_all = np.concatenate([st0[sl][:, None, :], sig_t], axis=1)
            s_all = np.concatenate([np.zeros((m, 1)), s], axis=1)
            tau_o = np.cumsum(0.5 * (st_all[:, 1:] + st_all[:, :-1]) * np.diff(s_all, axis=1)[..., None], axis=1)
        incoming = np.zeros((m * samples, 3))
        up = -np.repeat(d[sl], samples, axis=0)                               # view propagation, to the surface
        st_x = sig_t.reshape(-1, 3)
        for bl in beams:
            for b in range(len(bl)):
                incoming += _beam(bl, b, x, st_x, up, mesh, med, eta, g)
        weight = W[..., None] * sig_s * np.exp(-tau_o)
        L = (weight * incoming.reshape(m, samples, 3)).sum(axis=1)
        out[idx[sl]] = f_o[sl, None] * L
        if fluence is not None:
            phi = np.maximum(fluence(x), 0.0).reshape(m, samples, 3)
            gathered[idx[sl]] = f_o[sl, None] * (weight * phi).sum(axis=1) / (4.0 * np.pi)
    return out, gathered


def _beam(bl: _Beams, b: int, x: Array, st_x: Array, up: Array, mesh: Any, med: _Medium, eta: float,
          g: float) -> Array:
    """Phase-weighted, attenuated normal irradiance ``(M, 3)`` of beam ``b`` at sample points ``x``
    (``st_x``: the extinction there)."""
    res = np.zeros((len(x), 3))
    ell = bl.entry(b, x)
    w = bl.towards(b, x)
    ok = np.flatnonzero(np.isfinite(ell))
    if ok.size == 0:
        return res
    x, w, ell = x[ok], w[ok], ell[ok]
    y = x + ell[:, None] * w
    n_y = bl.entry_normals(b, y)
    miss = np.flatnonzero(~np.isfinite(n_y[:, 0]))
    if miss.size:                           # no face stored there (not expected: same coverage)
        n_y[miss] = closest_points(mesh, y[miss], exact=False)[3]
    I, c, t, w_y = bl.inside(b, y, n_y, ell, eta)
    lit = c > 0.0
    path = ell * c / t                                                       # Jensen's s'
    T, _ = refract(-w_y, n_y, 1.0 / eta)                                     # refracted propagation
    phase = henyey_greenstein(np.einsum("ij,ij->i", T, up[ok]), g)
    if med.homogeneous:
        tau = path[:, None] * med.const[1]
    else:
        s0 = st_x[ok]
        _, s1 = med(0.5 * (x + y))
        _, s2 = med(y)
        tau = path[:, None] * (s0 + 4.0 * s1 + s2) / 6.0
    res[ok] = np.where(lit[:, None], (phase[:, None] * I) * np.exp(-tau), 0.0)
    return res
