"""Scenes for ``glsldiff render``: a TOML file, validated field by field.

Every length is in mm and every coefficient in mm^-1. All tables are optional except
``[mesh]`` (the built-in default scene, :func:`default_scene`, fills every field); unknown
tables or keys are errors naming ``[table].key``. The format's reference, one valid example
per table, is the documentation page ``docs/reference/scene.md`` (each of its TOML blocks is
parsed by ``tests/test_docs.py``). ``[[lights]]`` tables parse straight into the light types of
:mod:`glsldiff.physics.lights` (``Scene.lights``); image and volume files are read (and
checked) when the scene is parsed.
"""
from __future__ import annotations

import importlib.resources
import math
try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.errors import InputError
from glsldiff.core.io import not_a_file, read_image, read_npz
from glsldiff.grids.tetrahedral.fem_grid import FEM_BYTES_PER_NODE, FEM_MAX_NODES
from glsldiff.grids.polygrid import node_budget_problem
from glsldiff.mesh import GENERATED_MESHES, SAMPLE_MESHES
from glsldiff.mesh.load import MAX_SIZE_MM, MIN_SIZE_MM
from glsldiff.physics.exitance import EXITANT, INCIDENCE
from glsldiff.physics.collision import SOURCES
from glsldiff.physics.lights import (KINDS, AreaLight, DirectionalLight, EnvironmentLight, Light, PointLight, ProjectorLight,
                                     SpotLight)
from glsldiff.physics.material import preset as lookup_preset
from glsldiff.physics.procedural import POINT_KINDS

#: [polygrid].discretisation: the 6-point lattice stencils (system.problem) or P1 tetrahedra (oracle.fem)
#: on the pillowed polycube (fem) or on an fTetWild mesh of the surface (tetwild, grids.tetrahedral.tetwild).
DISCRETISATIONS = ("conservative", "paper", "fem", "tetwild")
#: The discretisations on tetrahedra (the P1 system, the volume source, the gradient flux).
TETRAHEDRAL = ("fem", "tetwild")
#: tetwild's default target edge length: the mesh's longest extent over this.
TETWILD_EDGES_PER_SIZE = 40
#: The fem discretisation's default node budget: [polygrid].cubes defaults to this / n^3 (many
#: small cubes reach thin parts; the lattice's default, 253 cubes of n = 8, is about as many nodes).
FEM_NODES = 120_000
#: The fem discretisation's default nodes per cube edge (the lattice's: 8, with 253 cubes).
FEM_N = 2


def default_cubes(discretisation: str, n: int) -> int:
    """[polygrid].cubes when the scene gives none: :data:`FEM_NODES` / n^3 for fem, 253 for the lattice."""
    return max(1, round(FEM_NODES / n ** 3)) if discretisation == "fem" else 253


PROCEDURAL = ("veins",) + POINT_KINDS  # veins: a marble lattice; the others: weights at the nodes
LIGHT_TYPES = tuple(KINDS)
#: Keys of a ``[[lights]]`` table (module docstring); which ones each kind reads: :func:`_light`.
LIGHT_KEYS = ("type", "direction", "position", "irradiance", "intensity", "cone_deg", "falloff_deg", "path",
              "scale", "shadows", "image", "up", "fov_deg", "size", "radiance", "samples")
#: The keys each kind of light reads (the others are errors, not silently ignored).
LIGHT_READS = {
    "directional": ("type", "direction", "irradiance", "shadows"),
    "point": ("type", "position", "intensity", "shadows"),
    "spot": ("type", "position", "direction", "intensity", "cone_deg", "falloff_deg", "shadows"),
    "projector": ("type", "position", "direction", "image", "intensity", "up", "fov_deg", "shadows"),
    "area": ("type", "position", "direction", "size", "radiance", "up", "samples", "shadows"),
    "environment": ("type", "path", "scale"),
}
#: ``[camera].type``: a pinhole (``fov_deg``) or parallel view rays (``width_mm``).
CAMERA_TYPES = ("perspective", "orthographic")
SCHEMES = ("single", "hierarchical", "multigrid")
#: Where pass 3 takes the outward flux of the exitant bracket from (``[options].flux``).
#: smoothed: the Robin condition's flux with the bracket's q and phi smoothed along the surface over
#: a half and an eighth of a transport mean free path (tetrahedral grids; the lattice takes
#: boundary); boundary: the local Robin flux; gradient: the solution's recovered gradient.
FLUXES = ("smoothed", "boundary", "gradient")
#: ``[options].model``: the transport split (:mod:`glsldiff.physics.split`; the default) or classical
#: diffusion with its P1 exitance (:mod:`glsldiff.physics.exitance`; Wang et al.'s model).
MODELS = ("split", "diffusion")


@dataclass(frozen=True)
class MeshSpec:
    source: str = "bunny"
    size_mm: float = 100.0


