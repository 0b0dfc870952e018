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


def shade(ctx: moderngl.Context, vertices: NDArray, faces: NDArray, normals: NDArray, ms: NDArray,
          vis: NDArray, ss: NDArray, lights: list[DirectLight], eye: NDArray, mvp: NDArray, eta: float,
          rho_s: float, alpha: float, size: tuple[int, int]) -> NDArray[np.float32]:
    """Pass 3: rasterise the mesh into an ``(h, w, 3)`` float image (row 0 = top).

    ``vertices``, ``normals``, ``ms``, ``ss``: ``(V, 3)``; ``vis``: ``(V, MAX_SHADER_LIGHTS)``;
    ``faces``: ``(F, 3)``; ``lights``: at most :data:`MAX_SHADER_LIGHTS`, no environment;
    ``eye``: camera position (mm); ``mvp``: row-major world -> clip matrix; ``size``: ``(w, h)``.
    """
    gl.make_current(ctx)
    w, h = size
    with gl.Resources() as res, gl.keep_framebuffer(ctx):   # ours released after the caller's is bound
        prog = res.add(gl.program(ctx, "shade.vert", "shade.frag", {"MAX_LIGHTS": MAX_SHADER_LIGHTS}))
        data = np.hstack([vertices, normals, ms, vis, ss]).astype("f4")
        vbo = res.add(ctx.buffer(np.ascontiguousarray(data).tobytes()))
        ibo = res.add(ctx.buffer(np.ascontiguousarray(faces.astype("i4")).tobytes()))
        vao = res.add(ctx.vertex_array(prog, [(vbo, "3f 3f 3f 4f 3f", "in_pos", "in_normal", "in_ms", "in_vis",
                                               "in_ss")], index_buffer=ibo))
        color = res.add(ctx.texture((w, h), 4, dtype="f4"))
        depth = res.add(ctx.depth_renderbuffer((w, h)))
        fbo = res.add(ctx.framebuffer(color_attachments=[color], depth_attachment=depth))
        gl.set_uniforms(prog, {"u_mvp": np.asarray(mvp), "u_eye": tuple(float(x) for x in eye),
                               "u_eta": float(eta), "u_rho_s": float(rho_s), "u_alpha": float(alpha),
                               **_light_uniforms(lights)})
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
