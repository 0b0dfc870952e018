"""White balance and projector black level from a Macbeth ColorChecker (24 patches, 4 x 6).

Wang et al. 2008, section 4.1: the camera's white balance is calibrated with respect to the
projector from a projected white image on a colour chart of known albedos, and the chart is
also used to measure the projector's black level. Inputs are linear HDR images (OpenEXR from
:mod:`glsldiff.calibration.hdr`, all merged with the same camera response).

Finding the patches: ``cv2.mcc`` (``CCheckerDetector``, ``MCC24``) on an 8-bit tone-mapped
rendition of the HDR image gives the central part of each patch; the patch means are then
taken from the linear HDR image. Where detection fails, the chart's four corner points (pixels
of the outer corners of the patch area: the corners of patches 1 dark skin, 6 bluish green,
24 black and 19 white, in that order) give the 4 x 6 grid through a homography; the central
half of every grid cell is sampled.

* white balance: per-channel gains ``g`` with ``g_c * measured_c`` proportional to the
  chart's linear albedo, least squares over the grey patches (or all 24), ``g_G = 1``;
* black level: per patch and channel ``HDR(black) / HDR(white)`` (projected all-black over
  all-white image), mean and standard deviation over the patches (or over the cells of a
  rectangle given instead of the chart).

Command line: ``glsldiff capture white-balance --help`` and ``glsldiff capture black-level --help``
(:func:`white_balance_file`, :func:`black_level_files`).
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from typing import Sequence

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.calibration.common import save_json
from glsldiff.calibration.hdr import read_hdr
from glsldiff.core.errors import InputError
from glsldiff.core.io import tonemap

Array = NDArray[np.float64]

#: X-Rite ColorChecker Classic: the commonly published sRGB (D65) 8-bit values of its
#: patches, in reading order: rows top to bottom, columns left to right (1 dark skin ..
#: 6 bluish green, ..., 19 white .. 24 black). A chart's own data sheet can be passed as
#: ``albedo`` instead.
COLORCHECKER_SRGB8 = np.array([
    [115, 82, 68], [194, 150, 130], [98, 122, 157], [87, 108, 67], [133, 128, 177], [103, 189, 170],
    [214, 126, 44], [80, 91, 166], [193, 90, 99], [94, 60, 108], [157, 188, 64], [224, 163, 46],
    [56, 61, 150], [70, 148, 73], [175, 54, 60], [231, 199, 31], [187, 86, 149], [8, 133, 161],
    [243, 243, 242], [200, 200, 200], [160, 160, 160], [122, 122, 121], [85, 85, 85], [52, 52, 52],
], dtype=np.float64)
NEUTRAL = np.arange(18, 24)  # patches 19..24: white .. black


def srgb_to_linear(v: ArrayLike) -> Array:
    """The sRGB transfer function inverted: encoded values in [0, 1] -> linear."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


#: Linear albedos (reflectance per R, G, B channel) of the 24 patches, ``(24, 3)``.
COLORCHECKER_ALBEDO = srgb_to_linear(COLORCHECKER_SRGB8 / 255.0)


# ----------------------------------------------------------------------------- patches

def detect_chart(hdr: ArrayLike) -> NDArray[np.float64] | None:
    """Patch polygons ``(24, 4, 2)`` (pixels, reading order) found by ``cv2.mcc`` on an 8-bit
    rendition of the linear image ``(rows, cols, 3)``; None when no chart is found."""
    img = np.asarray(hdr, dtype=np.float64)
    top = np.percentile(img, 99.5)
    if not top > 0:
        return None
    bgr = np.ascontiguousarray(tonemap(img, 1.0 / top)[..., ::-1])
    det = cv2.mcc.CCheckerDetector_create()
    det.setColorChartType(cv2.mcc.MCC24)
    if not det.process(bgr, 1):
        return None
    polys = np.asarray(det.getBestColorChecker().getColorCharts(), dtype=np.float64)
    return polys.reshape(24, 4, 2) if polys.size == 24 * 4 * 2 else None