#: Lights whose own profile has an edge across the lit surface (a cone's rim, a projector pattern):
#: ``[polygrid] adapt = "auto"`` refines the grid under them.
EDGED_LIGHTS = (SpotLight, ProjectorLight)


@dataclass(frozen=True)
class PolygridSpec:
    n: int = FEM_N
    cubes: int = default_cubes("fem", FEM_N)
    levels: int = 1
    discretisation: str = "fem"
    edge_mm: float | None = None     # tetwild: target tetrahedron edge, mm (default size_mm / 40)
    adapt: bool | str = "auto"       # fem: refine the grid under the lights' sharp edges (grids.tetrahedral.adapt):
                                     # true | false | "auto" (when a spot or projector light is in the scene)

    def refines(self, lights: Sequence[Light]) -> bool:
        """The grid is refined under ``lights``' sharp edges: ``adapt`` on a fem grid, and with
        ``"auto"`` only for a spot or projector light (:data:`EDGED_LIGHTS`: an edge in the light's
        own profile, across the lit surface), not for shadow borders alone."""
        if self.discretisation != "fem":
            return False
        if self.adapt == "auto":
            return any(isinstance(light, EDGED_LIGHTS) for light in lights)
        return bool(self.adapt)


#: The lattice polygrid of interactive editing (glsldiff view's bunny, glsldiff bench edit): many small
#: cubes (n = 4, about 2000 of them, 2 levels; 125 k nodes on the bunny) put nodes into thin parts the
#: default lattice (n = 8, 253 cubes) leaves empty, e.g. the bunny's far ear, at the same node count.
EDIT_LATTICE = PolygridSpec(4, 2000, 2, "conservative")
#: The torus "Hole" of Table III on the default (tetrahedral) grid in ``glsldiff view`` and ``glsldiff
#: bench edit``: 45k nodes (the cube sizes the torus allows jump from 45k nodes at 6000 cubes to 99k at 6500).
HOLE_CUBES = 6000


@dataclass(frozen=True)
class MaterialSpec:
    preset: str | None = "marble"
    sigma_a: tuple[float, float, float] | None = None
    sigma_s_prime: tuple[float, float, float] | None = None
    eta: float = 1.3
    procedural: str | None = None
    vein: str | None = None
    seed: int = 0
    volume: str | None = None
    nodes: str | None = None
    core: str = "mean"
    shell_mm: float | None = None
    reflectance: tuple[float, float, float] | str | None = None   # diffuse surface albedo, or a map (EXR)


@dataclass(frozen=True)
class CameraSpec:
    position: tuple[float, float, float] | None = None   # None: framed automatically
    target: tuple[float, float, float] | None = None
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_deg: float = 30.0
    type: str = "perspective"                             # or "orthographic" (parallel view rays)
    width_mm: float | None = None                         # orthographic: the view's width, mm (None: framed)


@dataclass(frozen=True)
class OutputSpec:
    width: int = 512
    height: int = 512
    exposure: float | str = "auto"


@dataclass(frozen=True)
class SpecularSpec:
    rho_s: float = 0.04
    alpha: float = 0.2


@dataclass(frozen=True)
class OptionsSpec:
    scheme: str = "hierarchical"
    tol: float = 1e-4
    precision: str = "fp32"
    exitant: str = "p1"              # model = "diffusion" only
    single_scattering: bool | str = "auto"   # "auto": the model's (split: always; diffusion: off) | true | false
    source: str = "auto"             # auto (split: volume where the grid resolves the mean free path; diffusion:
                                     # surface) | surface | volume
    unscattered: bool = True
    flux: str = "smoothed"           # model = "diffusion" only; lattice discretisations: "boundary"
    incidence: str = "local"         # model = "diffusion" only: local | transport (Chandrasekhar) | marshak
    model: str = "split"             # split (exact local transport + the diffusion's far field) | diffusion

    @property
    def split(self) -> bool:
        """The transport split (:mod:`glsldiff.physics.split`) renders the scene."""
        return self.model == "split"


@dataclass(frozen=True)
class CutSpec:
    plane: tuple[float, float, float, float] | None = None
    stroke: tuple[tuple[float, float], ...] | None = None
    iterations: int = 40


@dataclass(frozen=True)
class PaintSpec:
    points: tuple[tuple[float, float, float], ...]
    radius_mm: float
    sigma_a: tuple[float, float, float] | None = None
    sigma_s_prime: tuple[float, float, float] | None = None
    strength: float = 1.0


