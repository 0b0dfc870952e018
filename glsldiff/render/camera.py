"""A scene's camera (``[camera]``): where it stands and its world -> clip matrix (mm).

The matrix math is :mod:`glsldiff.core.camera`; this module adds the scene's defaults: with
no ``position`` the camera frames the mesh's bounding sphere from the front (+z), slightly
above, and the depth range hugs the mesh.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.camera import look_at, perspective
from glsldiff.render.scene import Scene, vec


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


def scene_camera(scene: Scene, vertices: NDArray) -> tuple[NDArray, NDArray]:
    """Eye (mm) and the row-major world -> clip matrix ``proj @ view`` of ``scene``'s camera
    for the mesh ``vertices``: near and far 2 mesh radii before and behind the target."""
    eye, target, up = frame_camera(scene, vertices)
    radius = 0.5 * float(np.linalg.norm(np.ptp(vertices, axis=0)))
    dist = float(np.linalg.norm(eye - target))
    proj = perspective(scene.camera.fov_deg, scene.output.width / scene.output.height,
                       max(1e-3, dist - 2 * radius), dist + 2 * radius)
    return eye, proj @ look_at(eye, target, up)
