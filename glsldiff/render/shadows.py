"""Shadow maps of directional, point, spot and projector lights (GL, read back to numpy).

The closed mesh is rendered from the light with moderngl (``shaders/light_depth.*``) into an
RG32F colour target, with ``glBlendEquation(GL_MIN)`` instead of a depth buffer: channel r
keeps the nearest surface facing the light, channel g the nearest surface facing away
(``gl_FrontFacing``; the mesh is outward oriented). Stored depths are world distances in mm,
computed per fragment from the interpolated position, so they are exact up to float32: along
the light direction for a directional light (orthographic view fitted to the mesh's bounding
sphere), Euclidean distance from the light for point and spot lights (a spot light up to
``cone_deg`` = 60 uses one perspective view of its cone, wider spots and point lights six
90-degree cube faces packed 3 x 2 in one texture). A projector is shadowed as the hard-edged
spot light whose cone circumscribes its frustum
(:attr:`glsldiff.physics.lights.ProjectorLight.spot`). Every shadow map is ``size`` squared
per view.

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
fractional (in [0, 1]) along shadow edges. Limits: where the object is thinner along the ray
than about twice the bias (grazing light near the terminator, thin sheets) the classification
may go either way; there n . w is small anyway. Points outside the shadow map (outside the
mesh's footprint, behind a spot light) count as lit.

GL objects (program, buffers, texture, framebuffer) live in a :class:`DepthRenderer` and are
released by its ``release`` (or ``with``); the caller's framebuffer and enable flags are
restored and the blend equation is set back to GL's default ``FUNC_ADD`` (moderngl cannot read
the previous one; the blend function is not touched). Units: mm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff import gl
from glsldiff.core.camera import orthonormal_frame, projection, view_matrix
from glsldiff.core.errors import InputError
from glsldiff.physics.lights import DirectionalLight, Light, ProjectorLight, SpotLight

__all__ = ["DepthRenderer", "ShadowMap", "View", "BIAS_TEXELS", "BIAS_SLOPE", "MAX_BIAS_TAN",
           "SPOT_SINGLE_VIEW_MAX_DEG"]

BIAS_TEXELS = 1.0          # constant part of the depth bias, in shadow-map texels (world size)
BIAS_SLOPE = 1.5           # slope part: texels per unit tan(angle between normal and light)
MAX_BIAS_TAN = 8.0         # tan clipped here (about 83 degrees)
SPOT_SINGLE_VIEW_MAX_DEG = 60.0  # wider spots use a cube of six views
_FAR = 1.0e30              # clear value of the shadow map (no surface)
_FIT = 1.02                # orthographic window: bounding radius times this
_SHADER_DEFINES = {"LIGHT_FAR": "1.0e30"}


@dataclass(frozen=True)
class View:
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
        """Clip matrix (projection times view) of this view."""
        s = 1.0 / self.half
        return (projection(s, s, self.near, self.far, orthographic=self.ortho)
                @ view_matrix(self.eye, self.right, self.up, -self.forward))


@dataclass
class ShadowMap:
    """Read-back midpoint depths of a set of views packed in an atlas of ``size``-texel tiles."""

    views: list[View]
    size: int
    mid: NDArray[np.float32] = field(repr=False)  # (rows * size, cols * size)
    front: NDArray[np.float32] = field(repr=False)  # nearest surface facing the light

    @property
    def label(self) -> str:
        s = f"{self.size}x{self.size}"
        return s if len(self.views) == 1 else f"{len(self.views)} x {s} (cube)"

    def _views_of(self, p: NDArray[np.float64]) -> NDArray[np.int64]:
        """Index of the view each point (relative to the centre) falls in: 0, or for a cube the
        face of the major axis of ``p - eye``."""
        if len(self.views) == 1:
            return np.zeros(len(p), dtype=np.int64)
        d = p - self.views[0].eye
        ax = np.argmax(np.abs(d), axis=1)
        neg = d[np.arange(len(p)), ax] < 0
        return 2 * ax + neg

    @staticmethod
    def _project(v: View, p: NDArray[np.float64], size: int
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
                            NDArray[np.bool_], NDArray[np.float64]]:
        """Points ``p`` in view ``v``: depth (the map's metric), continuous texel coordinates
        (x, y) within the tile, inside-the-view mask and the window half-size at the point."""
        d = p - v.eye
        x, y, z = d @ v.right, d @ v.up, d @ v.forward
        if v.ortho:
            depth = z
            scale = np.full(len(p), v.half)
            ok = np.ones(len(p), dtype=bool)
        else:
            depth = np.linalg.norm(d, axis=1)
            ok = z > 1e-9 * max(v.far, 1.0)
            scale = np.where(ok, z, 1.0) * v.half
        nx, ny = x / scale, y / scale
        ok &= (np.abs(nx) <= 1.0) & (np.abs(ny) <= 1.0)
        return depth, (nx + 1.0) * 0.5 * size - 0.5, (ny + 1.0) * 0.5 * size - 0.5, ok, scale

    def _texels(self, v: View, fx: NDArray[np.float64], fy: NDArray[np.float64]
                ) -> list[tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]]:
        """The 2 x 2 texels around (fx, fy) of view ``v`` as atlas (row, column) and bilinear weights."""
        S = self.size
        x0, y0 = np.floor(fx), np.floor(fy)
        wx, wy = fx - x0, fy - y0
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        ox, oy = v.tile[0] * S, v.tile[1] * S
        return [(np.clip(y0 + dy, 0, S - 1) + oy, np.clip(x0 + dx, 0, S - 1) + ox, w)
                for dx, dy, w in ((0, 0, (1 - wx) * (1 - wy)), (1, 0, wx * (1 - wy)),
                                  (0, 1, (1 - wx) * wy), (1, 1, wx * wy))]

    def lookup(self, p: NDArray[np.float64], to_light: NDArray[np.float64],
               normals: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """Visibility in [0, 1] of points ``p`` (relative to the centre), 2 x 2 PCF."""
        n_pts = len(p)
        vis = np.ones(n_pts)
        if n_pts == 0:
            return vis
        which = self._views_of(p)
        if normals is None:
            tan = np.ones(n_pts)
        else:  # points facing away lie on the far surface: no slope allowance for them
            c = np.einsum("ij,ij->i", normals, to_light)
            cc = np.clip(c, 1e-6, 1.0)
            tan = np.where(c > 0, np.minimum(np.sqrt(np.maximum(1.0 - cc * cc, 0.0)) / cc, MAX_BIAS_TAN), 0.0)
        for k, v in enumerate(self.views):
            sel = np.flatnonzero(which == k)
            if sel.size == 0:
                continue
            depth, fx, fy, ok, scale = self._project(v, p[sel], self.size)
            bias = 2.0 * scale / self.size * (BIAS_TEXELS + BIAS_SLOPE * tan[sel])
            acc = np.zeros(sel.size)
            for iy, ix, w in self._texels(v, fx, fy):
                acc += w * (depth <= self.mid[iy, ix] + bias)
            vis[sel] = np.where(ok, acc, 1.0)
        vis = np.clip(vis, 0.0, 1.0)
        vis[vis > 1.0 - 1e-9] = 1.0  # bilinear weights sum to 1 only up to rounding
        vis[vis < 1e-9] = 0.0
        return vis

    def entry(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance (mm) from points ``p`` (relative to the centre, normally inside the object)
        back along the light's ray to the nearest surface facing the light: the depth of ``p``
        minus the stored front depth, bilinear over the 2 x 2 texels when all four hold a
        surface, else the nearest one's; clipped at 0; NaN where no surface is stored or the
        point is outside every view (translucent shadow maps, Dachsbacher and Stamminger 2003)."""
        out = np.full(len(p), np.nan)
        which = self._views_of(p)
        for k, v in enumerate(self.views):
            sel = np.flatnonzero(which == k)
            if sel.size == 0:
                continue
            depth, fx, fy, ok, _ = self._project(v, p[sel], self.size)
            taps = self._texels(v, fx, fy)
            vals = np.stack([self.front[iy, ix] for iy, ix, _ in taps])             # (4, n)
            wts = np.stack([w for _, _, w in taps])
            have = vals < 0.5 * _FAR
            bil = (np.where(have, vals, 0.0) * wts).sum(axis=0)
            near = vals[np.argmax(wts, axis=0), np.arange(sel.size)]
            front = np.where(have.all(axis=0), bil, np.where(near < 0.5 * _FAR, near, np.nan))
            out[sel] = np.where(ok, np.maximum(depth - front, 0.0), np.nan)
        return out


class DepthRenderer:
    """GL resources to render a mesh's front/back depth from lights; release with ``release``
    (or use as a context manager). Coordinates are relative to the bounding-sphere centre."""

    def __init__(self, ctx: moderngl.Context, mesh: Any) -> None:
        self.ctx = ctx
        v = np.asarray(mesh.vertices, dtype=np.float64)
        f = np.asarray(mesh.faces, dtype=np.int64)
        lo, hi = v.min(axis=0), v.max(axis=0)
        self.centre = 0.5 * (lo + hi)
        self.radius = max(float(np.linalg.norm(v - self.centre, axis=1).max()), 1e-9)
        self._res = gl.Resources()
        self._atlas: tuple[tuple[int, int], moderngl.Texture, moderngl.Framebuffer] | None = None
        gl.make_current(ctx)
        try:
            self.prog = self._res.add(gl.program(ctx, "light_depth.vert", "light_depth.frag", _SHADER_DEFINES))
            vbo = self._res.add(ctx.buffer(np.ascontiguousarray(v - self.centre, dtype="f4").tobytes()))
            ibo = self._res.add(ctx.buffer(np.ascontiguousarray(f, dtype="i4").tobytes()))
            self.vao = self._res.add(ctx.vertex_array(self.prog, [(vbo, "3f", "in_pos")],
                                                      index_buffer=ibo, index_element_size=4))
        except BaseException:
            self.release()
            raise

    def __enter__(self) -> "DepthRenderer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def release(self) -> None:
        self._release_atlas()
        self._res.release()

    def _release_atlas(self) -> None:
        if self._atlas is not None:
            self._atlas[2].release()
            self._atlas[1].release()
            self._atlas = None

    # ---- views ------------------------------------------------------------------------
    def directional_view(self, towards_light: NDArray[np.float64], size: int) -> list[View]:
        fwd = -np.asarray(towards_light, dtype=np.float64)
        right, up, _ = orthonormal_frame(fwd)
        R = self.radius
        return [View(eye=-2.0 * R * fwd, forward=fwd, right=right, up=up, near=0.5 * R, far=3.5 * R,
                     half=_FIT * R, ortho=True, tile=(0, 0))]

    def perspective_views(self, position: NDArray[np.float64], size: int,
                          axis: NDArray[np.float64] | None = None,
                          cone_deg: float | None = None) -> list[View]:
        eye = np.asarray(position, dtype=np.float64) - self.centre
        D, R = float(np.linalg.norm(eye)), self.radius
        far = D + 1.05 * R

        def near(half: float) -> float:
            # the clip planes bound the depth along the view axis, which is as small as
            # distance * cos(corner angle) for a surface point at the frustum's corner
            return max((D - 1.05 * R) / math.sqrt(1.0 + 2.0 * half * half), 1e-5 * far)

        if axis is not None and cone_deg is not None and cone_deg <= SPOT_SINGLE_VIEW_MAX_DEG:
            fwd = np.asarray(axis, dtype=np.float64)
            right, up, _ = orthonormal_frame(fwd)
            half = math.tan(math.radians(cone_deg)) * 1.02 + 2.0 / size
            return [View(eye, fwd, right, up, near(half), far, half, False, (0, 0))]
        views = []
        half = 1.0 + 4.0 / size  # a little beyond 90 degrees: the 2 x 2 filter stays inside
        for k in range(6):
            fwd = np.zeros(3)
            fwd[k // 2] = -1.0 if k % 2 else 1.0
            right, up, _ = orthonormal_frame(fwd)
            views.append(View(eye, fwd, right, up, near(half), far, half, False, (k % 3, k // 3)))
        return views

    # ---- rendering --------------------------------------------------------------------
    def _framebuffer(self, shape: tuple[int, int]) -> tuple[moderngl.Texture, moderngl.Framebuffer]:
        """The RG32F atlas of ``shape`` texels, kept while the size stays the same."""
        if self._atlas is None or self._atlas[0] != shape:
            self._release_atlas()
            tex = self.ctx.texture(shape, 2, dtype="f4")
            try:
                fbo = self.ctx.framebuffer(color_attachments=[tex])
            except BaseException:
                tex.release()
                raise
            self._atlas = (shape, tex, fbo)
        return self._atlas[1], self._atlas[2]

    def render(self, views: list[View], size: int) -> ShadowMap:
        ctx = self.ctx
        cols = max(v.tile[0] for v in views) + 1
        rows = max(v.tile[1] for v in views) + 1
        shape = (cols * size, rows * size)
        max_tex = int(ctx.info.get("GL_MAX_TEXTURE_SIZE", 8192))
        if max(shape) > max_tex:
            raise InputError(f"shadow_map_size={size} needs a {shape[0]}x{shape[1]} texture, beyond "
                             f"this GL's limit {max_tex}; lower shadow_map_size")
        gl.make_current(ctx)
        tex, fbo = self._framebuffer(shape)
        scope = ctx.scope(fbo, enable_only=moderngl.BLEND)
        try:
            with gl.keep_framebuffer(ctx), scope:
                fbo.use()
                fbo.clear(_FAR, _FAR, 0.0, 0.0)
                ctx.blend_equation = moderngl.MIN  # ignores the blend function
                for v in views:
                    ctx.viewport = (v.tile[0] * size, v.tile[1] * size, size, size)
                    gl.set_uniforms(self.prog, {"u_mvp": v.matrix(), "u_origin": tuple(float(x) for x in v.eye),
                                                "u_axis": tuple(float(x) for x in v.forward),
                                                "u_mode": 0 if v.ortho else 1})
                    self.vao.render(moderngl.TRIANGLES)
                raw = tex.read(alignment=1)
        finally:
            ctx.blend_equation = moderngl.FUNC_ADD
            scope.release()
        depth = np.frombuffer(raw, dtype=np.float32).reshape(shape[1], shape[0], 2)
        mid = 0.5 * (depth[..., 0].astype(np.float64) + depth[..., 1])
        return ShadowMap(views, size, mid, depth[..., 0])

    def camera_distance(self, mvp: NDArray[np.float64], eye: NDArray[np.float64],
                        size: tuple[int, int]) -> NDArray[np.float32]:
        """``(H, W)`` Euclidean distance (mm) from ``eye`` to the nearest front-facing surface
        in each pixel of a camera with world -> clip matrix ``mvp``, row 0 at the top; 1e30
        where no surface is seen (the material editor's depth-below-surface reference)."""
        W, H = (int(s) for s in size)
        T = np.eye(4)
        T[:3, 3] = self.centre                  # the vertex buffer is relative to the centre
        gl.make_current(self.ctx)
        tex, fbo = self._framebuffer((W, H))
        scope = self.ctx.scope(fbo, enable_only=moderngl.BLEND)
        try:
            with gl.keep_framebuffer(self.ctx), scope:
                fbo.use()
                fbo.clear(_FAR, _FAR, 0.0, 0.0)
                self.ctx.blend_equation = moderngl.MIN
                self.ctx.viewport = (0, 0, W, H)
                gl.set_uniforms(self.prog, {"u_mvp": np.asarray(mvp, dtype=np.float64) @ T,
                                            "u_origin": tuple(float(x) for x in np.asarray(eye) - self.centre),
                                            "u_axis": (0.0, 0.0, 1.0), "u_mode": 1})
                self.vao.render(moderngl.TRIANGLES)
                raw = tex.read(alignment=1)
        finally:
            self.ctx.blend_equation = moderngl.FUNC_ADD
            scope.release()
        return np.frombuffer(raw, dtype=np.float32).reshape(H, W, 2)[::-1, :, 0].copy()

    def shadow_map(self, light: Light, size: int, direction: NDArray[np.float64] | None = None
                   ) -> ShadowMap:
        """The shadow map of ``light`` (``direction``: an orthographic view towards it instead,
        e.g. one direction of an environment light)."""
        if isinstance(light, ProjectorLight):
            light = light.spot
        if isinstance(light, DirectionalLight) or direction is not None:
            w = np.asarray(light.direction if direction is None else direction, dtype=np.float64)
            return self.render(self.directional_view(w, size), size)
        if isinstance(light, SpotLight):
            return self.render(self.perspective_views(np.asarray(light.position), size,
                                                      np.asarray(light.direction), light.cone_deg), size)
        return self.render(self.perspective_views(np.asarray(light.position), size), size)
