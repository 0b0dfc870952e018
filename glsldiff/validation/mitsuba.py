"""Monte Carlo reference renderer (Mitsuba 3 ``volpath``) for validating the diffusion renderer.

:func:`render_mitsuba` renders a closed :class:`~glsldiff.mesh.Mesh` filled with a homogeneous
or a gridded heterogeneous medium (isotropic phase function) under a directional or an
environment light (:mod:`glsldiff.physics.lights`), with Mitsuba 3's volumetric path tracer.
Scene units are mm, so coefficients in mm^-1 apply directly and radiance comes out in the
light's units (irradiance E of a directional light in W mm^-2 gives radiance in W mm^-2
sr^-1, and so on).

Model
-----
- Medium: sigma_a, sigma_s [mm^-1] per RGB channel. The phase function is isotropic, so
  sigma_s is also the reduced scattering coefficient sigma_s' of the diffusion model
  (kappa = 1/(3 (sigma_a + sigma_s)), mu = sigma_a, see :mod:`glsldiff.physics.material`). Mitsuba is
  given sigma_t = sigma_a + sigma_s and albedo = sigma_s / sigma_t (0 where sigma_t = 0).
- Boundary: ``eta == 1`` gives a ``null`` BSDF (index matched: light crosses the surface
  unchanged, and volpath treats the crossing as a free, uncounted event); any other ``eta``
  gives a smooth ``dielectric`` with ``int_ior = eta``, ``ext_ior = 1`` (Fresnel reflection and
  refraction; radiance leaving the denser medium is divided by eta^2 as physics requires).
- Lights (``light``): the renderer's own :mod:`glsldiff.physics.lights` types, converted to
  Mitsuba emitters here:

  :class:`~glsldiff.physics.lights.DirectionalLight`
      Mitsuba's ``directional`` emitter with the light's ``irradiance`` [RGB] on a surface facing
      it; its ``direction`` points FROM the object TOWARDS the light, so it is negated for
      Mitsuba, which takes the propagation direction. A delta light: it is reached only by
      next-event estimation, which cannot pass a smooth dielectric (a delta BSDF), so
      ``eta != 1`` with a directional light raises :class:`~glsldiff.core.errors.InputError`
      (use ``eta = 1``, or an environment light).
  :class:`~glsldiff.physics.lights.EnvironmentLight` of a uniform map
      Mitsuba's ``constant`` emitter, radiance ``scale`` times the pixel value [RGB].
  :class:`~glsldiff.physics.lights.EnvironmentLight`
      Mitsuba's ``envmap`` (lat-long radiance [RGB], bilinear lookup) with the light's
      ``scale``; the map is at least 2 x 2 pixels. Its spherical-harmonics ``order``,
      ``visibility`` and ``directions`` are pass 1's approximations and are not used.
      Mitsuba's own lat-long convention (measured): row centres at the polar angle
      theta = pi row / (H - 1) from +y (row 0 *on* the +y pole, the last row on the -y pole);
      column centres at u = (column + 0.5) / W, u running through the directions -z (u = 0),
      +x (u = 1/4), +z (u = 1/2), -x (u = 3/4), wrapping around. The glsldiff convention
      (:func:`glsldiff.physics.sh.latlong_directions`: row centres at theta = pi (row + 0.5) / H
      from +z; azimuth phi = -pi + 2 pi u from +x towards +y, u = (column + 0.5) / W, so
      u = 1/4 is -y, 1/2 is +x, 3/4 is +y) is mapped onto Mitsuba's by mirroring the columns
      (u -> 1 - u, exact), resampling the rows linearly in theta onto Mitsuba's row centres,
      and the ``to_world`` rotation that sends Mitsuba's local (x, y, z) to world (y, z, x); a
      test compares directions against :func:`~glsldiff.physics.sh.latlong_directions`.

- Camera: :class:`McCamera`, a pinhole with a *vertical* field of view (Mitsuba ``perspective``
  with ``fov_axis = "y"``); box reconstruction filter, so every pixel is the plain mean of its
  own samples. Row 0 of the image is the top, column 0 the left, as seen with ``up`` up. The
  camera must be outside the mesh (the sensor has no medium).

Heterogeneous volumes
---------------------
``volume = {"sigma_a": (nz, ny, nx, 3), "sigma_s": (nz, ny, nx, 3), "bbox_min": (3,),
"bbox_max": (3,)}`` (optional ``"filter": "trilinear" | "nearest"``, default ``"trilinear"``)
becomes a Mitsuba ``heterogeneous`` medium with two ``gridvolume`` textures (sigma_t and albedo)
whose ``to_world`` maps the unit cube onto the box [bbox_min, bbox_max] mm. Axis order: Mitsuba
grids are stored C-order as ``data[z, y, x, channel]`` (``gridvolume`` docs: "data[((zpos*yres +
ypos)*xres + xpos)*channels + chan]"; a ``VolumeGrid`` built from an array of shape
(2, 3, 4, 3) reports size [4, 3, 2] = (x, y, z)), i.e. the same (nz, ny, nx, 3) layout as
:mod:`glsldiff.physics.material` volumes; the last array axis runs along world +x. Sample positions are
*cell centred*: voxel (k, j, i) has its centre at ``bbox_min + ((i, j, k) + 0.5) / (nx, ny, nz)
* (bbox_max - bbox_min)``; a volume sampled at grid *nodes* spanning [p0, p1] with spacing h
should be passed with ``bbox_min = p0 - h/2``, ``bbox_max = p1 + h/2``. Outside the box the
values are clamped to the edge voxels (wrap mode ``clamp``); the medium exists only inside the
mesh. With ``trilinear`` filtering sigma_t and albedo are interpolated separately, so sigma_s
between voxel centres is the product of interpolants (exact with ``"nearest"``). When ``volume``
is given, the ``sigma_a`` / ``sigma_s`` arguments are not used (they may be None).

What ``max_depth`` counts (volpath source, ``src/integrators/volpath.cpp``, checked here by the
tests)
----------------------------------------------------------------------------------------------
``depth`` starts at 0 for the camera ray and is incremented by every *real* scattering event in
a medium and by every sampled *non-null* BSDF event (each dielectric reflection or refraction);
``null`` BSDF crossings and the null-collisions of delta tracking in heterogeneous media are not
counted. A path stops at a vertex whose depth reaches ``max_depth`` before anything is sampled
there (no next-event estimate, no emitter hit after it). Hence, with ``eta == 1`` (null
boundary):

- ``max_depth = 1``: only emitters seen directly or through the medium (unscattered, order 0);
- ``max_depth = k + 1``: scattering orders 0..k;
- ``max_depth = -1`` (default): all orders.

With a dielectric boundary every refraction and internal reflection also counts (the camera ray
entering is depth 1), so ``max_depth`` does not separate scattering orders there;
:func:`render_scattering_orders` refuses ``eta != 1``. What *can* be separated at any eta is the
surface reflection: :func:`render_subsurface` renders the object a second time with an opaque,
purely absorbing interior (same seed, low-discrepancy sampler) and subtracts.

Noise
-----
Area lights: no next-event estimation from medium vertices (the medium's
``sample_emitters = False``); paths reach the rectangle by phase-function sampling. Measured
with Mitsuba 3.9 scalar_rgb: a 40 x 40 x 5 mm slab (eta = 1) back-lit by a 4 x 4 mm rectangle
0.02 mm below it, the whole scene translated, image sums at 4096 spp: with NEE 6.54 (light at
z = -5), 7.08 (light at z = 0), 4.76 (shifted 20 mm in z), 4.16 (20 mm in x and y); without
NEE 7.19, 7.19, 7.21, 7.21. So NEE to a rectangle through a null (index-matched) boundary
loses light depending on where the scene sits; a rectangle lighting a diffuse surface with
the ``path`` integrator is exact at any offset, and a directional light through the same slab
is translation invariant to 0.2 %. With a dielectric boundary NEE cannot pass it anyway.

Chromatic extinction: volpath samples free-flight distances with one randomly chosen channel's
sigma_t and reweights the other channels by transmittance ratios, which explode on long random
walks when sigma_t differs between channels. So by default (``channels="auto"``) a medium whose
sigma_t = sigma_a + sigma_s is not grey is rendered once per channel with grey coefficients
(3x the time, far less noise; numbers in :func:`render_mitsuba`).

Russian roulette: Mitsuba's default (``rr_depth = 5``, survival probability capped at 0.95)
multiplies the weights of long random walks by 1.05^n, which makes deep, high-albedo media
(hundreds of scattering events per transmitted path) very noisy. The default here is
``rr_depth = 1_000_000`` (no roulette): without it a path ends only when it escapes the object
(absorption is handled by weighting, never by termination), which is unbiased and, for closed
objects, terminates with probability 1.
"""
from __future__ import annotations

