"""Projector calibration with Gray-code structured light (Moreno & Taubin 2012).

For each pose of a planar board, the projector shows the Gray-code sequence
(:mod:`.graycode`: column and row bits each followed by its inverse, then white and black) and
the camera captures one image per pattern. Per pose:

1. decode, per camera pixel, the projector column and row (vectorised; shadow mask from
   white - black, per-bit contrast threshold);
2. find the board corners in the white image;
3. for every corner, fit a local homography camera -> projector (``cv2.findHomography``,
   RANSAC) to the decoded pixels of a ``window x window`` px neighbourhood and map the corner
   through it: the corner's projector coordinates (px).

Then the camera and the projector are calibrated on their own (Zhang, ``cv2.calibrateCamera``)
and the stereo extrinsics found with ``cv2.stereoCalibrate(..., CALIB_FIX_INTRINSIC)``.

Capture folder layout: ``FOLDER/capture_*/`` one sub-folder per pose, each with exactly
:func:`~.graycode.sequence_length` images (``*.png``/``*.jpg``... sorted by name, in pattern
order, white and black last). kamino410/procam-calibration's layout is read as it is:
``capture_*/graycode_00.png ...`` (only the ``graycode_*`` images of a folder count when it has
any, :func:`~.graycode.sequence_images`), and its ``camera_config.json`` is accepted for
``--camera``. ``glsldiff capture patterns`` writes the projector images and ``glsldiff capture
calibrate`` calibrates; ``--step N`` (both steps, procam-calibration's ``graycode_step``) shows
each code pixel as an ``N x N`` block, see :mod:`.graycode` for how codes map back to projector
pixels.

``rig.json`` (written atomically by :func:`calibrate_folder`)::

    {"version": 1, "kind": "camera-projector",
     "camera":    {"image_size": [cols, rows], "K": 3x3, "dist": [k1, k2, p1, p2, k3],
                   "rms": px, "per_view_rms": [px, ...]},
     "projector": {same keys, for the projector image},
     "stereo":    {"R": 3x3, "T": [mm x3],      # X_projector = R X_camera + T
                   "E": 3x3, "F": 3x3, "rms": px, "per_view_rms": [[camera px, projector px], ...],
                   "baseline_mm": |T|},
     "poses": [{"folder": path, "corners": n, "decoded_fraction": of lit pixels,
                "camera_points": [[u, v], ...], "projector_points": [[u, v], ...]}, ...],
     "rejected": [{"folder": path, "reason": text}, ...],
     "board": {...},                             # as in camera.json
     "settings": {"window_px", "shadow_threshold", "bit_threshold",   # 8-bit grey levels
                  "min_fraction", "ransac_px", "graycode_step",       # step: projector px per code
                  "flags"}}                                           # cv2.calibrateCamera flags

Errors a user can cause raise :class:`~glsldiff.core.errors.InputError` naming the folder or file.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from glsldiff.calibration.camera import (DEFAULT_FLAGS, MAX_ITERATIONS, BoardSpec, Intrinsics, calibrate_points,
                                         to_uint8)
from glsldiff.calibration.common import save_json
from glsldiff.calibration.graycode import (Decoded, bit_counts, capture_folders, code_size, decode,
                                           read_stack, sequence_images, sequence_length)
from glsldiff.core.errors import InputError

Array = NDArray[np.float64]


#: Largest fraction of lit, reliably decoded pixels whose Gray code may lie beyond the stated
#: projector size (a few from defocus at the frame's edge); more means a wrong or swapped size.
MAX_OUT_OF_RANGE = 0.02
#: A pose keeps its corners that decoded; it is refused with fewer than this many, or fewer
#: than this fraction of the board's corners.
MIN_CORNERS = 6
MIN_CORNER_FRACTION = 0.5
#: Largest RMS residual (projector px) of a pose's corners from one homography: lens distortion
#: stays below it; a torn mapping (pattern/inverse swapped, bad decoding) does not.
MAX_PLANE_RESIDUAL_PX = 10.0
MAX_PLANE_RESIDUAL_FRACTION = 0.02


@dataclass
class DecodeSettings:
    """Decoding and corner-mapping parameters: window side (camera px), white - black shadow
    threshold and per-bit contrast threshold (8-bit grey levels), minimum fraction of decoded
    pixels in a corner's window, RANSAC threshold (code px: ``ransac_px * step`` projector px,
    as codes are ``step`` px apart), Gray-code ``step`` (projector px per code pixel)."""

    window: int = 47
    shadow_threshold: float = 20.0
    bit_threshold: float = 3.0
    min_fraction: float = 0.2
    ransac_px: float = 2.0
    step: int = 1

    def to_json(self) -> dict:
        return {"window_px": self.window, "shadow_threshold": self.shadow_threshold,
                "bit_threshold": self.bit_threshold, "min_fraction": self.min_fraction,
                "ransac_px": self.ransac_px, "graycode_step": self.step}


@dataclass
class PoseCorners:
    """One pose: board points (mm) and their camera and projector coordinates (px)."""

    folder: str
    object_points: NDArray[np.float32]
    camera_points: NDArray[np.float32]
    projector_points: NDArray[np.float32]
    image_size: tuple[int, int]
    decoded_fraction: float
    dropped: list[int] = field(default_factory=list)  # board corners without a decoded window
    # every corner the camera found, the dropped ones too (the camera's own calibration uses them)
    all_object_points: NDArray[np.float32] | None = None
    all_camera_points: NDArray[np.float32] | None = None

    @property
    def camera_view(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Board and camera points for the camera's calibration: every corner found."""
        if self.all_object_points is None or self.all_camera_points is None:
            return self.object_points, self.camera_points
        return self.all_object_points, self.all_camera_points

    def to_json(self) -> dict:
        return {"folder": self.folder, "corners": len(self.object_points), "dropped_corners": self.dropped,
                "decoded_fraction": self.decoded_fraction,
                "camera_points": np.round(self.camera_points, 4).tolist(),
                "projector_points": np.round(self.projector_points, 4).tolist()}


