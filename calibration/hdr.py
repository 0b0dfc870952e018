"""Camera response (Debevec and Malik 1997) and HDR merging of exposure brackets, with OpenCV.

A *bracket* is one folder of 8-bit images of a static scene taken with different exposure
times, plus the times: a sidecar file (``exposures.json`` ``{"img_00.png": 0.0333, ...}``,
or ``exposures.csv`` / ``exposures.txt`` with two columns ``file, seconds``, or one column of
seconds in the images' file-name order; seconds may be written ``1/30``) or, without a
sidecar, each image's EXIF ``ExposureTime``. Images are read
with OpenCV and kept as RGB ``(rows, cols, 3)`` uint8 (grey images are expanded to three
equal channels, an alpha channel is dropped). OpenCV's Debevec calibration and merge accept
8-bit images only: a 16-bit image is refused with an error (rescaling it to 8 bits would
throw away exactly what a 16-bit camera measures).

Units: the *response* is OpenCV's inverse camera response, ``(256, 3)`` float (columns R, G,
B): the relative sensor exposure (irradiance x seconds, arbitrary units) that produces each
pixel value. Debevec-Malik fixes each channel's scale separately (OpenCV: ``response[128] =
1``, one noisy point); :func:`calibrate_response` rescales each channel so that the geometric
mean of the response over the trusted pixel values ``LO..HI`` is 1, so equal pixel values mean
equal exposure on average in every channel. A merged image is linear relative radiance
(response units per second). Its colour balance follows that per-channel normalisation, which
is why white-balance gains (:mod:`glsldiff.calibration.color`) must be computed with the same
response as the images they correct.

Response file (JSON)::

    {"format": "glsldiff-camera-response", "version": 1, "channels": ["R", "G", "B"],
     "description": "...", "response": [[r, g, b], ...  256 rows, pixel values 0..255]}

Any positive ``(256, 3)`` table is accepted on reading (e.g. OpenCV's own normalisation).

Noise floor: pixel values below ``lo`` carry no weight in the merge. ``lo`` is per channel
and, unless given, measured from a *black frame*: an image of the bracket's size taken with the
lens capped (or the scene unlit) at the bracket's longest exposure, either named ``black.*`` in
the bracket folder (e.g. ``black.png``; it is then not one of the bracket's images and needs no
exposure time) or passed as ``--black FILE``. The floor is the 99.9th percentile of each
channel of the black frame, rounded up, plus 3 levels (:func:`noise_floor`): at the
percentile itself a black pixel still passes once in 1000 per exposure (~0.5 % over a
5-exposure bracket), and a dark pixel whose little signal the noise lifts just over the floor
is read many times too bright; the margin keeps both out. On the simulated camera of
:func:`~.synth_radiometric.noisy_camera` (black frame 17 / 20 / 18 at the 99.9th percentile)
the dark pixels off by more than a factor 2 fall from 0.7-0.9 % with a cutoff of 20 to
0.05-0.07 % (0.15-0.22 % with a margin of 2). Without a black frame the floor is estimated
from the bracket's shortest exposure (:func:`bracket_noise_floor`: 23 / 24 / 23 there, dark
speckle <= 0.01 % per channel against 1.9 % in green with the fixed 20), or, where that
exposure has too few signal-free pixels, ``lo`` is :data:`LO` = 20.
OpenCV's Debevec merge weighs the remaining values with a fixed triangle (``cv2.MergeDebevec``
takes no per-pixel weights, nor does ``cv2.MergeRobertson``), so the floor is where the sensor
noise enters the merge.

Command line: ``glsldiff capture response --help`` and ``glsldiff capture merge --help``
(:func:`response_from_folders`, :func:`merge_folder`). Reading, the response and the merge stay
in one module: they share the bracket and response formats documented here.
"""
from __future__ import annotations

import csv
import json
import math
import os
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from PIL import ExifTags, Image, UnidentifiedImageError

from glsldiff.core.errors import InputError
from glsldiff.core.io import LDR_SUFFIXES, atomic_path, read_image, write_exr

