"""``glsldiff validate``: the diffusion renderer against Monte Carlo (Mitsuba 3) and the dipole.

Each case is rendered with the same mesh, camera, light and material by
:class:`glsldiff.render.renderer.Renderer` (the diffusion image: no specular, no single
scattering; then the frame with single scattering, :mod:`glsldiff.render.single`, whose
difference is our single-scattering image) and by Mitsuba 3's ``volpath``
(:mod:`glsldiff.validation.mitsuba`). Components compared where Monte Carlo splits them
(eta = 1): multiple (diffusion vs MC multiple), single (ours vs MC single, each with MC's
noise), total (diffusion, and diffusion + single, vs all orders); the localized cases add the
unscattered light.

Lights: a directional light (irradiance 1 on a surface facing it), or an environment
(:data:`ENVIRONMENTS`, radiance about 1): one :class:`~glsldiff.physics.lights.EnvironmentLight`
of the lat-long map (:func:`environment_map`) goes to both renderers: to the diffusion
renderer (order-2 spherical harmonics, Fresnel transmission folded in, per-node visibility)
and to Mitsuba's ``envmap`` in the renderer's z-up convention (tested against
:func:`glsldiff.physics.sh.latlong_directions`); the uniform one becomes Mitsuba's
``constant`` emitter (:mod:`glsldiff.validation.mitsuba` converts the light).

Boundary: ``eta = 1`` is index matched (Mitsuba ``null`` BSDF); the Monte Carlo image is then
split into scattering orders (:func:`~glsldiff.validation.mitsuba.render_scattering_orders`) and its
*multiple-scattering* part is compared too. ``eta != 1`` is a smooth dielectric; it needs an
environment light (a delta light cannot be reached through a delta BSDF by next-event
estimation). There ``max_depth`` also counts refractions and internal reflections, so orders
cannot be split; instead :func:`~glsldiff.validation.mitsuba.render_subsurface` renders the same
boundary around an opaque absorbing interior (reflection only) with the same random numbers and
subtracts, which removes the specular surface reflection exactly (the renderer's Ward specular
is off, rho_s = 0). Every case is compared with the *subsurface* image, all scattering orders:
unscattered + single + multiple for eta = 1, full - reflection for eta != 1 (both include the
light seen straight through a thin part).

Error: relative RMSE ``sqrt(mean (L - L_mc)^2 / mean L_mc^2)`` over the pixels inside the
object in both images, one pixel away from the silhouette (anti-aliased edge pixels differ by
construction); also the ratio of the means (a global scale error), the Monte Carlo noise
level of the subsurface image (standard error of the mean image, from two half-sample
renders), and the share of the Monte Carlo image on the object that the surface reflects.

The slab case also reports the face-centre radiance against the dipole's total diffuse
reflectance (``L = rho_dipole E / pi``; the slab is 20 transport mean free paths thick, so the
semi-infinite dipole applies).
"""
from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import binary_erosion

from glsldiff.core import checks, io
from glsldiff.core.plotting import pyplot
from glsldiff.core.errors import InputError
from glsldiff.mesh import box_mesh
from glsldiff.physics.collision import SOURCES
from glsldiff.physics.lights import AreaLight, DirectionalLight, EnvironmentLight, Light, SpotLight
from glsldiff.physics.optics import dipole_total_reflectance
from glsldiff.physics.sh import latlong_directions
from glsldiff.render.camera import frame_camera
from glsldiff.render.materials import node_material
from glsldiff.render.renderer import Renderer
from glsldiff.render.unscattered import sees_through
from glsldiff.physics.exitance import INCIDENCE
from glsldiff.render.scene import (FLUXES, MODELS, CameraSpec, MaterialSpec, MeshSpec, OptionsSpec, OutputSpec, PolygridSpec,
                                   Scene, SpecularSpec, default_cubes)
from glsldiff.validation.mitsuba import McCamera, render_scattering_orders, render_subsurface
from glsldiff.validation.mitsuba_scene import load_mitsuba

#: Environment lights a case may name (:func:`environment_map`).
ENVIRONMENTS = ("constant", "sky")
#: Localized lights a slab case may name: a diffuse square behind it, a hard-edged spot in front.
LOCALIZED = ("patch", "spot")
#: Distance of the "spot" light from the slab's front face, mm.
SPOT_DISTANCE_MM = 100.0


Coefficient = float | tuple[float, float, float]


def _rgb(x: Coefficient) -> tuple[float, float, float]:
    return tuple(float(v) for v in x) if isinstance(x, tuple) else (float(x),) * 3   # type: ignore[return-value]


