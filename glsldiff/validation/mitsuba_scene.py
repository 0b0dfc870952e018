"""Mitsuba 3 scene assembly for :mod:`glsldiff.validation.mitsuba`: input checks, the pinhole
:class:`McCamera`, the variant loader (JIT variants probed out of process), and the medium,
shape, emitter and sensor dictionaries (the conventions are documented in
:mod:`glsldiff.validation.mitsuba`). Lengths in mm, coefficients in mm^-1.
"""
from __future__ import annotations

import functools
import subprocess
import sys
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from glsldiff.core import checks
from glsldiff.core.errors import BackendError, InputError
from glsldiff.mesh import Mesh
from glsldiff.physics.lights import AreaLight, DirectionalLight, EnvironmentLight, SpotLight

#: Mitsuba variants usable here (RGB rendering: spectral variants would upsample coefficients).
RGB_VARIANTS = ("scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb")
VOLUME_KEYS = ("sigma_a", "sigma_s", "bbox_min", "bbox_max")
VOLUME_FILTERS = ("trilinear", "nearest")
SAMPLERS = ("independent", "ldsampler")


# ---------------------------------------------------------------------------------------
# Input checks
# ---------------------------------------------------------------------------------------
def positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise InputError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


@dataclass(frozen=True)
class McCamera:
    """Pinhole or orthographic camera for :func:`render_mitsuba`.

    Attributes
    ----------
    origin, target
        Eye and look-at points, mm.
    up
        Up direction (need not be orthogonal to the view direction, must not be parallel).
    fov_deg
        *Vertical* field of view in degrees, 0 < fov < 180 (Mitsuba ``fov_axis = "y"``).
    width, height
        Image size in pixels.
    width_mm
        When given, an orthographic camera (Mitsuba's ``orthographic`` sensor: parallel rays
        along the view) whose image is ``width_mm`` wide (square pixels); ``fov_deg`` is then
        unused. Per-pixel comparisons with a grid need it (a pinhole far away only approaches it).
    """

    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_deg: float
    width: int
    height: int
    width_mm: float | None = None

    def __post_init__(self) -> None:
        o, t, u = (checks.vector3(getattr(self, n), f"camera.{n}") for n in ("origin", "target", "up"))
        d = t - o
        if np.linalg.norm(d) == 0:
            raise InputError("camera.target must differ from camera.origin")
        if np.linalg.norm(np.cross(d / np.linalg.norm(d), u)) < 1e-6 * max(np.linalg.norm(u), 1e-300):
            raise InputError(f"camera.up {u.tolist()} must be non-zero and not parallel to the view "
                             f"direction {d.tolist()}")
        fov = float(checks.finite_array(self.fov_deg, "camera.fov_deg"))
        if not 0.0 < fov < 180.0:
            raise InputError(f"camera.fov_deg must be in (0, 180) degrees (vertical), got {fov}")
        for name, v in (("origin", o), ("target", t), ("up", u)):
            object.__setattr__(self, name, tuple(float(x) for x in v))
        object.__setattr__(self, "fov_deg", fov)
        if self.width_mm is not None:
            w = float(checks.finite_array(self.width_mm, "camera.width_mm"))
            if not w > 0.0:
                raise InputError(f"camera.width_mm must be > 0 (mm), got {w}")
            object.__setattr__(self, "width_mm", w)
        object.__setattr__(self, "width", positive_int("camera.width", self.width))
        object.__setattr__(self, "height", positive_int("camera.height", self.height))


