"""Pass 1 of the renderer: light transmitted into the object at its boundary nodes.

Wang et al. 2008, section 5: before the diffusion pass, the incident light at every boundary
node is computed "using shadow buffers for directional and point lights, and ambient
occlusion or precomputed radiance transfer for environment lighting". This module returns,
per boundary node x with outward unit normal n, the transmitted irradiance (in the units of
``DirectionalLight.irradiance``, of ``PointLight.intensity`` per mm^2, or of the environment's
radiance times sr)

    E_t(x) = sum over lights of  L_i(w) (n . w)^+ F_t(eta, n . w) V(x, w)      (dw integrated
                                                                              for environments)

with w the unit direction from x towards the light, F_t = 1 - Fresnel reflectance of the smooth
interface (:func:`glsldiff.physics.optics.fresnel_transmittance`, eta = n_inside / n_outside) and V the
visibility. This is the source q of the boundary condition (Wang et al. eq. 2).

Lights
------
:class:`DirectionalLight`
    ``irradiance`` E0 on a surface facing the light: L cos dw = E0 (n . w)^+.
:class:`PointLight`
    Radiant ``intensity`` I: irradiance I (n . w)^+ / r^2, r the distance in mm.
:class:`SpotLight`
    A point light times a smooth cone factor: 1 inside ``falloff_deg`` of the axis, 0 beyond
    ``cone_deg``, and the smoothstep ``t^2 (3 - 2 t)`` in between, with
    ``t = (cos a - cos cone) / (cos falloff - cos cone)`` and a the angle from the axis.
:class:`ProjectorLight`
    A pinhole projector: a point light whose radiant intensity towards x is ``intensity``
    times its ``image`` sampled where x projects (:func:`projector_factor`): irradiance
    ``I img(u, v) (n . w)^+ / r^2``, 0 outside the image's frustum and behind the projector.
:class:`EnvironmentLight`
    A lat-long radiance map (see below).

Shadow maps (directional, point and spot lights)
------------------------------------------------
The closed mesh is rendered from the light with moderngl into an RG32F colour target, with
``glBlendEquation(GL_MIN)`` instead of a depth buffer: channel r keeps the nearest surface
facing the light, channel g the nearest surface facing away (``gl_FrontFacing``; the mesh is
outward oriented). Stored depths are world distances in mm, computed per fragment from the
interpolated position, so they are exact up to float32: along the light direction for a
directional light (orthographic view fitted to the mesh's bounding sphere), Euclidean distance
from the light for point and spot lights (a spot light up to ``cone_deg`` = 60 uses one
perspective view of its cone, wider spots and point lights six 90-degree cube faces packed
3 x 2 in one texture). A projector is shadowed as the hard-edged spot light whose cone
circumscribes its frustum (:attr:`ProjectorLight.spot`). Every shadow map is
``shadow_map_size`` squared per view.

The map is read back and each point is compared in numpy against the *midpoint*
``(front + back) / 2`` of the first object along the light ray (Woo's midpoint shadow map,
possible because the mesh is closed and outward oriented). A point on the lit surface then
sits half the local thickness in front of the stored value and a point on the far side half
the thickness behind it, so surface nodes and nodes slightly inside the surface (less than half
the local thickness) are classified without shadow acne. On top of that a slope-scaled bias
``texel * (BIAS_TEXELS + BIAS_SLOPE * tan(theta))`` (tan clipped at ``MAX_BIAS_TAN``, theta the
angle between the normal and the light; ``tan = 1`` without normals, 0 for points facing away,
which lie on the far surface) lets lit points win across the footprint of the 2 x 2 filter.
The lookup is a bilinear percentage-closer filter over 2 x 2 texels, so visibility is
fractional (in [0, 1]) along shadow edges. Limits: where the object is
thinner along the ray than about twice the bias (grazing light near the terminator, thin
sheets) the classification may go either way; there n . w is small anyway. Points outside the
shadow map (outside the mesh's footprint, behind a spot light) count as lit.

Environment light
-----------------
The map is projected onto real orthonormal spherical harmonics up to band ``order`` (9
coefficients for 2), each pixel taken as constant radiance over its exact solid angle
(:func:`sh_project`).
The unshadowed transmitted irradiance uses the Funk-Hecke theorem: the kernel
h(t) = t^+ F_t(eta, t) depends only on t = n . w, so

    E_sh(n) = sum_lm lambda_l c_lm Y_lm(n),   lambda_l = 2 pi int_0^1 t F_t(eta, t) P_l(t) dt,

with lambda_l computed by adaptive quadrature (:func:`transfer_coefficients`). The Fresnel
factor is therefore included *exactly* in the kernel; the only approximation is the band
limit of the radiance (the classic irradiance-map error, a few percent for order 2 on
natural maps, more for a small bright sun in the map, which belongs in a DirectionalLight;
exact for maps that are themselves band limited; negative ringing is clipped to 0). With eta = 1 the lambdas are
pi, 2 pi / 3, pi / 4 (Ramamoorthi and Hanrahan 2001).

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

GL objects (program, buffers, texture, framebuffer) are created per call and released in a
``finally`` block; the caller's framebuffer and enable flags are restored and the blend
equation is set back to GL's default ``FUNC_ADD`` (moderngl cannot read the previous one; the
blend function is not touched). Units: mm, radiance and irradiance in the caller's units.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Any, Sequence, Union

import moderngl
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import integrate

from glsldiff import gl
from glsldiff.core.checks import boolean as _bool
from glsldiff.core.checks import integer as _integer
from glsldiff.core.checks import radiance_map as _radiance_map
from glsldiff.core.checks import real as _real
from glsldiff.core.checks import rgb as _rgb
from glsldiff.core.checks import unit_vector as _unit
from glsldiff.core.checks import vector3 as _vector
from glsldiff.core.errors import InputError
from glsldiff.physics.optics import fresnel_transmittance

__all__ = [
    "DirectionalLight", "PointLight", "SpotLight", "ProjectorLight", "EnvironmentLight", "Light",
    "casts_shadows", "incident_light", "visibility", "spot_factor", "projector_factor",
    "sh_basis", "sh_project", "sh_evaluate", "sh_irradiance", "transfer_coefficients",
    "fibonacci_directions", "latlong_directions",
    "BIAS_TEXELS", "BIAS_SLOPE", "MAX_BIAS_TAN", "ENV_SHADOW_MAP_MAX", "MAX_SH_ORDER",
]

BIAS_TEXELS = 1.0          # constant part of the depth bias, in shadow-map texels (world size)
BIAS_SLOPE = 1.5           # slope part: texels per unit tan(angle between normal and light)
MAX_BIAS_TAN = 8.0         # tan clipped here (about 83 degrees)
ENV_SHADOW_MAP_MAX = 512   # shadow maps of environment directions are at most this size
MAX_SH_ORDER = 8
SPOT_SINGLE_VIEW_MAX_DEG = 60.0  # wider spots use a cube of six views
MAX_DIRECTIONS = 4096
_FAR = 1.0e30              # clear value of the shadow map (no surface)
_FIT = 1.02                # orthographic window: bounding radius times this
_SHADER_DEFINES = {"LIGHT_FAR": "1.0e30"}


# ---------------------------------------------------------------------------------------
# lights
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DirectionalLight:
    """Distant light (sun).

    Parameters
    ----------
    direction
        ``(3,)`` direction from the object *towards* the light (normalised on construction).
    irradiance
        ``(3,)`` RGB irradiance on a surface facing the light (a scalar means grey).
    shadows
        Whether :func:`incident_light` renders a shadow map for it.
    """

    direction: tuple[float, float, float]
    irradiance: tuple[float, float, float]
    shadows: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "direction", _unit(self.direction, "DirectionalLight.direction"))
        object.__setattr__(self, "irradiance", _rgb(self.irradiance, "DirectionalLight.irradiance"))
        object.__setattr__(self, "shadows", _bool(self.shadows, "DirectionalLight.shadows"))


@dataclass(frozen=True)
class PointLight:
    """Isotropic point light.

    Parameters
    ----------
    position
        ``(3,)`` mm.
    intensity
        ``(3,)`` RGB radiant intensity: irradiance ``I cos / r^2`` at distance r mm.
    shadows
        Whether :func:`incident_light` renders a (cube) shadow map for it.
    """

    position: tuple[float, float, float]
    intensity: tuple[float, float, float]
    shadows: bool = True

    def __post_init__(self) -> None:
        pos = _vector(self.position, "PointLight.position")
        object.__setattr__(self, "position", tuple(float(x) for x in pos))
        object.__setattr__(self, "intensity", _rgb(self.intensity, "PointLight.intensity"))
        object.__setattr__(self, "shadows", _bool(self.shadows, "PointLight.shadows"))


@dataclass(frozen=True)
class SpotLight:
    """Point light restricted to a cone with a smooth edge (see the module docstring).

    Parameters
    ----------
    position
        ``(3,)`` mm.
    direction
        ``(3,)`` spot axis from the light *into* the scene (normalised on construction).
    intensity
        ``(3,)`` RGB radiant intensity on the axis.
    cone_deg
        Half angle of the full cutoff, in (0, 180).
    falloff_deg
        Half angle where the smooth falloff starts, in [0, cone_deg]; equal to ``cone_deg``
        gives a hard edge.
    shadows
        Whether :func:`incident_light` renders a shadow map for it.
    """

    position: tuple[float, float, float]
    direction: tuple[float, float, float]
    intensity: tuple[float, float, float]
    cone_deg: float = 30.0
    falloff_deg: float = 25.0
    shadows: bool = True

    def __post_init__(self) -> None:
        pos = _vector(self.position, "SpotLight.position")
        object.__setattr__(self, "position", tuple(float(x) for x in pos))
        object.__setattr__(self, "direction", _unit(self.direction, "SpotLight.direction"))
        object.__setattr__(self, "intensity", _rgb(self.intensity, "SpotLight.intensity"))
        cone = _real(self.cone_deg, "SpotLight.cone_deg", 0.0, 180.0, lo_open=True, hi_open=True)
        fall = _real(self.falloff_deg, "SpotLight.falloff_deg", 0.0, 180.0)
        if fall > cone:
            raise InputError(f"SpotLight.falloff_deg={fall:g} must not exceed cone_deg={cone:g} "
                             "(the falloff starts inside the cone)")
        object.__setattr__(self, "cone_deg", cone)
        object.__setattr__(self, "falloff_deg", fall)
        object.__setattr__(self, "shadows", _bool(self.shadows, "SpotLight.shadows"))


@dataclass(frozen=True, eq=False)
class ProjectorLight:
    """Pinhole projector casting an RGB image (the capture setup of Wang et al. 2008, sec. 4.1).

    Parameters
    ----------
    position
        ``(3,)`` centre of projection, mm.
    direction
        ``(3,)`` optical axis from the projector *into* the scene (normalised on construction).
    image
        ``(H, W, 3)`` float radiance-scale map, finite and >= 0, as seen from the projector:
        row 0 is the top (towards ``up``), column 0 the projector's left. Stored as a
        read-only float64 copy.
    intensity
        ``(3,)`` RGB radiant intensity of a white (1.0) pixel: irradiance
        ``I img(u, v) cos / r^2`` at distance r mm.
    up
        ``(3,)`` the image's up direction (orthogonalised against ``direction``; normalised
        on construction); must not be parallel to ``direction``.
    fov_deg
        Vertical full field of view in degrees, in (0, 180); the horizontal one follows
        from the aspect ratio W / H.
    shadows
        Whether :func:`incident_light` renders a shadow map for it (that of :attr:`spot`).
    """

    position: tuple[float, float, float]
    direction: tuple[float, float, float]
    image: NDArray[np.float64]
    intensity: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_deg: float = 30.0
    shadows: bool = True

    def __post_init__(self) -> None:
        pos = _vector(self.position, "ProjectorLight.position")
        object.__setattr__(self, "position", tuple(float(x) for x in pos))
        fwd = _unit(self.direction, "ProjectorLight.direction")
        up = _unit(self.up, "ProjectorLight.up")
        if np.linalg.norm(np.cross(fwd, up)) < 1e-6:
            raise InputError(f"ProjectorLight.up={self.up!r} is parallel to direction={self.direction!r}; "
                             "give an up vector across the optical axis")
        object.__setattr__(self, "direction", fwd)
        object.__setattr__(self, "up", up)
        img = _radiance_map(self.image, "ProjectorLight.image")
        img.setflags(write=False)
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "intensity", _rgb(self.intensity, "ProjectorLight.intensity"))
        object.__setattr__(self, "fov_deg", _real(self.fov_deg, "ProjectorLight.fov_deg", 0.0, 180.0,
                                                  lo_open=True, hi_open=True))
        object.__setattr__(self, "shadows", _bool(self.shadows, "ProjectorLight.shadows"))

    @property
    def aspect(self) -> float:
        """Image width over height."""
        return self.image.shape[1] / self.image.shape[0]

    @cached_property
    def frame(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Unit ``right, up, forward`` of the projector (right-handed camera frame)."""
        fwd = np.asarray(self.direction)
        right = np.cross(fwd, self.up)
        right /= np.linalg.norm(right)
        return right, np.cross(right, fwd), fwd

    @cached_property
    def spot(self) -> SpotLight:
        """The hard-edged spot light whose cone circumscribes the frustum (for shadow maps)."""
        tan_half = math.tan(math.radians(self.fov_deg) / 2.0)
        cone = math.degrees(math.atan(tan_half * math.hypot(1.0, self.aspect)))
        return SpotLight(self.position, self.direction, self.intensity, cone_deg=cone, falloff_deg=cone,
                         shadows=self.shadows)