@dataclass(frozen=True)
class Case:
    """One validation scene: lengths in mm, coefficients in mm^-1 (grey, or RGB tuples).

    The renderer's options below default to ``None``: the scene's own default (what ``glsldiff
    render`` does with a scene that does not set them). A case that sets any of them is an
    extra row, "tuned", and the table's ``options`` column names what it sets."""

    name: str
    mesh: str                       # "sphere" or "slab" or a sample name
    size_mm: float
    sigma_a: Coefficient
    sigma_s: Coefficient            # sigma_s' (isotropic phase in Mitsuba)
    light: tuple[float, float, float] | str   # towards a directional light, a name in ENVIRONMENTS, or "patch"
    camera_dir: tuple[float, float, float]
    procedural: str | None = None
    eta: float = 1.0                # relative index of refraction of the boundary
    thickness_mm: float | None = None   # slab thickness (default size_mm / 3)
    patch_mm: float = 4.0           # side of the "patch" light: a diffuse square against the slab's back face;
                                    # full cone angle of the "spot" light, 100 mm in front of the slab (degrees)
    view_mm: float | None = None    # half-width of the field seen (default: the object framed)
    spp_factor: int = 1             # Monte Carlo samples per pixel: this times the command's spp
    volume_mm: float | None = None  # voxel size of Mitsuba's copy of a procedural material (default 48 cells)
    pixels: int | None = None       # image side (default: the command's --size)
    # the renderer's options; None = the scene default
    n: int | None = None
    cubes: int | None = None
    discretisation: str | None = None
    edge_mm: float | None = None    # tetwild's target edge length, mm
    adapt: bool | str | None = None
    model: str | None = None
    source: str | None = None
    flux: str | None = None
    incidence: str | None = None
    single_scattering: bool | str | None = None
    tol: float | None = None

    #: The option fields, in the order the ``options`` column lists them.
    OPTIONS = ("n", "cubes", "discretisation", "edge_mm", "adapt", "model", "source", "flux", "incidence",
               "single_scattering", "tol")

    @property
    def options(self) -> str:
        """``"defaults"``, or the options this case sets (``"n=2 cubes=15000 source=volume"``)."""
        given = [f"{k}={getattr(self, k)}" for k in self.OPTIONS if getattr(self, k) is not None]
        return " ".join(given) if given else "defaults"

    @property
    def albedo(self) -> str:
        """The reduced albedo per channel, as text (one number when grey)."""
        a = [s / (s + sa) for s, sa in zip(_rgb(self.sigma_s), _rgb(self.sigma_a))]
        return f"{a[0]:.3g}" if len(set(a)) == 1 else "/".join(f"{x:.3g}" for x in a)

    @property
    def refines(self) -> bool:
        """The diffusion grid is refined under the light's sharp edges (:meth:`PolygridSpec.refines`)."""
        return _polygrid(self).refines((_light(self),))

    def __post_init__(self) -> None:
        if isinstance(self.light, str) and self.light not in ENVIRONMENTS + LOCALIZED:
            raise InputError(f"case {self.name}: light {self.light!r} is not an environment "
                             f"({', '.join(ENVIRONMENTS)}), one of {', '.join(LOCALIZED)} or a direction")
        if self.light in LOCALIZED and self.mesh != "slab":
            raise InputError(f"case {self.name}: the {self.light} light is placed for a slab; mesh = \"slab\"")
        if self.eta != 1.0 and not isinstance(self.light, str):
            raise InputError(f"case {self.name}: eta = {self.eta} needs an environment light (a directional "
                             "light cannot reach a dielectric interior by next-event estimation)")


_SPHERE = Case("sphere", "sphere", 20.0, 0.005, 1.0, (1.0, 0.3, 0.6), (0.0, 0.0, 1.0))
#: Issue 18's localized case: a 5 mm slab back-lit by a 4 x 4 mm diffuse patch, seen from the front.
_PATCH = Case("slab-patch", "slab", 40.0, 0.02, 1.2, "patch", (0.0, 0.0, 1.0), eta=1.4, thickness_mm=5.0,
              view_mm=12.0, spp_factor=64)
#: Back-lit slabs of a few transport mean free paths: 20 x 20 mm, sigma_s' 1, sigma_a 0.01 /mm, eta 1.3,
#: a 5 x 5 mm Lambertian patch touching the back face, seen from the front over +-8 mm.
_BACKLIT = Case("slab-backlit", "slab", 20.0, 0.01, 1.0, "patch", (0.0, 0.0, 1.0), eta=1.3, patch_mm=5.0,
                view_mm=8.0, pixels=32, spp_factor=64)