import logging
import time
from typing import Any, Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core import checks
from glsldiff.core.errors import InputError
from glsldiff.mesh import Mesh
from glsldiff.physics.lights import Light
from glsldiff.validation.mitsuba_scene import (RGB_VARIANTS, SAMPLERS, McCamera, check_eta, check_light,
                                               check_volume, emitter_dict, load_mitsuba, medium_dict,
                                               positive_int, sensor_dict, shape_dict)

__all__ = ["McCamera", "check_ldsampler_spp", "render_mitsuba", "render_scattering_orders", "render_subsurface",
           "single_scattering_share", "RGB_VARIANTS"]

log = logging.getLogger(__name__)

#: Extinction [mm^-1] of the opaque, purely absorbing interior of :func:`render_subsurface`.
OPAQUE_SIGMA_A = 1.0e4
_NO_ROULETTE = 1_000_000
_CHANNEL_MODES = ("auto", "split", "rgb")



def check_ldsampler_spp(spp: int) -> int:
    """``spp`` if it is a power of 4 (what Mitsuba's low-discrepancy sampler renders), else an
    :class:`InputError`."""
    if spp < 4 or spp & (spp - 1) or spp.bit_length() % 2 == 0:
        raise InputError(f"spp = {spp} must be a power of 4 (4, 16, 64, 256, ...) with sampler='ldsampler' "
                         "(Mitsuba would silently round it up to one)")
    return spp