def check_light(light: Any, eta: float) -> dict[str, Any]:
    """The Mitsuba emitter parameters of ``light`` (module docstring): ``type`` (``directional``,
    ``spot`` (hard-edged only, eta = 1), ``area`` (a ``rectangle`` shape with an ``area``
    emitter, one-sided like the :class:`~glsldiff.physics.lights.AreaLight`), ``constant`` or
    ``envmap``) and its values as arrays."""
    if isinstance(light, (DirectionalLight, SpotLight)) and eta != 1.0:
        raise InputError(
            f"a {'directional' if isinstance(light, DirectionalLight) else 'spot'} (delta) light cannot be reached "
            f"through a smooth dielectric boundary (eta = {eta}) by next-event estimation, so Mitsuba would render "
            "the medium black; use eta = 1 (index matched) or an environment or area light")
    if isinstance(light, DirectionalLight):
        return {"type": "directional", "direction": np.asarray(light.direction),
                "irradiance": np.asarray(light.irradiance)}
    if isinstance(light, SpotLight):
        if light.falloff_deg != light.cone_deg:
            raise InputError(f"a spot light for the Monte Carlo reference must be hard-edged (falloff_deg = cone_deg "
                             f"= {light.cone_deg}): Mitsuba's spot fades linearly in angle, glsldiff's by smoothstep")
        return {"type": "spot", "position": np.asarray(light.position), "direction": np.asarray(light.direction),
                "intensity": np.asarray(light.intensity), "cone_deg": light.cone_deg}
    if isinstance(light, AreaLight):
        right, up, fwd = light.frame
        w, h = light.size
        # Mitsuba's rectangle: [-1, 1]^2 in local x, y, normal +z; x cross y must be the emitting side
        to_world = np.eye(4)
        to_world[:3, 0], to_world[:3, 1], to_world[:3, 2] = up * h / 2, right * w / 2, fwd
        to_world[:3, 3] = light.position
        return {"type": "area", "to_world": to_world, "radiance": np.asarray(light.radiance)}
    if isinstance(light, EnvironmentLight):
        img = light.image
        if np.all(img == img[0, 0]):   # uniform: Mitsuba's constant emitter, sampled exactly
            return {"type": "constant", "radiance": light.scale * img[0, 0]}
        if img.shape[0] < 2 or img.shape[1] < 2:
            raise InputError(f"light.image of an environment light must be at least 2 x 2 pixels for Mitsuba's "
                             f"envmap, got {img.shape[0]} x {img.shape[1]}")
        return {"type": "envmap", "image": img, "scale": light.scale}
    raise InputError(f"light must be a DirectionalLight, SpotLight, AreaLight or EnvironmentLight (glsldiff.physics.lights) for the "
                     f"Monte Carlo reference, got {type(light).__name__}")


def check_volume(volume: Any) -> dict[str, Any]:
    if not isinstance(volume, Mapping):
        raise InputError(f"volume must be a dict with keys {', '.join(VOLUME_KEYS)}, got {type(volume).__name__}")
    missing = [k for k in VOLUME_KEYS if k not in volume]
    extra = sorted(set(volume) - set(VOLUME_KEYS) - {"filter"})
    if missing:
        raise InputError(f"volume is missing the key(s) {', '.join(missing)}")
    if extra:
        raise InputError(f"volume has unknown key(s) {', '.join(extra)}; allowed: "
                         f"{', '.join(VOLUME_KEYS)}, filter")
    out: dict[str, Any] = {}
    for name in ("sigma_a", "sigma_s"):
        a = checks.finite_array(volume[name], f"volume['{name}']")
        if a.ndim != 4 or a.shape[3] != 3 or min(a.shape) < 1:
            raise InputError(f"volume['{name}'] must have shape (nz, ny, nx, 3) [mm^-1], got {a.shape}")
        if (a < 0).any():
            raise InputError(f"volume['{name}'] has {int((a < 0).sum())} negative values; coefficients "
                             "are >= 0 mm^-1")
        out[name] = a
    if out["sigma_a"].shape != out["sigma_s"].shape:
        raise InputError(f"volume['sigma_a'] {out['sigma_a'].shape} and volume['sigma_s'] "
                         f"{out['sigma_s'].shape} must have the same shape (nz, ny, nx, 3)")
    lo = checks.vector3(volume["bbox_min"], "volume['bbox_min']")
    hi = checks.vector3(volume["bbox_max"], "volume['bbox_max']")
    if not (hi > lo).all():
        raise InputError(f"volume['bbox_max'] {hi.tolist()} must exceed volume['bbox_min'] {lo.tolist()} "
                         "on every axis (mm)")
    filt = volume.get("filter", "trilinear")
    if filt not in VOLUME_FILTERS:
        raise InputError(f"volume['filter'] = {filt!r} must be one of {', '.join(VOLUME_FILTERS)}")
    out.update(bbox_min=lo, bbox_max=hi, filter=filt)
    return out


def check_eta(eta: Any) -> float:
    e = float(checks.finite_array(eta, "eta"))
    if e <= 0:
        raise InputError(f"eta must be a relative index of refraction > 0 (1 = index matched), got {e}")
    return e