#: Camera directions of the environment cases: the sky's zenith (+z) at the image's left.
_ENV_VIEW = {"constant": (0.0, 0.0, 1.0), "sky": (1.0, 0.0, 0.0)}
#: The front-lit sphere's albedos (sigma_s' 1 /mm, sigma_a = (1 - a) / a).
ALBEDOS = (0.3, 0.5, 0.7, 0.8, 0.9, 0.95, 0.99)
#: Back-lit slab thicknesses, transport mean free paths.
BACKLIT_MFP = (2, 4, 8)
CASES = {c.name: c for c in (
    Case("slab", "slab", 60.0, 0.005, 1.0, (0.0, 0.0, 1.0), (0.0, 0.35, 1.0)),
    _SPHERE,
    *(replace(_SPHERE, name=f"sphere-albedo{a:g}", sigma_a=round((1.0 - a) / a, 6)) for a in ALBEDOS),
    replace(_SPHERE, name="sphere-skin", sigma_a=(0.032, 0.17, 0.48), sigma_s=(0.74, 0.88, 1.01)),
    replace(_SPHERE, name="sphere-ketchup", sigma_a=(0.061, 0.97, 1.45), sigma_s=(0.18, 0.07, 0.03)),
    replace(_SPHERE, name="sphere-veins", procedural="veins"),
    Case("bunny-veins", "bunny", 60.0, 0.005, 1.0, (-0.4, 0.7, 0.6), (0.0, 0.2, 1.0), procedural="veins"),
    Case("bunny-veins-tetwild", "bunny", 60.0, 0.005, 1.0, (-0.4, 0.7, 0.6), (0.0, 0.2, 1.0), procedural="veins",
         discretisation="tetwild", edge_mm=1.5),
    *(replace(_SPHERE, name=f"sphere{'-eta1.3' if eta != 1.0 else ''}-{env}", light=env, eta=eta,
              camera_dir=_ENV_VIEW[env]) for eta in (1.0, 1.3) for env in ENVIRONMENTS),
    _PATCH,
    replace(_PATCH, name="slab-patch-tuned", n=2, cubes=15000, source="volume", model="diffusion", tol=1e-5),
    *(replace(_BACKLIT, name=f"slab-backlit-{m}mfp", thickness_mm=round(m / 1.01, 4)) for m in BACKLIT_MFP),
    replace(_PATCH, name="slab-spot", light="spot", patch_mm=6.0, eta=1.0, thickness_mm=10.0, spp_factor=4),
    replace(_PATCH, name="slab-patch-eta1", eta=1.0, spp_factor=16),
    replace(_PATCH, name="slab-inclusion", eta=1.0, procedural="sphere", spp_factor=16, volume_mm=0.2),
)}
#: Named groups of cases for ``--cases``.
GROUPS = {
    "default": ("slab", "sphere", "sphere-veins", "sphere-constant", "sphere-eta1.3-constant", "sphere-sky",
                "sphere-eta1.3-sky"),
    "albedo": tuple(f"sphere-albedo{a:g}" for a in ALBEDOS),
    "backlit": tuple(f"slab-backlit-{m}mfp" for m in BACKLIT_MFP),
    "rgb": ("sphere-skin", "sphere-ketchup"),
    "localized": ("slab-patch", "slab-patch-tuned", "slab-spot", "slab-patch-eta1", "slab-inclusion"),
}


def expand_cases(names: Sequence[str]) -> list[str]:
    """Case names, with group names (:data:`GROUPS`, and ``all``) expanded, in order, once each."""
    out: list[str] = []
    for name in names:
        group = tuple(CASES) if name == "all" else GROUPS.get(name, (name,))
        out.extend(n for n in group if n not in out)
    return out


#: Samples per pixel of each of the two Monte Carlo renders of the unscattered light alone.
UNSCATTERED_SPP = 8192
#: Where the patch light sits below the slab's back face, mm (Mitsuba needs a gap between them).
PATCH_GAP_MM = 0.02


def environment_map(name: str, height: int = 64, width: int = 128) -> NDArray[np.float64]:
    """Lat-long radiance map ``(height, width, 3)`` of environment ``name`` in the convention of
    :class:`glsldiff.physics.lights.EnvironmentLight` (row 0 is the zenith +z).

    ``"constant"``: 1 everywhere. ``"sky"``: ``0.05 + a (1 + z)^2 + b (1 + y)`` for the unit
    direction (x, y, z), a = (0.20, 0.22, 0.25) and b = (0.15, 0.12, 0.08) per RGB channel: a
    bluish upper hemisphere (about 1.1 at the zenith) over a dim lower one (0.05 to 0.35), with
    a warm gradient towards +y. A quadratic polynomial of the direction, so it is exactly band
    limited to spherical-harmonic order 2: the renderer's projection loses nothing, and what
    differs from Monte Carlo is the diffusion model (and the map's pixel sampling), not the
    light's band limit.
    """
    if name not in ENVIRONMENTS:
        raise InputError(f"unknown environment {name!r}; valid: {', '.join(ENVIRONMENTS)}")
    if name == "constant":
        return np.ones((height, width, 3))
    d, _ = latlong_directions(height, width)
    y, z = d[..., 1:2], d[..., 2:3]
    return 0.05 + np.array([0.20, 0.22, 0.25]) * (1.0 + z) ** 2 + np.array([0.15, 0.12, 0.08]) * (1.0 + y)


def _thickness(case: Case) -> float:
    return case.thickness_mm if case.thickness_mm is not None else case.size_mm / 3.0