def render_mitsuba(mesh: Mesh, sigma_a: ArrayLike | None, sigma_s: ArrayLike | None, eta: float,
                   camera: McCamera, light: Light, spp: int = 256, seed: int = 0,
                   volume: Mapping[str, Any] | None = None, max_depth: int = -1,
                   variant: str = "scalar_rgb", *, rr_depth: int = _NO_ROULETTE,
                   sampler: str = "independent", channels: str = "auto", area_light_transparent: bool = False
                   ) -> tuple[NDArray[np.float32], dict[str, Any]]:
    """Render ``mesh`` filled with a scattering medium with Mitsuba 3 ``volpath``.

    Parameters
    ----------
    mesh
        Closed, outward oriented mesh, mm (the medium is its interior).
    sigma_a, sigma_s
        Homogeneous absorption and scattering coefficients [mm^-1], scalars or RGB (3,), >= 0;
        isotropic phase, so ``sigma_s`` is sigma_s'. Unused (may be None) when ``volume`` is given.
    eta
        Relative index of refraction of the medium; 1 gives an index-matched (null) boundary.
    camera
        :class:`McCamera` (vertical field of view), outside the mesh.
    light
        A :class:`~glsldiff.physics.lights.DirectionalLight` or
        :class:`~glsldiff.physics.lights.EnvironmentLight` (module docstring).
    spp, seed
        Samples per pixel and the sampler's seed; equal arguments give equal images.
    volume
        Heterogeneous medium (grid, axis order (z, y, x, RGB), cell centred; module docstring).
    max_depth
        Passed to volpath; -1 = unlimited. With ``eta == 1``, ``k + 1`` keeps scattering orders
        0..k (see the module docstring for what is counted).
    variant
        Mitsuba variant, one of :data:`RGB_VARIANTS`; JIT variants are first probed in a child
        process (BackendError if they cannot run).
    rr_depth
        Depth from which volpath uses Russian roulette; default: never (see module docstring).
    sampler
        ``"independent"`` (any ``spp``) or ``"ldsampler"`` (Mitsuba's low-discrepancy sampler;
        ``spp`` must be a power of 4: 4, 16, 64, 256, ...; Mitsuba rounds any other count up
        to one, 8 to 16 and 128 to 256, and renders that many). With ``"ldsampler"`` each
        sample's random numbers depend only on (pixel, sample index, dimension), so renders
        that differ only in ``max_depth`` (or in the medium) share their path prefixes exactly
        (used by :func:`render_scattering_orders` and :func:`render_subsurface`); the
        independent sampler draws from one stream per image block, so a path that stops
        earlier shifts the numbers of all later samples.
    channels
        ``"auto"``: one RGB render if sigma_t = sigma_a + sigma_s is the same in the three
        channels (everywhere, for a volume), else ``"split"``; ``"split"``: one render per channel
        with that channel's coefficients in all three (grey extinction), keeping channel c of
        render c; ``"rgb"``: a single RGB render. volpath samples distances with one randomly
        chosen channel's sigma_t and reweights the others by a transmittance ratio, which explodes
        on long random walks when sigma_t differs between channels (Mitsuba's docs say so and
        recommend volpathmis). Measured here, 10 mm marble slab (Jensen 2001 preset), back-lit,
        16x16 px, 64 spp: pixel relative standard deviation 9.4 / 4.3 / 1.5 (R/G/B) for one RGB
        render against 0.55 / 0.66 / 0.81 for ``"split"`` at 3x the time.
    area_light_transparent
        False: an :class:`~glsldiff.physics.lights.AreaLight`'s rectangle has Mitsuba's default
        BSDF for an emitter's shape (black diffuse, checked with Mitsuba 3.9: it absorbs the light
        that reaches it and hides what lies behind it from a camera); True: a ``null`` BSDF, so
        it still emits (one-sided) but a camera behind it sees through it. The light leaving the
        object towards it is lost either way (images from its emitting side are equal bit for bit).

    Returns
    -------
    image
        ``(height, width, 3)`` float32 linear radiance, row 0 at the top.
    info
        ``{"seconds", "spp", "seed", "variant", "integrator", "max_depth", "rr_depth", "sampler",
        "channels", "medium", "boundary", "light"}``; ``seconds`` is the wall time of scene
        loading plus rendering (all renders); ``channels`` is ``"rgb"`` or ``"split"``.
    """
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a glsldiff.mesh.Mesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise InputError(f"mesh {mesh.name!r} has no faces")
    eta = check_eta(eta)
    if not isinstance(camera, McCamera):
        raise InputError(f"camera must be a McCamera, got {type(camera).__name__}")
    lt = check_light(light, eta)
    spp = positive_int("spp", spp)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**32:
        raise InputError(f"seed must be an integer in [0, 2^32), got {seed!r}")
    if isinstance(max_depth, bool) or not isinstance(max_depth, (int, np.integer)) or \
            (max_depth < 1 and max_depth != -1):
        raise InputError(f"max_depth must be -1 (unlimited) or an integer >= 1, got {max_depth!r}")
    rr_depth = positive_int("rr_depth", rr_depth)
    if sampler not in SAMPLERS:
        raise InputError(f"sampler must be one of {', '.join(SAMPLERS)}, got {sampler!r}")
    if sampler == "ldsampler":
        check_ldsampler_spp(spp)
    if channels not in _CHANNEL_MODES:
        raise InputError(f"channels must be one of {', '.join(_CHANNEL_MODES)}, got {channels!r}")
    if area_light_transparent and lt["type"] != "area":
        raise InputError(f"area_light_transparent applies to an AreaLight, not a {type(light).__name__}; "
                         "leave it False")
    if volume is None:
        if sigma_a is None or sigma_s is None:
            raise InputError("sigma_a and sigma_s are required for a homogeneous medium (volume=None)")
        sa = np.array(checks.rgb(sigma_a, "sigma_a", "mm^-1"))
        ss = np.array(checks.rgb(sigma_s, "sigma_s", "mm^-1"))
        coeffs: dict[str, Any] = {"sigma_a": sa, "sigma_s": ss}
        st = sa + ss
    else:
        coeffs = check_volume(volume)
        st = coeffs["sigma_a"] + coeffs["sigma_s"]
    grey = bool(np.all(st == st[..., :1]))
    split = channels == "split" or (channels == "auto" and not grey)
    mi = load_mitsuba(variant)

    def render(c: dict[str, Any]) -> NDArray[np.float32]:
        scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "volpath", "max_depth": int(max_depth), "rr_depth": rr_depth},
            "sensor": sensor_dict(mi, camera, spp, int(seed), sampler),
            "light": emitter_dict(mi, lt, area_light_transparent),
            "object": shape_dict(mi, mesh, medium_dict(mi, c, volume is not None, lt["type"] != "area"), eta),
        })
        img = np.array(mi.render(scene, spp=spp, seed=int(seed)), dtype=np.float32)
        return img.reshape(camera.height, camera.width, -1)[..., :3]

    t0 = time.perf_counter()
    if split:
        image = np.empty((camera.height, camera.width, 3), np.float32)
        for k in range(3):
            one = {name: (np.repeat(a[..., k:k + 1], 3, axis=-1) if name in ("sigma_a", "sigma_s") else a)
                   for name, a in coeffs.items()}
            image[..., k] = render(one)[..., k]
    else:
        image = render(coeffs)
    seconds = time.perf_counter() - t0
    medium = ("homogeneous" if volume is None else
              f"heterogeneous {coeffs['sigma_a'].shape[:3]} ({coeffs['filter']})")
    info = {"seconds": seconds, "spp": spp, "seed": int(seed), "variant": variant,
            "integrator": "volpath", "max_depth": int(max_depth), "rr_depth": rr_depth,
            "sampler": sampler, "channels": "split" if split else "rgb", "medium": medium,
            "boundary": "null" if eta == 1.0 else f"dielectric eta={eta}", "light": lt["type"]}
    log.info("mitsuba %s: %dx%d, %d spp, %s, %.2f s", variant, camera.width, camera.height, spp,
             info["channels"], seconds)
    return image, info


