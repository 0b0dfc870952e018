"""Headless pictures of node lattices inside a triangle mesh (Wang et al. 2008, figure 5).

:func:`render_nodes` draws a triangle mesh as a light-grey, semi-transparent, Lambert-shaded
surface with opaque round dots for node sets (e.g. boundary nodes red on the surface,
interior nodes blue inside) and optional thin line segments (e.g. node links). Clip planes
can hide the nodes on one side, so a slab of the inner lattice shows.

Drawing order: dots and lines first (opaque, depth test and write), then the surface with
alpha blending and depth test but no depth write, its triangles sorted back to front, so
nodes behind the translucent surface stay visible but dimmed. The picture is rendered
``supersample`` times larger into an offscreen RGBA8 + depth renderbuffer framebuffer and
box-filtered down in numpy (works identically on Mesa llvmpipe through EGL and OSMesa, no
multisample resolve needed). Every GL object is released and the caller's framebuffer and
enable flags are restored before returning.

Units: positions in mm (any consistent unit works), sizes in output pixels, colours linear
RGB in [0, 1].

(Over 400 lines: one public drawing function with the checks of its many inputs and its
orbit camera; the matrix math itself is :mod:`glsldiff.core.camera`.)
"""
from __future__ import annotations

import math
import numbers
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import moderngl
import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff import gl
from glsldiff.core import io
from glsldiff.core.camera import projection, view_matrix
from glsldiff.core.checks import finite_array
from glsldiff.core.errors import InputError
from glsldiff.grids.polygrid import Polygrid

MAX_CLIP_PLANES = 4
_FIT_MARGIN = 1.06         # the mesh fills 1/_FIT_MARGIN of the smaller field of view
_POINT_BIAS = 0.01         # dots/lines pulled this fraction of the mesh radius towards the camera
_AMBIENT = 0.45
_DEFINES = {"MAX_CLIP_PLANES": MAX_CLIP_PLANES}

Colour = tuple[float, float, float]


@dataclass(frozen=True)
class View:
    """Perspective camera orbiting the mesh's bounding-box centre.

    Parameters
    ----------
    azimuth_deg
        Rotation about the up axis; 0 looks from the front (+z for up = +y), 90 from +x.
    elevation_deg
        Angle above the plane normal to the up axis (90 looks straight down).
    fov_deg
        Vertical field of view; the distance is chosen so the whole mesh fits.
    up
        World up axis (need not be unit length).
    """

    azimuth_deg: float = 30.0
    elevation_deg: float = 20.0
    fov_deg: float = 30.0
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)


@dataclass(frozen=True)
class Camera:
    """Matrices of one :class:`View` framing one mesh (row-major numpy, world in mm).

    ``mvp = proj @ view`` maps homogeneous world points to clip space.
    """

    eye: NDArray[np.float64]
    centre: NDArray[np.float64]
    view: NDArray[np.float64]
    proj: NDArray[np.float64]
    size: tuple[int, int]
    radius: float

    @property
    def mvp(self) -> NDArray[np.float64]:
        return self.proj @ self.view

    def project(self, xyz: ArrayLike) -> NDArray[np.float64]:
        """Pixel coordinates ``(N, 2)`` as (column, row), row 0 = top of the image."""
        p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        clip = np.c_[p, np.ones(len(p))] @ self.mvp.T
        ndc = clip[:, :2] / clip[:, 3:4]
        w, h = self.size
        return np.c_[(ndc[:, 0] + 1.0) * 0.5 * w, (1.0 - ndc[:, 1]) * 0.5 * h]


