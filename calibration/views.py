"""Synthetic calibration data: a printed planar board seen by the simulated camera and lit
by the simulated projector (``simcam``), with known ground truth.

World frame = camera frame (mm): the camera sits at the origin looking along +z; the
projector sits ``baseline`` mm to the side (+x) and is turned towards the point 550 mm in
front of the camera. A board pose ``(R, t)`` maps board coordinates (mm, first inner corner
at the origin, see :class:`~glsldiff.calibration.camera.BoardSpec`) to world coordinates.

Rendering: every camera pixel is supersampled ``s x s`` (box filter, so corners and stripe
edges are anti-aliased). A sub-sample's ray meets the board plane at ``X``; the paper's albedo
there (``dark`` / ``light``, margin ``light``, nothing beyond the paper) times the light gives
the radiance ``albedo (cos_i E_proj + ambient)``: ``E_proj`` is the projector's emitted
radiance (``SimProjector.emitted``) of the projector pixel that ``X`` falls in (nearest pixel,
as ``SimProjector.illuminate``), ``cos_i`` the incidence cosine. Plain views use a uniform
``flood`` light instead of the projector. The camera then adds vignetting, noise, its response
and 8-bit quantisation (``SimCamera.capture``).

Folders written by :func:`write_projector_dataset` (the layout :mod:`.projector` reads)::

    OUT/capture_000/img_00.png ... img_NN.png   # one per Gray-code pattern, then white, black
    OUT/capture_001/...
    OUT/truth.json

or, with ``layout="procam"``, kamino410/procam-calibration's names ``OUT/capture_0/graycode_00.png
...``; with ``step`` > 1 the patterns have that Gray-code step (:func:`~.graycode.patterns`).

and by :func:`write_camera_dataset`: ``OUT/view_00.png ...`` plus ``OUT/truth.json``.
``truth.json``: ``{"camera": {"K", "dist", "image_size"}, "projector": {...} | null,
"R", "T"`` (camera -> projector: ``X_p = R X_c + T``, mm) ``, "baseline_mm", "board": {...},
"poses": [{"R", "t"}, ...]}`` (board -> camera), plus ``"graycode_step"`` for projector datasets.

Commands: ``glsldiff capture synth-projector-views OUT`` and ``glsldiff capture
synth-camera-views OUT`` (:func:`synthetic_rig` and the writers above).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np
from numpy.typing import NDArray

from glsldiff.calibration.camera import BoardSpec
from glsldiff.calibration.common import atomic_folder
from glsldiff.calibration.graycode import patterns
from glsldiff.calibration.simcam import Pinhole, SimCamera, SimProjector, intersect_plane
from glsldiff.core.camera import opencv_pose
from glsldiff.core.errors import InputError

Array = NDArray[np.float64]
AIM_MM = 550.0  # the projector is aimed at the point this far in front of the camera


# ---- devices and poses ----------------------------------------------------------------------
def default_devices(camera_size: tuple[int, int] = (1280, 1024), projector_size: tuple[int, int] = (1024, 768),
                    baseline: float = 150.0) -> tuple[SimCamera, SimProjector]:
    """A camera at the origin (f = 1.33 x width px, mild barrel distortion) and a projector
    ``baseline`` mm to its right (f = 1.37 x width px, principal point below the centre, slight
    distortion), both 8-bit / gamma 2.2. The camera's gain puts white paper (albedo 0.85) under
    the projector's full white near 90 % of the sensor range."""
    w, h = camera_size
    K = np.array([[1.33 * w, 0, (w - 1) / 2 + 0.006 * w], [0, 1.33 * w, (h - 1) / 2 - 0.005 * w], [0, 0, 1]])
    cam = SimCamera(K, (w, h), dist=np.array([-0.12, 0.09, 4e-4, -3e-4, 0.0]), gain=1.05,
                    vignetting=0.1)
    pw, ph = projector_size
    Kp = np.array([[1.37 * pw, 0, (pw - 1) / 2], [0, 1.37 * pw, 0.6 * (ph - 1)], [0, 0, 1]])
    eye = np.array([baseline, 0.0, 0.0])
    Rp, tp = opencv_pose(eye, np.array([0.0, 0.0, AIM_MM]), up=(0.0, -1.0, 0.0))
    proj = SimProjector(Kp, (pw, ph), Rp, tp, dist=np.array([0.03, 0.0, 0.0, 0.0, 0.0]), black=0.01)
    return cam, proj


def paper_corners(board: BoardSpec, margin: float) -> Array:
    """The printed paper's four corners ``(4, 3)`` in board coordinates (mm)."""
    s = board.square
    x0, y0, x1, y1 = -s - margin, -s - margin, board.cols * s + margin, board.rows * s + margin
    return np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], np.float64)