def render_scattering_orders(mesh: Mesh, sigma_a: ArrayLike | None, sigma_s: ArrayLike | None,
                             eta: float, camera: McCamera, light: Light, spp: int = 256,
                             seed: int = 0, volume: Mapping[str, Any] | None = None,
                             variant: str = "scalar_rgb", *, rr_depth: int = _NO_ROULETTE,
                             channels: str = "auto", area_light_transparent: bool = False
                             ) -> tuple[dict[str, NDArray[np.float32]], dict[str, Any]]:
    """Split the image into unscattered, single and multiple scattering (index-matched only).

    Renders three times with the same seed and ``sampler="ldsampler"`` (so ``spp`` must be a
    power of 4): ``max_depth`` = 1 (order 0), 2 (orders 0-1) and -1 (all orders), and
    subtracts (``area_light_transparent`` as in :func:`render_mitsuba`). With a null boundary
    ``max_depth`` counts exactly the real scattering events (module docstring). The
    low-discrepancy sampler gives sample i of a pixel the same random number in dimension d in
    all three renders, and a truncated path consumes them in the same
    order as the full one up to its cut, so the differences are the contributions of the *same*
    paths: exactly non-negative and free of extra noise from the subtraction (the tests check
    that order 0 of a purely absorbing box equals its full image bit for bit). With the
    independent sampler this fails: one random stream per image block, so a path that stops
    earlier shifts every later sample's numbers, and differences of ~50 with pixel values ~1
    were seen in a chromatic medium.

    Raises InputError for ``eta != 1``: a dielectric boundary's refractions and internal
    reflections are counted by ``max_depth`` too, so orders cannot be separated that way (use
    :func:`render_subsurface`, which separates the surface reflection from all scattering orders).

    Returns
    -------
    images
        ``{"unscattered", "single", "multiple", "full"}``, each ``(H, W, 3)`` float32 radiance;
        unscattered + single + multiple == full.
    info
        The full render's info plus ``"seconds_total"`` for the three renders.
    """
    if check_eta(eta) != 1.0:
        raise InputError(f"scattering orders need an index-matched boundary (eta = 1), got eta = {eta}: "
                         "with a dielectric, volpath's max_depth also counts every refraction and "
                         "internal reflection, so it does not separate scattering orders")
    args = (mesh, sigma_a, sigma_s, eta, camera, light, spp, seed, volume)
    kw = dict(variant=variant, rr_depth=rr_depth, sampler="ldsampler", channels=channels,
              area_light_transparent=area_light_transparent)
    low0, i0 = render_mitsuba(*args, max_depth=1, **kw)
    low1, i1 = render_mitsuba(*args, max_depth=2, **kw)
    full, info = render_mitsuba(*args, max_depth=-1, **kw)
    images = {"unscattered": low0, "single": low1 - low0, "multiple": full - low1, "full": full}
    return images, dict(info, seconds_total=i0["seconds"] + i1["seconds"] + info["seconds"])