def read_sequence(folder: str | Path, projector_size: tuple[int, int], step: int = 1) -> NDArray[np.float32]:
    """The captured sequence ``(n, rows, cols)`` of one pose (:func:`~.graycode.sequence_images`),
    checking the image count against the projector size and Gray-code ``step``."""
    paths = sequence_images(folder)
    n = sequence_length(projector_size, step)
    if len(paths) != n:
        nc, nr = bit_counts(code_size(projector_size, step))
        at = f" at --step {step}" if step != 1 else ""
        fits = [s for s in range(1, min(projector_size)) if sequence_length(projector_size, s) == len(paths)]
        hint = f"; {len(paths)} images fit --step {fits[0]}" if fits else ""
        raise InputError(f"{folder}: {len(paths)} images, expected {n} for a {projector_size[0]}x{projector_size[1]} "
                         f"projector{at} (2 x ({nc} column + {nr} row Gray bits) + white + black){hint}")
    return read_stack(paths, str(folder))


def corner_to_projector(decoded: Decoded, corner: NDArray, settings: DecodeSettings) -> NDArray | None:
    """Projector coordinates (px) of the camera point ``corner`` (px) from a local homography
    fitted to the decoded pixels of its window; None when too few pixels decoded."""
    half = settings.window // 2
    rows, cols = decoded.valid.shape
    cx, cy = int(round(float(corner[0]))), int(round(float(corner[1])))
    x0, x1, y0, y1 = max(cx - half, 0), min(cx + half + 1, cols), max(cy - half, 0), min(cy + half + 1, rows)
    ys, xs = np.nonzero(decoded.valid[y0:y1, x0:x1])
    if xs.size < max(settings.min_fraction * settings.window ** 2, 8):
        return None
    ys, xs = ys + y0, xs + x0
    src = np.stack([xs, ys], axis=1).astype(np.float64)
    dst = np.stack([decoded.col[ys, xs], decoded.row[ys, xs]], axis=1).astype(np.float64)
    H, _ = cv2.findHomography(src, dst, cv2.RANSAC, settings.ransac_px * settings.step)
    if H is None:
        return None
    return cv2.perspectiveTransform(np.asarray(corner, np.float64).reshape(1, 1, 2), H).reshape(2)


