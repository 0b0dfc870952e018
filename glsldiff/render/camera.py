"""A scene's camera (``[camera]``): where it stands and its world -> clip matrix (mm).

The matrix math is :mod:`glsldiff.core.camera`; this module adds the scene's defaults: with
no ``position`` the camera frames the mesh's bounding sphere (:class:`Framing`) from the
direction that shows its largest silhouette, slightly above, with the image's up +y where +y
lies across the image (else the object's longest axis), and the depth range hugs the mesh.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.camera import look_at, perspective, projection
from glsldiff.core.jit import kernel
from glsldiff.render.scene import Scene, vec


#: An orthographic camera's eye for shading: this many mesh radii away along the view axis, so
#: that every vertex's direction to it is the view direction within 1e-5 rad.
ORTHO_EYE_RADII = 1e5


#: The automatic camera's rays per side when it measures a silhouette (:func:`silhouette_area`).
SILHOUETTE_RAYS = 48
#: Silhouettes within this share of the largest count as equal: the tie goes to a coordinate axis
#: (meshes are mostly modelled along them; the bunny's is 7 % under its principal axis's), then
#: to the one nearest the front, +z.
SILHOUETTE_TIE = 0.10
#: In-plane extents within this share of the longest count as equal (up: the one nearer +z).
UP_TIE = 0.15
_FRONT = np.array([0.0, 0.2, 1.0])        # the automatic eye's elevation: slightly above the view axis


@dataclass(frozen=True)
class Framing:
    """What the automatic camera reads of a mesh (mm): its box's lowest and highest corner, the
    unit direction from the target towards the eye (before the elevation) and the image's up."""

    lo: NDArray
    hi: NDArray
    view: NDArray
    up: NDArray

    @property
    def radius(self) -> float:
        """Half the box's diagonal, mm."""
        return 0.5 * float(np.linalg.norm(self.hi - self.lo))

    @classmethod
    def of_box(cls, vertices: NDArray) -> "Framing":
        """The box of ``vertices`` seen from the front (+z), up +y (no surface to measure)."""
        v = np.asarray(vertices, dtype=np.float64)
        return cls(v.min(axis=0), v.max(axis=0), np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]))

    @classmethod
    def of_mesh(cls, mesh: Any) -> "Framing":
        """``mesh`` (a :class:`glsldiff.mesh.Mesh`) seen along the axis, among its principal axes
        (of the area-weighted surface) and the coordinate axes, that shows the largest silhouette
        (:func:`silhouette_area`), from the side nearer the front. Up: the axis across the image
        nearer +y where +y lies in the image (the OBJ and PLY files' up: a horse stands on its
        legs), else the object's longest axis across the image (the one nearer +z within
        :data:`UP_TIE`)."""
        v, tri = np.asarray(mesh.vertices, dtype=np.float64), mesh.triangles
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = 0.5 * np.linalg.norm(cross, axis=1)
        c = tri.mean(axis=1)
        x = c - (area[:, None] * c).sum(axis=0) / max(float(area.sum()), 1e-300)
        _, principal = np.linalg.eigh(np.einsum("f,fi,fj->ij", area, x, x))
        frames = [np.eye(3), principal.T]            # rows: the axes; coordinate axes first
        cands = [(k, i) for k in range(2) for i in range(3)]
        areas = np.array([silhouette_area(mesh, frames[k][i]) for k, i in cands])
        best = [c_ for c_, a in zip(cands, areas) if a >= (1.0 - SILHOUETTE_TIE) * areas.max()]
        k, i = min(best, key=lambda ki: (ki[0], -abs(frames[ki[0]][ki[1]] @ _FRONT)))
        axes = frames[k]
        view = axes[i] * (1.0 if axes[i] @ _FRONT >= 0.0 else -1.0)
        across = [axes[j] for j in range(3) if j != i]
        ext = [float(np.ptp(v @ a)) for a in across]
        if max(abs(a[1]) for a in across) >= 0.5:
            up = max(across, key=lambda a: abs(a[1]))
        elif abs(ext[0] - ext[1]) <= UP_TIE * max(ext):
            up = max(across, key=lambda a: abs(a[2]))
        else:
            up = across[int(np.argmax(ext))]
        up = up * (1.0 if (up[1], up[2], up[0]) >= (0.0, 0.0, 0.0) else -1.0)
        return cls(v.min(axis=0), v.max(axis=0), view, up)


