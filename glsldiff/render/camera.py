"""A scene's camera (``[camera]``): where it stands and its world -> clip matrix (mm).

The matrix math is :mod:`glsldiff.core.camera`; this module adds the scene's defaults: with
no ``position`` the camera frames the mesh's bounding sphere from the front (+z), slightly
above, and the depth range hugs the mesh.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.camera import look_at, perspective, projection
from glsldiff.render.scene import Scene, vec


#: An orthographic camera's eye for shading: this many mesh radii away along the view axis, so
#: that every vertex's direction to it is the view direction within 1e-5 rad.
ORTHO_EYE_RADII = 1e5


def _radius(vertices: NDArray) -> float:
    return 0.5 * float(np.linalg.norm(np.ptp(vertices, axis=0)))


def frame_camera(scene: Scene, vertices: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Eye, target, up (mm): the scene's, or framed on the mesh's bounding sphere from the
    front (+z), slightly above (an orthographic camera: 3 radii away)."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre = 0.5 * (lo + hi)
    target = vec(scene.camera.target) if scene.camera.target is not None else centre
    up = vec(scene.camera.up)
    if scene.camera.position is not None:
        return vec(scene.camera.position), target, up
    radius = _radius(vertices)
    dist = (3.0 * radius if scene.camera.type == "orthographic"
            else 1.08 * radius / math.sin(math.radians(scene.camera.fov_deg) / 2.0))
    d = np.array([0.0, 0.2, 1.0])
    return target + dist * d / np.linalg.norm(d), target, up


def ortho_width(scene: Scene, vertices: NDArray) -> float:
    """An orthographic camera's view width (mm): ``[camera].width_mm``, or the bounding sphere
    framed with the perspective default's margin (2.16 radii) along the shorter image side."""
    if scene.camera.width_mm is not None:
        return float(scene.camera.width_mm)
    aspect = scene.output.width / scene.output.height
    return 2.16 * _radius(vertices) * max(1.0, aspect)


def scene_camera(scene: Scene, vertices: NDArray) -> tuple[NDArray, NDArray]:
    """Eye (mm) and the row-major world -> clip matrix ``proj @ view`` of ``scene``'s camera
    for the mesh ``vertices``: near and far 2 mesh radii before and behind the target. For an
    orthographic camera the eye returned is the shading eye, :data:`ORTHO_EYE_RADII` radii out
    along the view axis (the directions to the eye are the parallel view rays')."""
    eye, target, up = frame_camera(scene, vertices)
    radius = _radius(vertices)
    dist = float(np.linalg.norm(eye - target))
    near, far = max(1e-3, dist - 2 * radius), dist + 2 * radius
    aspect = scene.output.width / scene.output.height
    if scene.camera.type == "orthographic":
        w = ortho_width(scene, vertices)
        proj = projection(2.0 / w, 2.0 * aspect / w, near, far, orthographic=True)
        view = look_at(eye, target, up)
        back = (eye - target) / dist
        return target + ORTHO_EYE_RADII * max(radius, 1e-3) * back, proj @ view
    proj = perspective(scene.camera.fov_deg, aspect, near, far)
    return eye, proj @ look_at(eye, target, up)