@dataclass(frozen=True, eq=False)
class EnvironmentLight:
    """Distant radiance from every direction: a lat-long (equirectangular) map.

    Parameters
    ----------
    image
        ``(H, W, 3)`` float radiance, finite and >= 0. Row 0 is the zenith (+z), row H - 1
        the nadir; column u = 0 is azimuth -pi and azimuth grows with u (u = 0.5 is +x,
        u = 0.75 is +y). Stored as a read-only float64 copy.
    scale
        Multiplies the radiance.
    order
        Spherical-harmonics band limit (``(order + 1)^2`` coefficients), 0 to 8.
    visibility
        Whether to include per-node visibility (ambient occlusion with ``directions``
        shadow maps); otherwise the surface is treated as unoccluded.
    directions
        Number of visibility directions (Fibonacci sphere), 1 to 4096.
    """

    image: NDArray[np.float64]
    scale: float = 1.0
    order: int = 2
    visibility: bool = True
    directions: int = 64

    def __post_init__(self) -> None:
        img = _radiance_map(self.image, "EnvironmentLight.image")
        img.setflags(write=False)
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "scale", _real(self.scale, "EnvironmentLight.scale", 0.0, math.inf,
                                                hi_open=True))
        object.__setattr__(self, "order", _integer(self.order, "EnvironmentLight.order", 0, MAX_SH_ORDER))
        object.__setattr__(self, "visibility", _bool(self.visibility, "EnvironmentLight.visibility"))
        object.__setattr__(self, "directions", _integer(self.directions, "EnvironmentLight.directions",
                                                        1, MAX_DIRECTIONS))

    @cached_property
    def sh(self) -> NDArray[np.float64]:
        """``((order + 1)^2, 3)`` SH coefficients of ``scale * image`` (computed once)."""
        return self.scale * sh_project(self.image, self.order)