Array = NDArray[np.float64]
SIDECARS = ("exposures.json", "exposures.csv", "exposures.txt")
RESPONSE_FORMAT = "glsldiff-camera-response"
LO, HI = 20, 235  # trusted pixel values: outside [LO, HI] noise, quantisation or clipping dominate
BLACK_STEM = "black"  # a bracket folder's black frame: black.png, black.jpg, ... (not a bracket image)
NOISE_PERCENTILE, NOISE_MARGIN = 99.9, 3  # noise floor = ceil(99.9th percentile of the black frame) + 3


@dataclass(frozen=True)
class Bracket:
    """One exposure bracket: RGB uint8 images ``(rows, cols, 3)``, their exposure times
    (seconds, ascending) and source files (for messages; ``bracket/image k`` in memory), and
    optionally a black frame (RGB uint8, same size) and its file."""

    images: tuple[NDArray[np.uint8], ...]
    times: Array
    files: tuple[Path, ...]
    black: NDArray[np.uint8] | None = None
    black_file: Path | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.images[0].shape[:2]


def make_bracket(images: Sequence[ArrayLike], times: Sequence[float],
                 files: Sequence[str | os.PathLike] | None = None, black: ArrayLike | None = None,
                 black_file: str | os.PathLike | None = None) -> Bracket:
    """Validate and sort (by time) a bracket: 8-bit RGB images of one size, at least two
    distinct positive exposure times (seconds); ``black`` an optional black frame of that size
    (see the module docstring), ``black_file`` its name in messages."""
    names = ([Path(f) for f in files] if files is not None
             else [Path("bracket", f"image {k}") for k in range(len(images))])
    if not (len(images) == len(times) == len(names)):
        raise InputError(f"bracket: {len(images)} images, {len(times)} exposure times and {len(names)} names")
    imgs = []
    for img, name in zip(images, names):
        img = np.asarray(img)
        if img.dtype != np.uint8:
            raise InputError(f"{name}: {img.dtype} image; OpenCV's Debevec response and merge need 8-bit "
                             f"images (convert the camera output to 8-bit RGB)")
        if img.ndim != 3 or img.shape[2] != 3 or img.size == 0:
            raise InputError(f"{name}: expected an (rows, cols, 3) RGB image, got shape {img.shape}")
        if imgs and img.shape != imgs[0].shape:
            raise InputError(f"{name}: image size {img.shape[1]}x{img.shape[0]} differs from "
                             f"{names[0]} ({imgs[0].shape[1]}x{imgs[0].shape[0]}); a bracket needs equal sizes")
        imgs.append(np.ascontiguousarray(img))
    t = np.asarray(times, dtype=np.float64)
    for ti, name in zip(t, names):
        if not (np.isfinite(ti) and ti > 0):
            raise InputError(f"{name}: exposure time {ti!r} s must be a positive number of seconds")
    if len(np.unique(t)) < 2:
        where = names[0].parent if names else "bracket"
        raise InputError(f"{where}: {len(imgs)} image(s) with {len(np.unique(t))} distinct exposure time(s); "
                         f"an HDR bracket needs at least two different exposures")
    order = np.argsort(t, kind="stable")
    means = np.array([imgs[k].mean() for k in order])
    if np.ptp(means) > 1.0 and np.corrcoef(np.log(t[order]), means)[0, 1] < 0:
        where = names[0].parent if names else "bracket"
        raise InputError(f"{where}: the images get darker as the exposure time grows (mean level "
                         f"{means[0]:.0f} at {t[order][0]:.4g} s, {means[-1]:.0f} at {t[order][-1]:.4g} s): the "
                         "exposure times are probably inverted (listed in reverse order, or given as 1/t)")
    blk, blk_name = None, None
    if black is not None:
        blk_name = Path(black_file) if black_file is not None else Path("bracket", "black frame")
        blk = np.asarray(black)
        if blk.dtype != np.uint8 or blk.shape != imgs[0].shape:
            raise InputError(f"{blk_name}: black frame of shape {blk.shape} ({blk.dtype}) does not match the "
                             f"bracket's images {imgs[0].shape} (uint8); take it with the same camera and size, "
                             f"or pass --low N instead")
        blk = np.ascontiguousarray(blk)
    return Bracket(tuple(imgs[k] for k in order), t[order], tuple(names[k] for k in order), blk, blk_name)


