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

Entry normals (single scattering only, ``render(..., normals=True)``; plain shadow maps do not
render them): a second draw of the same views with the same vertex and index buffers
(``light_depth.vert`` + ``shaders/light_face.frag``) keeps, with a depth test on the same
depth metric (linear, divided by the view's far distance) and the faces turned away from the
light discarded, the index of the nearest face facing the light (``gl_PrimitiveID``) in an
RG32F atlas of the same layout, read back as integers (``face``; -1: none). Its coverage is the
front channel's (same vertex shader, same views). For an entry point
``y`` (on the light's ray through a point, at the distance :meth:`ShadowMap.entry` gives),
:meth:`ShadowMap.entry_normals` takes the closest point of ``y`` on the face stored at its
nearest texel and, unless that point is inside the face and within ``ON_FACE_TEXELS`` texels
of ``y`` (``y`` lies on the face), the closest point on the nearest of the faces stored at the
2 x 2 texels around ``y``, and interpolates the mesh's corner normals there
(:attr:`glsldiff.mesh.types.Mesh.corner_normals`, barycentric, then normalised). That is what
:func:`glsldiff.mesh.closest_points` computes, with the candidate faces read from the map
instead of searched for in the mesh (tests/test_shadow_normals.py: the same normals at all
20,000 points in a box; in the bunny within 0.13 degrees for 95 % of the points at 512 texels). It differs where the filtered
depth puts ``y`` off the surface by more than the faces' spacing (silhouettes, the ears'
edges), and there keeps to faces the light sees, where closest points may fall on a face
turned away from it.

GL objects (programs, buffers, textures, framebuffers) live in a :class:`DepthRenderer` and are
released by its ``release`` (or ``with``); the caller's framebuffer and enable flags are
restored and the blend equation is set back to GL's default ``FUNC_ADD`` (moderngl cannot read
the previous one; the blend function is not touched); the face draw sets the depth function
to GL's default ``<`` (likewise unreadable). Units: mm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Sequence

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff import gl
from glsldiff.core.camera import orthonormal_frame, projection, view_matrix
from glsldiff.core.errors import InputError
from glsldiff.core.jit import kernel, prange
from glsldiff.mesh.closest import face_distance
from glsldiff.physics.lights import DirectionalLight, Light, ProjectorLight, SpotLight

__all__ = ["DepthRenderer", "ShadowMap", "View", "BIAS_TEXELS", "BIAS_SLOPE", "MAX_BIAS_TAN",
           "SPOT_SINGLE_VIEW_MAX_DEG", "ON_FACE_TEXELS"]