def process_capture(folder: str | Path, board: BoardSpec, projector_size: tuple[int, int],
                    settings: DecodeSettings | None = None) -> PoseCorners:
    """Decode one pose and map its board corners into the projector (steps 1-3 above)."""
    settings = settings or DecodeSettings()
    stack = read_sequence(folder, projector_size, settings.step)
    decoded = decode(stack, projector_size, settings.shadow_threshold, settings.bit_threshold, settings.step)
    if decoded.out_of_range > MAX_OUT_OF_RANGE:
        w, h = projector_size
        raise InputError(f"{folder}: {decoded.out_of_range:.0%} of the lit pixels decode beyond the stated "
                         f"{w}x{h} projector (columns up to {decoded.col_max}, rows up to {decoded.row_max}): "
                         f"the projector size is wrong or swapped (--projector takes COLSxROWS, e.g. "
                         f"{max(w, h)}x{min(w, h)} for a landscape projector), or this pose's pattern and "
                         "inverse images are in the wrong order (each pair: pattern, then inverse)")
    found = board.detect(to_uint8(stack[-2]))
    if found is None:
        raise InputError(f"{folder}: {board.kind} with {board.cols}x{board.rows} inner corners not found in the "
                         f"white image ({sequence_images(folder)[-2].name}); check --board and the lighting")
    obj, cam = found
    proj = [corner_to_projector(decoded, c, settings) for c in cam]
    missing = [i for i, p in enumerate(proj) if p is None]
    keep = [i for i, p in enumerate(proj) if p is not None]
    if len(keep) < max(MIN_CORNERS, MIN_CORNER_FRACTION * len(proj)):  # a pose that lost most corners
        raise InputError(f"{folder}: corners {missing[:10]}{'...' if len(missing) > 10 else ''} have fewer than "
                         f"{settings.min_fraction:.0%} decoded pixels in their {settings.window} px window, "
                         f"{len(keep)} of {len(proj)} corners left (decoded {decoded.fraction:.1%} of lit "
                         f"pixels; not lit by the projector, or lower --shadow-threshold/--bit-threshold)")
    pose = PoseCorners(str(folder), np.asarray(obj)[keep], np.asarray(cam)[keep],
                       np.asarray([proj[i] for i in keep], np.float32),
                       (stack.shape[2], stack.shape[1]), decoded.fraction, dropped=missing,
                       all_object_points=np.asarray(obj), all_camera_points=np.asarray(cam))
    rms = plane_residual(pose)
    limit = max(MAX_PLANE_RESIDUAL_PX, MAX_PLANE_RESIDUAL_FRACTION * max(projector_size))
    if rms > limit:
        raise InputError(f"{folder}: the decoded projector coordinates of the board's corners do not map a "
                         f"plane (homography residual {rms:.1f} px > {limit:.0f} px): this pose's pattern and "
                         "inverse images are probably in the wrong order (each pair: pattern, then inverse), "
                         "or the decoding failed (check the lighting and --bit-threshold)")
    return pose


def plane_residual(pose: PoseCorners) -> float:
    """RMS distance (projector px) of the pose's projector corners from the best homography of
    its camera corners: the board is a plane, so a sound decoding leaves lens distortion
    (a few px at most); a pose with pattern and inverse swapped decodes codes with their top
    bit flipped and tears the board in two (hundreds of px)."""
    cp, pp, H = _board_homography(pose)
    if H is None:
        return float("inf")
    fit = cv2.perspectiveTransform(cp.reshape(-1, 1, 2), H).reshape(-1, 2)
    return float(np.sqrt(((fit - pp) ** 2).sum(axis=1).mean()))


def _board_homography(pose: PoseCorners) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray | None]:
    """The pose's camera and projector corners ``(N, 2)`` and the least-squares homography from
    the first to the second (None where there is none)."""
    cp = pose.camera_points.reshape(-1, 2).astype(np.float64)
    pp = pose.projector_points.reshape(-1, 2).astype(np.float64)
    return cp, pp, cv2.findHomography(cp, pp, 0)[0]