# ----------------------------------------------------------------------------- reading

def parse_seconds(text: object, where: str) -> float:
    """Seconds from a number or a string such as ``"0.5"`` or ``"1/30"``; InputError naming
    ``where`` otherwise."""
    try:
        value = float(Fraction(str(text).strip())) if isinstance(text, str) else float(text)
    except (ValueError, TypeError, ZeroDivisionError):
        raise InputError(f"{where}: exposure time {text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"{where}: exposure time {text!r} must be positive and finite")
    return value


def read_sidecar(path: Path) -> dict[str, float] | list[float]:
    """``{file name: seconds}`` from ``exposures.json`` or a two-column CSV/text file, or the
    seconds of a one-column file (the images in file-name order)."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the exposure-time file ({exc})") from None
    if path.suffix == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"{path}: not valid JSON ({exc})") from None
        if not isinstance(data, dict):
            raise InputError(f"{path}: expected an object {{file name: seconds}}")
        return {str(k): parse_seconds(v, f"{path}: {k}") for k, v in data.items()}
    out = {}
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    cells = [[c.strip() for c in next(csv.reader([ln]))] if "," in ln else ln.split() for ln in lines]
    if cells and all(len(row) == 1 for row in cells):         # one column: seconds in file order
        rows = cells[1:] if not _is_number(cells[0][0]) else cells  # a header line
        return [parse_seconds(row[0], f"{path}: line {k + 1}") for k, row in enumerate(rows)]
    for k, (line, row) in enumerate(zip(lines, cells)):
        if len(row) != 2:
            raise InputError(f"{path}: line {line!r}: expected two columns 'file, seconds'")
        if k == 0 and not _is_number(row[1]):  # header line
            continue
        out[row[0]] = parse_seconds(row[1], f"{path}: {row[0]}")
    return out


def _is_number(text: str) -> bool:
    try:
        float(Fraction(text.strip()))
        return True
    except (ValueError, ZeroDivisionError):
        return False


def exif_exposure_time(path: str | os.PathLike) -> float | None:
    """EXIF ``ExposureTime`` (seconds) of an image file with Pillow; None when absent."""
    try:
        with Image.open(path) as im:
            im.load()  # PNG keeps its eXIf chunk after the pixels
            exif = im.getexif()
    except (OSError, UnidentifiedImageError):
        return None
    value = exif.get_ifd(ExifTags.IFD.Exif).get(ExifTags.Base.ExposureTime, exif.get(ExifTags.Base.ExposureTime))
    return None if value is None else parse_seconds(float(value), f"{path}: EXIF ExposureTime")


def read_image8(path: str | os.PathLike) -> NDArray[np.uint8]:
    """An 8-bit RGB image ``(rows, cols, 3)`` (grey expanded, alpha dropped); InputError
    naming the file when it cannot be read or is not 8-bit."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"{path}: cannot read the image (missing, not an image or unsupported format)")
    if img.dtype != np.uint8:
        raise InputError(f"{path}: {img.dtype} image; OpenCV's Debevec response and merge need 8-bit images")
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)