def silhouette_area(mesh: Any, d: NDArray, rays: int = SILHOUETTE_RAYS) -> float:
    """``mesh``'s silhouette seen along unit ``d`` (mm^2): the share of a ``rays`` x ``rays``
    grid of parallel rays over its bounding square that hits it (a ray hits where its point
    lies in a projected triangle: :func:`_cover`), times the square's area."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64) / np.linalg.norm(d)
    a = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(d, a)
    pa, pb = v @ a, v @ b
    side = max(float(np.ptp(pa)), float(np.ptp(pb)), 1e-9)
    # ray (i, j) passes through ((j + 0.5), (i + 0.5)) / rays * side from the low corner
    uv = np.stack([pa - pa.min(), pb - pb.min()], axis=1) * (rays / side) - 0.5
    mask = np.zeros((rays, rays), dtype=np.bool_)
    _cover(np.ascontiguousarray(uv), np.ascontiguousarray(mesh.faces, dtype=np.int64), mask)
    return float(mask.mean()) * side * side


@kernel
def _cover(uv: NDArray, faces: NDArray, mask: NDArray) -> None:
    """Set ``mask[i, j]`` where the point ``(j, i)`` lies in (or on) a triangle ``uv[faces]``
    (pixel units)."""
    h, w = mask.shape
    for f in range(len(faces)):
        x0, y0 = uv[faces[f, 0], 0], uv[faces[f, 0], 1]
        x1, y1 = uv[faces[f, 1], 0], uv[faces[f, 1], 1]
        x2, y2 = uv[faces[f, 2], 0], uv[faces[f, 2], 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0:
            continue
        s = 1.0 if area > 0.0 else -1.0
        j0, j1 = max(int(math.ceil(min(x0, x1, x2))), 0), min(int(math.floor(max(x0, x1, x2))), w - 1)
        i0, i1 = max(int(math.ceil(min(y0, y1, y2))), 0), min(int(math.floor(max(y0, y1, y2))), h - 1)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                e0 = s * ((x1 - x0) * (i - y0) - (j - x0) * (y1 - y0))
                e1 = s * ((x2 - x1) * (i - y1) - (j - x1) * (y2 - y1))
                e2 = s * ((x0 - x2) * (i - y2) - (j - x2) * (y0 - y2))
                if e0 >= 0.0 and e1 >= 0.0 and e2 >= 0.0:
                    mask[i, j] = True


def _framing(vertices: "Framing | NDArray") -> Framing:
    return vertices if isinstance(vertices, Framing) else Framing.of_box(vertices)


def frame_camera(scene: Scene, vertices: "Framing | NDArray") -> tuple[NDArray, NDArray, NDArray]:
    """Eye, target, up (mm): the scene's, or the mesh's :class:`Framing` (``vertices``: a
    mesh's framing, or its vertices alone: the box seen from the front, +z) framed on its
    bounding sphere, slightly above (an orthographic camera: 3 radii away)."""
    fr = _framing(vertices)
    centre = 0.5 * (fr.lo + fr.hi)
    target = vec(scene.camera.target) if scene.camera.target is not None else centre
    if scene.camera.position is not None:
        return vec(scene.camera.position), target, vec(scene.camera.up)
    radius = fr.radius
    dist = (3.0 * radius if scene.camera.type == "orthographic"
            else 1.08 * radius / math.sin(math.radians(scene.camera.fov_deg) / 2.0))
    d = fr.view + _FRONT[1] * fr.up
    return target + dist * d / np.linalg.norm(d), target, fr.up


def ortho_width(scene: Scene, vertices: "Framing | NDArray") -> float:
    """An orthographic camera's view width (mm): ``[camera].width_mm``, or the bounding sphere
    framed with the perspective default's margin (2.16 radii) along the shorter image side."""
    if scene.camera.width_mm is not None:
        return float(scene.camera.width_mm)
    aspect = scene.output.width / scene.output.height
    return 2.16 * _framing(vertices).radius * max(1.0, aspect)


def scene_camera(scene: Scene, vertices: "Framing | NDArray") -> tuple[NDArray, NDArray]:
    """Eye (mm) and the row-major world -> clip matrix ``proj @ view`` of ``scene``'s camera
    for the mesh (its :class:`Framing`, or its vertices): near and far 2 mesh radii before and behind the target. For an
    orthographic camera the eye returned is the shading eye, :data:`ORTHO_EYE_RADII` radii out
    along the view axis (the directions to the eye are the parallel view rays')."""
    fr = _framing(vertices)
    eye, target, up = frame_camera(scene, fr)
    radius = fr.radius
    dist = float(np.linalg.norm(eye - target))
    near, far = max(1e-3, dist - 2 * radius), dist + 2 * radius
    aspect = scene.output.width / scene.output.height
    if scene.camera.type == "orthographic":
        w = ortho_width(scene, fr)
        proj = projection(2.0 / w, 2.0 * aspect / w, near, far, orthographic=True)
        view = look_at(eye, target, up)
        back = (eye - target) / dist
        return target + ORTHO_EYE_RADII * max(radius, 1e-3) * back, proj @ view
    proj = perspective(scene.camera.fov_deg, aspect, near, far)
    return eye, proj @ look_at(eye, target, up)