@dataclass(frozen=True)
class Scene:
    """A validated scene (module docstring); ``source`` names the file for messages."""

    mesh: MeshSpec = MeshSpec()
    polygrid: PolygridSpec = PolygridSpec()
    material: MaterialSpec = MaterialSpec()
    lights: tuple[Light, ...] = ()
    camera: CameraSpec = CameraSpec()
    output: OutputSpec = OutputSpec()
    specular: SpecularSpec = SpecularSpec()
    options: OptionsSpec = OptionsSpec()
    source: str = "<built-in>"
    base_dir: Path = field(default=Path("."), compare=False)
    cut: CutSpec | None = None
    paint: tuple[PaintSpec, ...] = ()

    @property
    def refines(self) -> bool:
        """The grid is refined under the lights' sharp edges (:meth:`PolygridSpec.refines`)."""
        return self.polygrid.refines(self.lights)

    def resolve(self, path: str) -> Path:
        """A path from the scene file, relative to the file's directory."""
        return _resolve(self.base_dir, path)


def _resolve(base_dir: Path, path: str) -> Path:
    p = Path(path).expanduser()
    return p if p.is_absolute() else base_dir / p


def tetrahedral(scene: Scene, cubes: int | None = None) -> Scene:
    """``scene`` on the default (tetrahedral) grid with about ``cubes`` cubes (default: the
    default grid's count)."""
    grid = PolygridSpec()
    return replace(scene, polygrid=replace(grid, cubes=cubes or grid.cubes))


def default_scene() -> Scene:
    """The built-in scene: the pymeshlab bunny (100 mm) in veined marble under a
    directional light from the upper left front, camera framed automatically."""
    return Scene(material=MaterialSpec(preset="marble", procedural="veins"),
                 lights=(DirectionalLight(_unit((-0.4, 0.7, 0.6)), (1.0, 1.0, 1.0)),))


def _unit(a: Any) -> NDArray[np.float64]:
    return vec(a) / np.linalg.norm(a)