def _rotation(axis: Array, angle_deg: float) -> Array:
    R, _ = cv2.Rodrigues(np.asarray(axis, np.float64) / np.linalg.norm(axis) * np.radians(angle_deg))
    return R


def _inside(dev: Pinhole, X: Array, border: float) -> bool:
    """All points in front of ``dev`` and at least ``border`` x size inside its frame."""
    uv = dev.project(X)
    w, h = dev.size
    return bool(np.all(dev.depth(X) > 0) and np.all(uv[:, 0] > border * w) and np.all(uv[:, 0] < (1 - border) * w)
                and np.all(uv[:, 1] > border * h) and np.all(uv[:, 1] < (1 - border) * h))


def board_poses(n: int, board: BoardSpec, camera: Pinhole, projector: Pinhole | None = None,
                distance: tuple[float, float] = (450.0, 650.0), tilt: tuple[float, float] = (10.0, 40.0),
                margin: float = 10.0, seed: int = 0) -> list[tuple[Array, Array]]:
    """``n`` board poses ``(R, t)`` (board -> world; ``t`` is the first inner corner, mm) whose
    whole paper is seen by the camera and, when given, lit by the projector: board centre at
    ``distance`` mm, tilt ``tilt`` degrees about axes spread evenly around the view axis,
    in-plane roll within +-15 degrees."""
    rng = np.random.default_rng(seed)
    centre = np.array([(board.cols - 1) * board.square / 2, (board.rows - 1) * board.square / 2, 0.0])
    paper = paper_corners(board, margin)
    out = []
    for k in range(n):
        for _ in range(2000):
            phi = 2 * np.pi * (k + rng.uniform(-0.3, 0.3)) / n
            R = _rotation([np.cos(phi), np.sin(phi), 0.0], rng.uniform(*tilt)) @ _rotation([0, 0, 1], rng.uniform(-15, 15))
            d = rng.uniform(*distance)
            target = np.array([rng.uniform(-0.05, 0.05) * d, rng.uniform(-0.05, 0.05) * d, d])
            t = target - R @ centre
            X = paper @ R.T + t
            if _inside(camera, X, 0.02) and (projector is None or _inside(projector, X, 0.01)):
                out.append((R, t))
                break
        else:
            raise InputError(f"board_poses: no pose {k} keeps the {board.cols}x{board.rows} board "
                             f"({board.square} mm squares) inside the frames at {distance} mm")
    return out


# ---- rendering ------------------------------------------------------------------------------
def _albedo_function(board: BoardSpec, dark: float, light: float,
                     margin: float) -> Callable[[NDArray, NDArray], NDArray[np.float32]]:
    """``f(x, y)`` -> albedo on the board (mm), 0 off the paper."""
    s = board.square
    x0, y0, x1, y1 = paper_corners(board, margin)[[0, 2], :2].ravel()
    if board.kind == "charuco":
        ppm = 8.0  # texture px per mm
        cb = board.charuco_board()
        tex = cb.generateImage((int(round((board.cols + 1) * s * ppm)), int(round((board.rows + 1) * s * ppm))),
                               marginSize=0, borderBits=1).astype(np.float32) / 255.0

    def albedo(x: NDArray, y: NDArray) -> NDArray[np.float32]:
        on_paper = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
        i, j = np.floor(x / s), np.floor(y / s)
        in_squares = (i >= -1) & (i <= board.cols - 1) & (j >= -1) & (j <= board.rows - 1)
        if board.kind == "charuco":
            ti = np.clip(((x + s) * ppm).astype(np.int64), 0, tex.shape[1] - 1)
            tj = np.clip(((y + s) * ppm).astype(np.int64), 0, tex.shape[0] - 1)
            v = np.where(in_squares, tex[tj, ti], 1.0)
        else:
            v = np.where(in_squares & ((i + j) % 2 == 0), 0.0, 1.0)
        return np.where(on_paper, dark + (light - dark) * v, 0.0).astype(np.float32)

    return albedo


def subpixel_rays(camera: Pinhole, s: int, band_rows: int = 64) -> tuple[Array, NDArray[np.float32]]:
    """World ray origin and float32 unit directions ``(rows*s, cols*s, 3)`` through the centres
    of the ``s x s`` sub-pixels of every pixel, computed in bands of ``band_rows`` pixel rows."""
    w, h = camera.size
    dirs = np.empty((h * s, w * s, 3), np.float32)
    for r0 in range(0, h, band_rows):
        r1 = min(h, r0 + band_rows)
        K = np.array(camera.K, np.float64) * [[s, s, s], [s, s, s], [1, 1, 1]]
        K[0, 2] += (s - 1) / 2
        K[1, 2] += (s - 1) / 2 - r0 * s
        sub = Pinhole(K, (w * s, (r1 - r0) * s), camera.R, camera.t, camera.dist)
        origin, d = sub.pixel_rays()
        dirs[r0 * s:r1 * s] = d
    return camera.center, dirs


