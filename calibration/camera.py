"""Camera intrinsics from chessboard or ChArUco images (Zhang 1999, ``cv2.calibrateCamera``).

Boards: ``--board 9x7`` counts *inner* corners (columns x rows) for both kinds; a ChArUco board
with 9x7 inner corners has 10x8 squares. Board coordinates (mm) put the first inner corner at
the origin, x along board columns, y along rows, z = 0 on the board.

Corners: ``cv2.findChessboardCornersSB`` (falls back to ``findChessboardCorners`` +
``cornerSubPix``), or ``cv2.aruco.CharucoDetector`` (partial views allowed).

A view whose RMS reprojection error exceeds ``outlier_factor`` x the median view RMS *and*
``outlier_px`` is flagged as an outlier; with ``drop_outliers`` those views are removed and the
camera is recalibrated once.

``camera.json`` (written atomically by :func:`save_json`)::

    {"version": 1, "kind": "camera",
     "image_size": [cols, rows],               # px
     "K": 3x3, "dist": [k1, k2, p1, p2, k3],   # OpenCV model, px
     "rms": px,                                # over all corners of the used views
     "views": [{"file": path, "rms": px, "corners": n, "outlier": bool}, ...],
     "files_used": [...], "rejected": [{"file": path, "reason": text}, ...],
     "board": {"kind", "cols", "rows", "square_mm", "marker_mm", "dictionary"},
     "flags": int}                              # cv2.calibrateCamera flags

Command: ``glsldiff capture camera IMAGES_OR_FOLDERS --board 9x7 --square 20 -o camera.json``
(see ``--help``). Errors print one line ``glsldiff: error: ...`` and exit with status 2. A
projector capture root (a folder with ``capture_*`` sub-folders) or one ``capture_*`` folder
contributes the white frame of each pose: the second to last image of its Gray-code sequence
(:func:`~.graycode.sequence_images`: patterns, then white, then black).

:func:`load_intrinsics` also reads kamino410/procam-calibration's camera parameter file
(``camera_config.json``: ``{"camera": {"P": 9 numbers (3x3 K, row by row), "distortion":
[k1, k2, p1, p2, k3], "width": cols, "height": rows}}``), told apart from ``camera.json`` by
its content; without ``width``/``height`` the image size is taken from the captures.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from glsldiff.calibration.graycode import capture_folders, list_images, read_gray, sequence_images
from glsldiff.calibration.common import save_json
from glsldiff.core.checks import choice, real
from glsldiff.core.errors import InputError

Array = NDArray[np.float64]
DEFAULT_FLAGS = cv2.CALIB_FIX_K3
BOARD_KINDS = ("chessboard", "charuco")


@dataclass(frozen=True)
class BoardSpec:
    """A planar target: ``cols x rows`` inner corners, ``square`` mm; ChArUco markers of
    ``marker`` mm from the OpenCV dictionary ``dictionary``."""

    cols: int
    rows: int
    square: float
    kind: str = "chessboard"
    marker: float | None = None
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        choice(self.kind, "board kind", BOARD_KINDS)
        if self.cols < 2 or self.rows < 2:
            raise InputError(f"board {self.cols}x{self.rows}: at least 2x2 inner corners are needed")
        real(self.square, "board square size (mm)", 0.0, lo_open=True)
        if self.kind == "charuco":
            if self.marker is None or not 0 < self.marker < self.square:
                raise InputError(f"ChArUco marker size {self.marker} mm must be in (0, square={self.square})")
            if not hasattr(cv2.aruco, self.dictionary):
                raise InputError(f"unknown ArUco dictionary {self.dictionary!r} (e.g. DICT_5X5_100)")

    @property
    def pattern_size(self) -> tuple[int, int]:
        return self.cols, self.rows

    def object_points(self) -> NDArray[np.float32]:
        """All inner corners ``(cols*rows, 3)`` in mm, row by row (OpenCV's order)."""
        j, i = np.mgrid[0:self.rows, 0:self.cols]
        pts = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1) * self.square
        return pts.astype(np.float32)

    def charuco_board(self) -> "cv2.aruco.CharucoBoard":
        dic = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols + 1, self.rows + 1), float(self.square),
                                      float(self.marker), dic)

    def detect(self, gray: NDArray[np.uint8]) -> tuple[NDArray[np.float32], NDArray[np.float32]] | None:
        """Board corners in an 8-bit image: ``(object points (n, 3) mm, image points (n, 2) px)``,
        or None when the board is not found."""
        return _detect_charuco(self, gray) if self.kind == "charuco" else _detect_chessboard(self, gray)

    def to_json(self) -> dict:
        d = asdict(self)
        return {"kind": d["kind"], "cols": d["cols"], "rows": d["rows"], "square_mm": d["square"],
                "marker_mm": d["marker"], "dictionary": d["dictionary"]}

    @classmethod
    def from_json(cls, d: dict) -> "BoardSpec":
        return cls(int(d["cols"]), int(d["rows"]), float(d["square_mm"]), d.get("kind", "chessboard"),
                   d.get("marker_mm"), d.get("dictionary", "DICT_5X5_100"))