def grid_patches(corners: ArrayLike, fraction: float = 0.5) -> NDArray[np.float64]:
    """Patch polygons ``(24, 4, 2)`` from the 4 outer corners of the patch area (pixels:
    patch 1, 6, 24, 19 corners, i.e. top-left, top-right, bottom-right, bottom-left of the
    chart in reading order): the central ``fraction`` (side) of each of the 4 x 6 cells."""
    c = np.asarray(corners, dtype=np.float64)
    if c.shape not in ((4, 2), (8,)) or not np.all(np.isfinite(c)):
        raise InputError(f"chart corners: expected 4 (x, y) pixel points, got {np.shape(corners)}")
    H = cv2.getPerspectiveTransform(np.float32([[0, 0], [6, 0], [6, 4], [0, 4]]), c.reshape(4, 2).astype(np.float32))
    a, b = 0.5 - fraction / 2, 0.5 + fraction / 2
    r, col = np.divmod(np.arange(24), 6)
    unit = np.array([[a, a], [b, a], [b, b], [a, b]])
    pts = np.stack([col, r], axis=1)[:, None, :] + unit[None]  # (24, 4, 2) in grid units
    return cv2.perspectiveTransform(pts.reshape(-1, 1, 2), H).reshape(24, 4, 2)


def region_means(img: ArrayLike, polygons: ArrayLike) -> Array:
    """Mean ``(n, 3)`` of ``img`` inside each convex polygon ``(n, k, 2)`` (pixels)."""
    im = np.asarray(img, dtype=np.float32)
    out = []
    for poly in np.asarray(polygons, dtype=np.float64):
        mask = np.zeros(im.shape[:2], np.uint8)
        cv2.fillConvexPoly(mask, np.round(poly).astype(np.int32), 1)
        if not mask.any():
            raise InputError(f"chart patch at {np.round(poly.mean(axis=0)).tolist()} px lies outside the "
                             f"{im.shape[1]}x{im.shape[0]} image")
        out.append(cv2.mean(im, mask=mask)[:3])
    return np.asarray(out, dtype=np.float64)


def chart_patches(hdr: ArrayLike, corners: ArrayLike | None = None, name: str = "image") -> tuple[Array, str]:
    """Patch polygons ``(24, 4, 2)`` and how they were found (``"corners"`` when given,
    else ``"mcc"``); InputError naming ``name`` when the chart is not found."""
    if corners is not None:
        return grid_patches(corners), "corners"
    polys = detect_chart(hdr)
    if polys is None:
        raise InputError(f"{name}: no ColorChecker found by cv2.mcc; give the chart's 4 corner points "
                         f"(--corners X1,Y1 X2,Y2 X3,Y3 X4,Y4: patches 1, 6, 24, 19)")
    return polys, "mcc"


def _check_order(means: Array, name: str, how: str) -> None:
    grey = means[NEUTRAL]
    if not np.all(np.diff(grey, axis=0) < 0):
        raise InputError(f"{name}: chart patches 19..24 ({how}) are not a decreasing grey ramp "
                         f"{np.round(grey.mean(axis=1), 6).tolist()}; wrong corner order or not a ColorChecker")


# ----------------------------------------------------------------------------- calibration

@dataclass
class WhiteBalance:
    """Per-channel gains (R, G, B; G = 1), the relative RMS of the fit per channel, the 24
    patch means (linear HDR units) and how the chart was found."""

    gains: Array
    fit_rms: Array
    patch_means: Array
    method: str


def white_balance_from_means(means: ArrayLike, patches: str = "neutral",
                             albedo: ArrayLike = COLORCHECKER_ALBEDO) -> tuple[Array, Array]:
    """Gains ``(3,)`` (green = 1) and relative RMS residual ``(3,)`` from the 24 patch means:
    per channel ``s_c = argmin sum (s albedo - mean)^2`` over the ``"neutral"`` or ``"all"``
    patches, gains ``s_G / s_c``. ``albedo``: linear ``(24, 3)`` patch albedos."""
    if patches not in ("neutral", "all"):
        raise InputError(f"patches={patches!r}; choose 'neutral' or 'all'")
    alb = np.asarray(albedo, dtype=np.float64)
    if alb.shape != (24, 3) or not np.all((alb > 0) & (alb <= 1)):
        raise InputError(f"albedo: expected (24, 3) values in (0, 1], got shape {alb.shape}")
    m = np.asarray(means, dtype=np.float64).reshape(24, 3)
    idx = NEUTRAL if patches == "neutral" else np.arange(24)
    a, y = alb[idx], m[idx]
    s = (a * y).sum(axis=0) / (a * a).sum(axis=0)
    if not np.all(s > 0):
        raise InputError(f"chart patch means {np.round(y, 6).tolist()} are not positive in every channel")
    rms = np.sqrt(np.mean(((y - s * a) / (s * a)) ** 2, axis=0))
    return s[1] / s, rms


