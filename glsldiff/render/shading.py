"""Pass 3 (Wang et al. 2008, section 5): the mesh rasterised with ``shaders/shade.{vert,frag}``.

Per vertex the caller supplies the multiple-scattering factor ``ms`` (the exitant bracket of
:mod:`glsldiff.physics.exitance` interpolated from the boundary nodes, :func:`vertex_interpolation`),
one shadow visibility per shader light and the view-dependent extras ``ss`` (single
scattering, diffuse surface reflectance). Per fragment the shader adds up

    ``L = F_t(eta, n.w_o) ms + ss + sum_lights Ward(rho_s, alpha) cos_i E vis``

with ``F_t`` the Fresnel transmittance (:func:`glsldiff.physics.optics.fresnel_transmittance`)
and the isotropic Ward lobe ``rho_s exp(-tan^2 theta_h / alpha^2) / (4 pi alpha^2
sqrt(cos_i cos_o))``. Positions in mm; ``E`` is irradiance (directional) or intensity / r^2
(point, spot with its cone factor; a projector is a point light whose image factor is in
``vis``).
"""
from __future__ import annotations

import math
from typing import Any

import moderngl
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from glsldiff import gl
from glsldiff.core import cache
from glsldiff.mesh import Mesh, closest_points
from glsldiff.mesh.closest import closest_on_triangles
from glsldiff.physics.lights import DirectionalLight, DirectLight, SpotLight

MAX_SHADER_LIGHTS = 4  # lights with specular highlights in pass 3 (environment light: diffuse only)
#: Part of every cached interpolation's key: bump it when :func:`surface_interpolation` changes.
INTERPOLATION_CACHE_VERSION = 1


def vertex_interpolation(vertices: NDArray, nodes: NDArray, k: int = 4) -> sp.csr_matrix:
    """``(V, Nb)`` inverse-squared-distance weights of the ``k`` nearest boundary nodes (mm)."""
    k = min(k, len(nodes))
    d, idx = cKDTree(nodes).query(vertices, k=k)
    d, idx = d.reshape(len(vertices), k), idx.reshape(len(vertices), k)
    w = 1.0 / np.maximum(d, 1e-6 * max(float(np.ptp(nodes, axis=0).max()), 1e-9)) ** 2
    w /= w.sum(axis=1, keepdims=True)
    rows = np.repeat(np.arange(len(vertices)), k)
    return sp.csr_matrix((w.ravel(), (rows, idx.ravel())), shape=(len(vertices), len(nodes)))


def surface_interpolation(vertices: NDArray, nodes: NDArray, triangles: NDArray) -> sp.csr_matrix:
    """``(V, S)`` barycentric weights of each vertex's closest point on the triangle surface
    that the surface ``nodes`` ``(S, 3)`` span (``triangles`` ``(F, 3)`` into ``nodes``).

    Unlike nearest-node weights this follows the surface: a vertex takes its colour from the
    three nodes of the surface triangle under it, never from nodes across a thin gap."""
    surf = Mesh(np.asarray(nodes, dtype=np.float64), np.asarray(triangles, dtype=np.int64), name="surface nodes")
    p = np.asarray(vertices, dtype=np.float64)
    _, _, tri, _ = closest_points(surf, p)
    t = surf.faces[tri]
    w = closest_on_triangles(p, *(surf.vertices[t[:, k]] for k in range(3)))   # barycentrics, >= 0, sum 1
    rows = np.repeat(np.arange(len(vertices)), 3)
    return sp.csr_matrix((w.ravel(), (rows, t.ravel())), shape=(len(vertices), len(nodes)))


def cached_surface_interpolation(vertices: NDArray, nodes: NDArray, triangles: NDArray) -> sp.csr_matrix:
    """:func:`surface_interpolation` through the on-disk cache (:mod:`glsldiff.core.cache`),
    keyed by the three arrays (positions in mm): 0.5 s of closest points for the default bunny."""
    v, x, t = (np.asarray(vertices, dtype=np.float64), np.asarray(nodes, dtype=np.float64),
               np.asarray(triangles, dtype=np.int64))
    key = cache.digest(f"surface interpolation v{INTERPOLATION_CACHE_VERSION}", v, x, t)
    return cache.memo("interp", key, sp.csr_matrix, lambda: surface_interpolation(v, x, t))


def _light_uniforms(lights: list[DirectLight]) -> dict[str, Any]:
    k = MAX_SHADER_LIGHTS
    typ, lvec, axis, power, cone = [0] * k, [(0.0, 0.0, 1.0)] * k, [(0.0, 0.0, -1.0)] * k, [(0.0,) * 3] * k, [(0.0, 1.0)] * k
    for i, lt in enumerate(lights):
        if isinstance(lt, DirectionalLight):
            typ[i], lvec[i], power[i] = 0, lt.direction, lt.irradiance
        else:  # a projector is a point light here: its image factor, 0 outside the frustum, is in v_vis
            typ[i], lvec[i], power[i] = (2 if isinstance(lt, SpotLight) else 1), lt.position, lt.intensity
            if isinstance(lt, SpotLight):
                axis[i] = lt.direction
                cone[i] = (math.cos(math.radians(lt.cone_deg)), math.cos(math.radians(lt.falloff_deg)))
    def tup(rows: list) -> list[tuple[float, ...]]:
        return [tuple(float(x) for x in r) for r in rows]

    return {"u_nlights": len(lights), "u_type": [int(t) for t in typ], "u_lvec": tup(lvec), "u_axis": tup(axis),
            "u_power": tup(power), "u_cone": tup(cone)}