def _detect_chessboard(board: BoardSpec, gray: NDArray[np.uint8]):
    size = board.pattern_size
    ok, corners = cv2.findChessboardCornersSB(gray, size, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    if not ok:
        ok, corners = cv2.findChessboardCorners(gray, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                                | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            return None
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), crit)
    return board.object_points(), np.asarray(corners, np.float32).reshape(-1, 2)


def _detect_charuco(board: BoardSpec, gray: NDArray[np.uint8], min_corners: int = 8):
    cb = board.charuco_board()
    corners, ids, _, _ = cv2.aruco.CharucoDetector(cb).detectBoard(gray)
    if ids is None or len(ids) < min_corners:
        return None
    obj, img = cb.matchImagePoints(corners, ids)
    obj = np.asarray(obj, np.float32).reshape(-1, 3) - np.float32([board.square, board.square, 0.0])
    return obj, np.asarray(img, np.float32).reshape(-1, 2)


def to_uint8(gray: NDArray) -> NDArray[np.uint8]:
    """Grey levels on the 8-bit scale -> uint8 (rounded, clipped)."""
    return np.clip(np.rint(gray), 0, 255).astype(np.uint8)


# ---- calibration --------------------------------------------------------------------------
@dataclass
class Intrinsics:
    """Result of Zhang's calibration of one device (camera or projector)."""

    K: Array
    dist: Array
    size: tuple[int, int] | None  # (cols, rows) px; None: not stated by a loaded file
    rms: float  # px, over all points
    per_view_rms: Array  # px
    rvecs: list[Array] = field(repr=False)
    tvecs: list[Array] = field(repr=False)

    def to_json(self) -> dict:
        return {"image_size": list(self.size), "K": self.K.tolist(), "dist": self.dist.ravel().tolist(),
                "rms": self.rms, "per_view_rms": self.per_view_rms.tolist()}


def load_intrinsics(path: str | os.PathLike) -> Intrinsics:
    """Camera intrinsics to reuse in the projector calibration, from a ``camera.json`` written
    by this module (``image_size``, ``K``, ``dist``, ``rms``) or procam-calibration's
    ``camera_config.json`` (``camera``: ``P``, ``distortion``, ``width``, ``height``; see the
    module docstring), told apart by content."""
    p = Path(path)
    try:
        d = json.loads(p.read_text())
        if isinstance(d, dict) and isinstance(d.get("camera"), dict) and "P" in d["camera"]:
            c = d["camera"]  # procam-calibration
            K = np.asarray(c["P"], np.float64).reshape(3, 3)
            dist = np.asarray(c["distortion"], np.float64).ravel()
            size = (int(c["width"]), int(c["height"])) if "width" in c and "height" in c else None
            rms = float("nan")
        else:
            K = np.asarray(d["K"], np.float64)
            dist = np.asarray(d["dist"], np.float64).ravel()
            size = tuple(int(s) for s in d["image_size"])
            rms = float(d.get("rms", float("nan")))
    except FileNotFoundError:
        raise InputError(f"{p}: no such camera calibration file") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{p}: not a camera calibration (camera.json with image_size, K, dist, or "
                         f"procam-calibration's camera_config.json with camera.P, camera.distortion): {exc}") from None
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 \
            or (size is not None and (len(size) != 2 or min(size) <= 0)) \
            or dist.size not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(dist)):
        raise InputError(f"{p}: K must be a finite 3x3 camera matrix with positive focal lengths, dist an "
                         f"OpenCV distortion vector and image_size [cols, rows]")
    return Intrinsics(K=K, dist=dist, size=None if size is None else (size[0], size[1]), rms=rms,
                      per_view_rms=np.zeros(0), rvecs=[], tvecs=[])