# ---------------------------------------------------------------- validation helpers
class _Table:
    """One TOML table: typed getters that name ``[table].key`` in every error."""

    def __init__(self, src: str, name: str, data: Any, allowed: set[str]) -> None:
        self.src, self.name = src, name
        if not isinstance(data, dict):
            self.fail("", f"must be a table, got {type(data).__name__}")
        unknown = sorted(set(data) - allowed)
        if unknown:
            self.fail(unknown[0], f"unknown key; valid keys: {', '.join(sorted(allowed))}")
        self.data = data

    def fail(self, key: str, msg: str) -> None:
        where = f"[{self.name}].{key}" if key else f"[{self.name}]"
        raise InputError(f"{self.src}: {where}: {msg}")

    def has(self, key: str) -> bool:
        return key in self.data

    def number(self, key: str, default: Any, lo: float | None = None, lo_open: bool = False,
               hi: float | None = None) -> Any:
        v = self.data.get(key, default)
        if v is None or key not in self.data:
            return default
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(key, f"must be a finite number, got {v!r}")
        if lo is not None and (v <= lo if lo_open else v < lo):
            self.fail(key, f"must be {'>' if lo_open else '>='} {lo}, got {v}")
        if hi is not None and v > hi:
            self.fail(key, f"must be <= {hi}, got {v}")
        return float(v)

    def integer(self, key: str, default: int, lo: int) -> int:
        v = self.data.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(key, f"must be an integer, got {v!r}")
        if v < lo:
            self.fail(key, f"must be >= {lo}, got {v}")
        return int(v)

    def string(self, key: str, default: Any, choices: tuple[str, ...] | None = None) -> Any:
        v = self.data.get(key, default)
        if key not in self.data:
            return default
        if not isinstance(v, str) or not v:
            self.fail(key, f"must be a non-empty string, got {v!r}")
        if choices is not None and v not in choices:
            self.fail(key, f"{v!r} is not one of {', '.join(choices)}")
        return v

    def preset_name(self, key: str, name: str | None) -> None:
        """Fail unless ``name`` (if given) is a known material preset."""
        if name is not None:
            try:
                lookup_preset(name)
            except InputError as exc:
                self.fail(key, str(exc))

    def boolean(self, key: str, default: bool) -> bool:
        v = self.data.get(key, default)
        if not isinstance(v, bool):
            self.fail(key, f"must be true or false, got {v!r}")
        return v

    def vec3(self, key: str, default: Any, nonneg: bool = False, nonzero: bool = False) -> Any:
        if key not in self.data:
            return default
        v = self.data[key]
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v, v, v]
        if (not isinstance(v, list) or len(v) != 3
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
            self.fail(key, f"must be 3 finite numbers, got {v!r}")
        a = tuple(float(x) for x in v)
        if nonneg and min(a) < 0:
            self.fail(key, f"must not be negative, got {list(a)}")
        if nonzero and not any(a):
            self.fail(key, "must not be the zero vector")
        return a


def _material(t: _Table, scene_dir: Path) -> MaterialSpec:
    kinds = [k for k in ("sigma_a", "volume", "nodes") if t.has(k)]
    if t.has("procedural") and kinds and kinds != ["sigma_a"]:
        t.fail("procedural", f"give either a procedural volume or a {kinds[-1]} file, not both")
    if len(set(kinds) - {"sigma_a"}) > 1:
        t.fail("nodes", "give either a block volume or a node material file, not both")
    if t.has("preset") and (t.has("sigma_a") or t.has("sigma_s_prime")):
        t.fail("preset", "give either a preset or sigma_a/sigma_s_prime, not both")
    if t.has("sigma_a") != t.has("sigma_s_prime"):
        t.fail("sigma_a" if not t.has("sigma_a") else "sigma_s_prime", "sigma_a and sigma_s_prime go together")
    name = t.string("preset", None if kinds else "marble")
    t.preset_name("preset", name)
    sa = t.vec3("sigma_a", None, nonneg=True)
    ss = t.vec3("sigma_s_prime", None, nonneg=True)
    if ss is not None and min(sa[i] + ss[i] for i in range(3)) <= 0:
        t.fail("sigma_s_prime", "sigma_a + sigma_s_prime must be > 0 in every channel")
    vein = t.string("vein", None)
    t.preset_name("vein", vein)
    core = t.string("core", "mean")
    t.preset_name("core", None if core == "mean" else core)
    volume = t.string("volume", None)
    if volume is not None:  # read now: a bad file fails before the polygrid is built
        block_volume(_resolve(scene_dir, volume), f"{t.src}: [material].volume: file")
    nodes = t.string("nodes", None)
    if nodes is not None:
        if t.has("preset") or t.has("sigma_a"):
            t.fail("nodes", "a node material file holds the whole material: leave out preset and sigma_a")
        node_volume(_resolve(scene_dir, nodes), f"{t.src}: [material].nodes: file")
    reflectance: Any = None
    if isinstance(t.data.get("reflectance"), str):
        if volume is None:
            t.fail("reflectance", "a reflectance map tiles like the block volume: give [material].volume too, "
                                  "or a constant albedo")
        reflectance = t.string("reflectance", None)
        _image(t, "reflectance", scene_dir, "reflectance map", exr_only=True)
    else:
        reflectance = t.vec3("reflectance", None, nonneg=True)
        if reflectance is not None and max(reflectance) > 1.0:
            t.fail("reflectance", f"a diffuse albedo must be in [0, 1], got {list(reflectance)}")
    return MaterialSpec(preset=name, sigma_a=sa, sigma_s_prime=ss, eta=t.number("eta", 1.3, 0.0, lo_open=True),
                        procedural=t.string("procedural", None, PROCEDURAL), vein=vein,
                        seed=t.integer("seed", 0, 0), volume=volume, nodes=nodes, core=core,
                        shell_mm=t.number("shell_mm", None, 0.0, lo_open=True), reflectance=reflectance)


def _image(t: _Table, key: str, scene_dir: Path, what: str, exr_only: bool) -> NDArray[np.float64] | None:
    """The image of file ``[table].key`` (relative to the scene file), checked that it exists,
    decodes (:func:`glsldiff.core.io.read_image`) and has finite pixels >= 0; None if the key is absent."""
    path = t.string(key, None)
    if path is None:
        return None
    p = _resolve(scene_dir, path)
    if not p.is_file():
        t.fail(key, f"{what} {str(p)!r} {not_a_file(p)}")
    kind = "OpenEXR" if exr_only else "OpenEXR, PNG or JPEG"
    try:
        img = read_image(p, exr_only)
    except Exception as exc:  # OpenEXR raises plain exceptions on corrupt files
        t.fail(key, f"{what} {str(p)!r} is not a readable {kind} file ({' '.join(str(exc).split())})")
    if not np.all(np.isfinite(img)) or img.min() < 0:
        t.fail(key, f"{what} {str(p)!r} has negative or non-finite pixels")
    return img


def _size2(t: _Table) -> tuple[float, float]:
    v = t.data["size"]
    if (not isinstance(v, list) or len(v) != 2 or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                           and math.isfinite(x) and x > 0 for x in v)):
        t.fail("size", f"must be [width, height] in mm, both > 0, got {v!r}")
    return float(v[0]), float(v[1])