BIAS_TEXELS = 1.0          # constant part of the depth bias, in shadow-map texels (world size)
BIAS_SLOPE = 1.5           # slope part: texels per unit tan(angle between normal and light)
MAX_BIAS_TAN = 8.0         # tan clipped here (about 83 degrees)
SPOT_SINGLE_VIEW_MAX_DEG = 60.0  # wider spots use a cube of six views
ON_FACE_TEXELS = 0.01      # entry normals: a point this close to a face's interior lies on it
_FAR = 1.0e30              # clear value of the shadow map (no surface)
_FIT = 1.02                # orthographic window: bounding radius times this
_SHADER_DEFINES = {"LIGHT_FAR": "1.0e30"}
#: a view as the kernels read it (:attr:`ShadowMap.views_packed`)
_VIEW = np.dtype([(name, np.float64) for name in ("ex", "ey", "ez", "fx", "fy", "fz", "rx", "ry", "rz",
                                                  "ux", "uy", "uz", "half")]
                 + [("ortho", np.bool_), ("far", np.float64), ("col", np.int64), ("row", np.int64)])


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
    #: ``(rows * size, cols * size)`` index of the mesh face that is that surface, -1 where none;
    #: ``None`` unless rendered with ``normals=True``
    face: NDArray[np.int32] | None = field(default=None, repr=False)
    #: the mesh's triangles (relative to the centre) and corner normals, each ``(F, 3, 3)``,
    #: with ``face``
    surface: tuple[NDArray[np.float64], NDArray[np.float64]] | None = field(default=None, repr=False)

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

    @cached_property
    def views_packed(self) -> NDArray[np.void]:
        """The views for the kernels, a record per view (:data:`_VIEW`; records, unlike arrays,
        pass to a kernel's helpers without reference counting)."""
        return np.array([(*v.eye, *v.forward, *v.right, *v.up, v.half, v.ortho, v.far, *v.tile)
                         for v in self.views], dtype=_VIEW)

    def entry(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance (mm) from points ``p`` (relative to the centre, normally inside the object)
        back along the light's ray to the nearest surface facing the light: the depth of ``p``
        minus the stored front depth, bilinear over the 2 x 2 texels when all four hold a
        surface, else the nearest one's; clipped at 0; NaN where no surface is stored or the
        point is outside every view (translucent shadow maps, Dachsbacher and Stamminger 2003).
        A compiled kernel (:func:`_entry_kernel`)."""
        p = np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3)
        out = np.empty(len(p))
        _entry_kernel(p, self.views_packed, self.size, self.front, out)
        return out

    def entry_normals(self, y: NDArray[np.float64]) -> NDArray[np.float64]:
        """``(n, 3)`` unit outward normal of the mesh at entry points ``y`` (mm, relative to the
        centre): points on the nearest surface facing the light, ``p + entry(p) w`` for points
        ``p`` and ``w`` the unit direction towards the light (the same light ray, so the same
        texels). The corner normals interpolated at the closest point on the stored faces
        (module docstring); NaN rows where no face is stored near ``y``. Needs a map rendered
        with ``normals=True``. A compiled kernel (:func:`_entry_normals_kernel`)."""
        if self.face is None or self.surface is None:
            raise ValueError("this shadow map was rendered without normals (render(..., normals=True))")
        tri, cn = self.surface
        y = np.ascontiguousarray(y, dtype=np.float64).reshape(-1, 3)
        out = np.empty((len(y), 3))
        _entry_normals_kernel(y, self.views_packed, self.size, self.face, tri, cn, ON_FACE_TEXELS, out)
        return out


# ---- compiled kernels of entry and entry_normals, a point per iteration ----------------------
# (their helpers take scalars, tuples and records only: an array argument costs an atomic
# reference count per call, contended between the threads)
@kernel
def _first_max(a0: float, a1: float, a2: float, a3: float) -> int:
    """``np.argmax`` of four values: the first maximum, or the first NaN."""
    best, m = 0, a0
    if m == m and not a1 <= m:              # greater, or NaN
        best, m = 1, a1
    if m == m and not a2 <= m:
        best, m = 2, a2
    if m == m and not a3 <= m:
        best = 3
    return best


@kernel
def _index(f: float, size: int) -> tuple[int, int]:
    """Texel indices ``f`` and ``f + 1`` (``f`` floored) clipped to ``[0, size)``; as numpy's
    int64 cast on x86, a NaN or out-of-range ``f`` gives ``INT64_MIN``, clipped to 0."""
    if not (f >= -9.223372036854775808e18 and f < 9.223372036854775808e18):
        return 0, 0
    i = np.int64(f)
    return min(max(i, 0), size - 1), min(max(i + 1, 0), size - 1)


@kernel
def _view_of(p0: float, p1: float, p2: float, first: Any, n_views: int) -> int:
    """Index of the view a point (relative to the centre) falls in (``ShadowMap._views_of``
    for one point; ``first``: the first view's record): 0, or for a cube the face of the
    major axis of ``p - eye``."""
    if n_views == 1:
        return 0
    e0, e1, e2 = p0 - first["ex"], p1 - first["ey"], p2 - first["ez"]
    ax = _first_max(abs(e0), abs(e1), abs(e2), -np.inf)
    return 2 * ax + (1 if (e0 if ax == 0 else e1 if ax == 1 else e2) < 0 else 0)


@kernel
def _locate(p0: float, p1: float, p2: float, v: Any, size: int
            ) -> tuple[float, bool, float, tuple[int, int, int, int], tuple[int, int, int, int],
                       tuple[float, float, float, float]]:
    """A point (relative to the centre) in view ``v`` (a :data:`_VIEW` record): depth (the map's
    metric, mm), the inside-the-view flag, the texel's width there (mm), and the atlas rows,
    columns and bilinear weights of the 2 x 2 texels around it, in the order (0, 0), (1, 0),
    (0, 1), (1, 1) -- ``ShadowMap._project`` and ``_texels`` for one point."""
    d0, d1, d2 = p0 - v["ex"], p1 - v["ey"], p2 - v["ez"]
    x = d0 * v["rx"] + d1 * v["ry"] + d2 * v["rz"]
    y = d0 * v["ux"] + d1 * v["uy"] + d2 * v["uz"]
    z = d0 * v["fx"] + d1 * v["fy"] + d2 * v["fz"]
    if v["ortho"]:
        depth, ok, scale = z, True, v["half"]
    else:
        depth = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        ok = z > 1e-9 * max(v["far"], 1.0)
        scale = (z if ok else 1.0) * v["half"]
    nx, ny = x / scale, y / scale
    ok = ok and abs(nx) <= 1.0 and abs(ny) <= 1.0
    tx, ty = (nx + 1.0) * 0.5 * size - 0.5, (ny + 1.0) * 0.5 * size - 0.5
    x0, y0 = np.floor(tx), np.floor(ty)
    wx, wy = tx - x0, ty - y0
    c0, c1 = _index(x0, size)
    r0, r1 = _index(y0, size)
    ox, oy = v["col"] * size, v["row"] * size
    return (depth, ok, 2.0 * scale / size, (r0 + oy, r0 + oy, r1 + oy, r1 + oy),
            (c0 + ox, c1 + ox, c0 + ox, c1 + ox),
            ((1 - wx) * (1 - wy), wx * (1 - wy), (1 - wx) * wy, wx * wy))


@kernel(inline=True)
def entry_at(p0: float, p1: float, p2: float, views: NDArray[np.void], size: int,
             front: NDArray[np.float32]) -> float:
    """:meth:`ShadowMap.entry` of one point (relative to the centre; a kernel helper: ``views``
    is ``ShadowMap.views_packed``, ``front`` the map's ``front``)."""
    v = views[_view_of(p0, p1, p2, views[0], views.shape[0])]
    depth, ok, _, r, c, w = _locate(p0, p1, p2, v, size)
    if not ok:
        return np.nan
    vals = (np.float64(front[r[0], c[0]]), np.float64(front[r[1], c[1]]),
            np.float64(front[r[2], c[2]]), np.float64(front[r[3], c[3]]))
    bil, every = 0.0, True
    for j in range(4):
        if vals[j] < 0.5 * _FAR:
            bil += vals[j] * w[j]
        else:
            every = False
    if every:
        surf = bil
    else:
        surf = vals[_first_max(w[0], w[1], w[2], w[3])]
        if not surf < 0.5 * _FAR:
            surf = np.nan
    d = depth - surf
    return d if (d > 0.0 or d != d) else 0.0


@kernel(parallel=True)
def _entry_kernel(p: NDArray[np.float64], views: NDArray[np.void], size: int,
                  front: NDArray[np.float32], out: NDArray[np.float64]) -> None:
    """``out[i]``: :meth:`ShadowMap.entry` of point ``p[i]``."""
    for i in prange(p.shape[0]):
        out[i] = entry_at(p[i, 0], p[i, 1], p[i, 2], views, size, front)


@kernel(inline=True)
def _normal_from_taps(y0: float, y1: float, y2: float, faces: tuple[int, int, int, int], nearest: int,
                      texel: float, tri: NDArray[np.float64], cn: NDArray[np.float64],
                      on_face: float) -> tuple[float, float, float]:
    """The entry normal at a point (relative to the centre) from the faces stored at its 2 x 2
    texels (``nearest``: the nearest texel's tap; ``texel``: the texel's width there, mm)."""
    f0 = faces[nearest]                     # the nearest texel's face
    if f0 < 0:
        return np.nan, np.nan, np.nan
    f, d2, bary = f0, np.inf, (0.0, 0.0, 0.0)
    for j in range(-1, 4):
        if j < 0:
            fj = f0
        else:       # a point off the nearest texel's face: the other taps' faces, once each
            fj = faces[j]
            new = fj >= 0 and fj != f0
            for m in range(j):
                new = new and faces[m] != fj
            if not new:
                continue
        dj, bj = face_distance(y0, y1, y2, (tri[fj, 0, 0], tri[fj, 0, 1], tri[fj, 0, 2],
                                             tri[fj, 1, 0], tri[fj, 1, 1], tri[fj, 1, 2],
                                             tri[fj, 2, 0], tri[fj, 2, 1], tri[fj, 2, 2]))
        if dj < d2:
            f, d2, bary = fj, dj, bj
        if j < 0 and bj[0] > 0.0 and bj[1] > 0.0 and bj[2] > 0.0 and dj <= (on_face * texel) ** 2:
            break           # y lies on the nearest texel's face
    n0 = (bary[0] * cn[f, 0, 0] + bary[1] * cn[f, 1, 0]) + bary[2] * cn[f, 2, 0]
    n1 = (bary[0] * cn[f, 0, 1] + bary[1] * cn[f, 1, 1]) + bary[2] * cn[f, 2, 1]
    n2 = (bary[0] * cn[f, 0, 2] + bary[1] * cn[f, 1, 2]) + bary[2] * cn[f, 2, 2]
    length = np.sqrt((n0 * n0 + n1 * n1) + n2 * n2)
    if length > 0.0:                    # glsldiff.mesh.types.normalize: zero (or NaN) rows give 0
        return n0 / length, n1 / length, n2 / length
    return 0.0, 0.0, 0.0


@kernel(inline=True)
def entry_normal_at(y0: float, y1: float, y2: float, views: NDArray[np.void], size: int,
                    face: NDArray[np.int32], tri: NDArray[np.float64], cn: NDArray[np.float64],
                    on_face: float) -> tuple[float, float, float]:
    """:meth:`ShadowMap.entry_normals` at one point (relative to the centre; a kernel helper:
    ``views`` is ``ShadowMap.views_packed``, ``face`` and ``(tri, cn)`` the map's ``face`` and
    ``surface``, ``on_face`` :data:`ON_FACE_TEXELS`)."""
    v = views[_view_of(y0, y1, y2, views[0], views.shape[0])]
    _, _, texel, r, c, w = _locate(y0, y1, y2, v, size)
    faces = (np.int64(face[r[0], c[0]]), np.int64(face[r[1], c[1]]),
             np.int64(face[r[2], c[2]]), np.int64(face[r[3], c[3]]))
    return _normal_from_taps(y0, y1, y2, faces, _first_max(w[0], w[1], w[2], w[3]), texel, tri, cn, on_face)


@kernel(parallel=True)
def _entry_normals_kernel(y: NDArray[np.float64], views: NDArray[np.void], size: int,
                          face: NDArray[np.int32], tri: NDArray[np.float64], cn: NDArray[np.float64],
                          on_face: float, out: NDArray[np.float64]) -> None:
    """``out[i]``: :meth:`ShadowMap.entry_normals` at point ``y[i]`` (``on_face``: ``ON_FACE_TEXELS``).
    Two loops: the first reads each point's 2 x 2 faces from the atlas, the second finds the
    closest points (its reads of the faces' corners then do not wait on the atlas's)."""
    n_pts = y.shape[0]
    taps = np.empty((n_pts, 4), dtype=np.int32)
    nearest = np.empty(n_pts, dtype=np.int8)
    texels = np.empty(n_pts)
    for i in prange(n_pts):
        y0, y1, y2 = y[i, 0], y[i, 1], y[i, 2]
        v = views[_view_of(y0, y1, y2, views[0], views.shape[0])]
        _, _, texel, r, c, w = _locate(y0, y1, y2, v, size)
        taps[i, 0], taps[i, 1] = face[r[0], c[0]], face[r[1], c[1]]
        taps[i, 2], taps[i, 3] = face[r[2], c[2]], face[r[3], c[3]]
        nearest[i] = _first_max(w[0], w[1], w[2], w[3])
        texels[i] = texel
    for i in prange(n_pts):
        faces = (np.int64(taps[i, 0]), np.int64(taps[i, 1]), np.int64(taps[i, 2]), np.int64(taps[i, 3]))
        out[i, 0], out[i, 1], out[i, 2] = _normal_from_taps(y[i, 0], y[i, 1], y[i, 2], faces, nearest[i],
                                                            texels[i], tri, cn, on_face)


def _atlas_shape(views: list[View], size: int) -> tuple[int, int]:
    """``(width, height)`` texels of the atlas holding ``views``' ``size``-texel tiles."""
    return (max(v.tile[0] for v in views) + 1) * size, (max(v.tile[1] for v in views) + 1) * size


class DepthRenderer:
    """GL resources to render a mesh's front/back depth (and on request the faces for entry
    normals) from lights; release with ``release`` (or use as a context manager). Coordinates
    are relative to the bounding-sphere centre. ``mesh``: a :class:`glsldiff.mesh.Mesh` (its
    ``corner_normals`` are read only for entry normals). The face draw's program and targets
    are made on its first use.

    ``keep_maps``: :meth:`shadow_map` keeps each light's map (one view set per light, not the
    ``direction`` views of environment lights) and hands it out again while it is asked for
    with the same size, adding the face atlas when a later caller wants entry normals: the
    renderer's pass 1, shading visibility and 3-D march then share one map per light
    (:meth:`keep_lights` drops the maps of lights no longer in the scene)."""

    def __init__(self, ctx: moderngl.Context, mesh: Any, keep_maps: bool = False) -> None:
        self.ctx = ctx
        self.mesh = mesh
        self._kept: dict[tuple[str, int], ShadowMap] | None = {} if keep_maps else None
        v = np.asarray(mesh.vertices, dtype=np.float64)
        f = np.asarray(mesh.faces, dtype=np.int64)
        lo, hi = v.min(axis=0), v.max(axis=0)
        self.centre = 0.5 * (lo + hi)
        self.radius = max(float(np.linalg.norm(v - self.centre, axis=1).max()), 1e-9)
        self._res = gl.Resources()
        self._atlas: tuple[tuple[int, int], moderngl.Texture, moderngl.Framebuffer] | None = None
        self._face_atlas: tuple[tuple[int, int], moderngl.Texture, moderngl.Renderbuffer,
                                moderngl.Framebuffer] | None = None
        self._face_vao: moderngl.VertexArray | None = None
        self._surface_arrays: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
        gl.make_current(ctx)
        try:
            self.prog = self._res.add(gl.program(ctx, "light_depth.vert", "light_depth.frag", _SHADER_DEFINES))
            self._vbo = self._res.add(ctx.buffer(np.ascontiguousarray(v - self.centre, dtype="f4").tobytes()))
            self._ibo = self._res.add(ctx.buffer(np.ascontiguousarray(f, dtype="i4").tobytes()))
            self.vao = self._res.add(ctx.vertex_array(self.prog, [(self._vbo, "3f", "in_pos")],
                                                      index_buffer=self._ibo, index_element_size=4))
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
        self._release_face_atlas()

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

    @staticmethod
    def _uniforms(v: View) -> dict[str, Any]:
        """The light-view uniforms of ``light_depth.*`` and ``light_face.frag``."""
        return {"u_mvp": v.matrix(), "u_origin": tuple(float(x) for x in v.eye),
                "u_axis": tuple(float(x) for x in v.forward), "u_mode": 0 if v.ortho else 1,
                "u_far": float(v.far)}

    def _face_target(self, shape: tuple[int, int]) -> tuple[moderngl.Texture, moderngl.Framebuffer]:
        """The RG32F face atlas of ``shape`` texels with its depth buffer, kept while the size
        stays the same."""
        if self._face_atlas is None or self._face_atlas[0] != shape:
            self._release_face_atlas()
            made: list[Any] = []
            try:
                made.append(self.ctx.texture(shape, 2, dtype="f4"))
                made.append(self.ctx.depth_renderbuffer(shape))
                made.append(self.ctx.framebuffer(color_attachments=[made[0]], depth_attachment=made[1]))
            except BaseException:
                for obj in reversed(made):
                    obj.release()
                raise
            self._face_atlas = (shape, made[0], made[1], made[2])
        return self._face_atlas[1], self._face_atlas[3]

    def _release_face_atlas(self) -> None:
        if self._face_atlas is not None:
            for obj in self._face_atlas[:0:-1]:         # framebuffer, depth buffer, texture
                obj.release()
            self._face_atlas = None

    def _render_faces(self, views: list[View], size: int, shape: tuple[int, int]) -> NDArray[np.int32]:
        """``(shape[1], shape[0])`` index of the nearest face facing the light in each texel of
        the atlas of ``views``, -1 where none (module docstring)."""
        ctx = self.ctx
        if self._face_vao is None:          # made on first use: plain shadow maps never pay for it
            prog = self._res.add(gl.program(ctx, "light_depth.vert", "light_face.frag", _SHADER_DEFINES))
            self._face_vao = self._res.add(ctx.vertex_array(prog, [(self._vbo, "3f", "in_pos")],
                                                            index_buffer=self._ibo, index_element_size=4))
        tex, fbo = self._face_target(shape)
        scope = ctx.scope(fbo, enable_only=moderngl.DEPTH_TEST)
        try:
            with gl.keep_framebuffer(ctx), scope:
                fbo.use()
                fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
                ctx.depth_func = "<"
                for v in views:
                    ctx.viewport = (v.tile[0] * size, v.tile[1] * size, size, size)
                    gl.set_uniforms(self._face_vao.program, self._uniforms(v))
                    self._face_vao.render(moderngl.TRIANGLES)
                raw = tex.read(alignment=1)
        finally:
            scope.release()
        k = np.frombuffer(raw, dtype=np.float32).reshape(shape[1], shape[0], 2)
        return (k[..., 0].astype(np.int64) + (k[..., 1].astype(np.int64) << 20) - 1).astype(np.int32)

    def _surface(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The mesh's triangles relative to the centre and its corner normals, ``(F, 3, 3)``
        each, shared by every map with faces."""
        if self._surface_arrays is None:
            v = np.asarray(self.mesh.vertices, dtype=np.float64) - self.centre
            self._surface_arrays = (v[np.asarray(self.mesh.faces, dtype=np.int64)],
                                    np.asarray(self.mesh.corner_normals, dtype=np.float64))
        return self._surface_arrays

    def render(self, views: list[View], size: int, normals: bool = False) -> ShadowMap:
        """Depth maps of ``views`` packed in an atlas of ``size``-texel tiles, read back; with
        ``normals`` the face atlas too (:meth:`ShadowMap.entry_normals`)."""
        ctx = self.ctx
        shape = _atlas_shape(views, size)
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
                    gl.set_uniforms(self.prog, self._uniforms(v))
                    self.vao.render(moderngl.TRIANGLES)
                raw = tex.read(alignment=1)
        finally:
            ctx.blend_equation = moderngl.FUNC_ADD
            scope.release()
        depth = np.frombuffer(raw, dtype=np.float32).reshape(shape[1], shape[0], 2)
        mid = 0.5 * (depth[..., 0].astype(np.float64) + depth[..., 1])
        if not normals:
            return ShadowMap(views, size, mid, depth[..., 0])
        return ShadowMap(views, size, mid, depth[..., 0], self._render_faces(views, size, shape), self._surface())

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

    def shadow_map(self, light: Light, size: int, direction: NDArray[np.float64] | None = None,
                   normals: bool = False) -> ShadowMap:
        """The shadow map of ``light`` (``direction``: an orthographic view towards it instead,
        e.g. one direction of an environment light; ``normals``: with entry normals); a kept
        one where this renderer keeps maps (class docstring)."""
        key = (repr(light), int(size))
        if self._kept is None or direction is not None:
            return self._light_map(light, size, direction, normals)
        sm = self._kept.get(key)
        if sm is None:
            sm = self._kept[key] = self._light_map(light, size, None, normals)
        elif normals and sm.face is None:           # the same views' faces, added to the kept map
            sm.face = self._render_faces(sm.views, sm.size, _atlas_shape(sm.views, sm.size))
            sm.surface = self._surface()
        return sm

    def keep_lights(self, lights: Sequence[Light]) -> None:
        """Drop the kept maps of lights not among ``lights``."""
        if self._kept:
            names = {repr(lt) for lt in lights}
            self._kept = {k: v for k, v in self._kept.items() if k[0] in names}

    def _light_map(self, light: Light, size: int, direction: NDArray[np.float64] | None,
                   normals: bool) -> ShadowMap:
        if isinstance(light, ProjectorLight):
            light = light.spot
        if isinstance(light, DirectionalLight) or direction is not None:
            w = np.asarray(light.direction if direction is None else direction, dtype=np.float64)
            return self.render(self.directional_view(w, size), size, normals)
        if isinstance(light, SpotLight):
            return self.render(self.perspective_views(np.asarray(light.position), size,
                                                      np.asarray(light.direction), light.cone_deg), size, normals)
        return self.render(self.perspective_views(np.asarray(light.position), size), size, normals)