def render_subsurface(mesh: Mesh, sigma_a: ArrayLike | None, sigma_s: ArrayLike | None, eta: float,
                      camera: McCamera, light: Light, spp: int = 256, seed: int = 0,
                      volume: Mapping[str, Any] | None = None, variant: str = "scalar_rgb", *,
                      rr_depth: int = _NO_ROULETTE, channels: str = "auto"
                      ) -> tuple[dict[str, NDArray[np.float32]], dict[str, Any]]:
    """Split the image into the surface reflection and the light that entered the medium (any eta).

    Renders twice with the same seed and ``sampler="ldsampler"`` (``spp`` a power of 4): the
    object as given (``"full"``), and the same boundary around an opaque, purely absorbing
    interior (sigma_a = :data:`OPAQUE_SIGMA_A` mm^-1, sigma_s = 0: light that refracts in dies
    within about a micrometre), which leaves only what the boundary reflects (``"reflection"``;
    zero on the object for ``eta == 1``). ``"subsurface"`` = full - reflection is the light that
    entered the medium, all scattering orders (plus the unscattered light transmitted straight
    through, exp(-sigma_t chord), negligible in dense media). As in
    :func:`render_scattering_orders`, the low-discrepancy sampler gives the two renders the same
    random numbers, and a path uses them identically until it first enters the medium (camera
    ray, Fresnel choice at the boundary, reflected rays); so every reflected path cancels exactly,
    pixels off the object are exactly 0, and the subtraction adds no noise of its own. For a
    non-convex object, reflected light that refracts in elsewhere counts as subsurface.

    Returns ``({"reflection", "subsurface", "full"}, info)``, images ``(H, W, 3)`` float32; info is
    the full render's plus ``"seconds_total"`` for both renders.
    """
    args = (mesh, sigma_a, sigma_s, eta, camera, light, spp, seed, volume)
    kw = dict(variant=variant, rr_depth=rr_depth, sampler="ldsampler", channels=channels)
    full, info = render_mitsuba(*args, max_depth=-1, **kw)
    kw["channels"] = info["channels"]  # the same render mode, so the reflected paths are the same
    surface, i1 = render_mitsuba(mesh, OPAQUE_SIGMA_A, 0.0, eta, camera, light, spp, seed, None, **kw)
    images = {"reflection": surface, "subsurface": full - surface, "full": full}
    return images, dict(info, seconds_total=info["seconds"] + i1["seconds"])


def single_scattering_share(mesh: Mesh, sigma_a: ArrayLike | None, sigma_s: ArrayLike | None,
                            eta: float, camera: McCamera, light: Light, spp: int = 256,
                            seed: int = 0, volume: Mapping[str, Any] | None = None,
                            variant: str = "scalar_rgb", *, rr_depth: int = _NO_ROULETTE,
                            channels: str = "auto") -> tuple[NDArray[np.float32], dict[str, Any]]:
    """Per-pixel share of single scattering in the scattered radiance, single / (single + multiple).

    From :func:`render_scattering_orders` (eta = 1 only); pixels without scattered light get 0.
    The info dict carries the component images under ``"images"``, so the multiple-scattering-only
    image (what the diffusion model predicts) is ``info["images"]["multiple"]``.
    """
    images, info = render_scattering_orders(mesh, sigma_a, sigma_s, eta, camera, light, spp, seed,
                                            volume, variant, rr_depth=rr_depth, channels=channels)
    scattered = images["single"] + images["multiple"]
    share = np.divide(images["single"], scattered, out=np.zeros_like(scattered), where=scattered > 0)
    return share.astype(np.float32), dict(info, images=images)