Light = Union[DirectionalLight, PointLight, SpotLight, ProjectorLight, EnvironmentLight]
_KINDS = {DirectionalLight: "directional", PointLight: "point", SpotLight: "spot",
          ProjectorLight: "projector", EnvironmentLight: "environment"}
_KIND_NAMES = "a DirectionalLight, PointLight, SpotLight, ProjectorLight or EnvironmentLight"


def casts_shadows(light: Light) -> bool:
    """Whether :func:`incident_light` needs shadow maps for ``light``."""
    if isinstance(light, EnvironmentLight):
        return light.visibility
    if isinstance(light, (DirectionalLight, PointLight, SpotLight, ProjectorLight)):
        return light.shadows
    raise InputError(f"light must be {_KIND_NAMES}, got {type(light).__name__}")


def spot_factor(light: SpotLight, cos_axis: ArrayLike) -> NDArray[np.float64]:
    """Cone factor of a spot light for the cosine of the angle from its axis (see module doc)."""
    c = np.asarray(cos_axis, dtype=np.float64)
    c_cone = math.cos(math.radians(light.cone_deg))
    c_fall = math.cos(math.radians(light.falloff_deg))
    if c_fall - c_cone <= 1e-12:
        return (c > c_cone).astype(np.float64)
    t = np.clip((c - c_cone) / (c_fall - c_cone), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def projector_factor(light: ProjectorLight, points: ArrayLike) -> NDArray[np.float64]:
    """Image factor ``(N, 3)`` of a projector at ``points`` (N, 3) mm.

    Each point is projected through the pinhole (vertical half angle ``fov_deg / 2``, aspect
    W / H; image row 0 towards ``up``, column 0 on the projector's left) and the image is
    sampled bilinearly (pixel centres at half-integer positions, clamped at the border);
    0 outside the frustum and behind the projector. The irradiance on a surface is
    ``intensity * factor * (n . w)^+ / r^2``.
    """
    if not isinstance(light, ProjectorLight):
        raise InputError(f"light must be a ProjectorLight, got {type(light).__name__}")
    p = _points(points)
    img = light.image
    H, W, _ = img.shape
    right, up, fwd = light.frame
    d = p - np.asarray(light.position)
    z = d @ fwd
    ok = z > 0.0
    tan_half = math.tan(math.radians(light.fov_deg) / 2.0)
    zs = np.where(ok, z, 1.0) * tan_half
    nx, ny = (d @ right) / (zs * light.aspect), (d @ up) / zs
    ok &= (np.abs(nx) <= 1.0) & (np.abs(ny) <= 1.0)
    fx = (nx + 1.0) * 0.5 * W - 0.5
    fy = (1.0 - ny) * 0.5 * H - 0.5
    x0, y0 = np.floor(fx), np.floor(fy)
    wx, wy = (fx - x0)[:, None], (fy - y0)[:, None]
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    xa, xb = np.clip(x0, 0, W - 1), np.clip(x0 + 1, 0, W - 1)
    ya, yb = np.clip(y0, 0, H - 1), np.clip(y0 + 1, 0, H - 1)
    out = ((1.0 - wy) * ((1.0 - wx) * img[ya, xa] + wx * img[ya, xb])
           + wy * ((1.0 - wx) * img[yb, xa] + wx * img[yb, xb]))
    return np.where(ok[:, None], out, 0.0)


# ---------------------------------------------------------------------------------------
# spherical harmonics
# ---------------------------------------------------------------------------------------
def _sh_norm(order: int) -> NDArray[np.float64]:
    """Normalisation sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!) indexed [l, m], m >= 0."""
    out = np.zeros((order + 1, order + 1))
    for l in range(order + 1):
        for m in range(l + 1):
            out[l, m] = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - m) / math.factorial(l + m))
    return out