def load_bracket(folder: str | os.PathLike, black: str | os.PathLike | None = None) -> Bracket:
    """Read a bracket folder (images + exposure times, see the module docstring) and its black
    frame: ``black`` when given, else a ``black.*`` image in the folder, else none."""
    root = Path(folder)
    if not root.is_dir():
        raise InputError(f"{root}: no such bracket folder")
    found = sorted(p for p in root.iterdir()
                   if p.suffix.lower() in LDR_SUFFIXES and not p.name.startswith(".") and p.is_file())
    files = [p for p in found if p.stem.lower() != BLACK_STEM]
    blacks = [p for p in found if p.stem.lower() == BLACK_STEM]
    if black is None and len(blacks) > 1:
        raise InputError(f"{root}: several black frames ({', '.join(p.name for p in blacks)}); keep one "
                         f"or pass --black FILE")
    black_file = Path(black) if black is not None else (blacks[0] if blacks else None)
    if not files:
        raise InputError(f"{root}: no images ({', '.join(LDR_SUFFIXES)}) in the bracket folder")
    images = [read_image8(f) for f in files]
    sidecars = [root / s for s in SIDECARS if (root / s).is_file()]
    if len(sidecars) > 1:
        raise InputError(f"{root}: several exposure-time files ({', '.join(s.name for s in sidecars)}); keep one")
    if sidecars:
        table = read_sidecar(sidecars[0])
        if isinstance(table, list):                 # one column: the images in file-name order
            if len(table) != len(files):
                raise InputError(f"{sidecars[0]}: {len(table)} exposure times for the {len(files)} images of "
                                 f"{root} (one column lists one time per image, in file-name order: "
                                 f"{', '.join(f.name for f in files[:3])}{', ...' if len(files) > 3 else ''})")
            table = {f.name: t for f, t in zip(files, table)}
        for name in table:
            if not (root / name).is_file():
                raise InputError(f"{sidecars[0]}: lists {name!r}, which is not in {root}")
        missing = [f.name for f in files if f.name not in table]
        if missing:
            raise InputError(f"{root / missing[0]}: no exposure time in {sidecars[0]} "
                             f"({len(missing)} image(s) missing there)")
        times = [table[f.name] for f in files]
    else:
        times = []
        for f in files:
            t = exif_exposure_time(f)
            if t is None:
                raise InputError(f"{f}: no EXIF ExposureTime and no exposure-time file "
                                 f"({' / '.join(SIDECARS)}) in {root}")
            times.append(t)
    black_img = read_image8(black_file) if black_file is not None else None
    return make_bracket(images, times, files, black_img, black_file)


def read_hdr(path: str | os.PathLike) -> NDArray[np.float32]:
    """An OpenEXR image ``(rows, cols, 3)`` float32; InputError naming the file when it is
    missing or unreadable."""
    img = read_image(path, exr_only=True).astype(np.float32)
    if not np.all(np.isfinite(img)):
        raise InputError(f"{path}: {int((~np.isfinite(img)).sum())} non-finite pixel values")
    return img


# ----------------------------------------------------------------------------- response

def _as_brackets(brackets: Bracket | Sequence[Bracket]) -> list[Bracket]:
    out = [brackets] if isinstance(brackets, Bracket) else list(brackets)
    if not out:
        raise InputError("no exposure bracket given")
    for b in out[1:]:
        if b.times.shape != out[0].times.shape or not np.allclose(b.times, out[0].times, rtol=1e-6):
            raise InputError(f"{b.files[0].parent}: exposure times {b.times.tolist()} differ from "
                             f"{out[0].files[0].parent} ({out[0].times.tolist()}); calibrate brackets of "
                             f"one exposure series together")
    return out


def sample_pixels(brackets: Sequence[Bracket], samples: int, seed: int = 0) -> NDArray[np.uint8]:
    """``(exposures, samples, 3)`` pixel values of pixels picked from all brackets so that
    their brightness (summed over the bracket) covers its range evenly."""
    rng = np.random.default_rng(seed)
    cand = []
    for b in brackets:
        stack = np.stack([im.reshape(-1, 3) for im in b.images])  # (exposures, pixels, 3)
        pick = rng.choice(stack.shape[1], size=min(stack.shape[1], 20000), replace=False)
        cand.append(stack[:, pick])
    stack = np.concatenate(cand, axis=1)
    informative = ((stack > 0) & (stack < 255)).any(axis=(0, 2))
    if informative.sum() < 2:
        raise InputError(f"{brackets[0].files[0].parent}: every pixel is black or saturated in every exposure")
    stack = stack[:, informative]
    key = stack.astype(np.float64).sum(axis=(0, 2))
    order = np.argsort(key, kind="stable")
    targets = np.linspace(key[order[0]], key[order[-1]], samples)
    chosen = np.unique(np.clip(np.searchsorted(key[order], targets), 0, len(order) - 1))
    picked = order[chosen]
    if len(picked) < samples:  # few distinct levels: top up with random pixels
        rest = np.setdiff1d(np.arange(stack.shape[1]), picked)
        extra = rng.choice(rest, size=min(len(rest), samples - len(picked)), replace=False)
        picked = np.concatenate([picked, extra])
    return stack[:, picked]


