"""Three-pass rendering of a scene (Wang et al. 2008, section 5; Table III).

Stages, in the one direction data flows (numpy arrays between them):

* **setup** (per mesh + polygrid): mesh, polygrid, hierarchy, and the sparse matrix that
  interpolates boundary-node values to the mesh vertices (inverse-distance weights of the
  4 nearest boundary nodes). Not part of t1..t3 (the paper precomputes it too).
* **material** (per material): kappa (mm), mu (mm^-1) per node (:mod:`glsldiff.render.materials`),
  and the GLSL solver that holds them as textures.
* **pass 1** (t1, per light set): transmitted irradiance ``E_t`` at the boundary nodes
  (:func:`glsldiff.render.lighting.incident_light`: shadow maps, environment light with per-node
  visibility), and the solver's boundary source ``q``.
* **pass 2** (t2): the polygrid diffusion solve (:class:`glsldiff.solve.multilevel.MultilevelDiffusion`),
  warm-started from the previous frame's solution when only the light changed.
* **pass 3** (t3, every frame): the mesh rasterised with moderngl; per vertex, the
  multiple-scattering term interpolated from the boundary nodes times ``F_t(eta, n.w_o)``,
  plus Ward specular per light (per-vertex shadow visibility; a projector's image factor,
  :func:`glsldiff.render.lighting.projector_factor`, is folded into it as its channel mean, so the
  highlight takes the intensity's colour), plus optional single scattering
  (:mod:`glsldiff.physics.single`, with the projector's RGB image factor), plus an optional
  measured diffuse surface reflectance ``rho_d / pi * E`` (``[material].reflectance``,
  :mod:`glsldiff.inverse.reflectance`; ``E`` the incident irradiance with shadows).

Exitant radiance (``[options].exitant``): the conventions of :mod:`glsldiff.physics.exitance`.

On lit surfaces the bracket of ``p1``/``arbree`` can dip below zero where the diffusion
solution undershoots (low albedo); such vertices are clamped to 0 and counted in the report.

Skipping: every stage keeps the key of the scene parts it depends on; a stage whose key
did not change is skipped and the report says why (e.g. only the camera moved: passes 1
and 2 skipped; only a light moved: setup and material kept, pass 2 warm-started).
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import moderngl
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from glsldiff import gl
from glsldiff.core import io
from glsldiff.core.errors import InputError
from glsldiff.physics.exitance import exitant_bracket, source_from_irradiance
from glsldiff.render.scene import LightSpec, Scene, read_light_image, vec

MAX_SHADER_LIGHTS = 4  # lights with specular highlights in pass 3 (environment light: diffuse only)


@dataclass
class RenderReport:
    """What one :meth:`Renderer.render` call did, with times in seconds."""

    passes: list[dict[str, Any]] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    renderer: str = ""
    solver: Any = None
    nodes: int = 0
    boundary_nodes: int = 0
    clamped_vertices: int = 0
    image_size: tuple[int, int] = (0, 0)
    notes: list[str] = field(default_factory=list)

    def ran(self, name: str) -> bool:
        return any(p["pass"] == name and p["ran"] for p in self.passes)

    @property
    def frame_seconds(self) -> float:
        """t1 + t2 + t3 (what ran this frame)."""
        return sum(self.seconds.get(k, 0.0) for k in ("t1", "t2", "t3"))

    def lines(self) -> list[str]:
        out = [f"GL renderer: {self.renderer}",
               f"polygrid: {self.nodes} active nodes, {self.boundary_nodes} boundary; image {self.image_size[0]}x"
               f"{self.image_size[1]}"]
        for p in self.passes:
            state = f"ran     {p['seconds'] * 1e3:9.1f} ms" if p["ran"] else "skipped             "
            out.append(f"  {p['pass']:<8} {state}  {p['why']}")
        t = self.seconds
        fs = self.frame_seconds
        out.append(f"t1/t2/t3 = {t.get('t1', 0) * 1e3:.1f}/{t.get('t2', 0) * 1e3:.1f}/{t.get('t3', 0) * 1e3:.1f} ms, "
                   f"frame {fs * 1e3:.1f} ms = {1.0 / fs if fs > 0 else math.inf:.2f} fps-equivalent"
                   + (f" (setup {t['setup']:.2f} s)" if "setup" in t else ""))
        if self.solver is not None:
            out.append("solver: " + self.solver.summary())
        if self.clamped_vertices:
            out.append(f"exitant radiance clamped to 0 at {self.clamped_vertices} lit vertices (diffusion undershoot)")
        out.extend(self.notes)
        return out


# ---------------------------------------------------------------- small pure helpers
def vertex_interpolation(vertices: NDArray, nodes: NDArray, k: int = 4) -> sp.csr_matrix:
    """``(V, Nb)`` inverse-squared-distance weights of the ``k`` nearest boundary nodes."""
    k = min(k, len(nodes))
    d, idx = cKDTree(nodes).query(vertices, k=k)
    d, idx = d.reshape(len(vertices), k), idx.reshape(len(vertices), k)
    w = 1.0 / np.maximum(d, 1e-6 * max(float(np.ptp(nodes, axis=0).max()), 1e-9)) ** 2
    w /= w.sum(axis=1, keepdims=True)
    rows = np.repeat(np.arange(len(vertices)), k)
    return sp.csr_matrix((w.ravel(), (rows, idx.ravel())), shape=(len(vertices), len(nodes)))


def subdivide(mesh: Any, max_edge: float) -> Any:
    """``mesh`` with every edge split down to ``max_edge`` mm (pass 3 shades per vertex, so
    a coarse mesh such as a 12-triangle box needs vertices at about the node spacing)."""
    import trimesh.remesh

    from glsldiff.mesh import Mesh

    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    edges = np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2)
    if edges.max() <= max_edge:
        return mesh
    v2, f2 = trimesh.remesh.subdivide_to_size(v, f, max_edge=max_edge)
    return Mesh(np.asarray(v2, float), np.asarray(f2, np.int64), name=mesh.name)


def vertex_normals(vertices: NDArray, faces: NDArray) -> NDArray[np.float64]:
    """Area-weighted outward vertex normals."""
    v = vertices[faces]
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n = np.zeros_like(vertices)
    for c in range(3):
        np.add.at(n, faces[:, c], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def look_at(eye: NDArray, target: NDArray, up: NDArray) -> NDArray[np.float64]:
    f = target - eye
    f /= np.linalg.norm(f)
    s = np.cross(f, up)
    if np.linalg.norm(s) < 1e-9:
        raise InputError("[camera].up is parallel to the viewing direction; choose another up vector")
    s /= np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def perspective(fov_deg: float, aspect: float, near: float, far: float) -> NDArray[np.float64]:
    t = 1.0 / math.tan(math.radians(fov_deg) / 2.0)
    m = np.zeros((4, 4))
    m[0, 0], m[1, 1] = t / aspect, t
    m[2, 2], m[2, 3] = (far + near) / (near - far), 2.0 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def frame_camera(scene: Scene, vertices: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Eye, target, up (mm): the scene's, or framed on the mesh's bounding sphere from the
    front (+z), slightly above."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre = 0.5 * (lo + hi)
    target = vec(scene.camera.target) if scene.camera.target is not None else centre
    up = vec(scene.camera.up)
    if scene.camera.position is not None:
        return vec(scene.camera.position), target, up
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    dist = 1.08 * radius / math.sin(math.radians(scene.camera.fov_deg) / 2.0)
    d = np.array([0.0, 0.2, 1.0])
    return target + dist * d / np.linalg.norm(d), target, up


# ---------------------------------------------------------------- GL pass 3
_VERT = """
#version 330 core
uniform mat4 u_mvp;
in vec3 in_pos;
in vec3 in_normal;
in vec3 in_ms;
in vec4 in_vis;
in vec3 in_ss;
out vec3 v_pos;
out vec3 v_normal;
out vec3 v_ms;
out vec4 v_vis;
out vec3 v_ss;
void main() {
    v_pos = in_pos; v_normal = in_normal; v_ms = in_ms; v_vis = in_vis; v_ss = in_ss;
    gl_Position = u_mvp * vec4(in_pos, 1.0);
}
"""

_FRAG = """
#version 330 core
#define MAX_LIGHTS %d
uniform vec3 u_eye;
uniform float u_eta;
uniform float u_rho_s;
uniform float u_alpha;
uniform int u_nlights;
uniform int u_type[MAX_LIGHTS];       // 0 directional, 1 point (or projector), 2 spot
uniform vec3 u_lvec[MAX_LIGHTS];      // directional: towards the light; point/spot: position (mm)
uniform vec3 u_axis[MAX_LIGHTS];      // spot axis (from the light into the scene)
uniform vec3 u_power[MAX_LIGHTS];     // directional: irradiance; point/spot: intensity
uniform vec2 u_cone[MAX_LIGHTS];      // spot: cos(cone), cos(falloff)
in vec3 v_pos;
in vec3 v_normal;
in vec3 v_ms;
in vec4 v_vis;
in vec3 v_ss;
layout(location = 0) out vec4 f_color;