def view_rms(obj: NDArray, img: NDArray, K: Array, dist: Array, rvec: Array, tvec: Array) -> float:
    """RMS distance (px) between ``img`` and the projection of ``obj``."""
    proj, _ = cv2.projectPoints(np.asarray(obj, np.float64).reshape(-1, 1, 3), rvec, tvec, K, dist)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - np.asarray(img).reshape(-1, 2)) ** 2, axis=1))))


#: Iteration cap of the calibration optimisers (a safety net; they stop on convergence first).
MAX_ITERATIONS = 10_000


def calibrate_points(object_points: Sequence[NDArray], image_points: Sequence[NDArray],
                     size: tuple[int, int], flags: int = DEFAULT_FLAGS, what: str = "camera") -> Intrinsics:
    """Zhang calibration of corners ``(n_i, 2)`` px against board points ``(n_i, 3)`` mm for
    an image of ``size = (cols, rows)``; ``what`` names the device in errors."""
    if len(object_points) < 3:
        raise InputError(f"{what}: {len(object_points)} usable views; at least 3 are needed")
    obj = [np.asarray(o, np.float32).reshape(-1, 1, 3) for o in object_points]
    img = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in image_points]
    # stop on convergence (EPS), not on a small iteration cap: OpenCV 5's optimiser stopped at
    # 100 iterations on a real projector capture before converging (cy off 10 %)
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, MAX_ITERATIONS, 1e-12)
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(int(s) for s in size), None, None,
                                                         flags=flags, criteria=crit)
    except cv2.error as exc:
        raise InputError(f"{what}: OpenCV calibration failed ({exc.err})") from exc
    per_view = np.array([view_rms(o, p, K, dist, r, t) for o, p, r, t in zip(obj, img, rvecs, tvecs)])
    return Intrinsics(K=np.asarray(K, np.float64), dist=np.asarray(dist, np.float64).ravel(),
                      size=(int(size[0]), int(size[1])), rms=float(rms), per_view_rms=per_view,
                      rvecs=list(rvecs), tvecs=list(tvecs))


def outliers(per_view_rms: NDArray, factor: float = 3.0, min_px: float = 1.0) -> NDArray[np.bool_]:
    """Views whose RMS exceeds ``factor`` x the median and ``min_px`` px."""
    e = np.asarray(per_view_rms, np.float64)
    return (e > factor * np.median(e)) & (e > min_px)


@dataclass
class CameraCalibration:
    """Camera intrinsics plus the bookkeeping of which files were used."""

    intrinsics: Intrinsics
    board: BoardSpec
    files: list[str]
    corners: list[int]
    outlier: NDArray[np.bool_]
    rejected: list[dict]
    flags: int

    def to_json(self) -> dict:
        i = self.intrinsics
        return {"version": 1, "kind": "camera", "image_size": list(i.size), "K": i.K.tolist(),
                "dist": i.dist.tolist(), "rms": i.rms,
                "views": [{"file": f, "rms": float(e), "corners": n, "outlier": bool(o)}
                          for f, e, n, o in zip(self.files, i.per_view_rms, self.corners, self.outlier)],
                "files_used": self.files, "rejected": self.rejected,
                "board": self.board.to_json(), "flags": int(self.flags)}


def white_frame(folder: str | os.PathLike) -> Path:
    """The white frame of a Gray-code capture folder: the second to last image of its
    sequence (patterns, white, black; :func:`~.graycode.sequence_images`)."""
    paths = sequence_images(folder)
    if len(paths) < 6 or len(paths) % 2:
        count = f"{len(paths)} images" if paths else "no images (png, jpg, tif, bmp)"
        raise InputError(f"{folder}: {count}; a capture_* folder is read as a Gray-code sequence "
                         f"(2 per bit, then white and black: an even number >= 6) and its white frame used; "
                         f"rename the folder or pass its board images as files")
    return paths[-2]


def expand_inputs(inputs: Sequence[str | os.PathLike]) -> list[Path]:
    """Files and folders -> image paths. A folder with ``capture_*`` sub-folders (a projector
    capture root) gives the white frame of each (:func:`white_frame`; its other images are not
    used), a ``capture_*`` folder its white frame, any other folder all its images (sorted by
    name)."""
    paths: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir() and any(q.is_dir() for q in p.glob("capture_*")):
            paths += [white_frame(q) for q in capture_folders(p)]
        elif p.is_dir() and p.name.startswith("capture_"):
            paths.append(white_frame(p))
        elif p.is_dir():
            found = list_images(p)
            if not found:
                raise InputError(f"{p}: folder has no images (png, jpg, tif, bmp)")
            paths += found
        elif p.is_file():
            paths.append(p)
        else:
            raise InputError(f"{p}: no such file or folder")
    if not paths:
        raise InputError("no input images given")
    return paths