def calibrate_response(brackets: Bracket | Sequence[Bracket], samples: int = 256, smoothness: float = 50.0,
                       seed: int = 0) -> Array:
    """Inverse camera response ``(256, 3)`` (see the module docstring) from one or more
    brackets with the same exposure times, by ``cv2.createCalibrateDebevec``.

    ``samples`` pixels are picked over all brackets (:func:`sample_pixels`) and laid out as
    blocks of a small mosaic whose block centres are the grid OpenCV samples; ``smoothness``
    is Debevec-Malik's lambda (with OpenCV's default 10, 8-bit quantisation and sensor noise
    make the curve wiggle by up to 5 % on the simulated camera; 50 keeps it within ~3.5 %)."""
    bs = _as_brackets(brackets)
    side = max(2, math.ceil(math.sqrt(samples)))
    vals = sample_pixels(bs, side * side, seed)
    if vals.shape[1] < side * side:  # fewer candidate pixels than blocks: repeat them
        vals = vals[:, np.resize(np.arange(vals.shape[1]), side * side)]
    block = 4  # OpenCV samples a side x side grid at step/2 + k step: one point per block
    mosaic = [np.ascontiguousarray(np.repeat(np.repeat(v.reshape(side, side, 3), block, 0), block, 1))
              for v in vals]
    cal = cv2.createCalibrateDebevec(samples=side * side, lambda_=float(smoothness), random=False)
    resp = cal.process(mosaic, bs[0].times.astype(np.float32)).reshape(256, 3).astype(np.float64)
    if not (np.all(np.isfinite(resp)) and np.all(resp > 0)):
        raise InputError(f"{bs[0].files[0].parent}: the recovered camera response is not finite and "
                         f"positive; the bracket does not constrain it (too few exposures or levels)")
    falling = [c for c in range(3) if resp[HI, c] <= resp[LO, c]]
    if falling:
        raise InputError(f"{bs[0].files[0].parent}: the recovered response falls with the pixel value in channel "
                         f"{'RGB'[falling[0]]}: check the exposure times (order and units) of the bracket")
    return resp / np.exp(np.log(resp[LO:HI + 1]).mean(axis=0))


def inverse_response_error(response: ArrayLike, truth: ArrayLike | Callable[[Array], Array],
                           lo: int = LO, hi: int = HI) -> float:
    """Max relative error, over pixel values ``lo..hi`` and channels, of a recovered inverse
    response against the true one (``(256,)``/``(256, 3)`` or a function of the pixel value
    ``z = 0..255``), after fitting the unknown per-channel scale by relative least squares."""
    r = np.asarray(response, dtype=np.float64).reshape(256, -1)
    z = np.arange(256, dtype=np.float64)
    t = np.asarray(truth(z) if callable(truth) else truth, dtype=np.float64)
    t = np.broadcast_to(t.reshape(256, -1), r.shape)[lo:hi + 1]
    q = r[lo:hi + 1] / t
    scale = q.sum(axis=0) / (q * q).sum(axis=0)  # argmin_s sum (s r / t - 1)^2
    return float(np.max(np.abs(scale * q - 1.0)))