# ---------------------------------------------------------------------------------------
# Mitsuba variant handling
# ---------------------------------------------------------------------------------------
PROBE = """
import mitsuba as mi
mi.set_variant({variant!r})
s = mi.load_dict({{"type": "scene", "integrator": {{"type": "volpath"}},
    "sensor": {{"type": "perspective", "film": {{"type": "hdrfilm", "width": 2, "height": 2}}}},
    "env": {{"type": "constant"}}, "ball": {{"type": "sphere", "center": [0, 0, 4],
    "bsdf": {{"type": "null"}}, "interior": {{"type": "homogeneous"}}}}}})
mi.render(s, spp=1)
"""


@functools.lru_cache(maxsize=None)
def probe_variant(variant: str) -> str:
    """'' if ``variant`` renders in a child process, else the reason it does not.

    JIT variants are probed out of process because a failing LLVM back end (Debian 12's
    LLVM 15 with Mitsuba 3.9's ``llvm_ad_rgb``) aborts the whole interpreter.
    """
    try:
        r = subprocess.run([sys.executable, "-c", PROBE.format(variant=variant)], capture_output=True,
                           text=True, timeout=300)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return str(exc)
    if r.returncode == 0:
        return ""
    tail = (r.stderr or r.stdout).strip().splitlines()
    return f"exit status {r.returncode}: {tail[0] if tail else 'no output'}"


def load_mitsuba(variant: str) -> Any:
    """Import mitsuba and switch to ``variant`` (global Mitsuba state)."""
    if variant not in RGB_VARIANTS:
        raise InputError(f"variant {variant!r} is not supported; use one of {', '.join(RGB_VARIANTS)} "
                         "(RGB rendering; spectral variants would upsample the coefficients)")
    try:
        import mitsuba as mi  # heavy optional dependency (the dev extra), loaded only to render
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise BackendError("the Monte Carlo reference needs Mitsuba 3: pip install mitsuba") from exc
    if variant not in mi.variants():  # pragma: no cover - depends on the wheel
        raise BackendError(f"this Mitsuba build lacks the variant {variant!r} (has {', '.join(mi.variants())})")
    if not variant.startswith("scalar"):
        reason = probe_variant(variant)
        if reason:
            raise BackendError(
                f"Mitsuba variant {variant!r} does not run here ({reason}); use variant='scalar_rgb', or "
                "for llvm_ad_rgb install a newer LLVM (e.g. libllvm19) and set DRJIT_LIBLLVM_PATH")
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


# ---------------------------------------------------------------------------------------
# Scene assembly
# ---------------------------------------------------------------------------------------
def medium_dict(mi: Any, c: dict[str, Any], gridded: bool, sample_emitters: bool = True) -> Any:
    """Mitsuba medium from checked coefficients: RGB (3,) arrays, or a checked volume dict;
    ``sample_emitters``: next-event estimation from medium vertices (see
    :func:`glsldiff.validation.mitsuba.render_mitsuba` for when it is off)."""
    st = c["sigma_a"] + c["sigma_s"]
    albedo = np.divide(c["sigma_s"], st, out=np.zeros_like(st), where=st > 0)
    if not gridded:
        scale = float(st.max()) or 1.0  # Mitsuba's 'rgb' inputs must lie in [0, 1]: scale them
        return mi.load_dict({"type": "homogeneous", "sample_emitters": sample_emitters,
                             "albedo": {"type": "rgb", "value": albedo.tolist()},
                             "sigma_t": {"type": "rgb", "value": (st / scale).tolist()},
                             "scale": scale, "phase": {"type": "isotropic"}})
    lo, hi = c["bbox_min"], c["bbox_max"]
    to_world = mi.ScalarTransform4f().translate(lo.tolist()).scale((hi - lo).tolist())

    def grid(data: NDArray) -> dict[str, Any]:
        return {"type": "gridvolume", "grid": mi.VolumeGrid(np.ascontiguousarray(data, dtype=np.float32)),
                "to_world": to_world, "filter_type": c["filter"], "wrap_mode": "clamp", "raw": True}

    return mi.load_dict({"type": "heterogeneous", "sample_emitters": sample_emitters, "scale": 1.0,
                         "albedo": grid(albedo), "sigma_t": grid(st), "phase": {"type": "isotropic"}})