@dataclass
class PoseScene:
    """Per sub-pixel precomputation of one board pose: albedo, projector pixel index (flat,
    ``-1`` where unlit) and projector incidence cosine."""

    albedo: NDArray[np.float32]
    index: NDArray[np.int32]
    cosine: NDArray[np.float32]
    s: int

    def _box(self, sub: NDArray[np.float32]) -> Array:
        """Mean over each pixel's ``s x s`` sub-pixels (an exact box filter for integer factors)."""
        H, W = sub.shape
        return cv2.resize(sub, (W // self.s, H // self.s), interpolation=cv2.INTER_AREA).astype(np.float64)

    def radiance(self, projector: SimProjector, pattern: NDArray[np.uint8], ambient: float) -> Array:
        """Radiance ``(rows, cols)`` of the board lit by ``pattern`` (8-bit) plus ``ambient``."""
        em = projector.emitted(np.asarray(pattern, np.float64) / 255.0).astype(np.float32).ravel()
        E = np.take(np.append(em, np.float32(0.0)), self.index)  # index -1 -> 0
        E *= self.cosine
        E += np.float32(ambient)
        E *= self.albedo
        return self._box(E)

    def flood(self, level: float) -> Array:
        """Radiance ``(rows, cols)`` under a uniform light ``level``."""
        return self._box(self.albedo * np.float32(level))


def pose_scene(rays: tuple[Array, NDArray], s: int, board: BoardSpec, pose: tuple[Array, Array],
               projector: SimProjector | None, dark: float, light: float, margin: float) -> PoseScene:
    """Intersect the sub-pixel ``rays`` (:func:`subpixel_rays`) with the board at ``pose``."""
    origin, dirs = rays
    R, t = (np.asarray(a, np.float64) for a in pose)
    H, W = dirs.shape[:2]
    albedo = np.zeros((H, W), np.float32)
    index = np.full((H, W), -1, np.int32)
    cosine = np.zeros((H, W), np.float32)
    f = _albedo_function(board, dark, light, margin)
    n = R[:, 2]
    step = max(1, 2_000_000 // W)
    for r0 in range(0, H, step):
        d = dirs[r0:r0 + step].astype(np.float64)
        X, hit = intersect_plane(origin, d, t, n)
        b = (X - t) @ R  # board coordinates
        a = np.where(hit, f(b[..., 0], b[..., 1]), 0.0)
        albedo[r0:r0 + step] = a
        if projector is None or not np.any(a > 0):
            continue
        on = (a > 0).ravel()
        Xo = X.reshape(-1, 3)[on]
        uv = projector.project(Xo)
        pw, ph = projector.size
        ui, vi = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
        lit = (ui >= 0) & (ui < pw) & (vi >= 0) & (vi < ph) & (projector.depth(Xo) > 0)
        idx = np.full(on.size, -1, np.int32)
        idx[np.flatnonzero(on)[lit]] = (vi * pw + ui)[lit]
        to_p = projector.center - Xo
        cos = np.zeros(on.size, np.float32)
        cos[on] = np.abs(to_p @ n) / np.linalg.norm(to_p, axis=1)
        rows = index[r0:r0 + step].shape[0]
        index[r0:r0 + step] = idx.reshape(rows, W)
        cosine[r0:r0 + step] = cos.reshape(rows, W)
    return PoseScene(albedo, index, cosine, s)


# ---- datasets -------------------------------------------------------------------------------
@dataclass
class SyntheticRig:
    """Everything a synthetic dataset is made from (see the module docstring)."""

    camera: SimCamera
    projector: SimProjector | None
    board: BoardSpec
    poses: list[tuple[Array, Array]]
    dark: float = 0.05
    light: float = 0.85
    margin: float = 10.0  # mm of white paper around the squares
    ambient: float = 0.02  # ambient light / projector white
    supersample: int = 3  # odd: with an even factor a stripe edge can split a pixel exactly in half
    seed: int = 0

    def __post_init__(self) -> None:
        if self.supersample < 1 or self.supersample % 2 == 0:
            raise InputError(f"supersample={self.supersample}: use an odd factor >= 1 (an even one lets "
                             f"Gray-code stripe edges split pixels exactly in half, which no real sensor does)")

    def scenes(self, with_projector: bool = True) -> Iterator[PoseScene]:
        """Yield the :class:`PoseScene` of every pose (sub-pixel rays computed once)."""
        rays = subpixel_rays(self.camera, self.supersample)
        for pose in self.poses:
            yield pose_scene(rays, self.supersample, self.board, pose, self.projector if with_projector else None,
                             self.dark, self.light, self.margin)

    def true_projector_pixels(self, k: int) -> Array:
        """Projector coordinates ``(rows, cols, 2)`` (px, continuous) of the board point seen at
        every camera pixel centre in pose ``k``; NaN off the paper or outside the projector frame."""
        origin, dirs = self.camera.pixel_rays()
        R, t = self.poses[k]
        X, hit = intersect_plane(origin, dirs, t, R[:, 2])
        b = (X - t) @ R
        on = hit & (_albedo_function(self.board, self.dark, self.light, self.margin)(b[..., 0], b[..., 1]) > 0)
        uv = np.full(X.shape[:2] + (2,), np.nan)
        uv[on] = self.projector.project(X[on])
        w, h = self.projector.size
        outside = (uv[..., 0] < -0.5) | (uv[..., 0] >= w - 0.5) | (uv[..., 1] < -0.5) | (uv[..., 1] >= h - 0.5)
        uv[outside] = np.nan
        return uv

    def truth(self) -> dict:
        cam = self.camera
        out = {"camera": {"K": cam.K.tolist(), "dist": cam.dist.tolist(), "image_size": list(cam.size)},
               "projector": None, "board": self.board.to_json(),
               "poses": [{"R": R.tolist(), "t": t.tolist()} for R, t in self.poses]}
        if self.projector is not None:
            p = self.projector
            R = p.R @ cam.R.T
            T = p.t - R @ cam.t
            out.update(projector={"K": p.K.tolist(), "dist": p.dist.tolist(), "image_size": list(p.size)},
                       R=R.tolist(), T=T.tolist(), baseline_mm=float(np.linalg.norm(T)))
        return out


def synthetic_rig(n_poses: int, camera_size: tuple[int, int] = (1280, 1024),
                  projector_size: tuple[int, int] | None = (1024, 768), board: BoardSpec | None = None,
                  baseline: float = 150.0, seed: int = 0, **kwargs) -> SyntheticRig:
    """Default devices (:func:`default_devices`), a 9x7 / 20 mm chessboard unless ``board``,
    and ``n_poses`` poses kept inside the camera (and projector) frames."""
    board = board or BoardSpec(9, 7, 20.0)
    cam, proj = default_devices(camera_size, projector_size or (1024, 768), baseline)
    proj = proj if projector_size is not None else None
    poses = board_poses(n_poses, board, cam, proj, margin=kwargs.get("margin", 10.0), seed=seed)
    return SyntheticRig(cam, proj, board, poses, seed=seed, **kwargs)


def _write(path: Path, img: NDArray) -> None:
    if not cv2.imwrite(str(path), img):
        raise InputError(f"cannot write {path}")


#: Capture folder and image names per layout: this package's, and kamino410/procam-calibration's.
LAYOUTS = {"glsldiff": ("capture_{:03d}", "img_{:02d}.png"), "procam": ("capture_{}", "graycode_{:02d}.png")}


def write_projector_dataset(out: str | os.PathLike, rig: SyntheticRig, step: int = 1,
                            layout: str = "glsldiff") -> Path:
    """Render every pose under every Gray-code pattern of Gray-code ``step`` (+ white, black)
    into ``out/capture_XXX/img_YY.png`` (``layout="procam"``: ``out/capture_K/graycode_YY.png``)
    plus ``out/truth.json``; ``out`` appears only when complete."""
    if rig.projector is None:
        raise InputError("write_projector_dataset: the rig has no projector")
    if layout not in LAYOUTS:
        raise InputError(f"layout {layout!r}: choose one of {', '.join(LAYOUTS)}")
    folder_name, image_name = LAYOUTS[layout]
    seq = patterns(rig.projector.size, step)
    rng = np.random.default_rng(rig.seed)
    with atomic_folder(out) as tmp:
        for k, scene in enumerate(rig.scenes()):
            folder = tmp / folder_name.format(k)
            folder.mkdir()
            for i, pat in enumerate(seq):
                img = rig.camera.capture(scene.radiance(rig.projector, pat, rig.ambient), 1.0, rng)
                _write(folder / image_name.format(i), img)
        (tmp / "truth.json").write_text(json.dumps({**rig.truth(), "graycode_step": step}, indent=1))
    return Path(out)


def write_camera_dataset(out: str | os.PathLike, rig: SyntheticRig, flood: float = 1.0) -> Path:
    """Plain board views under a uniform ``flood`` light: ``out/view_XX.png`` + ``truth.json``."""
    rng = np.random.default_rng(rig.seed)
    with atomic_folder(out) as tmp:
        for k, scene in enumerate(rig.scenes(with_projector=False)):
            _write(tmp / f"view_{k:02d}.png", rig.camera.capture(scene.flood(flood + rig.ambient), 1.0, rng))
        (tmp / "truth.json").write_text(json.dumps(rig.truth(), indent=1))
    return Path(out)