def _light(t: _Table, scene_dir: Path) -> Light:
    kind = t.data.get("type")
    if kind not in LIGHT_TYPES:
        t.fail("type", f"{kind!r} is not one of {', '.join(LIGHT_TYPES)}")
    need = {"directional": ("direction",), "point": ("position",), "spot": ("position", "direction"),
            "projector": ("position", "direction", "image"), "area": ("position", "direction", "size"),
            "environment": ("path",)}[kind]
    for k in need:
        if not t.has(k):
            t.fail(k, f"a {kind} light needs {k}")
    for k in LIGHT_KEYS:
        if t.has(k) and k not in LIGHT_READS[kind]:
            t.fail(k, f"a {kind} light has no {k} (it reads {', '.join(LIGHT_READS[kind][1:])}); remove the key")
    cone = t.number("cone_deg", 30.0, 0.0, lo_open=True, hi=90.0)
    falloff = t.number("falloff_deg", min(25.0, cone), 0.0)
    if falloff > cone:
        t.fail("falloff_deg", f"must be <= cone_deg ({cone}), got {falloff}")
    fov = t.number("fov_deg", 30.0, 0.0, lo_open=True)
    if fov >= 180.0:
        t.fail("fov_deg", f"must be < 180, got {fov}")
    direction = t.vec3("direction", None, nonzero=True)
    up = t.vec3("up", None, nonzero=True)
    if kind in ("projector", "area"):
        u = up if up is not None else (0.0, 1.0, 0.0)
        a, b = vec(direction), vec(u)
        where = "across the optical axis" if kind == "projector" else "in the rectangle's plane"
        if np.linalg.norm(np.cross(a, b)) < 1e-6 * np.linalg.norm(a) * np.linalg.norm(b):
            t.fail("up", f"{list(u)}{'' if up else ' (the default)'} is parallel to direction "
                         f"{list(direction)}; give an up vector {where}")
    position = t.vec3("position", None)
    irradiance = t.vec3("irradiance", (1.0, 1.0, 1.0), nonneg=True)
    intensity = t.vec3("intensity", (1.0e4, 1.0e4, 1.0e4), nonneg=True)
    env_map = _image(t, "path", scene_dir, "environment map", exr_only=True)
    scale = t.number("scale", 1.0, 0.0)
    shadows = t.boolean("shadows", kind != "area")
    size = _size2(t) if kind == "area" else None
    radiance = t.vec3("radiance", (1.0, 1.0, 1.0), nonneg=True)
    samples = t.integer("samples", AreaLight.samples, 1)
    image = _image(t, "image", scene_dir, "projector image", exr_only=False)
    try:
        if kind == "directional":
            return DirectionalLight(_unit(direction), irradiance, shadows)
        if kind == "point":
            return PointLight(position, intensity, shadows)
        if kind == "spot":
            return SpotLight(position, _unit(direction), intensity, cone, falloff, shadows)
        if kind == "projector":
            return ProjectorLight(position, direction, image, intensity, up=up if up is not None else (0.0, 1.0, 0.0),
                                  fov_deg=fov, shadows=shadows)
        if kind == "area":
            return AreaLight(position, direction, size, radiance, up=up if up is not None else (0.0, 1.0, 0.0),
                             samples=samples, shadows=shadows)
        return EnvironmentLight(env_map, scale)   # visibility on; ``shadows`` is not read
    except InputError as exc:   # e.g. "SpotLight.direction must be ...": name the table's key
        key = str(exc).split(" ", 1)[0].partition(".")[2].partition("=")[0]
        t.fail(key if key in LIGHT_KEYS else "", str(exc))
        raise   # not reached: fail raises


_TABLES = ("mesh", "polygrid", "material", "lights", "camera", "output", "specular", "options", "cut", "paint")


def _points(t: _Table, key: str, dim: int) -> tuple[tuple[float, ...], ...]:
    v = t.data[key]
    ok = (isinstance(v, list) and len(v) >= 1 and all(
        isinstance(p, list) and len(p) == dim and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                      and math.isfinite(x) for x in p) for p in v))
    if not ok:
        t.fail(key, f"must be a list of [{', '.join('xyz'[:dim] if dim == 3 else 'uv')}] points of finite numbers, "
                    f"got {v!r}")
    return tuple(tuple(float(x) for x in p) for p in v)


def _cut(t: _Table, camera: CameraSpec) -> CutSpec:
    if t.has("plane") == t.has("stroke"):
        t.fail("plane", "give exactly one of plane = [n_x, n_y, n_z, d] or stroke = [[u, v], ...]")
    plane, stroke = None, None
    if t.has("plane"):
        v = t.data["plane"]
        if (not isinstance(v, list) or len(v) != 4 or not all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
                or not any(v[:3])):
            t.fail("plane", f"must be [n_x, n_y, n_z, d] (finite, normal not zero), got {v!r}")
        plane = tuple(float(x) for x in v)
    else:
        stroke = _points(t, "stroke", 2)
        if len(stroke) < 2:
            t.fail("stroke", "needs at least two [u, v] points")
        if camera.position is None:
            t.fail("stroke", "a stroke is drawn in the camera's image: give [camera] position (and target) so the "
                             "view does not move with the cut")
    return CutSpec(plane, stroke, t.integer("iterations", 40, 0))


def _paint(t: _Table) -> PaintSpec:
    if not t.has("points") or not t.has("radius_mm"):
        t.fail("points" if not t.has("points") else "radius_mm", "missing; a paint stroke needs points and radius_mm")
    if not (t.has("sigma_a") or t.has("sigma_s_prime")):
        t.fail("sigma_a", "give the target sigma_a and/or sigma_s_prime (mm^-1)")
    return PaintSpec(_points(t, "points", 3), t.number("radius_mm", 1.0, 0.0, lo_open=True),  # type: ignore[arg-type]
                     t.vec3("sigma_a", None, nonneg=True), t.vec3("sigma_s_prime", None, nonneg=True),
                     t.number("strength", 1.0, 0.0, hi=1.0))