class Shader:
    """Pass 3's GL objects, kept from frame to frame (a camera move re-uploads the per-vertex
    values only): the program, the mesh's buffers (made again when its faces or vertex count
    change) and the target (made again when the image size changes). Owned by its creator:
    release with :meth:`release` (or use as a context manager)."""

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self._prog: Any = None
        self._mesh: gl.Resources | None = None
        self._faces: NDArray | None = None           # the faces the index buffer holds
        self._vbo: Any = None
        self._vao: Any = None
        self._n_vertices = -1
        self._target: gl.Resources | None = None
        self._fbo: Any = None
        self._size: tuple[int, int] | None = None

    def _buffers(self, n_vertices: int, faces: NDArray) -> None:
        same = self._faces is not None and (self._faces is faces or (self._faces.shape == faces.shape
                                                                      and np.array_equal(self._faces, faces)))
        if same and n_vertices == self._n_vertices:
            return
        if self._mesh is not None:
            self._mesh.release()
        self._mesh = res = gl.Resources()
        self._vbo = res.add(self.ctx.buffer(reserve=n_vertices * 16 * 4))
        ibo = res.add(self.ctx.buffer(np.ascontiguousarray(faces, dtype="i4").tobytes()))
        self._vao = res.add(self.ctx.vertex_array(self._prog, [(self._vbo, "3f 3f 3f 4f 3f", "in_pos", "in_normal",
                                                                "in_ms", "in_vis", "in_ss")], index_buffer=ibo))
        self._faces, self._n_vertices = faces, n_vertices

    def _framebuffer(self, size: tuple[int, int]) -> Any:
        if self._size != size:
            if self._target is not None:
                self._target.release()
            self._target = res = gl.Resources()
            color = res.add(self.ctx.texture(size, 4, dtype="f4"))
            depth = res.add(self.ctx.depth_renderbuffer(size))
            self._fbo = res.add(self.ctx.framebuffer(color_attachments=[color], depth_attachment=depth))
            self._size = size
        return self._fbo

    def shade(self, vertices: NDArray, faces: NDArray, normals: NDArray, ms: NDArray, vis: NDArray, ss: NDArray,
              lights: list[DirectLight], eye: NDArray, mvp: NDArray, eta: float, rho_s: float, alpha: float,
              size: tuple[int, int]) -> NDArray[np.float32]:
        """Pass 3: rasterise the mesh into an ``(h, w, 3)`` float image (row 0 = top).

        ``vertices``, ``normals``, ``ms``, ``ss``: ``(V, 3)``; ``vis``: ``(V, MAX_SHADER_LIGHTS)``;
        ``faces``: ``(F, 3)``; ``lights``: at most :data:`MAX_SHADER_LIGHTS`, no environment;
        ``eye``: camera position (mm); ``mvp``: row-major world -> clip matrix; ``size``: ``(w, h)``.
        """
        ctx = self.ctx
        gl.make_current(ctx)
        w, h = size
        if self._prog is None:
            self._prog = gl.program(ctx, "shade.vert", "shade.frag", {"MAX_LIGHTS": MAX_SHADER_LIGHTS})
        self._buffers(len(vertices), faces)
        data = np.empty((len(vertices), 16), dtype="f4")
        data[:, 0:3], data[:, 3:6], data[:, 6:9], data[:, 9:13], data[:, 13:16] = vertices, normals, ms, vis, ss
        self._vbo.write(data)
        gl.set_uniforms(self._prog, {"u_mvp": np.asarray(mvp), "u_eye": tuple(float(x) for x in eye),
                                     "u_eta": float(eta), "u_rho_s": float(rho_s), "u_alpha": float(alpha),
                                     **_light_uniforms(lights)})
        with gl.keep_framebuffer(ctx):       # the caller's framebuffer bound again after ours
            fbo = self._framebuffer((w, h))
            fbo.use()
            fbo.viewport = (0, 0, w, h)
            fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
            ctx.enable(moderngl.DEPTH_TEST)
            try:
                self._vao.render(moderngl.TRIANGLES)
                ctx.finish()
            finally:
                ctx.disable(moderngl.DEPTH_TEST)
            img = np.frombuffer(fbo.read(components=4, dtype="f4"), dtype=np.float32).reshape(h, w, 4)
        return np.ascontiguousarray(img[::-1, :, :3])

    def release(self) -> None:
        for res in (self._target, self._mesh):
            if res is not None:
                res.release()
        if self._prog is not None:
            self._prog.release()
        self._prog = self._mesh = self._target = self._faces = None
        self._size, self._n_vertices = None, -1

    def __enter__(self) -> "Shader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def shade(ctx: moderngl.Context, vertices: NDArray, faces: NDArray, normals: NDArray, ms: NDArray,
          vis: NDArray, ss: NDArray, lights: list[DirectLight], eye: NDArray, mvp: NDArray, eta: float,
          rho_s: float, alpha: float, size: tuple[int, int]) -> NDArray[np.float32]:
    """:meth:`Shader.shade` once, its GL objects released after (a renderer keeps a :class:`Shader`)."""
    with Shader(ctx) as shader:
        return shader.shade(vertices, faces, normals, ms, vis, ss, lights, eye, mvp, eta, rho_s, alpha, size)
