"""Light types: the one representation of each kind of light, pure numpy (no GL).

Scenes parse into these (:mod:`glsldiff.render.scene`); pass 1 (:mod:`glsldiff.render.pass1`),
the pass-3 shader uniforms, single scattering (:mod:`glsldiff.physics.single`) and the Monte
Carlo reference (:mod:`glsldiff.validation.mitsuba`) take them. Lengths in mm; irradiance and
intensity in the caller's units (irradiance = intensity / mm^2).

:class:`DirectionalLight`
    ``irradiance`` E0 on a surface facing the light: L cos dw = E0 (n . w)^+.
:class:`PointLight`
    Radiant ``intensity`` I: irradiance I (n . w)^+ / r^2, r the distance in mm.
:class:`SpotLight`
    A point light times a smooth cone factor (:func:`spot_factor`): 1 inside ``falloff_deg``
    of the axis, 0 beyond ``cone_deg``, and the smoothstep ``t^2 (3 - 2 t)`` in between, with
    ``t = (cos a - cos cone) / (cos falloff - cos cone)`` and a the angle from the axis.
:class:`ProjectorLight`
    A pinhole projector: a point light whose radiant intensity towards x is ``intensity``
    times its ``image`` sampled where x projects (:func:`projector_factor`): irradiance
    ``I img(u, v) (n . w)^+ / r^2``, 0 outside the image's frustum and behind the projector.
    Shadowed as the hard-edged spot light whose cone circumscribes its frustum (:attr:`spot`).
:class:`AreaLight`
    A one-sided Lambertian rectangle (a light box, a lit projector region) of ``radiance``
    L: irradiance ``L * integral over the rectangle of cos_r cos_e / r^2 dA``, computed by
    :mod:`glsldiff.physics.area` (exact polygon form factors of its ``samples`` x ``samples``
    sub-rectangles). Not shadowed (``shadows`` must stay False) and not in pass 3's
    specular term.
:class:`EnvironmentLight`
    A lat-long radiance map (convention: :func:`glsldiff.physics.sh.latlong_directions`),
    projected onto spherical harmonics (:attr:`EnvironmentLight.sh`).

:func:`incidence` gives the unshadowed normal irradiance of the first four kinds at points
(the one place their falloff is written); w in it, as everywhere, is the unit direction from
a point *towards* the light (:func:`to_light`).

Lights with an image (projector, environment) compare by identity; their ``digest`` of the
pixels is part of their ``repr``, so a repr names the light's full state.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core import checks
from glsldiff.core.checks import boolean, integer, radiance_map, real, rgb, unit_vector, vector3
from glsldiff.core.camera import orthonormal_frame
from glsldiff.core.errors import InputError
from glsldiff.physics.sh import MAX_DIRECTIONS, MAX_SH_ORDER, sh_project

__all__ = ["DirectionalLight", "PointLight", "SpotLight", "ProjectorLight", "AreaLight", "EnvironmentLight", "Light",
           "DirectLight", "KINDS", "light_kind", "check_light", "casts_shadows", "spot_factor",
           "projector_factor", "to_light", "incidence"]


def _position(value: Any, name: str) -> tuple[float, float, float]:
    return tuple(float(x) for x in vector3(value, name))  # type: ignore[return-value]


def _orient(light: Any, kind: str, where: str) -> None:
    """Check and normalise the ``position``, ``direction`` and ``up`` of a light with a frame."""
    object.__setattr__(light, "position", _position(light.position, f"{kind}.position"))
    fwd = unit_vector(light.direction, f"{kind}.direction")
    up = unit_vector(light.up, f"{kind}.up")
    if np.linalg.norm(np.cross(fwd, up)) < 1e-6:
        raise InputError(f"{kind}.up={light.up!r} is parallel to direction={light.direction!r}; "
                         f"give an up vector {where}")
    object.__setattr__(light, "direction", fwd)
    object.__setattr__(light, "up", up)


def _digest(image: NDArray[np.float64]) -> str:
    """Short hex digest of an image's shape and pixels."""
    h = hashlib.blake2b(repr(image.shape).encode(), digest_size=10)
    h.update(np.ascontiguousarray(image).data)
    return h.hexdigest()


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
        Whether pass 1 renders a shadow map for it.
    """

    direction: tuple[float, float, float]
    irradiance: tuple[float, float, float]
    shadows: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "direction", unit_vector(self.direction, "DirectionalLight.direction"))
        object.__setattr__(self, "irradiance", rgb(self.irradiance, "DirectionalLight.irradiance"))
        object.__setattr__(self, "shadows", boolean(self.shadows, "DirectionalLight.shadows"))


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
        Whether pass 1 renders a (cube) shadow map for it.
    """

    position: tuple[float, float, float]
    intensity: tuple[float, float, float]
    shadows: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _position(self.position, "PointLight.position"))
        object.__setattr__(self, "intensity", rgb(self.intensity, "PointLight.intensity"))
        object.__setattr__(self, "shadows", boolean(self.shadows, "PointLight.shadows"))


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
        Whether pass 1 renders a shadow map for it.
    """

    position: tuple[float, float, float]
    direction: tuple[float, float, float]
    intensity: tuple[float, float, float]
    cone_deg: float = 30.0
    falloff_deg: float = 25.0
    shadows: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _position(self.position, "SpotLight.position"))
        object.__setattr__(self, "direction", unit_vector(self.direction, "SpotLight.direction"))
        object.__setattr__(self, "intensity", rgb(self.intensity, "SpotLight.intensity"))
        cone = real(self.cone_deg, "SpotLight.cone_deg", 0.0, 180.0, lo_open=True, hi_open=True)
        fall = real(self.falloff_deg, "SpotLight.falloff_deg", 0.0, 180.0)
        if fall > cone:
            raise InputError(f"SpotLight.falloff_deg={fall:g} must not exceed cone_deg={cone:g} "
                             "(the falloff starts inside the cone)")
        object.__setattr__(self, "cone_deg", cone)
        object.__setattr__(self, "falloff_deg", fall)
        object.__setattr__(self, "shadows", boolean(self.shadows, "SpotLight.shadows"))


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
        Whether pass 1 renders a shadow map for it (that of :attr:`spot`).
    """

    position: tuple[float, float, float]
    direction: tuple[float, float, float]
    image: NDArray[np.float64] = field(repr=False)
    intensity: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_deg: float = 30.0
    shadows: bool = True
    digest: str = field(init=False, default="")   #: of the image (module docstring)

    def __post_init__(self) -> None:
        _orient(self, "ProjectorLight", "across the optical axis")
        img = radiance_map(self.image, "ProjectorLight.image")
        img.setflags(write=False)
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "digest", _digest(img))
        object.__setattr__(self, "intensity", rgb(self.intensity, "ProjectorLight.intensity"))
        object.__setattr__(self, "fov_deg", real(self.fov_deg, "ProjectorLight.fov_deg", 0.0, 180.0,
                                                 lo_open=True, hi_open=True))
        object.__setattr__(self, "shadows", boolean(self.shadows, "ProjectorLight.shadows"))

    @property
    def aspect(self) -> float:
        """Image width over height."""
        return self.image.shape[1] / self.image.shape[0]

    @cached_property
    def frame(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Unit ``right, up, forward`` of the projector (right-handed camera frame)."""
        return orthonormal_frame(self.direction, self.up)

    @cached_property
    def spot(self) -> SpotLight:
        """The hard-edged spot light whose cone circumscribes the frustum (for shadow maps)."""
        tan_half = math.tan(math.radians(self.fov_deg) / 2.0)
        cone = math.degrees(math.atan(tan_half * math.hypot(1.0, self.aspect)))
        return SpotLight(self.position, self.direction, self.intensity, cone_deg=cone, falloff_deg=cone,
                         shadows=self.shadows)


@dataclass(frozen=True)
class AreaLight:
    """One-sided Lambertian rectangle (module docstring).

    Parameters
    ----------
    position
        ``(3,)`` centre of the rectangle, mm.
    direction
        ``(3,)`` the emitting side's normal, from the rectangle *into* the scene
        (normalised on construction); nothing is emitted behind it.
    size
        ``(width, height)`` mm, > 0: along ``right`` and ``up`` of :attr:`frame`.
    radiance
        ``(3,)`` RGB radiance of the emitting side (irradiance = radiance x sr).
    up
        ``(3,)`` the direction of the height (orthogonalised against ``direction``).
    samples
        Sub-rectangles per side for pass 1's form factors and the first-collision beams
        (:mod:`glsldiff.physics.area`), 1-64. The form factors are exact at any count; it
        sets how finely the Fresnel factor and the refracted direction follow the rectangle
        (4: within 0.1 % of the converged transmitted irradiance in the tests).
    shadows
        Must be False: area lights are not shadowed (an occluder between the rectangle
        and a surface point is not seen).
    """

    position: tuple[float, float, float]
    direction: tuple[float, float, float]
    size: tuple[float, float]
    radiance: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    samples: int = 4
    shadows: bool = False

    def __post_init__(self) -> None:
        _orient(self, "AreaLight", "in the rectangle's plane")
        size = checks.finite_array(self.size, "AreaLight.size")
        if size.shape != (2,) or np.any(size <= 0):
            raise InputError(f"AreaLight.size={self.size!r} must be (width, height) in mm, both > 0")
        object.__setattr__(self, "size", (float(size[0]), float(size[1])))
        object.__setattr__(self, "radiance", rgb(self.radiance, "AreaLight.radiance"))
        object.__setattr__(self, "samples", integer(self.samples, "AreaLight.samples", 1, 64))
        if boolean(self.shadows, "AreaLight.shadows"):
            raise InputError("AreaLight.shadows = true is not supported: area lights are not shadowed; "
                             "set shadows = false")

    @cached_property
    def frame(self) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Unit ``right, up, forward`` (forward = the emitting normal)."""
        return orthonormal_frame(self.direction, self.up)


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
        Multiplies the radiance, >= 0.
    order
        Spherical-harmonics band limit (``(order + 1)^2`` coefficients), 0 to 8.
    visibility
        Whether pass 1 includes per-node visibility (ambient occlusion with ``directions``
        shadow maps); otherwise the surface is treated as unoccluded.
    directions
        Number of visibility directions (Fibonacci sphere), 1 to 4096.
    """

    image: NDArray[np.float64] = field(repr=False)
    scale: float = 1.0
    order: int = 2
    visibility: bool = True
    directions: int = 64
    digest: str = field(init=False, default="")   #: of the image (module docstring)

    def __post_init__(self) -> None:
        img = radiance_map(self.image, "EnvironmentLight.image")
        img.setflags(write=False)
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "digest", _digest(img))
        object.__setattr__(self, "scale", real(self.scale, "EnvironmentLight.scale", 0.0, math.inf,
                                               hi_open=True))
        object.__setattr__(self, "order", integer(self.order, "EnvironmentLight.order", 0, MAX_SH_ORDER))
        object.__setattr__(self, "visibility", boolean(self.visibility, "EnvironmentLight.visibility"))
        object.__setattr__(self, "directions", integer(self.directions, "EnvironmentLight.directions",
                                                       1, MAX_DIRECTIONS))

    @cached_property
    def sh(self) -> NDArray[np.float64]:
        """``((order + 1)^2, 3)`` SH coefficients of ``scale * image`` (computed once)."""
        return self.scale * sh_project(self.image, self.order)


Light = Union[DirectionalLight, PointLight, SpotLight, ProjectorLight, AreaLight, EnvironmentLight]
#: Lights that reach a point from one direction (all but the area and environment lights).
DirectLight = Union[DirectionalLight, PointLight, SpotLight, ProjectorLight]
#: Kind names (scene files' ``type``, pass 1's reports) and their types.
KINDS: dict[str, type] = {"directional": DirectionalLight, "point": PointLight, "spot": SpotLight,
                          "projector": ProjectorLight, "area": AreaLight, "environment": EnvironmentLight}
_KIND_OF = {cls: name for name, cls in KINDS.items()}
_KIND_NAMES = "a DirectionalLight, PointLight, SpotLight, ProjectorLight, AreaLight or EnvironmentLight"


def check_light(light: Any, name: str = "light") -> Light:
    """``light`` if it is one of the light types, else an :class:`InputError` naming ``name``."""
    if type(light) not in _KIND_OF:
        raise InputError(f"{name} must be {_KIND_NAMES}, got {type(light).__name__}")
    return light


def light_kind(light: Light) -> str:
    """The kind name of ``light``: ``"directional"``, ``"point"``, ... (keys of :data:`KINDS`)."""
    return _KIND_OF[type(check_light(light))]


def casts_shadows(light: Light) -> bool:
    """Whether pass 1 needs shadow maps for ``light``."""
    if isinstance(check_light(light), EnvironmentLight):
        return light.visibility
    return light.shadows


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
    p = checks.points(points)
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


def _direct(light: Any) -> DirectLight:
    if isinstance(check_light(light), (EnvironmentLight, AreaLight)):
        raise InputError("light must be a directional, point, spot or projector light (an environment or "
                         "area light reaches a point from many directions)")
    return light


def to_light(light: DirectLight, points: ArrayLike) -> NDArray[np.float64]:
    """Unit directions ``(N, 3)`` from ``points`` (N, 3) mm towards the light (0 at a
    point light's own position)."""
    p = checks.points(points)
    if isinstance(_direct(light), DirectionalLight):
        return np.broadcast_to(np.asarray(light.direction), p.shape)
    d = np.asarray(light.position) - p
    r = np.linalg.norm(d, axis=1, keepdims=True)
    return np.divide(d, r, out=np.zeros_like(d), where=r > 0)


def incidence(light: DirectLight, points: ArrayLike, weight: ArrayLike | None = None
              ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unshadowed light at ``points`` (N, 3) mm as ``(scale (N,), colour)``.

    The normal irradiance (on a surface facing the light) is ``scale[:, None] * colour``:
    ``scale`` is ``weight`` (default 1; pass 1 passes its cosine-Fresnel factor), divided by
    r^2 for a positional light (0 at r = 0) and times :func:`spot_factor` for a spot light;
    ``colour`` is the ``irradiance`` or ``intensity`` ``(3,)``, for a projector times
    :func:`projector_factor` ``(N, 3)`` (``scale`` set to 0 where that is black).
    """
    p = checks.points(points)
    scale = np.ones(len(p)) if weight is None else np.asarray(weight, dtype=np.float64)
    if isinstance(_direct(light), DirectionalLight):
        return scale, np.asarray(light.irradiance)
    colour = np.asarray(light.intensity)
    r2 = ((np.asarray(light.position) - p) ** 2).sum(axis=1)
    scale = np.where(r2 > 0, scale / np.where(r2 > 0, r2, 1.0), 0.0)
    if isinstance(light, SpotLight):
        scale = scale * spot_factor(light, -(to_light(light, p) @ np.asarray(light.direction)))
    if isinstance(light, ProjectorLight):
        colour = colour * projector_factor(light, p)     # (N, 3)
        scale = np.where(colour.any(axis=1), scale, 0.0)
    return scale, colour