def white_balance(hdr: ArrayLike, corners: ArrayLike | None = None, patches: str = "neutral",
                  name: str = "image", albedo: ArrayLike = COLORCHECKER_ALBEDO) -> WhiteBalance:
    """White-balance gains from an HDR image of the chart under a projected white image
    (``corners``: see :func:`grid_patches`; ``name`` for messages)."""
    img = np.asarray(hdr, dtype=np.float64)
    polys, how = chart_patches(img, corners, name)
    means = region_means(img, polys)
    _check_order(means, name, how)
    gains, rms = white_balance_from_means(means, patches, albedo)
    return WhiteBalance(gains, rms, means, how)


@dataclass
class BlackLevel:
    """Projector black level: ``HDR(black) / HDR(white)`` per channel, mean and standard
    deviation over ``count`` regions (chart patches or cells of a rectangle)."""

    mean: Array
    std: Array
    count: int
    method: str


def roi_cells(roi: Sequence[float], cells: int = 4) -> Array:
    """Polygons ``(cells^2, 4, 2)`` tiling the rectangle ``(x, y, width, height)`` (pixels)."""
    x, y, w, h = (float(v) for v in roi)
    if not (w > 0 and h > 0):
        raise InputError(f"roi={list(roi)}: width and height must be positive")
    xs, ys = np.linspace(x, x + w, cells + 1), np.linspace(y, y + h, cells + 1)
    return np.array([[[xs[i], ys[j]], [xs[i + 1], ys[j]], [xs[i + 1], ys[j + 1]], [xs[i], ys[j + 1]]]
                     for j in range(cells) for i in range(cells)])


def black_level(black: ArrayLike, white: ArrayLike, polygons: ArrayLike, method: str = "regions",
                names: tuple[str, str] = ("black image", "white image")) -> BlackLevel:
    """Black level from HDR images under a projected black and white image, averaged inside
    each polygon ``(n, k, 2)`` (pixels) of the same camera view."""
    b, w = np.asarray(black, dtype=np.float64), np.asarray(white, dtype=np.float64)
    if b.shape != w.shape:
        raise InputError(f"{names[0]} {b.shape[:2]} and {names[1]} {w.shape[:2]} differ in size")
    mb, mw = region_means(b, polygons), region_means(w, polygons)
    if not np.all(mw > mb):
        raise InputError(f"{names[1]}: not brighter than {names[0]} in every region and channel; "
                         f"swapped inputs or the projector was off")
    ratio = mb / mw
    return BlackLevel(ratio.mean(axis=0), ratio.std(axis=0), len(ratio), method)


# ----------------------------------------------------------------------------- files

def _jsonable(obj: object) -> dict:
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(obj).items()}


def white_balance_file(image: str | os.PathLike, output: str | os.PathLike, corners: ArrayLike | None = None,
                       patches: str = "neutral") -> WhiteBalance:
    """White-balance gains from the HDR image (OpenEXR) ``image`` of the chart under a projected
    white image, written to the JSON file ``output`` (atomically). ``corners``: the chart's four
    corner pixels ``(4, 2)`` when ``cv2.mcc`` does not find it (:func:`grid_patches`);
    ``patches``: ``"neutral"`` (the 6 grey patches) or ``"all"``."""
    wb = white_balance(read_hdr(image), corners, patches, name=str(image))
    data = {"description": "white-balance gains (R, G, B; G = 1): multiply linear HDR images by them",
            "image": str(image), "patches": patches, **_jsonable(wb)}
    save_json(output, data)
    return wb


def black_level_files(black: str | os.PathLike, white: str | os.PathLike, output: str | os.PathLike,
                      corners: ArrayLike | None = None, roi: Sequence[float] | None = None) -> BlackLevel:
    """Projector black level from HDR images (OpenEXR) under a projected black and white image,
    written to the JSON file ``output`` (atomically): over the chart's patches (found by
    ``cv2.mcc``, or from ``corners``, pixels, as in :func:`white_balance_file`), or over the
    cells of the rectangle ``roi = (x, y, width, height)`` pixels instead of the chart."""
    black_img, white_img = read_hdr(black), read_hdr(white)
    if roi:
        polys, how = roi_cells(roi), "roi"
    else:
        polys, how = chart_patches(white_img, corners, str(white))
        _check_order(region_means(white_img, polys), str(white), how)
    bl = black_level(black_img, white_img, polys, how, (str(black), str(white)))
    data = {"description": "projector black level: HDR(black) / HDR(white) per channel (R, G, B), "
                           "mean and standard deviation over the regions",
            "black_image": str(black), "white_image": str(white), **_jsonable(bl)}
    save_json(output, data)
    return bl