def _keys(cls: type) -> set[str]:
    return {f.name for f in fields(cls)}


def parse_scene(data: dict[str, Any], src: str = "<scene>", base_dir: Path = Path(".")) -> Scene:
    """A :class:`Scene` from parsed TOML (a dict); every error names ``[table].key``."""
    unknown = sorted(set(data) - set(_TABLES))
    if unknown:
        raise InputError(f"{src}: unknown table [{unknown[0]}]; valid tables: {', '.join(_TABLES)}")
    if "mesh" not in data:
        raise InputError(f"{src}: [mesh]: missing; a scene needs [mesh] source = \"bunny\" or a mesh file path")
    m = _Table(src, "mesh", data["mesh"], _keys(MeshSpec))
    if not m.has("source"):
        m.fail("source", "missing; give a sample name (bunny, cow, bone, airplane, sphere, torus) or a mesh file path")
    source = m.string("source", "bunny")
    if source not in SAMPLE_MESHES and source not in GENERATED_MESHES:
        p = _resolve(base_dir, source)
        if not p.is_file():
            m.fail("source", f"mesh file {str(p)!r} {not_a_file(p)} (sample names: "
                             f"{', '.join((*SAMPLE_MESHES, *GENERATED_MESHES))})")
    mesh = MeshSpec(source, m.number("size_mm", 100.0, MIN_SIZE_MM, hi=MAX_SIZE_MM))

    g = _Table(src, "polygrid", data.get("polygrid", {}), _keys(PolygridSpec))
    disc = g.string("discretisation", "fem", DISCRETISATIONS)
    if disc == "tetwild":
        for key in ("n", "cubes", "levels", "adapt"):
            if g.has(key):
                g.fail(key, "not used by discretisation = \"tetwild\" (an fTetWild mesh of the surface); give "
                            "edge_mm, the target tetrahedron edge in mm")
        lo = mesh.size_mm / 200.0
        poly = PolygridSpec(FEM_N, 1, 1, disc, g.number("edge_mm", mesh.size_mm / TETWILD_EDGES_PER_SIZE, lo,
                                                        hi=mesh.size_mm / 4.0), adapt=False)
    else:
        if g.has("edge_mm"):
            g.fail("edge_mm", f"only discretisation = \"tetwild\" takes an edge length (this one: {disc!r})")
        n = g.integer("n", 8 if disc != "fem" else FEM_N, 2)
        levels = g.integer("levels", 3 if disc != "fem" else 1, 1)
        if disc == "fem" and levels != 1:
            g.fail("levels", "the fem discretisation (the default) solves on one level with its own algebraic "
                             "multigrid; leave levels out, or set discretisation = \"conservative\" for the "
                             "lattice hierarchy")
        if n % 2 and disc != "fem":
            g.fail("n", f"must be even (the hierarchy halves it), got {n}")
        adapt: bool | str = "auto"
        if g.has("adapt"):
            adapt = g.data["adapt"]
            if adapt != "auto" and not isinstance(adapt, bool):
                g.fail("adapt", f"must be true, false or \"auto\", got {adapt!r}")
        if adapt is True and disc != "fem":
            g.fail("adapt", f"the refinement under sharp light is for discretisation = \"fem\" only (this one: "
                            f"{disc!r}); leave adapt out")
        poly = PolygridSpec(n, g.integer("cubes", default_cubes(disc, n), 1), levels, disc, adapt=adapt)
        problem = (node_budget_problem(poly.cubes, n, FEM_MAX_NODES, FEM_BYTES_PER_NODE) if disc == "fem"
                   else node_budget_problem(poly.cubes, n))
        if problem:   # the count given is what to change (n alone sets the default count within budget)
            g.fail("cubes" if g.has("cubes") else "n", problem)
    if poly.levels > 1 and poly.n >> (poly.levels - 1) < 2:
        g.fail("levels", f"{poly.levels} levels need n >= {2 ** poly.levels}, got n = {poly.n}")

    material = _material(_Table(src, "material", data.get("material", {}), _keys(MaterialSpec)), base_dir)
    if material.volume and poly.discretisation == "tetwild":
        raise InputError(f"{src}: [material].volume: a shell-mapped volume needs the polycube's shell (discretisation "
                         "\"fem\" or a lattice one), not \"tetwild\"; use a procedural material or another "
                         "discretisation")
    raw = data.get("lights", [])
    if not isinstance(raw, list):
        raise InputError(f"{src}: [[lights]]: must be an array of tables ([[lights]]), got {type(raw).__name__}")
    lights = tuple(_light(_Table(src, f"lights.{i}", d, set(LIGHT_KEYS)), base_dir) for i, d in enumerate(raw))
    if not lights:
        raise InputError(f"{src}: [[lights]]: the scene has no light; add a [[lights]] table")

    c = _Table(src, "camera", data.get("camera", {}), _keys(CameraSpec))
    kind = c.string("type", "perspective", CAMERA_TYPES)
    if kind == "orthographic" and c.has("fov_deg"):
        c.fail("fov_deg", "an orthographic camera has no field of view: give width_mm (the view's width, mm)")
    if kind == "perspective" and c.has("width_mm"):
        c.fail("width_mm", 'is the view width of an orthographic camera: set type = "orthographic" or leave it out')
    camera = CameraSpec(c.vec3("position", None), c.vec3("target", None), c.vec3("up", (0.0, 1.0, 0.0), nonzero=True),
                        c.number("fov_deg", 30.0, 0.0, lo_open=True, hi=170.0), kind,
                        c.number("width_mm", None, 0.0, lo_open=True, hi=MAX_SIZE_MM * 10))
    if camera.position is not None and camera.target is not None and camera.position == camera.target:
        c.fail("position", "must differ from target")
    o = _Table(src, "output", data.get("output", {}), _keys(OutputSpec))
    exposure = o.data.get("exposure", "auto")
    if exposure != "auto":
        exposure = o.number("exposure", 1.0, 0.0, lo_open=True)
    output = OutputSpec(o.integer("width", 512, 1), o.integer("height", 512, 1), exposure)
    if max(output.width, output.height) > 8192:
        o.fail("width", f"image sides are limited to 8192 pixels, got {output.width}x{output.height}")
    s = _Table(src, "specular", data.get("specular", {}), _keys(SpecularSpec))
    specular = SpecularSpec(s.number("rho_s", 0.04, 0.0, hi=1.0), s.number("alpha", 0.2, 0.0, lo_open=True, hi=1.0))
    t = _Table(src, "options", data.get("options", {}), _keys(OptionsSpec))
    single = t.data.get("single_scattering", "auto")
    if single != "auto" and not isinstance(single, bool):
        t.fail("single_scattering", f"must be true, false or \"auto\", got {single!r}")
    model = t.string("model", "split", MODELS)
    if model == "split":
        for key in ("exitant", "incidence", "flux"):
            if t.has(key):
                t.fail(key, "applies to model = \"diffusion\" only (the split's exitance is exact local transport "
                            "plus the diffusion's far field); remove it or set model = \"diffusion\"")
    options = OptionsSpec(t.string("scheme", "hierarchical", SCHEMES), t.number("tol", 1e-4, 0.0, lo_open=True, hi=0.1),
                          t.string("precision", "fp32", ("fp32", "fp16", "paper")),
                          t.string("exitant", "p1", EXITANT), single,
                          t.string("source", "auto", ("auto",) + SOURCES), t.boolean("unscattered", True),
                          t.string("flux", "smoothed" if poly.discretisation in TETRAHEDRAL else "boundary",
                                   FLUXES), t.string("incidence", "local", INCIDENCE), model)
    if options.flux == "gradient" and poly.discretisation not in TETRAHEDRAL:
        t.fail("flux", "\"gradient\" (the flux of the solution's gradient) needs the tetrahedral grid; set "
                       "[polygrid] discretisation = \"fem\" (the default) or flux = \"boundary\"")
    if options.flux == "smoothed" and poly.discretisation not in TETRAHEDRAL:
        t.fail("flux", "\"smoothed\" (the source smoothed along the surface's triangles) needs the tetrahedral "
                       "grid; set [polygrid] discretisation = \"fem\" (the default) or flux = \"boundary\"")
    if options.source == "volume" and poly.discretisation not in TETRAHEDRAL:
        t.fail("source", "\"volume\" (the first-collision source) is solved on tetrahedra only; set [polygrid] "
                         "discretisation = \"fem\" (the default) or source = \"surface\"")
    if options.scheme != "single" and poly.levels == 1:
        options = replace(options, scheme="single")
    cut = None
    if "cut" in data:
        ct = _Table(src, "cut", data["cut"], _keys(CutSpec))
        if poly.discretisation != "tetwild":
            ct.fail("", "cutting needs the fTetWild mesh: set [polygrid] discretisation = \"tetwild\"")
        cut = _cut(ct, camera)
    raw_paint = data.get("paint", [])
    if not isinstance(raw_paint, list):
        raise InputError(f"{src}: [[paint]]: must be an array of tables ([[paint]]), got {type(raw_paint).__name__}")
    paint = tuple(_paint(_Table(src, f"paint.{i}", d, _keys(PaintSpec))) for i, d in enumerate(raw_paint))
    if paint and poly.discretisation != "tetwild":
        raise InputError(f"{src}: [[paint]]: painting needs the fTetWild mesh: set [polygrid] discretisation = "
                         "\"tetwild\"")
    return Scene(mesh, poly, material, lights, camera, output, specular, options, src, base_dir, cut, paint)


