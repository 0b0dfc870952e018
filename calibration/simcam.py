"""Simulated camera and projector: the data source of the virtual rig and the tests.

Conventions (OpenCV's): world points ``X`` (mm) map to camera coordinates ``R X + t``
(a pose aimed at a point: :func:`glsldiff.core.camera.opencv_pose`); pixel
``(u, v)`` has ``u`` along image columns, ``v`` along rows, origin at the top-left pixel
centre. Images are ``(rows, cols)`` or ``(rows, cols, 3)`` arrays.

A camera turns scene radiance into pixel values the way a real one does, in this order:
radiance x exposure time x vignetting -> photon (shot) noise + read noise -> camera response
``f`` (monotone, to [0, 1]) -> quantisation to ``bits`` and clipping. A projector turns a
pattern image (values in [0, 1]) into emitted radiance: ``black + (1 - black) v^gamma``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass
class Pinhole:
    """Pinhole device with OpenCV distortion: intrinsics ``K``, distortion ``dist`` (k1, k2,
    p1, p2, k3), pose ``(R, t)`` world -> device, image ``size = (cols, rows)``."""

    K: Array
    size: tuple[int, int]
    R: Array = field(default_factory=lambda: np.eye(3))
    t: Array = field(default_factory=lambda: np.zeros(3))
    dist: Array = field(default_factory=lambda: np.zeros(5))

    @property
    def center(self) -> Array:
        """Optical centre in world coordinates (mm)."""
        return -self.R.T @ self.t

    def project(self, X: Array) -> Array:
        """World points ``(n, 3)`` -> distorted pixel coordinates ``(n, 2)``."""
        rvec, _ = cv2.Rodrigues(np.asarray(self.R, dtype=np.float64))
        uv, _ = cv2.projectPoints(np.asarray(X, dtype=np.float64).reshape(-1, 1, 3), rvec,
                                  np.asarray(self.t, dtype=np.float64), self.K, self.dist)
        return uv.reshape(-1, 2)

    def depth(self, X: Array) -> Array:
        """Distance along the optical axis of world points ``(n, 3)``."""
        return (np.asarray(X) @ self.R.T + self.t)[:, 2]

    def pixel_rays(self) -> tuple[Array, Array]:
        """World ray origin ``(3,)`` and unit directions ``(rows, cols, 3)`` through every pixel
        centre (distortion removed)."""
        w, h = self.size
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        xy = cv2.undistortPoints(pts, self.K, self.dist).reshape(-1, 2)
        d = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1) @ self.R  # R^T d_cam
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return self.center, d.reshape(h, w, 3)


def gamma_response(x: Array, gamma: float = 2.2) -> Array:
    """A camera response: ``f(x) = x^(1/gamma)`` on [0, 1] (clipped)."""
    return np.clip(x, 0.0, 1.0) ** (1.0 / gamma)


@dataclass
class SimCamera(Pinhole):
    """Camera with response, noise, vignetting and quantisation.

    ``gain`` scales radiance x seconds to the [0, 1] sensor range; ``full_well`` (electrons at
    saturation) sets the shot noise; ``read_noise`` is in electrons; ``vignetting`` is ``k`` in
    the falloff ``1 - k r^2`` with ``r`` the distance from the image centre over the half
    diagonal; ``bits`` 8, 12 or 16.
    """

    gamma: float = 2.2
    gain: float = 1.0
    full_well: float = 20000.0
    read_noise: float = 5.0
    vignetting: float = 0.0
    bits: int = 8

    def response(self, x: Array) -> Array:
        """Response ``f``: normalised sensor exposure -> [0, 1]."""
        return gamma_response(x, self.gamma)

    def vignette(self) -> Array:
        """``(rows, cols)`` vignetting factor."""
        w, h = self.size
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        r2 = ((u - (w - 1) / 2) ** 2 + (v - (h - 1) / 2) ** 2) / (((w - 1) / 2) ** 2 + ((h - 1) / 2) ** 2)
        return 1.0 - self.vignetting * r2

    def capture(self, radiance: Array, seconds: float, rng: np.random.Generator | int | None = None) -> NDArray:
        """Pixel values (uint8 for 8 bits, else uint16) of a radiance image ``(rows, cols[, 3])``
        exposed for ``seconds``."""
        gen = np.random.default_rng(rng)
        L = np.asarray(radiance, dtype=np.float64)
        vig = self.vignette()
        x = L * seconds * self.gain * (vig[..., None] if L.ndim == 3 else vig)
        electrons = np.clip(x, 0.0, None) * self.full_well
        if self.full_well > 0:
            electrons = gen.poisson(np.minimum(electrons, 1e12)).astype(np.float64)
        electrons += self.read_noise * gen.standard_normal(electrons.shape)
        top = 2**self.bits - 1
        values = np.round(self.response(electrons / self.full_well) * top)
        return np.clip(values, 0, top).astype(np.uint8 if self.bits == 8 else np.uint16)


@dataclass
class SimProjector(Pinhole):
    """Projector: pattern value ``v`` in [0, 1] -> radiance ``white (black + (1 - black) v^gamma)``."""

    gamma: float = 2.2
    black: float = 0.01
    white: float = 1.0

    def emitted(self, pattern: Array) -> Array:
        p = np.clip(np.asarray(pattern, dtype=np.float64), 0.0, 1.0)
        return self.white * (self.black + (1.0 - self.black) * p**self.gamma)

    def illuminate(self, pattern: Array, X: Array) -> Array:
        """Radiance arriving at world points ``X`` ``(n, 3)`` (no falloff) from ``pattern``
        ``(rows, cols[, 3])``; 0 outside the projector frame or behind it."""
        uv = self.project(X)
        w, h = self.size
        ui, vi = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        inside = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h) & (self.depth(X) > 0)
        em = self.emitted(pattern)
        out = np.zeros((X.shape[0],) + em.shape[2:])
        out[inside] = em[vi[inside], ui[inside]]
        return out


def intersect_plane(origin: Array, dirs: Array, point: Array, normal: Array) -> tuple[Array, Array]:
    """Points where rays ``origin + s dirs`` meet the plane (``point``, ``normal``) and a mask
    of rays that hit it in front of the origin."""
    n = np.asarray(normal, dtype=np.float64)
    den = dirs @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((np.asarray(point) - origin) @ n) / den
    hit = np.isfinite(s) & (s > 0)
    X = origin + np.where(hit, s, 0.0)[..., None] * dirs
    return X, hit