def _light(case: Case) -> Light:
    """The case's light, the same for the renderer and for
    :func:`glsldiff.validation.mitsuba.render_mitsuba`."""
    if case.light == "spot":    # irradiance 1 at the front face's centre, a disc of radius d tan(cone / 2)
        d = SPOT_DISTANCE_MM
        return SpotLight((0.0, 0.0, d), (0.0, 0.0, -1.0), (d * d,) * 3, cone_deg=case.patch_mm / 2.0,
                         falloff_deg=case.patch_mm / 2.0)
    if case.light == "patch":   # the slab spans z in [-thickness, 0]: the patch faces its back face
        return AreaLight((0.0, 0.0, -_thickness(case) - PATCH_GAP_MM), (0.0, 0.0, 1.0), (case.patch_mm,) * 2,
                         (1.0, 1.0, 1.0))
    if isinstance(case.light, str):
        return EnvironmentLight(environment_map(case.light))
    return DirectionalLight(case.light, (1.0, 1.0, 1.0))


def _polygrid(case: Case) -> PolygridSpec:
    """The case's ``[polygrid]``: the scene default with the options the case sets."""
    disc = case.discretisation or PolygridSpec().discretisation
    if disc == "tetwild":
        return PolygridSpec(discretisation="tetwild", edge_mm=case.edge_mm, adapt=False)
    n = case.n if case.n is not None else PolygridSpec().n if disc == "fem" else 8
    cubes = case.cubes if case.cubes is not None else default_cubes(disc, n)
    levels = 1 if disc == "fem" else (3 if n >= 8 else (2 if n >= 6 else 1))
    adapt = (case.adapt if case.adapt is not None else PolygridSpec().adapt) if disc == "fem" else False
    return PolygridSpec(n, cubes, levels, disc, adapt=adapt)


def _options(case: Case) -> OptionsSpec:
    """The case's ``[options]``: the scene default with the options the case sets."""
    given = {k: getattr(case, k) for k in ("model", "source", "flux", "incidence", "single_scattering", "tol")
             if getattr(case, k) is not None}
    return replace(OptionsSpec(), **given)


def _scene(case: Case, mesh_path: str | None, size: int) -> Scene:
    return Scene(mesh=MeshSpec(mesh_path or case.mesh, case.size_mm),
                 polygrid=_polygrid(case),
                 material=MaterialSpec(preset=None, sigma_a=_rgb(case.sigma_a), sigma_s_prime=_rgb(case.sigma_s),
                                       eta=case.eta, procedural=case.procedural),
                 lights=(_light(case),),
                 camera=CameraSpec(fov_deg=30.0), output=OutputSpec(size, size), specular=SpecularSpec(0.0, 0.2),
                 options=_options(case))


def rmse(ours: NDArray, ref: NDArray, mask: NDArray) -> float:
    """Relative RMSE over ``mask``."""
    a, b = ours[mask], ref[mask]
    return float(math.sqrt(np.mean((a - b) ** 2) / np.mean(b ** 2)))


def _standard_error(parts: Sequence[NDArray], mask: NDArray) -> float:
    """Relative standard error over ``mask`` of the mean of independent renders ``parts``:
    ``sqrt(mean s^2 / m / mean L^2)``, s^2 the per-pixel sample variance of the m renders and L
    their mean (for two renders, half the relative RMS difference)."""
    stack = np.stack([p[mask] for p in parts])
    m = len(parts)
    return float(math.sqrt(np.mean(stack.var(axis=0, ddof=1)) / m / np.mean(stack.mean(axis=0) ** 2)))


def _slab_file(folder: Path, size: float, thickness: float) -> str:
    import trimesh   # heavy import, only for the PLY export

    m = box_mesh((size, size, thickness), origin=(-size / 2, -size / 2, -thickness))

    path = folder / "slab.ply"
    trimesh.Trimesh(m.vertices, m.faces, process=False).export(path)
    return str(path)