float fresnel_t(float eta, float c) {   // unpolarised dielectric transmittance, outside -> inside
    c = clamp(c, 0.0, 1.0);
    float s2 = (1.0 - c * c) / (eta * eta);
    if (s2 >= 1.0) return 0.0;
    float ct = sqrt(1.0 - s2);
    float rs = (c - eta * ct) / (c + eta * ct);
    float rp = (eta * c - ct) / (eta * c + ct);
    return 1.0 - 0.5 * (rs * rs + rp * rp);
}

void main() {
    vec3 n = normalize(v_normal);
    vec3 wo = normalize(u_eye - v_pos);
    float co = dot(n, wo);
    if (co <= 0.0) { n = -n; co = -co; }   // silhouette vertices interpolate past 90 degrees
    vec3 L = fresnel_t(u_eta, co) * v_ms + v_ss;
    for (int i = 0; i < u_nlights; ++i) {
        vec3 wi; vec3 E;
        if (u_type[i] == 0) { wi = normalize(u_lvec[i]); E = u_power[i]; }
        else {
            vec3 d = u_lvec[i] - v_pos; float r2 = dot(d, d); wi = d * inversesqrt(r2);
            E = u_power[i] / r2;
            if (u_type[i] == 2) {  // lighting.spot_factor; a hard edge where falloff = cone
                float c = dot(-wi, normalize(u_axis[i]));
                E *= u_cone[i].y - u_cone[i].x > 1e-6 ? smoothstep(u_cone[i].x, u_cone[i].y, c)
                                                      : step(u_cone[i].x, c);
            }
        }
        float ci = dot(n, wi);
        if (ci <= 0.0) continue;
        vec3 h = normalize(wi + wo);
        float ch = max(dot(n, h), 1e-4);
        float t2 = (1.0 - ch * ch) / (ch * ch);
        float f = u_rho_s * exp(-t2 / (u_alpha * u_alpha)) / (4.0 * 3.14159265 * u_alpha * u_alpha * sqrt(ci * co));
        L += f * ci * E * v_vis[i];
    }
    f_color = vec4(L, 1.0);
}
""" % MAX_SHADER_LIGHTS


def _light_uniforms(lights: list[LightSpec]) -> dict[str, Any]:
    k = MAX_SHADER_LIGHTS
    typ, lvec, axis, power, cone = [0] * k, [(0.0, 0.0, 1.0)] * k, [(0.0, 0.0, -1.0)] * k, [(0.0,) * 3] * k, [(0.0, 1.0)] * k
    for i, lt in enumerate(lights):
        if lt.type == "directional":
            d = vec(lt.direction)
            typ[i], lvec[i], power[i] = 0, tuple(d / np.linalg.norm(d)), lt.irradiance
        else:  # a projector is a point light here: its image factor, 0 outside the frustum, is in v_vis
            typ[i], lvec[i], power[i] = (2 if lt.type == "spot" else 1), lt.position, lt.intensity
            if lt.type == "spot":
                axis[i] = lt.direction
                cone[i] = (math.cos(math.radians(lt.cone_deg)), math.cos(math.radians(lt.falloff_deg)))
    def tup(rows: list) -> list[tuple[float, ...]]:
        return [tuple(float(x) for x in r) for r in rows]

    return {"u_nlights": len(lights), "u_type": [int(t) for t in typ], "u_lvec": tup(lvec), "u_axis": tup(axis),
            "u_power": tup(power), "u_cone": tup(cone)}


def _set(prog: moderngl.Program, values: dict[str, Any]) -> None:
    for name, value in values.items():
        if name in prog:
            prog[name].value = value


def shade(ctx: moderngl.Context, vertices: NDArray, faces: NDArray, normals: NDArray, ms: NDArray,
          vis: NDArray, ss: NDArray, lights: list[LightSpec], eye: NDArray, mvp: NDArray, eta: float,
          rho_s: float, alpha: float, size: tuple[int, int]) -> NDArray[np.float32]:
    """Pass 3: rasterise the mesh into an ``(h, w, 3)`` float image (row 0 = top)."""
    gl.make_current(ctx)
    w, h = size
    objs: list[Any] = []
    previous = ctx.fbo
    try:
        prog = ctx.program(vertex_shader=_VERT, fragment_shader=_FRAG)
        objs.append(prog)
        data = np.hstack([vertices, normals, ms, vis, ss]).astype("f4")
        vbo = ctx.buffer(np.ascontiguousarray(data).tobytes())
        ibo = ctx.buffer(np.ascontiguousarray(faces.astype("i4")).tobytes())
        objs += [vbo, ibo]
        vao = ctx.vertex_array(prog, [(vbo, "3f 3f 3f 4f 3f", "in_pos", "in_normal", "in_ms", "in_vis", "in_ss")],
                               index_buffer=ibo)
        objs.append(vao)
        color = ctx.texture((w, h), 4, dtype="f4")
        depth = ctx.depth_renderbuffer((w, h))
        fbo = ctx.framebuffer(color_attachments=[color], depth_attachment=depth)
        objs += [color, depth, fbo]
        prog["u_mvp"].write(np.ascontiguousarray(mvp.T, dtype="f4").tobytes())
        _set(prog, {"u_eye": tuple(float(x) for x in eye), "u_eta": float(eta), "u_rho_s": float(rho_s),
                    "u_alpha": float(alpha), **_light_uniforms(lights)})
        fbo.use()
        fbo.viewport = (0, 0, w, h)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        try:
            vao.render(moderngl.TRIANGLES)
            ctx.finish()
        finally:
            ctx.disable(moderngl.DEPTH_TEST)
        img = np.frombuffer(fbo.read(components=4, dtype="f4"), dtype=np.float32).reshape(h, w, 4)
        return np.ascontiguousarray(img[::-1, :, :3])
    finally:
        previous.use()   # the caller's framebuffer, before ours is released
        for o in reversed(objs):
            o.release()


# ---------------------------------------------------------------- the renderer
def _key(*parts: Any) -> str:
    return repr(parts)


class Renderer:
    """Renders scenes, keeping each stage's result while its inputs stay the same.

    >>> r = Renderer()                       # doctest: +SKIP
    >>> img, rep = r.render(default_scene())  # doctest: +SKIP
    """

    def __init__(self, ctx: moderngl.Context | None = None, progress: bool = False) -> None:
        self.ctx = ctx if ctx is not None else gl.get_context()
        self.progress = progress
        self._keys: dict[str, str] = {}
        self._geo: dict[str, Any] = {}
        self._solver: Any = None
        self._mat: dict[str, Any] = {}
        self._E_t: NDArray | None = None
        self._q: NDArray | None = None
        self._phi_b: NDArray | None = None
        self._solve_report: Any = None

    @property
    def mesh(self) -> Any:
        """The render mesh (subdivided to the node spacing), after the first frame."""
        return self._geo["render_mesh"]

    @property
    def polygrid(self) -> Any:
        return self._geo["pg"]

    # -- stages --------------------------------------------------------------------
    def _setup(self, scene: Scene) -> None:
        from glsldiff.grids.hierarchy import Hierarchy
        from glsldiff.mesh import load_mesh, sphere_mesh
        from glsldiff.grids.polygrid import build_polygrid

        m, g = scene.mesh, scene.polygrid
        if m.source == "sphere":
            mesh = sphere_mesh(m.size_mm / 2.0)
        else:
            src = m.source if m.source in _samples() else str(scene.resolve(m.source))
            mesh = load_mesh(src, size_mm=m.size_mm)
        pg = build_polygrid(mesh, n=g.n, n_cubes=g.cubes)
        hier = Hierarchy.build(pg, g.levels)   # levels = 1: the polygrid alone
        render_mesh = subdivide(mesh, pg.lattice.h)
        v, f = np.asarray(render_mesh.vertices), np.asarray(render_mesh.faces)
        self._geo = {"mesh": mesh, "render_mesh": render_mesh, "pg": pg, "hier": hier, "vertices": v, "faces": f,
                     "normals": vertex_normals(v, f), "interp": vertex_interpolation(v, pg.boundary_positions)}

    def _material(self, scene: Scene) -> None:
        from glsldiff.render.materials import node_material

        pg = self._geo["pg"]
        kappa, mu, info = node_material(scene, pg.positions, pg)
        self._mat = {"kappa": kappa.reshape(pg.shape + (3,)), "mu": mu.reshape(pg.shape + (3,)), "info": info}
        if self._solver is not None:
            self._solver.release()
            self._solver = None

    def _pass1(self, scene: Scene) -> None:
        from glsldiff.render.lighting import incident_light

        pg = self._geo["pg"]
        E_t, info = incident_light(self._geo["mesh"], pg.boundary_positions, pg.normals, self._lights(scene),
                                   scene.material.eta, ctx=self.ctx)
        self._E_t = np.asarray(E_t, dtype=np.float64)
        self._q = source_from_irradiance(self._E_t, scene.material.eta, scene.options.exitant)
        self._light_info = info

    def _pass2(self, scene: Scene, warm: bool) -> None:
        from glsldiff.solve.multilevel import MultilevelDiffusion
        from glsldiff.system.problem import DiffusionProblem

        pg, opts = self._geo["pg"], scene.options
        gl.make_current(self.ctx)
        if self._solver is None:
            problem = DiffusionProblem(pg, self._mat["kappa"], self._mat["mu"], self._q, eta=scene.material.eta,
                                       stencil="conservative")
            self._solver = MultilevelDiffusion(self._geo["hier"], problem, opts.scheme, ctx=self.ctx, precision=opts.precision)
            warm = False
        else:
            self._solver.set_q(self._q)
        phi, rep = self._solver.solve(tol=opts.tol, keep=warm and opts.scheme != "multigrid")
        self._phi_b = np.asarray(phi, dtype=np.float64).reshape(-1, 3)[pg.lattice.boundary]
        self._solve_report = rep

    @staticmethod
    def _light(lt: LightSpec, scene: Scene) -> Any:
        from glsldiff.render import lighting

        if lt.type == "directional":
            return lighting.DirectionalLight(vec(lt.direction) / np.linalg.norm(lt.direction), vec(lt.irradiance),
                                             lt.shadows)
        if lt.type == "point":
            return lighting.PointLight(vec(lt.position), vec(lt.intensity), lt.shadows)
        if lt.type == "spot":
            return lighting.SpotLight(vec(lt.position), vec(lt.direction) / np.linalg.norm(lt.direction),
                                      vec(lt.intensity), lt.cone_deg, lt.falloff_deg, lt.shadows)
        if lt.type == "projector":
            return lighting.ProjectorLight(vec(lt.position), vec(lt.direction),
                                           read_light_image(scene.resolve(lt.image)), vec(lt.intensity),
                                           up=lt.up if lt.up is not None else (0.0, 1.0, 0.0),
                                           fov_deg=lt.fov_deg, shadows=lt.shadows)
        return lighting.EnvironmentLight(read_light_image(scene.resolve(lt.path), exr_only=True), lt.scale)

    def _lights(self, scene: Scene) -> list[Any]:
        """The :mod:`glsldiff.render.lighting` objects of ``scene.lights``, built (image files read)
        once per change of the lights and shared by pass 1 and pass 3."""
        key = _key(scene.lights, str(scene.base_dir))
        if self._keys.get("light objects") != key:
            self._light_objects = [self._light(lt, scene) for lt in scene.lights]
            self._keys["light objects"] = key
        return self._light_objects

    def _shader_lights(self, scene: Scene) -> list[tuple[LightSpec, Any]]:
        """(spec, lighting object) of the lights pass 3 shades per light (all but environments)."""
        return [(lt, obj) for lt, obj in zip(scene.lights, self._lights(scene))
                if lt.type != "environment"][:MAX_SHADER_LIGHTS]

    def _pass3(self, scene: Scene) -> NDArray[np.float32]:
        from glsldiff.render.lighting import projector_factor, visibility

        geo, opts = self._geo, scene.options
        v, f, nrm = geo["vertices"], geo["faces"], geo["normals"]
        eta = scene.material.eta
        B = exitant_bracket(self._phi_b, self._q, eta, opts.exitant)
        ms = geo["interp"] @ B
        neg = ms < 0.0
        self._clamped = int(np.any(neg, axis=1).sum())
        ms = np.maximum(ms, 0.0)
        shader_lights = self._shader_lights(scene)
        vis_key = _key(scene.mesh, scene.polygrid, scene.lights)
        if self._keys.get("vis") != vis_key:
            # per shader light: shadow visibility (V,) and RGB image factor (V, 3), 1 but for projectors
            vis, tint = np.ones((len(v), 4)), np.ones((len(v), 4, 3))
            for i, (lt, light) in enumerate(shader_lights):
                if lt.shadows:
                    vis[:, i] = visibility(geo["mesh"], v, light, ctx=self.ctx, normals=nrm)
                if lt.type == "projector":
                    tint[:, i] = projector_factor(light, v)
            self._vis, self._tint, self._keys["vis"] = vis, tint, vis_key
        eye, target, up = frame_camera(scene, v)
        ss = np.zeros_like(v)
        if opts.single_scattering:
            ss = self._single(scene, eye)
        if scene.material.reflectance is not None:
            ss = ss + self._surface_diffuse(scene)
        w, h = scene.output.width, scene.output.height
        radius = 0.5 * float(np.linalg.norm(np.ptp(v, axis=0)))
        dist = float(np.linalg.norm(eye - target))
        proj = perspective(scene.camera.fov_deg, w / h, max(1e-3, dist - 2 * radius), dist + 2 * radius)
        mvp = proj @ look_at(eye, target, up)
        vis = self._vis * self._tint.mean(axis=2)   # the shader's visibility is one number per light
        return shade(self.ctx, v, f, nrm, ms, vis, ss, [lt for lt, _ in shader_lights], eye, mvp, eta,
                     scene.specular.rho_s, scene.specular.alpha, (w, h))

    def _surface_diffuse(self, scene: Scene) -> NDArray[np.float64]:
        """Per-vertex measured diffuse surface reflection ``rho_d / pi * E`` (Lambertian), with
        ``E`` the incident irradiance of all lights (shadows, environment visibility);
        cached until the lights, the geometry or the reflectance change (a change of the
        reflectance alone re-runs neither the material stage nor pass 1-2)."""
        from glsldiff.render.lighting import incident_light
        from glsldiff.render.materials import surface_reflectance

        geo = self._geo
        rho_key = _key(self._keys.get("geometry"), scene.material.reflectance, scene.material.volume)
        if self._keys.get("rho") != rho_key:
            self._rho, self._keys["rho"] = geo["interp"] @ surface_reflectance(scene, geo["pg"]), rho_key
        key = _key(rho_key, self._keys.get("light"))
        if self._keys.get("diffuse") != key:
            E, _ = incident_light(geo["mesh"], geo["vertices"], geo["normals"], self._lights(scene), None,
                                  ctx=self.ctx)
            self._diffuse, self._keys["diffuse"] = self._rho * E / math.pi, key
        return self._diffuse

    def _single(self, scene: Scene, eye: NDArray) -> NDArray[np.float64]:
        from glsldiff.render.lighting import spot_factor
        from glsldiff.physics.single import single_scattering
        from glsldiff.render.materials import node_material

        geo = self._geo
        v, nrm = geo["vertices"], geo["normals"]
        view = eye - v
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        pg = self._geo["pg"]
        lo, hi = pg.positions.min(axis=0), pg.positions.max(axis=0)

        def material(p: NDArray) -> tuple[NDArray, NDArray]:
            kappa, mu, _ = node_material(scene, np.vstack([lo, hi, p]), pg)   # same unit box as the nodes
            kappa, mu = kappa[2:], mu[2:]
            return mu, np.maximum(1.0 / (3.0 * kappa) - mu, 0.0)

        medium: Any = material
        if not (scene.material.procedural or scene.material.volume):
            sa, ss = material(v[:1])
            medium = (sa[0], ss[0])
        out = np.zeros_like(v)
        for i, (lt, light) in enumerate(self._shader_lights(scene)):
            if lt.type == "directional":
                ldir = np.broadcast_to(vec(lt.direction) / np.linalg.norm(lt.direction), v.shape)
                E = np.broadcast_to(vec(lt.irradiance), v.shape)
            else:
                d = vec(lt.position) - v
                r2 = np.sum(d * d, axis=1, keepdims=True)
                ldir = d / np.sqrt(r2)
                E = vec(lt.intensity) / r2
                if lt.type == "spot":
                    E = E * spot_factor(light, -(ldir @ np.asarray(light.direction)))[:, None]
            E = E * self._vis[:, i:i + 1] * self._tint[:, i]
            out += single_scattering(v, nrm, view, np.ascontiguousarray(ldir), np.ascontiguousarray(E),
                                     medium, scene.material.eta)
        return out

    # -- the frame -----------------------------------------------------------------
    def render(self, scene: Scene) -> tuple[NDArray[np.float32], RenderReport]:
        """One frame: ``(h, w, 3)`` linear radiance (row 0 = top) and the report."""
        rep = RenderReport(renderer=gl.describe(self.ctx), image_size=(scene.output.width, scene.output.height))
        geo_key = _key(scene.mesh, scene.polygrid, str(scene.base_dir))
        mat_key = _key(geo_key, replace(scene.material, reflectance=None),  # pass 3 alone uses the reflectance
                       scene.options.scheme, scene.options.precision, str(scene.base_dir))
        light_key = _key(geo_key, scene.lights, scene.material.eta, scene.options.exitant, str(scene.base_dir))
        solve_key = _key(mat_key, light_key, scene.options.tol)

        def stage(name: str, key_name: str, key: str, fn: Any, why_skip: str, timer: str | None) -> bool:
            if self._keys.get(key_name) == key:
                rep.passes.append({"pass": name, "ran": False, "seconds": 0.0, "why": why_skip})
                return False
            t0 = time.perf_counter()
            reason = "first frame" if key_name not in self._keys else f"{key_name} changed"
            fn()
            dt = time.perf_counter() - t0
            self._keys[key_name] = key
            rep.passes.append({"pass": name, "ran": True, "seconds": dt, "why": reason})
            if timer:
                rep.seconds[timer] = dt
            return True

        new_geo = stage("setup", "geometry", geo_key, lambda: self._setup(scene),
                        "mesh and polygrid unchanged (no re-packing)", "setup")
        if new_geo:
            self._keys.pop("material", None)
            self._keys.pop("light", None)
            self._keys.pop("solve", None)
        new_mat = stage("material", "material", mat_key, lambda: self._material(scene), "material unchanged", None)
        new_light = stage("pass1", "light", light_key, lambda: self._pass1(scene),
                          "lights unchanged: incident light kept", "t1")
        warm = not (new_geo or new_mat) and new_light
        stage("pass2", "solve", solve_key, lambda: self._pass2(scene, warm),
              "material and incident light unchanged: solution kept", "t2")
        if rep.ran("pass2") and warm:
            rep.passes[-1]["why"] = "light changed: warm start from the previous frame (frame coherence)"
        t0 = time.perf_counter()
        img = self._pass3(scene)
        rep.seconds["t3"] = time.perf_counter() - t0
        rep.passes.append({"pass": "pass3", "ran": True, "seconds": rep.seconds["t3"], "why": "every frame"})
        pg = self._geo["pg"]
        rep.nodes, rep.boundary_nodes = int(pg.n_active), int(len(pg.boundary_positions))
        rep.solver = self._solve_report
        rep.clamped_vertices = self._clamped
        rep.notes.append(f"material: {self._mat['info'].get('material')}; exitant: {scene.options.exitant}; "
                         f"single scattering: {'on' if scene.options.single_scattering else 'off'}; "
                         f"diffuse surface reflectance: "
                         f"{'off' if scene.material.reflectance is None else scene.material.reflectance}")
        for info in getattr(self, "_light_info", []):
            rep.notes.append("light: " + ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                                                   for k, v in info.items()))
        return img, rep

    def release(self) -> None:
        if self._solver is not None:
            self._solver.release()
            self._solver = None

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _samples() -> tuple[str, ...]:
    from glsldiff.mesh import SAMPLE_MESHES
    return tuple(SAMPLE_MESHES)


# ---------------------------------------------------------------- output files
def check_output(path: str | os.PathLike) -> Path:
    """Refuse an output path that cannot be written, before any work (see :func:`glsldiff.core.io.check_output`)."""
    return io.check_output(path, (".exr",), "a tone-mapped .png is written beside it")


def auto_exposure(img: NDArray) -> float:
    """Scale that maps the 99th percentile of the lit pixels' luminance to 0.9."""
    lum = img @ np.array([0.2126, 0.7152, 0.0722])
    lit = lum[lum > 0]
    return 0.9 / float(np.percentile(lit, 99)) if lit.size else 1.0


def save(img: NDArray, path: Path, scene: Scene, rep: RenderReport) -> tuple[Path, Path, float]:
    """EXR (linear radiance) and a tone-mapped PNG beside it, both written atomically."""

    exposure = auto_exposure(img) if scene.output.exposure == "auto" else float(scene.output.exposure)
    attrs = {"glsldiff_scene": scene.source, "glsldiff_renderer": rep.renderer,
             "glsldiff_t1_t2_t3_ms": "/".join(f"{rep.seconds.get(k, 0) * 1e3:.1f}" for k in ("t1", "t2", "t3"))}
    io.write_exr(path, img, attributes=attrs)
    png = path.with_suffix(".png")
    io.write_png(png, io.tonemap(img, exposure))
    return path, png, exposure
