"""Synthetic radiometric calibration data from the simulated camera and projector (tests, demos).

* :func:`ramp_radiance`: a log ramp of radiance along the columns (wide dynamic range);
* :func:`chart_radiance`: a ColorChecker (24 patches, 4 x 6, on a black card) seen in
  perspective, lit by a projector pattern value with a colour cast;
* :func:`capture_bracket` / :func:`write_bracket`: an exposure bracket of
  :class:`~glsldiff.calibration.simcam.SimCamera` captures, written as PNG with an
  ``exposures.json`` / ``exposures.csv`` sidecar or EXIF ``ExposureTime``;
* :class:`DarkOffsetCamera` / :func:`noisy_camera` / :func:`black_frame`: a camera with a
  per-channel dark offset and strong read noise, whose black frames reach the 18-21 levels of
  real brackets' noise floor, and its lens-capped frame.

Radiance is relative (camera ``gain`` maps radiance x seconds to the sensor range).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence, cast

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational

from glsldiff.calibration.color import COLORCHECKER_ALBEDO
from glsldiff.calibration.simcam import SimCamera, SimProjector

Array = NDArray[np.float64]
EXPOSURES = (1 / 30, 1 / 8, 1 / 2, 2.0, 8.0)  # seconds
CAST = (1.0, 0.9, 0.7)  # projector white x camera channel sensitivity, R G B
CHART_CORNERS = ((150.0, 128.0), (500.0, 113.0), (508.0, 356.0), (139.0, 341.0))  # patch area, px


def camera(size: tuple[int, int], gain: float, vignetting: float = 0.1, gamma: float = 2.2,
           cls: type[SimCamera] = SimCamera, **extra: Any) -> SimCamera:
    """A simulated 8-bit camera of ``size = (cols, rows)`` (intrinsics irrelevant here), of
    class ``cls`` with its further fields ``extra``."""
    w, h = size
    K = np.array([[w, 0.0, (w - 1) / 2], [0.0, w, (h - 1) / 2], [0.0, 0.0, 1.0]])
    return cls(K, (w, h), gain=gain, gamma=gamma, vignetting=vignetting, **extra)


@dataclass
class DarkOffsetCamera(SimCamera):
    """A :class:`~glsldiff.calibration.simcam.SimCamera` whose every exposure adds ``dark``
    electrons per channel (R, G, B; a black level left in the images, or dark signal), with
    their shot noise, before read noise and the response: the noise floor real 8-bit brackets
    show in their darkest pixels."""

    dark: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0))

    def capture(self, radiance: ArrayLike, seconds: float, rng: np.random.Generator | int | None = None) -> NDArray:
        """Pixel values of a radiance image ``(rows, cols, 3)`` exposed for ``seconds``."""
        L = np.asarray(radiance, dtype=np.float64)
        per_radiance = self.full_well * self.gain * seconds * self.vignette()[..., None]  # electrons per unit
        return super().capture(L + np.asarray(self.dark, dtype=np.float64) / per_radiance, seconds, rng)


#: Dark offset (electrons, R G B) and read noise (electrons) of :func:`noisy_camera`: black
#: frames at 99.9th percentile 17 / 20 / 18 levels (maximum 19-21) with gamma 2.2, full well 20000.
NOISY_DARK, NOISY_READ_NOISE = (25.0, 40.0, 30.0), 8.0


def noisy_camera(size: tuple[int, int], gain: float, dark: Sequence[float] = NOISY_DARK,
                 read_noise: float = NOISY_READ_NOISE, vignetting: float = 0.1) -> DarkOffsetCamera:
    """A simulated 8-bit gamma-2.2 camera like :func:`camera` with a dark offset ``dark``
    (electrons, R G B) and ``read_noise`` electrons."""
    return cast(DarkOffsetCamera, camera(size, gain, vignetting, cls=DarkOffsetCamera, read_noise=read_noise,
                                         dark=tuple(float(d) for d in dark)))


def black_frame(cam: SimCamera, seconds: float = EXPOSURES[-1], seed: int = 0) -> NDArray[np.uint8]:
    """The camera's lens-capped frame (RGB) at ``seconds`` (default the longest exposure)."""
    w, h = cam.size
    return cam.capture(np.zeros((h, w, 3)), seconds, np.random.default_rng(seed))