def _volume(scene: Scene, pg: Any, voxel_mm: float | None = None) -> dict[str, Any]:
    """The scene's procedural material on a regular grid spanning the nodes' bounding box
    (the same unit box :mod:`glsldiff.render.materials` evaluates it in), for Mitsuba: 48
    cells per axis, or cells of about ``voxel_mm`` (at most 256 per axis)."""
    lo, hi = pg.positions.min(axis=0), pg.positions.max(axis=0)
    cells = [48] * 3 if voxel_mm is None else [int(min(256, max(8, np.ceil((hi[i] - lo[i]) / voxel_mm) + 1)))
                                               for i in range(3)]
    axes = [np.linspace(lo[i], hi[i], cells[i]) for i in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    kappa, mu, _ = node_material(scene, pts, pg)
    shape = (cells[2], cells[1], cells[0], 3)
    sa = mu.reshape(shape)
    ss = np.maximum(1.0 / (3.0 * kappa) - mu, 0.0).reshape(shape)
    h = (hi - lo) / (np.asarray(cells) - 1)
    return {"sigma_a": sa, "sigma_s": ss, "bbox_min": lo - h / 2, "bbox_max": hi + h / 2}


def _mc_render(case: Case, mesh: Any, cam: Any, spp: int, seed: int,
               volume: dict[str, Any] | None) -> tuple[dict[str, NDArray], float]:
    """Mitsuba images of one case: ``"subsurface"`` (all scattering orders) and ``"full"``;
    with eta = 1 also the scattering orders ``"single"`` and ``"multiple"``, else
    ``"reflection"`` (module docstring); and the seconds taken."""
    sa, ss = (None, None) if volume else (_rgb(case.sigma_a), _rgb(case.sigma_s))
    args = (mesh, sa, ss, case.eta, cam, _light(case), spp, seed, volume)
    if case.eta != 1.0:
        images, info = render_subsurface(*args)
    else:
        images, info = render_scattering_orders(*args)
        # all orders, the light seen straight through a thin part (order 0) included, as at eta != 1
        images["subsurface"] = images["unscattered"] + images["single"] + images["multiple"]
    return images, info["seconds_total"]


def mc_split(spp: int) -> tuple[int, int]:
    """``spp`` samples per pixel as (renders, samples each): Mitsuba's low-discrepancy sampler
    needs a power of 4 per render (it silently rounds other counts up), and at least two
    renders with different seeds are needed for the noise estimate; so ``spp`` must be a power
    of two >= 8 (256 = 4 x 64, 512 = 2 x 256)."""
    if isinstance(spp, bool) or not isinstance(spp, int) or spp < 8 or spp & (spp - 1):
        raise InputError(f"spp = {spp!r} must be a power of two >= 8 (Monte Carlo renders of 4^k samples "
                         "per pixel, at least two of them)")
    each = 4 ** ((spp.bit_length() - 2) // 2)   # the largest power of 4 <= spp / 2
    return spp // each, each


def run_case(case: Case, size: int = 64, spp: int = 256, seed: int = 0,
             folder: Path | None = None) -> tuple[dict[str, Any], dict[str, NDArray]]:
    """One case: (row of numbers, images {"diffusion", "diffusion_single", "mc_subsurface",
    "mc_full"} and, with eta = 1, "mc_multiple" and "mc_single"; the patch case adds
    "diffusion_unscattered" and "mc_unscattered").
    With ``folder``, an environment map is written there as
    ``validation_<case>_environment.exr``."""
    env = case.light in ENVIRONMENTS
    localized = case.light in LOCALIZED
    size = case.pixels or size
    with tempfile.TemporaryDirectory() as tmp:
        mesh_path = _slab_file(Path(tmp), case.size_mm, _thickness(case)) if case.mesh == "slab" else None
        if env and folder is not None:   # the map both renderers get, for the record
            folder.mkdir(parents=True, exist_ok=True)
            io.write_exr(folder / f"validation_{case.name}_environment.exr", environment_map(str(case.light)))
        scene = _scene(case, mesh_path, size)
        d = np.asarray(case.camera_dir, float)
        d = d / np.linalg.norm(d)
        with Renderer() as r:
            _, rep1 = r.render(scene)             # set-up, passes 1-3 (camera framed automatically)
            eye, target, up = frame_camera(scene, r.mesh.vertices)
            fov = scene.camera.fov_deg
            if case.view_mm is not None:          # a field of +-view_mm around the origin, from 200 mm
                target, dist = np.zeros(3), 200.0
                fov = 2.0 * math.degrees(math.atan(case.view_mm / dist))
            else:
                dist = float(np.linalg.norm(eye - target))
            eye = target + dist * d
            if abs(float(np.dot(up, d))) > 0.99:
                up = np.array([0.0, 1.0, 0.0])
            scene = replace(scene, camera=CameraSpec(tuple(eye), tuple(target), tuple(up), fov))
            ours, rep = r.render(scene)           # the compared view: pass 3 only
            rep.seconds.update({k: rep1.seconds[k] for k in ("t1", "t2") if k in rep1.seconds})
            rep.solver = rep1.solver
            ours_s = rep.frame_seconds
            ours_unscattered = np.zeros_like(ours)
            if localized and sees_through(scene.lights):   # the unscattered term alone: the frame without it
                dark, _ = r.render(replace(scene, options=replace(scene.options, unscattered=False)))
                ours_unscattered = ours - dark
            t0 = time.perf_counter()
            split = scene.options.split
            if split:                                 # the split's own parts: single, and two or more orders
                bare = replace(scene, options=replace(scene.options, unscattered=False))
                r.split_part = "single"
                ours_single, _ = r.render(bare)
                r.split_part = "multiple"
                ours_multiple, _ = r.render(bare)
                r.split_part = None
            else:                                     # single scattering: the frame with it, minus without
                lit, _ = r.render(replace(scene, options=replace(scene.options, single_scattering=True)))
                ours_single = lit - ours
                ours_multiple = ours - ours_unscattered
            single_s = time.perf_counter() - t0
            pg, mesh = r.polygrid, r.mesh
            volume = _volume(scene, pg, case.volume_mm) if case.procedural else None
    cam = McCamera(tuple(eye), tuple(target), tuple(up), fov, size, size)
    renders, each = mc_split(spp * case.spp_factor)
    parts, seconds = zip(*(_mc_render(case, mesh, cam, each, seed + k, volume) for k in range(renders)))
    mc = {k: np.mean([p[k] for p in parts], axis=0) for k in parts[0]}
    sub = mc["subsurface"]
    if localized:
        row, images = _localized_row(case, rep, ours, ours_unscattered, ours_s, parts, mc, sum(seconds), mesh, cam,
                                     seed, renders * each, volume)
        every = np.ones(ours.shape[:2], dtype=bool)
        row.update(_single_columns(ours - ours_single if split else ours, ours_single, single_s, parts, mc, every))
        with_single = ours if split else ours + ours_single
        row["power_ratio_with_single"] = float(with_single.sum() / mc["subsurface"].sum())
        row["peak_ratio_with_single"] = _centre(with_single, _peak_half(case, size)) / row["peak_mc"]
        images["diffusion_single"] = ours_single
        if "single" in mc:
            images["mc_single"] = mc["single"]
        return row, images
    unsplit = np.full_like(sub, np.nan)   # eta != 1: no scattering orders, their numbers are NaN
    multiple, single = mc.get("multiple", unsplit), mc.get("single", unsplit)
    inside = binary_erosion((ours.sum(axis=2) > 0) & (sub.sum(axis=2) > 0), iterations=1)
    if inside.sum() < 16:
        raise InputError(f"case {case.name}: the object covers too few pixels ({int(inside.sum())}) to compare")
    sub_sum = max(float(sub[inside].sum()), 1e-30)
    row: dict[str, Any] = {
        "case": case.name, "options": case.options, "model": rep.model, "light": case.light if env else "directional",
        "eta": case.eta, "albedo": case.albedo, "material": case.procedural or "homogeneous",
        "nodes": rep.nodes, "adapt": case.refines, "pixels": int(inside.sum()),
        "rmse_vs_mc_all_scattering": rmse(ours, sub, inside),
        "mean_ratio_all_scattering": float(ours[inside].mean() / sub[inside].mean()),
        "rmse_vs_mc_multiple": rmse(ours_multiple, multiple, inside),
        "mean_ratio": float(ours_multiple[inside].mean() / multiple[inside].mean()),
        "mc_noise": _standard_error([p["subsurface"] for p in parts], inside),
        "single_share": float(single[inside].sum()) / sub_sum,
        "surface_share": 1.0 - sub_sum / max(float(mc["full"][inside].sum()), 1e-30),
        "diffusion_s": ours_s, "t1_t2_t3_ms": "/".join(f"{rep.seconds.get(k, 0) * 1e3:.0f}" for k in ("t1", "t2", "t3")),
        "mc_s": sum(seconds), "spp": renders * each, "solver_residual": rep.solver.residual if rep.solver else math.nan,
        **_single_columns(ours_multiple, ours_single, single_s, parts, mc, inside),
    }
    if case.mesh == "slab" and not env:
        c = size // 2
        patch = (slice(c - 2, c + 3), slice(c - 2, c + 3))
        rho = float(np.mean(dipole_total_reflectance(np.asarray(_rgb(case.sigma_a)), np.asarray(_rgb(case.sigma_s)),
                                                     case.eta)))
        row["centre_diffusion"] = float(ours_multiple[patch].mean())
        row["centre_mc_multiple"] = float(multiple[patch].mean())
        row["centre_dipole"] = rho * 1.0 * abs(case.light[2]) / np.linalg.norm(case.light) / math.pi
    images = {"diffusion": ours, "mc_subsurface": sub, "mc_full": mc["full"], "diffusion_single": ours_single,
              "diffusion_multiple": ours_multiple}
    if "multiple" in mc:
        images["mc_multiple"], images["mc_single"] = multiple, single
    return row, images


def _single_columns(ours: NDArray, single: NDArray, single_s: float, parts: Sequence[dict[str, NDArray]],
                    mc: dict[str, NDArray], mask: NDArray) -> dict[str, Any]:
    """Our single scattering (:mod:`glsldiff.render.single`) against Monte Carlo's (eta = 1:
    relative RMSE, ratio of sums, the noise of MC's single- and multiple-scattering images;
    NaN otherwise), and the frame with it (multiple + single) against all scattering orders."""
    sub = mc["subsurface"]
    row: dict[str, Any] = {"rmse_with_single_vs_mc_all": rmse(ours + single, sub, mask),
                           "single_share_ours": float(single[mask].sum() / max(float((ours + single)[mask].sum()), 1e-30)),
                           "single_s": single_s}
    if "single" in mc and mc["single"][mask].sum() > 0:
        row["rmse_single_vs_mc_single"] = rmse(single, mc["single"], mask)
        row["single_ratio"] = float(single[mask].sum() / mc["single"][mask].sum())
        row["mc_single_noise"] = _standard_error([p["single"] for p in parts], mask)
    else:
        row["rmse_single_vs_mc_single"] = row["single_ratio"] = row["mc_single_noise"] = math.nan
    row["mc_multiple_noise"] = (_standard_error([p["multiple"] for p in parts], mask) if "multiple" in mc
                                else math.nan)
    return row


def _peak_half(case: Case, size: int) -> int:
    """Half-width in pixels of the central 2 x 2 mm where a localized case's peak is measured."""
    px_mm = 2.0 * case.view_mm / size if case.view_mm else 1.0
    return max(1, int(round(1.0 / px_mm)))


def _centre(img: NDArray, half_px: int) -> float:
    c0, c1 = img.shape[0] // 2, img.shape[1] // 2
    return float(img[c0 - half_px:c0 + half_px, c1 - half_px:c1 + half_px].mean())


def _localized_row(case: Case, rep: Any, ours: NDArray, ours_unscattered: NDArray, ours_s: float,
                   parts: Sequence[dict[str, NDArray]], mc: dict[str, NDArray], mc_s: float, mesh: Any,
                   cam: McCamera, seed: int, spp: int, volume: dict[str, Any] | None = None
                   ) -> tuple[dict[str, Any], dict[str, NDArray]]:
    """Numbers and images of the localized cases (back-lit patch, spot): over the whole field
    (the slab fills it), relative L2 of the subsurface image, the ratio of the summed images
    (power), of the central 2 x 2 mm (peak), Monte Carlo's single-scattering share (eta = 1),
    and of the unscattered images: Monte Carlo's is a render of the same slab with sigma_s = 0
    (extinction sigma_a + sigma_s, nothing scatters; of the case's ``volume`` when
    heterogeneous), two renders of ``UNSCATTERED_SPP`` samples (their difference: the noise of
    its power); a spot light is never seen through."""
    from glsldiff.validation.mitsuba import render_mitsuba

    sub = mc["subsurface"]
    every = np.ones(sub.shape[:2], dtype=bool)
    st = tuple(a + b for a, b in zip(_rgb(case.sigma_a), _rgb(case.sigma_s)))
    t0 = time.perf_counter()   # nothing scatters: a path survives with probability exp(-tau), so many samples
    if case.light == "patch":
        straight = None if volume is None else {**volume, "sigma_a": volume["sigma_a"] + volume["sigma_s"],
                                                "sigma_s": np.zeros_like(volume["sigma_s"])}
        halves = [render_mitsuba(mesh, st, (0.0,) * 3, case.eta, cam, _light(case), UNSCATTERED_SPP,
                                 seed + 99 + k, straight)[0] for k in range(2)]
    else:                      # a point light is never seen through the object
        halves = [np.zeros_like(sub)] * 2
    unsc = 0.5 * (halves[0] + halves[1])
    mc_unsc_s = time.perf_counter() - t0
    half = _peak_half(case, sub.shape[0])
    peak_mc = _centre(sub, half)
    row: dict[str, Any] = {
        "case": case.name, "options": case.options, "model": rep.model, "eta": case.eta,
        "light": f"patch {case.patch_mm:g} mm" if case.light == "patch" else f"spot {case.patch_mm:g} deg",
        "albedo": case.albedo, "thickness_mm": _thickness(case), "nodes": rep.nodes,
        "adapt": case.refines, "pixels": int(every.sum()),
        "rel_l2": rmse(ours, sub, every), "power_ratio": float(ours.sum() / sub.sum()),
        "peak_ratio": _centre(ours, half) / peak_mc, "peak_mc": peak_mc,
        "mc_noise": _standard_error([p["subsurface"] for p in parts], every),
        "unscattered_share_mc": float(unsc.sum() / sub.sum()),
        "unscattered_mc_noise": (float(abs(halves[0].sum() - halves[1].sum()) / (2.0 * float(unsc.sum())))
                                 if unsc.sum() > 0 else math.nan),
        "unscattered_ratio": float(ours_unscattered.sum() / unsc.sum()) if unsc.sum() > 0 else math.nan,
        "single_share_mc": float(mc["single"].sum() / sub.sum()) if "single" in mc else math.nan,
        "diffusion_s": ours_s, "t1_t2_t3_ms": "/".join(f"{rep.seconds.get(k, 0) * 1e3:.0f}" for k in ("t1", "t2", "t3")),
        "mc_s": mc_s + mc_unsc_s, "spp": spp, "solver_residual": rep.solver.residual if rep.solver else math.nan,
    }
    images = {"diffusion": ours, "mc_subsurface": sub, "mc_full": mc["full"], "diffusion_unscattered": ours_unscattered,
              "mc_unscattered": np.asarray(unsc, dtype=np.float64)}
    return row, images


def _panels(path: Path, mc: NDArray, ours: NDArray, name: str, mc_title: str = "Monte Carlo (subsurface)",
            ours_title: str = "diffusion (ours)") -> None:
    """PNG of four panels (luminance, channel mean): Monte Carlo's subsurface image, ours, their
    difference (ours - MC, symmetric colour scale) and both along the centre row."""
    plt = pyplot()
    a, b = mc.mean(axis=2), ours.mean(axis=2)
    top = max(float(np.percentile(a, 99.5)), 1e-12)
    fig, ax = plt.subplots(1, 4, figsize=(15, 3.6))
    for k, (img, title) in enumerate(((a, mc_title), (b, ours_title))):
        im = ax[k].imshow(img, cmap="magma", vmin=0.0, vmax=top)
        ax[k].set_title(title)
        fig.colorbar(im, ax=ax[k], fraction=0.046)
    lim = max(float(np.abs(b - a).max()), 1e-12)
    im = ax[2].imshow(b - a, cmap="coolwarm", vmin=-lim, vmax=lim)
    ax[2].set_title("ours - Monte Carlo")
    fig.colorbar(im, ax=ax[2], fraction=0.046)
    row = a.shape[0] // 2
    ax[3].plot(a[row], "k-", label=mc_title)
    ax[3].plot(b[row], "r-", label=ours_title)
    ax[3].set_title("centre row")
    ax[3].set_xlabel("pixel")
    ax[3].legend()
    for k in range(3):
        ax[k].axhline(row, color="w", lw=0.5, ls=":")
        ax[k].set_xticks([])
        ax[k].set_yticks([])
    fig.suptitle(f"glsldiff validate: {name}")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def validate(cases: Sequence[str], out: Path, size: int = 64, spp: int = 256,
             source: str | None = None, adapt: bool | None = None, flux: str | None = None,
             incidence: str | None = None, model: str | None = None,
             progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """Run ``cases`` (names or :data:`GROUPS`, :func:`expand_cases`); write validation.csv, and
    per case a PNG (diffusion | MC multiple scattering (eta = 1) or MC subsurface, all orders
    (eta != 1) | MC full image, surface reflection and background included), a PNG of panels
    (:func:`_panels`: MC, ours, difference, centre-row profile) and with eta = 1 one of the
    single scattering alone, the images as EXR and the environment map (if any). Every case
    renders with the scene defaults but for the options it sets itself (:class:`Case`); the
    overrides ``model``, ``source``, ``flux``, ``incidence`` and ``adapt`` set that option in
    every case (the rows' ``options`` column then names it). ``progress`` receives a line
    before each case."""
    cases = expand_cases(cases)
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise InputError(f"unknown validation case {unknown[0]!r}; valid: {', '.join(CASES)}, or a group: "
                         f"{', '.join(GROUPS)}, all")
    mc_split(spp)                           # a bad sample count fails before any rendering
    if source is not None:                  # so does a bad source model
        checks.choice(source, "source", ("auto",) + SOURCES)
    if flux is not None:
        checks.choice(flux, "flux", FLUXES)
    if incidence is not None:
        checks.choice(incidence, "incidence", INCIDENCE)
    if model is not None:
        checks.choice(model, "model", MODELS)
    load_mitsuba("scalar_rgb")              # so does a missing Mitsuba
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    overrides = {k: v for k, v in (("adapt", adapt), ("flux", flux), ("incidence", incidence), ("source", source),
                                   ("model", model)) if v is not None}
    for k, name in enumerate(cases):
        case = replace(CASES[name], **overrides)
        if progress is not None:
            progress(f"validate: case {name} ({k + 1} of {len(cases)}; options: {case.options})")
        row, imgs = run_case(case, size, spp, folder=out)
        rows.append(row)
        middle = imgs.get("mc_multiple", imgs["mc_subsurface"])
        expo = 0.8 / max(float(np.percentile(imgs["mc_subsurface"], 99)), 1e-12)
        sheet = io.contact_sheet([imgs["diffusion"], middle, imgs["mc_full"]], 3, expo, scale=2)
        io.write_png(out / f"validation_{name}.png", sheet)
        _panels(out / f"validation_{name}_panels.png", imgs["mc_subsurface"], imgs["diffusion"], name)
        if "mc_single" in imgs:
            _panels(out / f"validation_{name}_single_panels.png", imgs["mc_single"], imgs["diffusion_single"],
                    f"{name}, single scattering", "Monte Carlo (single)", "ours (single)")
        for key, img in imgs.items():
            io.write_exr(out / f"validation_{name}_{key}.exr", img)
        io.write_csv(out / "validation.csv", rows)
    return rows