def detect_views(paths: Sequence[Path], board: BoardSpec, skip_bad: bool = False):
    """Detect the board in every image: ``(used paths, object points, image points, size,
    rejected)``. Images must all have one size; a board that is not found raises unless
    ``skip_bad`` (then the file is listed in ``rejected``)."""
    used, objs, imgs, rejected = [], [], [], []
    size = None
    for p in paths:
        gray = read_gray(p)
        shape = (gray.shape[1], gray.shape[0])
        if size is None:
            size = shape
        elif shape != size:
            raise InputError(f"{p}: size {shape[0]}x{shape[1]} differs from {paths[0]}'s {size[0]}x{size[1]}")
        found = board.detect(to_uint8(gray))
        if found is None:
            reason = f"{board.kind} with {board.cols}x{board.rows} inner corners not found"
            if not skip_bad:
                raise InputError(f"{p}: {reason} (check --board, lighting, focus; or pass --skip-bad)")
            rejected.append({"file": str(p), "reason": reason})
            continue
        used.append(p)
        objs.append(found[0])
        imgs.append(found[1])
    return used, objs, imgs, size, rejected


def calibrate_views(names: Sequence[str], object_points: Sequence[NDArray], image_points: Sequence[NDArray],
                    size: tuple[int, int], board: BoardSpec, flags: int = DEFAULT_FLAGS,
                    drop_outliers: bool = False, outlier_factor: float = 3.0, outlier_px: float = 1.0,
                    rejected: list[dict] | None = None) -> CameraCalibration:
    """Calibrate from detected corners of the views ``names``; flag outlier views (see the
    module docstring) and, with ``drop_outliers``, recalibrate once without them."""
    names, objs, imgs = list(names), list(object_points), list(image_points)
    rejected = list(rejected or [])
    intr = calibrate_points(objs, imgs, size, flags)
    bad = outliers(intr.per_view_rms, outlier_factor, outlier_px)
    if drop_outliers and bad.any():
        rejected += [{"file": n, "reason": f"outlier view: RMS {e:.3f} px"}
                     for n, e, b in zip(names, intr.per_view_rms, bad) if b]
        keep = np.flatnonzero(~bad)
        names, objs, imgs = [names[k] for k in keep], [objs[k] for k in keep], [imgs[k] for k in keep]
        intr = calibrate_points(objs, imgs, size, flags)
        bad = outliers(intr.per_view_rms, outlier_factor, outlier_px)
    return CameraCalibration(intr, board, names, [len(o) for o in objs], bad, rejected, flags)


def calibrate_camera(images: Sequence[str | os.PathLike], board: BoardSpec, flags: int = DEFAULT_FLAGS,
                     drop_outliers: bool = False, outlier_factor: float = 3.0, outlier_px: float = 1.0,
                     skip_bad: bool = False, output: str | os.PathLike | None = None) -> CameraCalibration:
    """Calibrate a camera from board images (files or folders, :func:`expand_inputs`); ``flags``
    are ``cv2.calibrateCamera``'s (:func:`calibration_flags`); a view whose RMS exceeds
    ``outlier_factor`` x the median view RMS and ``outlier_px`` px is flagged, and left out with
    ``drop_outliers``; an image without the board is skipped with ``skip_bad`` (else an error).
    Writes ``output`` JSON when given (atomically, only after success)."""
    paths, objs, imgs, size, rejected = detect_views(expand_inputs(images), board, skip_bad)
    result = calibrate_views([str(p) for p in paths], objs, imgs, size, board, flags, drop_outliers,
                             outlier_factor, outlier_px, rejected)
    if output is not None:
        save_json(output, result.to_json())
    return result


def calibration_flags(fix_k3: bool = True) -> int:
    """``cv2.calibrateCamera`` flags: :data:`DEFAULT_FLAGS` (the k3 radial distortion term kept
    at 0) with ``fix_k3``, else none (k3 estimated too)."""
    return DEFAULT_FLAGS if fix_k3 else 0
