"""Pinhole camera math, numpy only: view matrices, OpenGL clip matrices, OpenCV poses.

Positions in mm. Matrices are row-major numpy ``(4, 4)`` float64 arrays acting on column
vectors (``clip = proj @ view @ [x, y, z, 1]``); upload them to GLSL transposed
(:func:`glsldiff.gl.set_uniforms` does that for 2-D arrays).

OpenGL convention (:func:`look_at`, :func:`view_matrix`, :func:`projection`): camera x right,
y up, looking down -z; clip depth in [-w, w]. OpenCV convention (:func:`opencv_pose`): x right,
y down, z forward, world point ``X`` maps to ``R X + t``.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError

Matrix = NDArray[np.float64]


def view_matrix(eye: ArrayLike, right: ArrayLike, up: ArrayLike, back: ArrayLike) -> Matrix:
    """World -> camera of an orthonormal frame at ``eye`` (mm): rows ``right``, ``up`` and
    ``back`` (the unit vector from the target towards the eye; the camera looks along -back)."""
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = right, up, back
    m[:3, 3] = -m[:3, :3] @ np.asarray(eye, dtype=np.float64)
    return m


def orthonormal_frame(forward: ArrayLike, up: ArrayLike | None = None) -> tuple[NDArray, NDArray, NDArray]:
    """Unit ``right = forward x up``, ``up' = right x forward`` and ``forward`` (a unit vector):
    the right-handed camera frame of gluLookAt. Without ``up``, +z is used (+x when ``forward``
    is within about 25 degrees of the z axis)."""
    f = np.asarray(forward, dtype=np.float64)
    if up is None:
        up = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    s = np.cross(f, up)
    s /= np.linalg.norm(s)
    return s, np.cross(s, f), f


def _frame(eye: ArrayLike, target: ArrayLike, up: ArrayLike) -> tuple[NDArray, NDArray, NDArray]:
    """Unit forward ``f``, unit right ``s = f x up`` and ``u = s x f`` (OpenGL's gluLookAt)."""
    f = np.asarray(target, dtype=np.float64) - np.asarray(eye, dtype=np.float64)
    f /= np.linalg.norm(f)
    up = np.asarray(up, dtype=np.float64)
    if np.linalg.norm(np.cross(f, up)) < 1e-9:
        raise InputError(f"camera up {up.tolist()} is parallel to the viewing direction (a scene's "
                         "[camera].up); choose another up vector")
    s, u, _ = orthonormal_frame(f, up)
    return f, s, u


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike) -> Matrix:
    """OpenGL view matrix of a camera at ``eye`` looking at ``target`` (mm), image up along
    the part of ``up`` orthogonal to the view direction.

    Raises
    ------
    InputError
        ``up`` is parallel to the viewing direction.
    """
    f, s, u = _frame(eye, target, up)
    return view_matrix(eye, s, u, -f)


def projection(scale_x: float, scale_y: float, near: float, far: float,
               orthographic: bool = False) -> Matrix:
    """OpenGL clip matrix mapping depths ``near``..``far`` (mm, in front of the camera) to
    [-1, 1]. Perspective: ``scale = 1 / tan(half angle)`` per axis; orthographic:
    ``scale = 1 / half window (mm)``."""
    m = np.zeros((4, 4))
    m[0, 0], m[1, 1] = scale_x, scale_y
    if orthographic:
        m[2, 2], m[2, 3], m[3, 3] = -2.0 / (far - near), -(far + near) / (far - near), 1.0
    else:
        m[2, 2], m[2, 3], m[3, 2] = -(far + near) / (far - near), -2.0 * far * near / (far - near), -1.0
    return m


def perspective(fov_deg: float, aspect: float, near: float, far: float) -> Matrix:
    """OpenGL perspective clip matrix of vertical field of view ``fov_deg`` and ``aspect`` =
    width / height (gluPerspective)."""
    t = 1.0 / math.tan(math.radians(fov_deg) / 2.0)
    return projection(t / aspect, t, near, far)


def opencv_pose(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, -1.0, 0.0)
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(R, t)`` world -> OpenCV camera of a camera at ``eye`` looking at ``target`` (mm):
    :func:`look_at`'s frame with y and z flipped, so image rows follow ``-up``."""
    f, s, u = _frame(eye, target, up)
    R = np.stack([s, -u, f])
    return R, -R @ np.asarray(eye, dtype=np.float64)