# ---- validation -------------------------------------------------------------------
def _colour(c: Any, name: str) -> Colour:
    try:
        rgb = np.asarray(c, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: colour must be 3 numbers in [0, 1] ({exc})") from exc
    if rgb.shape != (3,) or not np.all(np.isfinite(rgb)) or rgb.min() < 0.0 or rgb.max() > 1.0:
        raise InputError(f"{name}: colour must be 3 numbers in [0, 1] (linear rgb), got {c!r}")
    return (float(rgb[0]), float(rgb[1]), float(rgb[2]))


def _mesh(vertices: ArrayLike, faces: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    v = finite_array(vertices, "vertices", (3,))
    try:
        f_raw = np.asarray(faces)
    except (TypeError, ValueError) as exc:
        raise InputError(f"faces: not an integer array ({exc})") from exc
    if f_raw.ndim != 2 or f_raw.shape[1] != 3:
        raise InputError(f"faces: expected shape (n, 3), got {f_raw.shape}")
    if len(v) < 3 or len(f_raw) == 0:
        raise InputError(f"empty mesh ({len(v)} vertices, {len(f_raw)} faces); "
                         "render_nodes needs at least one triangle")
    if not (np.issubdtype(f_raw.dtype, np.integer)
            or (np.issubdtype(f_raw.dtype, np.floating) and np.all(np.isfinite(f_raw))
                and np.all(f_raw == np.round(f_raw)))):
        raise InputError(f"faces: expected integer vertex indices, got dtype {f_raw.dtype}")
    f = f_raw.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(f"faces: indices must lie in [0, {len(v) - 1}], "
                         f"got [{f.min()}, {f.max()}]")
    return v, f


def _point_sets(points: Sequence[Any], name: str, tail: tuple[int, ...]
                ) -> list[tuple[NDArray[np.float64], Colour, bool]]:
    if isinstance(points, np.ndarray):
        raise InputError(f"{name}: expected a sequence of (array, rgb) or (array, rgb, clipped) "
                         "tuples, got a bare array")
    out = []
    for i, item in enumerate(points):
        if not isinstance(item, (tuple, list)) or len(item) not in (2, 3):
            raise InputError(f"{name}[{i}]: expected (array, rgb) or (array, rgb, clipped)")
        xyz = finite_array(item[0], f"{name}[{i}] positions", tail)
        rgb = _colour(item[1], f"{name}[{i}]")
        clipped = bool(item[2]) if len(item) == 3 else True
        out.append((xyz, rgb, clipped))
    return out


def _planes(clip: Any) -> NDArray[np.float64]:
    """``(k, 4)`` rows ``(nx, ny, nz, d)``: keep ``n . x <= d``."""
    if clip is None:
        return np.zeros((0, 4))
    try:
        single = len(clip) == 2 and isinstance(clip[1], (numbers.Real, np.ndarray)) \
            and np.ndim(clip[1]) == 0
        planes = [clip] if single else list(clip)
    except (TypeError, ValueError) as exc:
        raise InputError(f"clip: expected (normal, offset) or a list of them, got {clip!r}") from exc
    if not 1 <= len(planes) <= MAX_CLIP_PLANES:
        raise InputError(f"clip: 1 to {MAX_CLIP_PLANES} planes, got {len(planes)}")
    rows = []
    for i, plane in enumerate(planes):
        try:
            normal, offset = plane
            n = np.asarray(normal, dtype=np.float64)
            d = float(offset)
        except (TypeError, ValueError) as exc:
            raise InputError(f"clip[{i}]: expected (normal (3,), offset), got {plane!r}") from exc
        if n.shape != (3,) or not np.all(np.isfinite(n)) or not math.isfinite(d) or not np.any(n):
            raise InputError(f"clip[{i}]: normal must be 3 finite numbers, not all zero, and the "
                             f"offset finite; got {plane!r}")
        rows.append([*n, d])
    return np.asarray(rows, dtype=np.float64)


def _size(size: Any) -> tuple[int, int]:
    try:
        w, h = (int(s) for s in size)
        ok = (w, h) == tuple(size)
    except (TypeError, ValueError):
        ok = False
    if not ok or w < 1 or h < 1:
        raise InputError(f"size: expected (width, height) positive integers, got {size!r}")
    return w, h


# ---- camera -----------------------------------------------------------------------
def _normalized(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return v / np.linalg.norm(v)


def camera(vertices: ArrayLike, view: View = View(), size: tuple[int, int] = (900, 900),
           extra: ArrayLike | None = None) -> Camera:
    """The camera :func:`render_nodes` uses: looks at the bounding-box centre of ``vertices``.

    Parameters
    ----------
    vertices
        ``(V, 3)`` mesh vertices, mm; the distance is the smallest at which all of them fit
        (with a small margin) in both the vertical and the horizontal field of view.
    view
        Viewing direction and field of view.
    size
        Image ``(width, height)`` in pixels (sets the aspect ratio).
    extra
        ``(N, 3)`` further points (dots, line ends) kept between the near and far planes.
    """
    v = finite_array(vertices, "vertices", (3,))
    w, h = _size(size)
    for name in ("azimuth_deg", "elevation_deg", "fov_deg"):
        if not math.isfinite(getattr(view, name)):
            raise InputError(f"view.{name} must be finite, got {getattr(view, name)!r}")
    if not 1.0 <= view.fov_deg <= 170.0:
        raise InputError(f"view.fov_deg must lie in [1, 170], got {view.fov_deg}")
    up = np.asarray(view.up, dtype=np.float64)
    if up.shape != (3,) or not np.all(np.isfinite(up)) or not np.any(up):
        raise InputError(f"view.up must be a nonzero 3-vector, got {view.up!r}")
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    if not radius > 0.0:
        raise InputError("vertices: the mesh has zero extent (all vertices coincide)")

    # orthonormal frame: u = up, a = "front" reference (world +z for up = +y), b = u x a
    u = _normalized(up)
    ref = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    a = _normalized(ref - u * (ref @ u))
    b = np.cross(u, a)
    az, el = math.radians(view.azimuth_deg), math.radians(view.elevation_deg)
    back = math.cos(el) * (math.cos(az) * a + math.sin(az) * b) + math.sin(el) * u  # centre -> eye
    cam_up_ref = u if abs(math.sin(el)) < 0.999 else -math.copysign(1.0, el) * (
        math.cos(az) * a + math.sin(az) * b)
    right = _normalized(np.cross(cam_up_ref, back))
    cam_up = np.cross(back, right)

    tan_y = math.tan(math.radians(view.fov_deg) / 2.0)
    tan_x = tan_y * w / h
    rel = v - centre
    x, y, z = rel @ right, rel @ cam_up, rel @ back  # z towards the eye
    dist = float(np.max(np.maximum(z + np.abs(x) * _FIT_MARGIN / tan_x,
                                   z + np.abs(y) * _FIT_MARGIN / tan_y)))
    dist = max(dist, float(z.max()) + 0.05 * radius)
    eye = centre + dist * back

    every = v if extra is None else np.vstack([v, np.asarray(extra, dtype=np.float64).reshape(-1, 3)])
    depth = dist - (every - centre) @ back  # distance in front of the eye along the view axis
    pad = 0.02 * radius
    near = max(float(depth.min()) - pad, 1e-3 * dist)
    far = max(float(depth.max()) + pad, near * 1.001)

    return Camera(eye, centre, view_matrix(eye, right, cam_up, back),
                  projection(1.0 / tan_x, 1.0 / tan_y, near, far), (w, h), radius)


# ---- rendering --------------------------------------------------------------------
def render_nodes(vertices: ArrayLike, faces: ArrayLike,
                 points: Sequence[tuple[ArrayLike, Colour] | tuple[ArrayLike, Colour, bool]],
                 size: tuple[int, int] = (900, 900), view: View = View(), mesh_alpha: float = 0.35,
                 point_size_px: float = 3.0,
                 lines: Sequence[tuple[ArrayLike, Colour] | tuple[ArrayLike, Colour, bool]] = (),
                 clip: tuple[ArrayLike, float] | Sequence[tuple[ArrayLike, float]] | None = None,
                 ctx: moderngl.Context | None = None,
                 background: Colour = (1.0, 1.0, 1.0), *,
                 mesh_color: Colour = (0.72, 0.74, 0.78), line_width_px: float = 1.0,
                 clip_mesh: bool = False, supersample: int = 2) -> NDArray[np.uint8]:
    """Render a translucent mesh with coloured node dots (a polygrid figure).

    Parameters
    ----------
    vertices, faces
        Triangle mesh: ``(V, 3)`` positions (mm) and ``(F, 3)`` vertex indices; winding
        need not be consistent (shading is two-sided).
    points
        Dot sets ``(positions (N, 3), rgb)`` or ``(positions, rgb, clipped)``; ``clipped``
        (default true) says whether ``clip`` applies to the set. Drawn opaque.
    size
        Image ``(width, height)`` in pixels.
    view
        Camera direction and field of view (:class:`View`); see :func:`camera`.
    mesh_alpha
        Opacity of the surface seen head-on, in [0, 1]; it rises toward the silhouette.
    point_size_px
        Dot diameter in output pixels.
    lines
        Segment sets ``(ends (M, 2, 3), rgb)`` or ``(ends, rgb, clipped)``, drawn opaque,
        ``line_width_px`` wide.
    clip
        ``(normal (3,), offset)`` or a list of up to 4 such planes: dots (and line pieces) with
        ``normal . x > offset`` for any plane are not drawn; two opposite planes keep a slab.
    ctx
        Context to render with; default :func:`glsldiff.gl.get_context`.
    background
        Background rgb in [0, 1].
    mesh_color
        Surface albedo.
    line_width_px
        Line width in output pixels.
    clip_mesh
        Also cut the surface with ``clip``.
    supersample
        Render this many times larger per axis and box-filter down (anti-aliasing), 1 to 4.

    Returns
    -------
    image
        ``(height, width, 3)`` uint8 RGB, row 0 = top of the image.

    Raises
    ------
    InputError
        Malformed mesh, point or line arrays (shape, NaN), empty mesh, colours outside
        [0, 1], a bad size, view or clip plane.
    """
    v, f = _mesh(vertices, faces)
    dot_sets = _point_sets(points, "points", (3,))
    line_sets = _point_sets(lines, "lines", (2, 3))
    planes = _planes(clip)
    w, h = _size(size)
    bg = _colour(background, "background")
    albedo = _colour(mesh_color, "mesh_color")
    if not (isinstance(mesh_alpha, numbers.Real) and 0.0 <= mesh_alpha <= 1.0):
        raise InputError(f"mesh_alpha must lie in [0, 1], got {mesh_alpha!r}")
    for name, val in (("point_size_px", point_size_px), ("line_width_px", line_width_px)):
        if not (isinstance(val, numbers.Real) and math.isfinite(val) and val > 0.0):
            raise InputError(f"{name} must be a positive number, got {val!r}")
    if not (isinstance(supersample, (int, np.integer)) and 1 <= supersample <= 4):
        raise InputError(f"supersample must be an integer in [1, 4], got {supersample!r}")
    ss = int(supersample)

    # faces: drop degenerate ones, flat normals
    tri = v[f]                                                   # (F, 3, 3)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    keep = lengths > 1e-12 * max(float(np.abs(v).max()), 1.0) ** 2
    if not np.any(keep):
        raise InputError(f"empty mesh: all {len(f)} faces are degenerate (zero area)")
    tri, normals = tri[keep], normals[keep] / lengths[keep, None]

    extra = [p for p, _, _ in dot_sets] + [s.reshape(-1, 3) for s, _, _ in line_sets]
    cam = camera(v, view, (w, h), np.vstack(extra) if extra else None)
    # painter's order for the translucent surface: farthest triangles first
    order = np.argsort(-np.linalg.norm(tri.mean(axis=1) - cam.eye, axis=1), kind="stable")
    mesh_data = np.concatenate([tri[order], np.repeat(normals[order, None, :], 3, axis=1)], axis=2)

    dots = [(p, rgb, c) for p, rgb, c in dot_sets if len(p)]
    segs = [(s, rgb, c) for s, rgb, c in line_sets if len(s)]
    dot_data = None
    if dots:
        dot_data = np.concatenate([np.c_[p, np.tile(rgb, (len(p), 1)), np.full(len(p), float(c))]
                                   for p, rgb, c in dots])
    line_data = None
    if segs:
        chunks = []
        for s, rgb, c in segs:
            a, b = s[:, 0], s[:, 1]
            m = len(s)
            # quad corners: (end, other end, side); side flips at b, whose direction is reversed
            corner = [(a, b, -1.0), (a, b, 1.0), (b, a, -1.0), (a, b, -1.0), (b, a, -1.0), (b, a, 1.0)]
            per = [np.c_[p, np.tile(rgb, (m, 1)), np.full(m, float(c)), o, np.full(m, side)]
                   for p, o, side in corner]
            chunks.append(np.stack(per, axis=1).reshape(-1, 11))
        line_data = np.concatenate(chunks)

    gl_ctx = ctx if ctx is not None else gl.get_context()
    gl.make_current(gl_ctx)
    max_rb = int(gl_ctx.info.get("GL_MAX_RENDERBUFFER_SIZE", 4096))
    if max(w, h) * ss > max_rb:
        raise InputError(f"size {w}x{h} x supersample {ss} exceeds the GL renderbuffer limit "
                         f"{max_rb}; lower size or supersample")
    max_point = float(np.max(gl_ctx.info.get("GL_POINT_SIZE_RANGE", (1.0, 64.0))))
    point_px = min(point_size_px * ss, max_point)

    fw, fh = w * ss, h * ss
    with gl.Resources() as res, gl.keep_framebuffer(gl_ctx):   # ours released after the caller's is bound
        colour = res.add(gl_ctx.renderbuffer((fw, fh), components=4))
        depth = res.add(gl_ctx.depth_renderbuffer((fw, fh)))
        fbo = res.add(gl_ctx.framebuffer(color_attachments=[colour], depth_attachment=depth))
        # scope: restores the caller's enable flags on exit (moderngl has no getter for them)
        scope = res.add(gl_ctx.scope(fbo, enable_only=moderngl.DEPTH_TEST | moderngl.PROGRAM_POINT_SIZE))
        with scope:
            fbo.use()
            fbo.depth_mask = True
            fbo.clear(*bg, 1.0, depth=1.0)
            gl_ctx.depth_func = "<"
            plane_rows = np.zeros((MAX_CLIP_PLANES, 4))
            plane_rows[:len(planes)] = planes
            common = {"u_mvp": cam.mvp, "u_eye": tuple(float(e) for e in cam.eye),
                      "u_bias": _POINT_BIAS * cam.radius, "u_nplanes": len(planes),
                      "u_planes": [tuple(float(x) for x in row) for row in plane_rows]}

            def draw(prog: moderngl.Program, data: NDArray, layout: str, attrs: tuple[str, ...],
                     mode: int) -> None:
                buf = res.add(gl_ctx.buffer(np.ascontiguousarray(data, dtype="f4").tobytes()))
                res.add(gl_ctx.vertex_array(prog, [(buf, layout, *attrs)])).render(mode)

            if dot_data is not None:
                prog = res.add(gl.program(gl_ctx, "figure_points.vert", "figure_points.frag", _DEFINES))
                gl.set_uniforms(prog, {**common, "u_size": float(point_px)})
                draw(prog, dot_data, "3f 3f 1f", ("in_pos", "in_color", "in_clip"), moderngl.POINTS)
            if line_data is not None:
                prog = res.add(gl.program(gl_ctx, "figure_points.vert", "figure_points.frag",
                                          {**_DEFINES, "LINES": 1}))
                gl.set_uniforms(prog, {**common, "u_viewport": (float(fw), float(fh)),
                                       "u_width": float(line_width_px * ss)})
                draw(prog, line_data, "3f 3f 1f 3f 1f",
                     ("in_pos", "in_color", "in_clip", "in_other", "in_side"), moderngl.TRIANGLES)
            if mesh_alpha > 0.0:
                prog = res.add(gl.program(gl_ctx, "figure_mesh.vert", "figure_mesh.frag", _DEFINES))
                light = _normalized(-0.35 * cam.view[0, :3] + 0.55 * cam.view[1, :3]
                                    + 1.0 * cam.view[2, :3])
                gl.set_uniforms(prog, {**common, "u_light": tuple(float(x) for x in light), "u_color": albedo,
                                       "u_alpha": float(mesh_alpha), "u_ambient": _AMBIENT,
                                       "u_clip": int(bool(clip_mesh) and len(planes) > 0)})
                gl_ctx.enable(moderngl.BLEND)
                gl_ctx.blend_func = moderngl.DEFAULT_BLENDING
                fbo.depth_mask = False
                draw(prog, mesh_data.reshape(-1, 6), "3f 3f", ("in_pos", "in_normal"),
                     moderngl.TRIANGLES)
                fbo.depth_mask = True
            raw = fbo.read(components=3, alignment=1)
    img = np.frombuffer(raw, dtype=np.uint8).reshape(fh, fw, 3)[::-1]
    if ss > 1:
        img = img.reshape(h, ss, w, ss, 3).mean(axis=(1, 3))
        img = np.round(img).astype(np.uint8)
    return np.ascontiguousarray(img)


def save_nodes_png(path: str | os.PathLike, *args: Any, **kwargs: Any) -> Path:
    """:func:`render_nodes` (same arguments) written to ``path`` as PNG; returns the path."""
    return io.write_png(path, render_nodes(*args, **kwargs))


def polygrid_figure(pg: Polygrid, path: str, size: tuple[int, int] = (900, 900), slab: float = 0.5,
                    view: View | None = None, ctx: Any = None) -> str:
    """Paper figure 5: boundary nodes (red) on the translucent mesh, interior nodes (blue) in
    a slab of half-width ``slab`` cube edges around the median z of the interior nodes, and
    the boundary-to-partner links (grey)."""
    if pg.mesh is None:
        raise InputError("polygrid_figure needs a polygrid built from a mesh")
    lat = pg.lattice
    inner = pg.positions[lat.interior]
    zc = float(np.median(inner[:, 2]))
    half = max(slab * lat.size, 0.6 * lat.h)
    clip = [((0.0, 0.0, 1.0), zc + half), ((0.0, 0.0, -1.0), -(zc - half))]
    links = np.stack([pg.boundary_positions, pg.positions[lat.link]], axis=1)
    save_nodes_png(path, pg.mesh.vertices, pg.mesh.faces,
                   [(pg.boundary_positions, (0.85, 0.1, 0.1), False), (inner, (0.1, 0.25, 0.85))],
                   size=size, view=view if view is not None else View(), clip=clip,
                   lines=[(links, (0.3, 0.3, 0.3))], ctx=ctx, point_size_px=2.5)
    return path