def save_response(path: str | os.PathLike, response: ArrayLike, description: str = "") -> Path:
    """Write a ``(256, 3)`` response as the JSON file of the module docstring (atomically)."""
    r = _check_response(response, str(path))
    data = {"format": RESPONSE_FORMAT, "version": 1, "channels": ["R", "G", "B"],
            "description": description or "inverse camera response (Debevec-Malik, OpenCV): relative "
                                          "exposure per 8-bit pixel value",
            "response": [[float(f"{v:.9g}") for v in row] for row in r]}
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1))
    return Path(path)


def load_response(path: str | os.PathLike) -> Array:
    """Read a response JSON file; InputError naming the file when it is not one."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: cannot read the response file ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != RESPONSE_FORMAT or "response" not in data:
        raise InputError(f"{path}: not a {RESPONSE_FORMAT} JSON file")
    return _check_response(data["response"], str(path))


def _check_response(response: ArrayLike, name: str) -> Array:
    try:
        r = np.asarray(response, dtype=np.float64)
    except (ValueError, TypeError):
        raise InputError(f"{name}: response is not a numeric (256, 3) table") from None
    if r.shape != (256, 3):
        raise InputError(f"{name}: response has shape {r.shape}; expected (256, 3)")
    if not (np.all(np.isfinite(r)) and np.all(r > 0)):
        raise InputError(f"{name}: response values must be finite and positive")
    return r


# ----------------------------------------------------------------------------- merge

def noise_floor(black: ArrayLike, percentile: float = NOISE_PERCENTILE,
                margin: int = NOISE_MARGIN) -> NDArray[np.int64]:
    """Per-channel noise floor ``(3,)`` (8-bit levels) of a black frame ``(rows, cols, 3)``:
    ``ceil`` of the ``percentile`` of each channel plus ``margin`` (see the module docstring)."""
    b = np.asarray(black).reshape(-1, 3).astype(np.float64)
    return np.ceil(np.percentile(b, percentile, axis=0)).astype(np.int64) + int(margin)


#: The bracket's own noise floor needs this share of the shortest exposure at or below its most
#: common level (signal-free pixels), and that level below :data:`LO` x 2.
MIN_DARK_SHARE = 0.05


def bracket_noise_floor(bracket: Bracket) -> NDArray[np.int64] | None:
    """Per-channel noise floor ``(3,)`` estimated from the bracket itself, for a bracket without
    a black frame: in its shortest exposure the most common level of each channel is the black
    level of the pixels that receive no signal, and the values below it are their noise alone
    (signal only adds), provided those pixels stay at that level in the next exposure (else they
    are dim, not dark, and there is no estimate); the floor is ``ceil(mode + 3.09 sigma)``, ``sigma`` the RMS distance of
    those values below the mode (the 99.9th percentile of the noise, as :func:`noise_floor` takes
    of a black frame), and at least :data:`LO` (below it quantisation dominates even without
    noise). On the noisy synthetic camera (black frame floor 20 / 23 / 21) it gives 23 / 24 / 23;
    on a noise-free one :data:`LO`. None when the shortest exposure has too few signal-free pixels
    (:data:`MIN_DARK_SHARE`)."""
    order = np.argsort(bracket.times)
    v = bracket.images[int(order[0])].reshape(-1, 3).astype(np.int64)
    v2 = bracket.images[int(order[1])].reshape(-1, 3).astype(np.int64)
    out = []
    for c in range(3):
        mode = int(np.bincount(v[:, c], minlength=256).argmax())
        at_or_below = v[:, c] <= mode
        if mode >= 2 * LO or at_or_below.mean() < MIN_DARK_SHARE:
            return None
        # signal-free, not merely dim: the same pixels sit at the same level in the next exposure
        if abs(int(np.bincount(v2[at_or_below, c], minlength=256).argmax()) - mode) > 1:
            return None
        below = v[v[:, c] < mode, c].astype(np.float64)
        sigma = float(np.sqrt(np.mean((below - mode) ** 2))) if len(below) else 0.0
        out.append(int(np.ceil(mode + 3.09 * sigma)))
    return np.maximum(np.asarray(out, dtype=np.int64), LO)    # never below the quantisation floor


def low_cutoff(bracket: Bracket, lo: int | Sequence[int] | None = None,
               hi: int = HI) -> NDArray[np.int64]:
    """The per-channel lower cutoff ``(3,)`` a merge uses: ``lo`` when given (one value or
    R, G, B), else the :func:`noise_floor` of the bracket's black frame, else the bracket's own
    (:func:`bracket_noise_floor`), else :data:`LO`."""
    if lo is not None:
        try:
            low = np.broadcast_to(np.asarray(lo, dtype=np.int64), (3,)).copy()
        except (ValueError, TypeError):
            raise InputError(f"lo={lo!r}: give one pixel value or three (R, G, B)") from None
    else:
        own = bracket_noise_floor(bracket) if bracket.black is None else None
        low = (noise_floor(bracket.black) if bracket.black is not None else own if own is not None
               else np.full(3, LO, dtype=np.int64))
    given = lo if lo is not None else low.tolist()
    if not (0 < hi < 255 and np.all(low > 0)):
        raise InputError(f"lo={given}, hi={hi}: need 0 < lo < hi < 255")
    if np.any(low >= hi):
        if lo is None and bracket.black is not None:
            raise InputError(f"{bracket.black_file}: noise floor R G B = {' '.join(map(str, low))} reaches --high "
                             f"{hi}: not a black frame (cap the lens, same settings as the longest exposure) or "
                             "pass --low N")
        raise InputError(f"lo={given}, hi={hi}: need 0 < lo < hi < 255")
    return low


def unusable_mask(bracket: Bracket, lo: int | Sequence[int] | None = LO, hi: int = HI) -> NDArray[np.bool_]:
    """``(rows, cols, 3)`` True where a channel has no exposure with ``lo <= z <= hi``
    (dark in every exposure, saturated in every exposure, or both in turn); ``lo`` per
    channel or one value (None: :func:`low_cutoff`)."""
    low = low_cutoff(bracket, lo, hi)
    usable = np.zeros(bracket.images[0].shape, dtype=bool)
    for im in bracket.images:
        usable |= (im >= low) & (im <= hi)
    return ~usable


def merge_bracket(bracket: Bracket, response: ArrayLike | None = None, lo: int | Sequence[int] | None = None,
                  hi: int = HI) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    """Linear relative radiance ``(rows, cols, 3)`` float32 and the :func:`unusable_mask`.

    ``cv2.createMergeDebevec`` averages ``log(response[z] / t)`` over the exposures with
    triangle weights (zero at 0 and 255). Values outside ``[lo, hi]`` are set to 0 / 255
    first, so they get no weight (below ``lo`` noise dominates: the black frame's noise floor,
    or on an 8-bit gamma camera without one, below 20, noise and quantisation exceed 5 %), and
    it runs per channel so that a channel saturated in an exposure does not borrow the weights
    of the others. ``lo`` is one value or R, G, B; None: :func:`low_cutoff` (the black frame's
    :func:`noise_floor`, else :data:`LO`). Masked pixels get a bound instead: too bright in
    every exposure ``response[hi] / t_min`` (a lower bound), too dark in every exposure
    ``response[lo] / t_max`` (an upper bound, up to noise). Without ``response`` it is
    calibrated from this bracket."""
    low = low_cutoff(bracket, lo, hi)
    resp = calibrate_response(bracket) if response is None else _check_response(response, "response")
    times = bracket.times.astype(np.float32)
    merger = cv2.createMergeDebevec()
    out = np.empty(bracket.images[0].shape, dtype=np.float32)
    for c in range(3):
        chans = [np.where(im[..., c] < low[c], 0, np.where(im[..., c] > hi, 255, im[..., c])).astype(np.uint8)
                 for im in bracket.images]
        out[..., c] = merger.process(chans, times, np.ascontiguousarray(resp[:, c:c + 1], dtype=np.float32))
    mask = unusable_mask(bracket, low, hi)
    bright = np.all([im > hi for im in bracket.images], axis=0)
    dark = np.all([im < low for im in bracket.images], axis=0)
    out = np.where(bright, (resp[hi] / bracket.times[0]).astype(np.float32), out)
    out = np.where(dark, (resp[low, [0, 1, 2]] / bracket.times[-1]).astype(np.float32), out)
    if not np.all(np.isfinite(out)):
        raise InputError(f"{bracket.files[0].parent}: the merge produced non-finite values; check the response")
    return out, mask


# ----------------------------------------------------------------------------- folders to files

def response_from_folders(folders: Sequence[str | os.PathLike], output: str | os.PathLike, samples: int = 256,
                          smoothness: float = 50.0) -> tuple[Array, list[Bracket]]:
    """Recover the inverse camera response ``(256, 3)`` from one or more bracket folders with
    the same exposure times (:func:`calibrate_response`: ``samples`` pixels, Debevec-Malik
    smoothness lambda ``smoothness``) and write it to ``output`` (the response JSON of the module
    docstring, atomically). Returns the response and the brackets."""
    brackets = [load_bracket(f) for f in folders]
    resp = calibrate_response(brackets, samples=samples, smoothness=smoothness)
    save_response(output, resp, f"inverse camera response (Debevec-Malik, OpenCV) from "
                                f"{', '.join(str(f) for f in folders)}")
    return resp, brackets


@dataclass
class MergedFolder:
    """What :func:`merge_folder` wrote: the linear relative radiance ``(rows, cols, 3)`` and its
    unusable-pixel mask (:func:`merge_bracket`), the bracket, the lower cutoff ``(3,)`` (8-bit
    pixel values, R G B) and where that cutoff came from (a phrase for the user)."""

    image: NDArray[np.float32]
    mask: NDArray[np.bool_]
    bracket: Bracket
    low: NDArray[np.int64]
    low_source: str


def merge_folder(folder: str | os.PathLike, output: str | os.PathLike, response: str | os.PathLike | None = None,
                 half: bool = False, mask: str | os.PathLike | None = None, low: int | None = None,
                 black: str | os.PathLike | None = None, high: int = HI) -> MergedFolder:
    """Merge the bracket in ``folder`` into the OpenEXR image ``output`` (float32, or 16-bit half
    floats with ``half``): ``response`` a response JSON file (default: recovered from this
    bracket), ``low`` / ``high`` the trusted 8-bit pixel values (``low`` default: the noise floor
    of the black frame ``black`` or the folder's ``black.*``, see :func:`low_cutoff`), ``mask``
    an 8-bit PNG to write too, 255 where a channel is unusable. A bad cutoff is refused before
    the response solve; nothing is written unless the merge succeeds."""
    bracket = load_bracket(folder, black)
    cutoff = low_cutoff(bracket, low, high)  # refuse a bad cutoff before the response solve
    resp = load_response(response) if response else calibrate_response(bracket)
    img, unusable = merge_bracket(bracket, resp, lo=cutoff, hi=high)
    shortest = bracket.files[int(np.argmin(bracket.times))].name
    source = ("--low" if low is not None else
              f"noise floor of {bracket.black_file}" if bracket.black is not None else
              f"noise floor estimated from the shortest exposure {shortest}; a black frame measures it better"
              if bracket_noise_floor(bracket) is not None else
              f"default {LO}: no black frame, and {shortest} has too few signal-free pixels to estimate one")
    png = cv2.imencode(".png", (unusable[..., ::-1] * 255).astype(np.uint8))[1] if mask else None
    attrs = {"glsldiff": "linear relative radiance (Debevec-Malik merge, OpenCV)",
             "exposures_s": " ".join(f"{t:.6g}" for t in bracket.times)}
    write_exr(output, img, attrs, half=half)  # validates before writing anything
    if png is not None:
        with atomic_path(mask) as tmp:
            tmp.write_bytes(png.tobytes())
    return MergedFolder(img, unusable, bracket, cutoff, source)