def _legendre(order: int, z: NDArray[np.float64]) -> NDArray[np.float64]:
    """Associated Legendre P_l^m(z), m >= 0, without the Condon-Shortley phase: ``[l, m, ...]``."""
    z = np.asarray(z, dtype=np.float64)
    s = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    P = np.zeros((order + 1, order + 1) + z.shape)
    P[0, 0] = 1.0
    for m in range(order + 1):
        if m > 0:
            P[m, m] = (2 * m - 1) * s * P[m - 1, m - 1]
        if m + 1 <= order:
            P[m + 1, m] = (2 * m + 1) * z * P[m, m]
        for l in range(m + 2, order + 1):
            P[l, m] = ((2 * l - 1) * z * P[l - 1, m] - (l + m - 1) * P[l - 2, m]) / (l - m)
    return P


def _azimuthal(order: int, phi: NDArray[np.float64]) -> NDArray[np.float64]:
    """``[order + m, ...]``: sqrt2 cos(m phi) for m > 0, 1 for m = 0, sqrt2 sin(|m| phi) for m < 0."""
    phi = np.asarray(phi, dtype=np.float64)
    T = np.empty((2 * order + 1,) + phi.shape)
    for m in range(-order, order + 1):
        if m > 0:
            T[order + m] = math.sqrt(2.0) * np.cos(m * phi)
        elif m < 0:
            T[order + m] = math.sqrt(2.0) * np.sin(-m * phi)
        else:
            T[order] = 1.0
    return T


def _check_order(order: Any) -> int:
    return _integer(order, "order", 0, MAX_SH_ORDER)


def sh_basis(directions: ArrayLike, order: int = 2) -> NDArray[np.float64]:
    """Real orthonormal SH ``(N, (order + 1)^2)`` at unit ``directions`` (N, 3).

    Index ``k = l (l + 1) + m``; ``Y_1,-1, Y_10, Y_11`` are ``sqrt(3 / 4 pi) (y, z, x)``.
    """
    order = _check_order(order)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    P = _legendre(order, d[:, 2])
    T = _azimuthal(order, np.arctan2(d[:, 1], d[:, 0]))
    K = _sh_norm(order)
    out = np.empty((len(d), (order + 1) ** 2))
    for l in range(order + 1):
        for m in range(-l, l + 1):
            out[:, l * (l + 1) + m] = K[l, abs(m)] * P[l, abs(m)] * T[order + m]
    return out