def shape_dict(mi: Any, mesh: Mesh, medium: Any, eta: float) -> Any:
    props = mi.Properties()
    bsdf = {"type": "null"} if eta == 1.0 else {"type": "dielectric", "int_ior": eta, "ext_ior": 1.0}
    props["bsdf"] = mi.load_dict(bsdf)
    props["interior"] = medium
    shape = mi.Mesh(mesh.name or "mesh", len(mesh.vertices), len(mesh.faces), props=props)
    params = mi.traverse(shape)
    params["vertex_positions"] = type(params["vertex_positions"])(
        np.ascontiguousarray(mesh.vertices, dtype=np.float32).ravel())
    params["faces"] = type(params["faces"])(np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel())
    params.update()  # no vertex normals: flat face normals (matters for refraction at box edges)
    return shape


def emitter_dict(mi: Any, light: dict[str, Any], transparent: bool = False) -> dict[str, Any]:
    """Mitsuba emitter dict of checked light parameters (:func:`check_light`); ``transparent``
    gives an area light's rectangle a ``null`` BSDF (it emits, one-sided, and lets everything
    through) instead of Mitsuba's default for an emitter's shape (a black diffuse BSDF: it absorbs
    what reaches it and hides what lies behind it)."""
    if light["type"] == "directional":
        return {"type": "directional", "direction": (-light["direction"]).tolist(),
                "irradiance": {"type": "rgb", "value": light["irradiance"].tolist()}}
    if light["type"] == "spot":
        target = light["position"] + light["direction"]
        up = [0.0, 1.0, 0.0] if abs(light["direction"][1]) < 0.9 else [1.0, 0.0, 0.0]
        return {"type": "spot", "cutoff_angle": light["cone_deg"], "beam_width": light["cone_deg"],
                "intensity": {"type": "rgb", "value": light["intensity"].tolist()},
                "to_world": mi.ScalarTransform4f().look_at(origin=light["position"].tolist(), target=target.tolist(),
                                                           up=up)}
    if light["type"] == "area":
        return {"type": "rectangle", "to_world": mi.ScalarTransform4f(light["to_world"].tolist()),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": light["radiance"].tolist()}},
                **({"bsdf": {"type": "null"}} if transparent else {})}
    if light["type"] == "constant":
        return {"type": "constant", "radiance": {"type": "rgb", "value": light["radiance"].tolist()}}
    return {"type": "envmap", "scale": light["scale"],
            "to_world": mi.ScalarTransform4f([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]),
            "bitmap": mi.Bitmap(np.ascontiguousarray(z_up_to_mitsuba(light["image"]), dtype=np.float32))}


def z_up_to_mitsuba(img: NDArray[np.float64]) -> NDArray[np.float64]:
    """A glsldiff (z-up) lat-long map as the bitmap of a Mitsuba ``envmap`` whose
    ``to_world`` sends local (x, y, z) to world (y, z, x) (module docstring): columns mirrored,
    rows resampled linearly in polar angle from glsldiff's row centres theta = pi (i + 0.5) / H
    to Mitsuba's theta = pi j / (H - 1) (clamped to the first and last rows at the poles)."""
    h = img.shape[0]
    x = np.interp(np.arange(h) * np.pi / (h - 1), (np.arange(h) + 0.5) * np.pi / h, np.arange(h, dtype=float))
    i0 = np.minimum(np.floor(x).astype(int), h - 2)
    f = (x - i0)[:, None, None]
    return ((1.0 - f) * img[i0] + f * img[i0 + 1])[:, ::-1]


def sensor_dict(mi: Any, cam: McCamera, spp: int, seed: int, sampler: str) -> dict[str, Any]:
    look = mi.ScalarTransform4f().look_at(origin=list(cam.origin), target=list(cam.target), up=list(cam.up))
    if cam.width_mm is None:
        kind = {"type": "perspective", "fov": cam.fov_deg, "fov_axis": "y", "to_world": look}
    else:   # Mitsuba's orthographic image spans [-1, 1] across x (and 1/aspect along y) before to_world
        half = 0.5 * cam.width_mm
        kind = {"type": "orthographic", "to_world": look @ mi.ScalarTransform4f().scale([half, half, 1.0])}
    return {**kind, "near_clip": 1e-3, "far_clip": 1e7,
            "sampler": {"type": sampler, "sample_count": spp, "seed": seed},
            "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height,
                     "pixel_format": "rgb", "component_format": "float32", "rfilter": {"type": "box"}}}