def plane_orientation(pose: PoseCorners) -> int:
    """+1 or -1: whether the board's camera -> projector homography keeps or mirrors its
    orientation (the sign of its Jacobian at the board's centre). Camera and projector see the
    board's same face, so every pose of a rig has the same sign; a pose whose pattern and inverse
    are swapped for the top column (or row) bit decodes the board mirrored (a Gray code with its
    top bit flipped counts backwards), which a plane fit cannot see."""
    cp, _, H = _board_homography(pose)
    if H is None:
        return 0
    x, y = cp.mean(axis=0)
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    u, v = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w, (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w
    J = np.array([[H[0, 0] - u * H[2, 0], H[0, 1] - u * H[2, 1]], [H[1, 0] - v * H[2, 0], H[1, 1] - v * H[2, 1]]]) / w
    return int(np.sign(np.linalg.det(J)))


#: A pose whose plane residual is this many times the median of the rig's poses (and at least
#: :data:`OUTLIER_MIN_PX`) is refused: one swapped pair of a middle bit tears the board by tens
#: of px where sound poses fit within a fraction of a pixel.
OUTLIER_FACTOR = 20.0
OUTLIER_MIN_PX = 2.0


def inconsistent_poses(poses: Sequence[PoseCorners]) -> dict[str, str]:
    """Poses that disagree with the rest of the rig, ``{folder: reason}``: a mirrored board
    (:func:`plane_orientation` against the majority) or a plane residual far above the others'
    (:data:`OUTLIER_FACTOR`). Both mean a pattern/inverse pair in the wrong order for one bit."""
    bad: dict[str, str] = {}
    signs = [plane_orientation(p) for p in poses]
    if len(poses) >= 2:
        majority = 1 if signs.count(1) >= signs.count(-1) else -1
        for p, s in zip(poses, signs):
            if s != majority:
                bad[p.folder] = (f"{p.folder}: the board decodes mirrored in the projector against the other "
                                 f"{signs.count(majority)} poses: the pattern and inverse images of the top column or "
                                 "row bit are probably in the wrong order (each pair: pattern, then inverse)")
    res = [plane_residual(p) for p in poses]
    for k, (p, r) in enumerate(zip(poses, res)):
        others = [x for j, x in enumerate(res) if j != k]
        if others and p.folder not in bad and r > max(OUTLIER_MIN_PX, OUTLIER_FACTOR * float(np.median(others))):
            bad[p.folder] = (f"{p.folder}: the board's decoded projector corners leave a plane by {r:.1f} px RMS where "
                             f"the other poses leave {float(np.median(others)):.2f} px: one pattern/inverse pair is "
                             "probably in the wrong order (each pair: pattern, then inverse), or the decoding failed")
    return bad


@dataclass
class RigCalibration:
    """Camera and projector intrinsics and the camera -> projector extrinsics."""

    camera: Intrinsics
    projector: Intrinsics
    R: Array  # X_projector = R X_camera + T
    T: Array  # mm
    E: Array
    F: Array
    stereo_rms: float  # px, over the camera and projector points
    stereo_per_view: Array  # (poses, 2) px: camera, projector
    poses: list[PoseCorners]
    rejected: list[dict] = field(default_factory=list)

    @property
    def baseline(self) -> float:
        """Distance between the camera and projector centres, mm."""
        return float(np.linalg.norm(self.T))

    def to_json(self, board: BoardSpec, settings: DecodeSettings, flags: int) -> dict:
        return {"version": 1, "kind": "camera-projector", "camera": self.camera.to_json(),
                "projector": self.projector.to_json(),
                "stereo": {"R": self.R.tolist(), "T": self.T.ravel().tolist(), "E": self.E.tolist(),
                           "F": self.F.tolist(), "rms": self.stereo_rms,
                           "per_view_rms": self.stereo_per_view.tolist(), "baseline_mm": self.baseline},
                "poses": [p.to_json() for p in self.poses], "rejected": self.rejected,
                "board": board.to_json(), "settings": {**settings.to_json(), "flags": int(flags)}}


def calibrate_rig(poses: Sequence[PoseCorners], projector_size: tuple[int, int],
                  flags: int = DEFAULT_FLAGS, camera: Intrinsics | None = None) -> RigCalibration:
    """Camera, projector and stereo calibration from per-pose corners; with ``camera`` (e.g.
    :func:`~glsldiff.calibration.camera.load_intrinsics`) the camera is not re-calibrated."""
    if not poses:
        raise InputError("no usable poses (--skip-bad: each pose's reason is in the rig's 'rejected')")
    sizes = {p.image_size for p in poses}
    if len(sizes) > 1:
        raise InputError("camera images have different sizes across poses: "
                         + ", ".join(f"{p.folder}: {p.image_size[0]}x{p.image_size[1]}" for p in poses))
    obj = [p.object_points for p in poses]
    if camera is None:      # every corner the camera found, also those the projector's decoding lost
        cam = calibrate_points([p.camera_view[0] for p in poses], [p.camera_view[1] for p in poses],
                               poses[0].image_size, flags, "camera")
    elif camera.size is None:  # a file that does not state it (procam-calibration's camera_config.json)
        cam = replace(camera, size=tuple(poses[0].image_size))
    elif tuple(camera.size) != tuple(poses[0].image_size):
        raise InputError(f"--camera: its image size {camera.size[0]}x{camera.size[1]} differs from the captures' "
                         f"{poses[0].image_size[0]}x{poses[0].image_size[1]}; calibrate the camera at this "
                         "resolution or leave --camera out")
    else:
        cam = camera
    proj = calibrate_points(obj, [p.projector_points for p in poses], projector_size, flags, "projector")
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, MAX_ITERATIONS, 1e-10)  # see camera.py
    out = cv2.stereoCalibrateExtended(
        [o.reshape(-1, 1, 3) for o in obj], [p.camera_points.reshape(-1, 1, 2) for p in poses],
        [p.projector_points.reshape(-1, 1, 2) for p in poses], cam.K, cam.dist, proj.K, proj.dist,
        cam.size, None, None, flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    rms, _, _, _, _, R, T, E, F, _, _, per_view = out
    return RigCalibration(cam, proj, np.asarray(R), np.asarray(T).ravel(), np.asarray(E), np.asarray(F),
                          float(rms), np.asarray(per_view).reshape(-1, 2), list(poses))


def calibrate_folder(folder: str | Path, board: BoardSpec, projector_size: tuple[int, int],
                     settings: DecodeSettings | None = None, flags: int = DEFAULT_FLAGS,
                     skip_bad: bool = False, output: str | Path | None = None,
                     camera: Intrinsics | None = None) -> RigCalibration:
    """Calibrate from ``folder/capture_*``; a pose that fails raises unless ``skip_bad``
    (then it is listed in ``rejected``). Writes ``output`` JSON only after success."""
    settings = settings or DecodeSettings()
    code_size(projector_size, settings.step)   # a bad step would otherwise fail (or, skip_bad, reject) every pose
    poses, rejected = [], []
    for sub in capture_folders(folder):
        try:
            poses.append(process_capture(sub, board, projector_size, settings))
        except InputError as exc:
            if not skip_bad:
                raise
            rejected.append({"folder": str(sub), "reason": str(exc)})
    bad = inconsistent_poses(poses)
    if bad and not skip_bad:
        raise InputError(next(iter(bad.values())) + (f" (and {len(bad) - 1} more poses)" if len(bad) > 1 else "")
                         + "; fix the pose or pass --skip-bad to leave it out")
    rejected += [{"folder": p.folder, "reason": bad[p.folder]} for p in poses if p.folder in bad]
    poses = [p for p in poses if p.folder not in bad]
    if not poses and rejected:
        raise InputError(f"no usable poses: all {len(rejected)} were rejected; the first: {rejected[0]['reason']}")
    rig = calibrate_rig(poses, projector_size, flags, camera)
    rig.rejected = rejected
    if output is not None:
        save_json(output, rig.to_json(board, settings, flags))
    return rig