def projector(black: float = 0.01) -> SimProjector:
    """A simulated projector; only its ``emitted`` (gamma, black level) is used here."""
    return SimProjector(np.eye(3), (1, 1), black=black)


def true_inverse_response(cam: SimCamera) -> Array:
    """The camera's true inverse response at pixel values 0..255, ``(256,)``."""
    return (np.arange(256) / 255.0) ** cam.gamma


def ramp_radiance(shape: tuple[int, int] = (32, 256), lo: float = 1e-4, hi: float = 1e3,
                  color: Sequence[float] = (1.0, 1.0, 1.0)) -> Array:
    """``(rows, cols, 3)`` radiance growing geometrically from ``lo`` (first column) to
    ``hi`` (last column), times per-channel ``color``."""
    rows, cols = shape
    ramp = np.geomspace(lo, hi, cols)
    return np.broadcast_to(ramp[None, :, None] * np.asarray(color, dtype=np.float64), (rows, cols, 3)).copy()


def chart_radiance(size: tuple[int, int] = (640, 480), pattern: float = 1.0, proj: SimProjector | None = None,
                   cast: Sequence[float] = CAST, corners: ArrayLike = CHART_CORNERS,
                   background: float = 0.15, card: float = 0.02, supersample: int = 3) -> Array:
    """``(rows, cols, 3)`` radiance of a ColorChecker whose patch area has the outer corners
    ``corners`` (px; patches 1, 6, 24, 19) on a ``background`` of that albedo, lit by the
    projector showing the uniform value ``pattern`` (0 black .. 1 white) with colour ``cast``.
    Layout: patch side 1, gap 0.25, card border 0.5 around the patch area (patch units)."""
    proj = proj or projector()
    s, patch, gap, border = supersample, 40, 10, 20  # pixels of the flat (supersampled) chart
    pw, ph = 6 * patch + 5 * gap, 4 * patch + 3 * gap
    flat = np.full(((ph + 2 * border) * s, (pw + 2 * border) * s, 3), card, np.float32)
    for k, albedo in enumerate(COLORCHECKER_ALBEDO):
        r, c = divmod(k, 6)
        y, x = (border + r * (patch + gap)) * s, (border + c * (patch + gap)) * s
        flat[y:y + patch * s, x:x + patch * s] = albedo
    src = np.float32([[border, border], [border + pw, border], [border + pw, border + ph], [border, border + ph]]) * s
    H = cv2.getPerspectiveTransform(src, np.float32(corners) * s)
    w, h = size
    big = cv2.warpPerspective(flat, H, (w * s, h * s), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=(background,) * 3)
    albedo = cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64)
    return albedo * np.asarray(cast, dtype=np.float64) * proj.emitted(np.float64(pattern))


def capture_bracket(cam: SimCamera, radiance: ArrayLike, times: Sequence[float] = EXPOSURES,
                    seed: int = 0) -> list[NDArray[np.uint8]]:
    """8-bit RGB captures of ``radiance`` at each exposure time (seconds)."""
    rng = np.random.default_rng(seed)
    return [cam.capture(radiance, t, rng) for t in times]


def write_bracket(folder: str | os.PathLike, images: Sequence[NDArray[np.uint8]], times: Sequence[float],
                  sidecar: str = "json") -> Path:
    """Write ``img_XX.png`` and the exposure times as ``exposures.json`` (``"json"``),
    ``exposures.csv`` (``"csv"``) or EXIF ``ExposureTime`` in each PNG (``"exif"``)."""
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    names = [f"img_{k:02d}.png" for k in range(len(images))]
    for name, img, t in zip(names, images, times):
        if sidecar == "exif":
            exif = Image.Exif()
            exif[ExifTags.IFD.Exif] = {ExifTags.Base.ExposureTime: IFDRational(float(t))}
            Image.fromarray(img, "RGB").save(out / name, exif=exif)
        elif not cv2.imwrite(str(out / name), np.ascontiguousarray(img[..., ::-1])):
            raise OSError(f"cannot write {out / name}")
    if sidecar == "json":
        (out / "exposures.json").write_text(json.dumps(dict(zip(names, map(float, times))), indent=1))
    elif sidecar == "csv":
        (out / "exposures.csv").write_text("file,seconds\n" + "".join(f"{n},{t!r}\n" for n, t in zip(names, times)))
    elif sidecar != "exif":
        raise ValueError(f"sidecar={sidecar!r}; choose 'json', 'csv' or 'exif'")
    return out