def load_scene(path: str | Path) -> Scene:
    """Read and validate a TOML scene file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"scene file {str(p)!r} {not_a_file(p)}")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: not valid TOML ({exc})") from exc
    return parse_scene(data, str(p), p.parent)


def vec(a: Any) -> NDArray[np.float64]:
    """A scene 3-tuple as an array."""
    return np.asarray(a, dtype=np.float64)


def _check_coefficients(kappa: NDArray, mu: NDArray, path: str | Path, what: str, also: str = "",
                        rest_ok: bool = True) -> None:
    """InputError unless kappa is finite and > 0, mu finite and >= 0 (and ``rest_ok``, the file's
    other arrays checked by the caller, named in ``also``)."""
    if not (rest_ok and np.isfinite(kappa).all() and np.isfinite(mu).all()
            and (kappa > 0).all() and (mu >= 0).all()):
        raise InputError(f"{what} {str(path)!r}: kappa must be finite and > 0 (mm), mu finite and >= 0 "
                         f"(mm^-1){also}")


def block_volume(path: str | Path, what: str) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """kappa (mm), mu (mm^-1) as ``(nz, ny, nx, 3)`` and the voxel size h_mm of a block volume
    ``.npz`` (the ``[material].volume`` of a scene), checked."""
    return block_arrays(read_npz(path, what, ("kappa", "mu")), path, what)


def block_arrays(z: dict[str, NDArray], path: str | Path, what: str
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """:func:`block_volume` of the arrays ``z`` already read from ``path`` (adds ``h_mm`` to ``z``
    when only the fit's ``h`` is there)."""
    if "h_mm" not in z and "h" in z:        # glsldiff fit / synth write the voxel size as "h"
        z["h_mm"] = z["h"]
    if "h_mm" not in z:
        raise InputError(f"{what} {str(path)!r} lacks h_mm, the voxel size in mm (has {', '.join(z)})")
    kappa, mu = np.asarray(z["kappa"], dtype=np.float64), np.asarray(z["mu"], dtype=np.float64)
    if kappa.ndim != 4 or kappa.shape[3] != 3 or mu.shape != kappa.shape or min(kappa.shape[:3]) < 1:
        raise InputError(f"{what} {str(path)!r}: kappa and mu must both have shape (nz, ny, nx, 3), got "
                         f"{kappa.shape} and {mu.shape}")
    if z["h_mm"].size != 1:
        raise InputError(f"{what} {str(path)!r}: h_mm must be one number (mm), got shape {z['h_mm'].shape}")
    h = float(z["h_mm"].reshape(()))
    if not (np.isfinite(h) and h > 0):
        raise InputError(f"{what} {str(path)!r}: h_mm must be a positive voxel size in mm, got {h}")
    if not MIN_SIZE_MM * 1e-3 <= h <= MAX_SIZE_MM:   # a voxel larger than any object, or a sub-micron one: a unit slip
        raise InputError(f"{what} {str(path)!r}: h_mm = {h:g} is not a voxel size in mm (expected "
                         f"{MIN_SIZE_MM * 1e-3:g} .. {MAX_SIZE_MM:g}); write the voxel size in mm")
    _check_coefficients(kappa, mu, path, what, " everywhere")
    return kappa, mu, h


def node_volume(path: str | Path, what: str) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """kappa (mm), mu (mm^-1) and positions (mm), ``(N, 3)`` each, of a per-node material
    ``.npz`` (``[material].nodes``, written by :meth:`glsldiff.render.renderer.Renderer.save_material`), checked."""
    return node_arrays(read_npz(path, what, ("kappa", "mu", "positions_mm")), path, what)


def node_arrays(z: dict[str, NDArray], path: str | Path, what: str
                ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """:func:`node_volume` of the arrays ``z`` already read from ``path``."""
    kappa, mu, pos = (np.asarray(z[k], dtype=np.float64) for k in ("kappa", "mu", "positions_mm"))
    if pos.ndim != 2 or pos.shape[1] != 3 or len(pos) < 1 or kappa.shape != pos.shape or mu.shape != pos.shape:
        raise InputError(f"{what} {str(path)!r}: kappa, mu and positions_mm must all have shape (N, 3), got "
                         f"{kappa.shape}, {mu.shape} and {pos.shape}")
    _check_coefficients(kappa, mu, path, what, ", positions finite", rest_ok=bool(np.isfinite(pos).all()))
    return kappa, mu, pos


def example_names() -> tuple[str, ...]:
    """Names of the example scenes shipped in :mod:`glsldiff.render.examples`."""
    folder = importlib.resources.files("glsldiff.render.examples")
    return tuple(sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml")))


def example_scene(name: str) -> Scene:
    """A shipped example scene by name (:func:`example_names`)."""
    names = example_names()
    if name not in names:
        raise InputError(f"no example scene {name!r}; the examples are: {', '.join(names)}")
    with importlib.resources.as_file(importlib.resources.files("glsldiff.render.examples") / f"{name}.toml") as p:
        return load_scene(p)