def latlong_directions(height: int, width: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit directions ``(H, W, 3)`` of lat-long pixel centres and their solid angles ``(H, W)``
    (exact per pixel: ``(cos theta_top - cos theta_bottom) * 2 pi / W``; they sum to 4 pi)."""
    theta_edges = np.linspace(0.0, math.pi, height + 1)
    theta = 0.5 * (theta_edges[:-1] + theta_edges[1:])
    phi = -math.pi + (np.arange(width) + 0.5) * (2.0 * math.pi / width)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    d = np.stack([st * np.cos(phi)[None], st * np.sin(phi)[None], np.broadcast_to(ct, (height, width))], -1)
    band = np.cos(theta_edges[:-1]) - np.cos(theta_edges[1:])
    return d, np.repeat(band[:, None] * (2.0 * math.pi / width), width, axis=1)


def sh_project(image: ArrayLike, order: int = 2) -> NDArray[np.float64]:
    """SH coefficients ``((order + 1)^2, 3)`` of a lat-long radiance map ``(H, W, 3)``.

    Each pixel is taken as constant radiance over its solid angle and the basis is integrated
    over the pixel (exactly in azimuth, 8-point Gauss-Legendre in polar angle), so a constant
    map projects onto band 0 alone to rounding (see :func:`latlong_directions` for the map
    convention). Separable in rows and columns: memory stays O(H W) for large maps.
    """
    order = _check_order(order)
    img = _radiance_map(image, "image")
    H, W, _ = img.shape
    # pixels are taken as constant over their area; the basis is integrated over each pixel:
    # exactly in azimuth, by 8-point Gauss-Legendre in polar angle (weight sin theta) per row
    phi_edges = -math.pi + np.arange(W + 1) * (2.0 * math.pi / W)
    T = np.empty((2 * order + 1, W))
    T[order] = np.diff(phi_edges)
    for m in range(1, order + 1):
        T[order + m] = math.sqrt(2.0) * np.diff(np.sin(m * phi_edges)) / m
        T[order - m] = -math.sqrt(2.0) * np.diff(np.cos(m * phi_edges)) / m
    F = np.einsum("hwc,mw->hmc", img, T)                                  # (H, 2o+1, 3)
    gx, gw = np.polynomial.legendre.leggauss(8)
    edges = np.linspace(0.0, math.pi, H + 1)
    half = 0.5 * np.diff(edges)
    theta = (edges[:-1] + half)[:, None] + half[:, None] * gx[None, :]   # (H, 8)
    wt = half[:, None] * gw[None, :] * np.sin(theta)                     # (H, 8)
    P = _legendre(order, np.cos(theta))                                   # (o+1, o+1, H, 8)
    K = _sh_norm(order)
    out = np.empty(((order + 1) ** 2, 3))
    for l in range(order + 1):
        for m in range(-l, l + 1):
            w = K[l, abs(m)] * (P[l, abs(m)] * wt).sum(axis=1)            # (H,)
            out[l * (l + 1) + m] = w @ F[:, order + m]
    return out


def _order_of(coeffs: NDArray[np.float64]) -> int:
    k = coeffs.shape[0]
    order = int(round(math.sqrt(k))) - 1
    if (order + 1) ** 2 != k or order > MAX_SH_ORDER:
        raise InputError(f"coeffs must have (order + 1)^2 rows (1, 4, 9, ...), got {k}")
    return order


def _coeffs(coeffs: ArrayLike) -> NDArray[np.float64]:
    c = np.asarray(coeffs, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 3 or not np.isfinite(c).all():
        raise InputError(f"coeffs must be a finite ((order + 1)^2, 3) array, got shape {c.shape}")
    return c


def sh_evaluate(coeffs: ArrayLike, directions: ArrayLike) -> NDArray[np.float64]:
    """Band-limited radiance ``(N, 3)`` of SH ``coeffs`` in unit ``directions`` (N, 3)."""
    c = _coeffs(coeffs)
    return sh_basis(directions, _order_of(c)) @ c


@lru_cache(maxsize=64)
def _transfer(order: int, eta: float | None) -> tuple[float, ...]:
    from numpy.polynomial import legendre as leg

    out = []
    for l in range(order + 1):
        Pl = leg.Legendre.basis(l)
        if eta is None or eta == 1.0:
            f = lambda t, Pl=Pl: t * Pl(t)  # noqa: E731
        else:
            f = lambda t, Pl=Pl: t * float(fresnel_transmittance(eta, min(max(t, 0.0), 1.0))) * Pl(t)  # noqa: E731
        pts = None
        if eta is not None and eta < 1.0:  # total internal reflection beyond the critical angle
            pts = [math.sqrt(max(0.0, 1.0 - eta * eta))]
        val = integrate.quad(f, 0.0, 1.0, points=pts, epsabs=1e-13, epsrel=1e-11, limit=200)[0]
        out.append(2.0 * math.pi * val)
    return tuple(out)


def transfer_coefficients(order: int = 2, eta: float | None = None) -> NDArray[np.float64]:
    """Funk-Hecke eigenvalues ``lambda_l = 2 pi int_0^1 t F_t(eta, t) P_l(t) dt``, l = 0..order.

    ``eta=None`` (or 1) drops the Fresnel factor: pi, 2 pi / 3, pi / 4, 0, -pi / 24, ...
    """
    order = _check_order(order)
    if eta is not None:
        eta = _real(eta, "eta", 0.0, math.inf, lo_open=True, hi_open=True)
    return np.asarray(_transfer(order, eta))


def sh_irradiance(coeffs: ArrayLike, normals: ArrayLike, eta: float | None = None) -> NDArray[np.float64]:
    """Unshadowed irradiance ``(N, 3)`` on surfaces with unit ``normals`` (N, 3) under SH radiance.

    ``eta=None``: plain irradiance int L (n.w)^+ dw; with ``eta``: the transmitted irradiance
    int L (n.w)^+ F_t(eta, n.w) dw (Fresnel factor folded exactly into the zonal kernel).
    Negative values from SH ringing are clipped to 0.
    """
    c = _coeffs(coeffs)
    order = _order_of(c)
    lam = transfer_coefficients(order, eta)
    lam_k = np.concatenate([np.full(2 * l + 1, lam[l]) for l in range(order + 1)])
    return np.maximum(sh_basis(normals, order) @ (lam_k[:, None] * c), 0.0)


def fibonacci_directions(n: int) -> NDArray[np.float64]:
    """``n`` nearly uniformly spread unit directions ``(n, 3)`` (Fibonacci sphere)."""
    n = _integer(n, "directions", 1, MAX_DIRECTIONS)
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    s = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


# ---------------------------------------------------------------------------------------
# shadow maps
# ---------------------------------------------------------------------------------------
def _frame(forward: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``right, up`` completing ``forward`` to a right-handed camera frame (back = -forward)."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(forward, ref)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return right, up


@dataclass(frozen=True)
class _View:
    """One light view, coordinates relative to the mesh's bounding-sphere centre (mm)."""

    eye: NDArray[np.float64]
    forward: NDArray[np.float64]
    right: NDArray[np.float64]
    up: NDArray[np.float64]
    near: float
    far: float
    half: float            # orthographic: half window (mm); perspective: tan(half angle)
    ortho: bool
    tile: tuple[int, int]  # (column, row) in the atlas

    def matrix(self) -> NDArray[np.float64]:
        view = np.eye(4)
        view[0, :3], view[1, :3], view[2, :3] = self.right, self.up, -self.forward
        view[:3, 3] = -view[:3, :3] @ self.eye
        n, f = self.near, self.far
        proj = np.zeros((4, 4))
        if self.ortho:
            proj[0, 0] = proj[1, 1] = 1.0 / self.half
            proj[2, 2] = -2.0 / (f - n)
            proj[2, 3] = -(f + n) / (f - n)
            proj[3, 3] = 1.0
        else:
            proj[0, 0] = proj[1, 1] = 1.0 / self.half
            proj[2, 2] = -(f + n) / (f - n)
            proj[2, 3] = -2.0 * f * n / (f - n)
            proj[3, 2] = -1.0
        return proj @ view


@dataclass
class _ShadowMap:
    """Read-back midpoint depths of a set of views packed in an atlas of ``size``-texel tiles."""

    views: list[_View]
    size: int
    mid: NDArray[np.float32] = field(repr=False)  # (rows * size, cols * size)

    @property
    def label(self) -> str:
        s = f"{self.size}x{self.size}"
        return s if len(self.views) == 1 else f"{len(self.views)} x {s} (cube)"

    def lookup(self, p: NDArray[np.float64], to_light: NDArray[np.float64],
               normals: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """Visibility in [0, 1] of points ``p`` (relative to the centre), 2 x 2 PCF."""
        n_pts = len(p)
        vis = np.ones(n_pts)
        if n_pts == 0:
            return vis
        if len(self.views) == 1:
            which = np.zeros(n_pts, dtype=np.int64)
        else:  # cube: the face of the major axis of p - eye
            d = p - self.views[0].eye
            ax = np.argmax(np.abs(d), axis=1)
            neg = d[np.arange(n_pts), ax] < 0
            which = 2 * ax + neg
        if normals is None:
            tan = np.ones(n_pts)
        else:  # points facing away lie on the far surface: no slope allowance for them
            c = np.einsum("ij,ij->i", normals, to_light)
            cc = np.clip(c, 1e-6, 1.0)
            tan = np.where(c > 0, np.minimum(np.sqrt(np.maximum(1.0 - cc * cc, 0.0)) / cc, MAX_BIAS_TAN), 0.0)
        S = self.size
        for k, v in enumerate(self.views):
            sel = np.flatnonzero(which == k)
            if sel.size == 0:
                continue
            d = p[sel] - v.eye
            x, y, z = d @ v.right, d @ v.up, d @ v.forward
            if v.ortho:
                depth = z
                scale = np.full(sel.size, v.half)
                ok = np.ones(sel.size, dtype=bool)
            else:
                depth = np.linalg.norm(d, axis=1)
                ok = z > 1e-9 * max(v.far, 1.0)
                scale = np.where(ok, z, 1.0) * v.half
            nx, ny = x / scale, y / scale
            ok &= (np.abs(nx) <= 1.0) & (np.abs(ny) <= 1.0)
            texel = 2.0 * scale / S
            bias = texel * (BIAS_TEXELS + BIAS_SLOPE * tan[sel])
            fx = (nx + 1.0) * 0.5 * S - 0.5
            fy = (ny + 1.0) * 0.5 * S - 0.5
            x0, y0 = np.floor(fx), np.floor(fy)
            wx, wy = fx - x0, fy - y0
            x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
            acc = np.zeros(sel.size)
            ox, oy = v.tile[0] * S, v.tile[1] * S
            for dx, dy, w in ((0, 0, (1 - wx) * (1 - wy)), (1, 0, wx * (1 - wy)),
                              (0, 1, (1 - wx) * wy), (1, 1, wx * wy)):
                ix = np.clip(x0 + dx, 0, S - 1) + ox
                iy = np.clip(y0 + dy, 0, S - 1) + oy
                acc += w * (depth <= self.mid[iy, ix] + bias)
            vis[sel] = np.where(ok, acc, 1.0)
        vis = np.clip(vis, 0.0, 1.0)
        vis[vis > 1.0 - 1e-9] = 1.0  # bilinear weights sum to 1 only up to rounding
        vis[vis < 1e-9] = 0.0
        return vis


class _DepthRenderer:
    """GL resources to render a mesh's front/back depth from lights; release with ``release``
    (or use as a context manager). Coordinates are relative to the bounding-sphere centre."""

    def __init__(self, ctx: moderngl.Context, mesh: Any) -> None:
        self.ctx = ctx
        v = np.asarray(mesh.vertices, dtype=np.float64)
        f = np.asarray(mesh.faces, dtype=np.int64)
        lo, hi = v.min(axis=0), v.max(axis=0)
        self.centre = 0.5 * (lo + hi)
        self.radius = max(float(np.linalg.norm(v - self.centre, axis=1).max()), 1e-9)
        self._objects: list[Any] = []
        self._target: tuple[tuple[int, int], moderngl.Texture, moderngl.Framebuffer] | None = None
        gl.make_current(ctx)
        try:
            self.prog = self._keep(gl.program(ctx, "light_depth.vert", "light_depth.frag",
                                              _SHADER_DEFINES))
            vbo = self._keep(ctx.buffer(np.ascontiguousarray(v - self.centre, dtype="f4").tobytes()))
            ibo = self._keep(ctx.buffer(np.ascontiguousarray(f, dtype="i4").tobytes()))
            self.vao = self._keep(ctx.vertex_array(self.prog, [(vbo, "3f", "in_pos")],
                                                   index_buffer=ibo, index_element_size=4))
        except BaseException:
            self.release()
            raise

    def _keep(self, obj: Any) -> Any:
        self._objects.append(obj)
        return obj

    def __enter__(self) -> "_DepthRenderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def release(self) -> None:
        if self._target is not None:
            self._target[2].release()
            self._target[1].release()
            self._target = None
        for obj in reversed(self._objects):
            obj.release()
        self._objects.clear()

    # ---- views ------------------------------------------------------------------------
    def directional_view(self, towards_light: NDArray[np.float64], size: int) -> list[_View]:
        fwd = -np.asarray(towards_light, dtype=np.float64)
        right, up = _frame(fwd)
        R = self.radius
        return [_View(eye=-2.0 * R * fwd, forward=fwd, right=right, up=up, near=0.5 * R, far=3.5 * R,
                      half=_FIT * R, ortho=True, tile=(0, 0))]

    def perspective_views(self, position: NDArray[np.float64], size: int,
                          axis: NDArray[np.float64] | None = None,
                          cone_deg: float | None = None) -> list[_View]:
        eye = np.asarray(position, dtype=np.float64) - self.centre
        D, R = float(np.linalg.norm(eye)), self.radius
        far = D + 1.05 * R

        def near(half: float) -> float:
            # the clip planes bound the depth along the view axis, which is as small as
            # distance * cos(corner angle) for a surface point at the frustum's corner
            return max((D - 1.05 * R) / math.sqrt(1.0 + 2.0 * half * half), 1e-5 * far)

        if axis is not None and cone_deg is not None and cone_deg <= SPOT_SINGLE_VIEW_MAX_DEG:
            fwd = np.asarray(axis, dtype=np.float64)
            right, up = _frame(fwd)
            half = math.tan(math.radians(cone_deg)) * 1.02 + 2.0 / size
            return [_View(eye, fwd, right, up, near(half), far, half, False, (0, 0))]
        views = []
        half = 1.0 + 4.0 / size  # a little beyond 90 degrees: the 2 x 2 filter stays inside
        for k in range(6):
            fwd = np.zeros(3)
            fwd[k // 2] = -1.0 if k % 2 else 1.0
            right, up = _frame(fwd)
            views.append(_View(eye, fwd, right, up, near(half), far, half, False, (k % 3, k // 3)))
        return views

    # ---- rendering --------------------------------------------------------------------
    def render(self, views: list[_View], size: int) -> _ShadowMap:
        ctx = self.ctx
        cols = max(v.tile[0] for v in views) + 1
        rows = max(v.tile[1] for v in views) + 1
        shape = (cols * size, rows * size)
        max_tex = int(ctx.info.get("GL_MAX_TEXTURE_SIZE", 8192))
        if max(shape) > max_tex:
            raise InputError(f"shadow_map_size={size} needs a {shape[0]}x{shape[1]} texture, beyond "
                             f"this GL's limit {max_tex}; lower shadow_map_size")
        gl.make_current(ctx)
        if self._target is None or self._target[0] != shape:
            if self._target is not None:
                self._target[2].release()
                self._target[1].release()
                self._target = None
            tex = ctx.texture(shape, 2, dtype="f4")
            try:
                fbo = ctx.framebuffer(color_attachments=[tex])
            except BaseException:
                tex.release()
                raise
            self._target = (shape, tex, fbo)
        _, tex, fbo = self._target
        bound = ctx.fbo if ctx.fbo is not None else ctx.detect_framebuffer(0)
        scope = ctx.scope(fbo, enable_only=moderngl.BLEND)
        try:
            with scope:
                fbo.use()
                fbo.clear(_FAR, _FAR, 0.0, 0.0)
                ctx.blend_equation = moderngl.MIN  # ignores the blend function
                for v in views:
                    ctx.viewport = (v.tile[0] * size, v.tile[1] * size, size, size)
                    self.prog["u_mvp"].write(np.ascontiguousarray(v.matrix().T, dtype="f4").tobytes())
                    self.prog["u_origin"].value = tuple(float(x) for x in v.eye)
                    self.prog["u_axis"].value = tuple(float(x) for x in v.forward)
                    self.prog["u_mode"].value = 0 if v.ortho else 1
                    self.vao.render(moderngl.TRIANGLES)
                raw = tex.read(alignment=1)
        finally:
            ctx.blend_equation = moderngl.FUNC_ADD
            bound.use()
            scope.release()
        depth = np.frombuffer(raw, dtype=np.float32).reshape(shape[1], shape[0], 2)
        mid = 0.5 * (depth[..., 0].astype(np.float64) + depth[..., 1])
        return _ShadowMap(views, size, mid)

    def shadow_map(self, light: Light, size: int, direction: NDArray[np.float64] | None = None
                   ) -> _ShadowMap:
        if isinstance(light, ProjectorLight):
            light = light.spot
        if isinstance(light, DirectionalLight) or direction is not None:
            w = np.asarray(light.direction if direction is None else direction, dtype=np.float64)
            return self.render(self.directional_view(w, size), size)
        if isinstance(light, SpotLight):
            return self.render(self.perspective_views(np.asarray(light.position), size,
                                                      np.asarray(light.direction), light.cone_deg), size)
        return self.render(self.perspective_views(np.asarray(light.position), size), size)


# ---------------------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------------------
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


def _points(points: ArrayLike, name: str = "points") -> NDArray[np.float64]:
    try:
        p = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric (N, 3) array (mm)") from None
    if p.ndim == 1 and p.size == 0:
        p = p.reshape(0, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise InputError(f"{name} has {int((~np.isfinite(p)).any(axis=1).sum())} rows with non-finite values")
    return p


def _normals(normals: ArrayLike, n_points: int) -> NDArray[np.float64]:
    n = _points(normals, "normals")
    if len(n) != n_points:
        raise InputError(f"normals must have one row per point: {len(n)} normals for {n_points} points")
    length = np.linalg.norm(n, axis=1)
    if (length < 1e-12).any():
        raise InputError(f"normals has {int((length < 1e-12).sum())} zero-length rows; pass outward "
                         "unit normals")
    return n / length[:, None]


def _size(shadow_map_size: Any) -> int:
    return _integer(shadow_map_size, "shadow_map_size", 8, 8192)


def _light_list(lights: Any) -> list[Light]:
    if isinstance(lights, tuple(_KINDS)):
        lights = [lights]
    try:
        out = list(lights)
    except TypeError:
        raise InputError(f"lights must be a sequence of lights, got {type(lights).__name__}") from None
    for i, light in enumerate(out):
        if not isinstance(light, tuple(_KINDS)):
            raise InputError(f"lights[{i}] must be {_KIND_NAMES}, got {type(light).__name__}")
    return out


def _ft(eta: float | None, cos: NDArray[np.float64]) -> NDArray[np.float64]:
    """Fresnel transmittance for cosines clipped to [0, 1] (0 where cos <= 0); 1 for
    ``eta=None`` (the incident irradiance, no interface)."""
    if eta is None:
        return np.where(cos > 0.0, 1.0, 0.0)
    c = np.clip(cos, 0.0, 1.0)
    return np.where(cos > 0.0, np.asarray(fresnel_transmittance(eta, c)), 0.0)


def _context(ctx: moderngl.Context | None) -> moderngl.Context:
    c = ctx if ctx is not None else gl.get_context()
    gl.make_current(c)
    return c


def visibility(mesh: Any, points: ArrayLike, light: Light, ctx: moderngl.Context | None = None,
               shadow_map_size: int = 1024, normals: ArrayLike | None = None) -> NDArray[np.float64]:
    """Shadow-map visibility ``(N,)`` in [0, 1] of ``points`` (N, 3) mm for one light (1 = lit).

    Renders a shadow map whatever the light's ``shadows`` flag says. ``normals`` (N, 3),
    optional, set the slope part of the bias (see the module docstring). For an
    :class:`EnvironmentLight` the result is the ambient-occlusion fraction over its
    ``directions`` (weighted by ``(n . w)^+`` when normals are given, else unweighted), with
    shadow maps of at most ``ENV_SHADOW_MAP_MAX`` texels. For a :class:`ProjectorLight` it is
    the shadowing alone (points outside the frustum count as lit); its image is
    :func:`projector_factor`.
    """
    _mesh_arrays(mesh)
    p = _points(points)
    n = None if normals is None else _normals(normals, len(p))
    if not isinstance(light, tuple(_KINDS)):
        raise InputError(f"light must be {_KIND_NAMES}, got {type(light).__name__}")
    size = _size(shadow_map_size)
    if len(p) == 0:
        return np.ones(0)
    c = _context(ctx)
    with _DepthRenderer(c, mesh) as r:
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
        return sm.lookup(q, _to_light(light, p), n)


def _to_light(light: Light, p: NDArray[np.float64]) -> NDArray[np.float64]:
    if isinstance(light, DirectionalLight):
        return np.broadcast_to(np.asarray(light.direction), p.shape)
    d = np.asarray(light.position) - p
    r = np.linalg.norm(d, axis=1, keepdims=True)
    return np.divide(d, r, out=np.zeros_like(d), where=r > 0)


def incident_light(mesh: Any, points: ArrayLike, normals: ArrayLike, lights: Sequence[Light],
                   eta: float | None, ctx: moderngl.Context | None = None,
                   shadow_map_size: int = 1024) -> tuple[NDArray[np.float64], list[dict[str, Any]]]:
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
        Lights (a single light is accepted too).
    eta
        Relative refractive index n_inside / n_outside, > 0; ``None``: the incident
        irradiance (no Fresnel factor), e.g. for a diffuse surface reflectance.
    ctx
        GL context for the shadow maps; default :func:`glsldiff.gl.get_context` (only
        created when some light needs a shadow map).
    shadow_map_size
        Texels per side of each shadow-map view (environment directions: at most
        ``ENV_SHADOW_MAP_MAX``).

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
    p = _points(points)
    n = _normals(normals, len(p))
    eta_v = None if eta is None else _real(eta, "eta", 0.0, math.inf, lo_open=True, hi_open=True)
    light_list = _light_list(lights)
    size = _size(shadow_map_size)
    total = np.zeros((len(p), 3))
    infos: list[dict[str, Any]] = []
    renderer: _DepthRenderer | None = None
    try:
        for light in light_list:
            t0 = time.perf_counter()
            info: dict[str, Any] = {"light": _KINDS[type(light)]}
            needs_map = casts_shadows(light) and len(p) > 0
            if needs_map and renderer is None:
                renderer = _DepthRenderer(_context(ctx), mesh)
            if isinstance(light, EnvironmentLight):
                e = _environment(light, p, n, eta_v, renderer if needs_map else None, size, info)
            else:
                w = _to_light(light, p)
                cos = np.einsum("ij,ij->i", n, w)
                radiometric = np.asarray(light.irradiance if isinstance(light, DirectionalLight)
                                         else light.intensity)
                scale = cos.clip(0.0) * _ft(eta_v, cos)
                if not isinstance(light, DirectionalLight):
                    r2 = ((np.asarray(light.position) - p) ** 2).sum(axis=1)
                    scale = np.where(r2 > 0, scale / np.where(r2 > 0, r2, 1.0), 0.0)
                if isinstance(light, SpotLight):
                    scale = scale * spot_factor(light, -(w @ np.asarray(light.direction)))
                if isinstance(light, ProjectorLight):
                    radiometric = radiometric * projector_factor(light, p)     # (N, 3)
                    scale = np.where(radiometric.any(axis=1), scale, 0.0)
                facing = scale > 0
                if needs_map:
                    assert renderer is not None
                    sm = renderer.shadow_map(light, size)
                    vis = np.ones(len(p))
                    idx = np.flatnonzero(facing)
                    vis[idx] = sm.lookup(p[idx] - renderer.centre, w[idx], n[idx])
                    scale = scale * vis
                    info["shadow_map"] = sm.label
                    info["shadowed"] = int((vis[facing] < 0.5).sum())
                else:
                    info["shadow_map"] = "none (shadows off)"
                    info["shadowed"] = 0
                info["facing"] = int(facing.sum())
                e = scale[:, None] * np.atleast_2d(radiometric)
            total += e
            info["max"] = [float(x) for x in (e.max(axis=0) if len(e) else np.zeros(3))]
            info["seconds"] = time.perf_counter() - t0
            infos.append(info)
    finally:
        if renderer is not None:
            renderer.release()
    return total, infos


def _environment(light: EnvironmentLight, p: NDArray[np.float64], n: NDArray[np.float64], eta: float | None,
                 renderer: _DepthRenderer | None, size: int, info: dict[str, Any]) -> NDArray[np.float64]:
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
        g = cos.clip(0.0) * _ft(eta, cos)
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
