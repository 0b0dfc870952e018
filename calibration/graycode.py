"""Gray-code structured light: the projector pattern sequence and its vectorised decoding.

Sequence (OpenCV's ``cv2.structured_light.GrayCodePattern`` order, then two extra images):
for each of the ``ceil(log2(width))`` column bits, most significant first, the bit pattern and
its inverse; then the same for the ``ceil(log2(height))`` row bits; then all white and all
black. Projector column ``x`` shows bit ``k`` of its reflected Gray code ``x ^ (x >> 1)``.
A 1024 x 768 projector has 2 x (10 + 10) + 2 = 42 images.

Step (``--step N``, the ``graycode_step`` of kamino410/procam-calibration): the codes are
those of a ``ceil(W/N) x ceil(H/N)`` projector (:func:`code_size`) and each code pixel is shown
as an ``N x N`` block of projector pixels (cropped at the right and bottom edges); white and
black stay full size. Larger steps survive defocus and moire at the cost of coarser codes.

Decoding, per camera pixel: a bit is 1 where the pattern image is brighter than its inverse,
and reliable where they differ by at least ``bit_threshold`` (8-bit grey levels); the pixel
is lit where ``white - black >= shadow_threshold``. A pixel decodes when it is lit, all its
bits are reliable and the codes fall inside the projector frame. Projector coordinates are
pixel indices: index ``i`` is the pixel centred at ``u = i`` (OpenCV's convention). With a step
``N``, code ``c`` is reported as projector pixel ``N c``, the first pixel of its block, as the
reference tool does (see :func:`decode`).

Capture folders: ``capture_*`` sub-folders of one root, one per pose (:func:`capture_folders`);
the images of each in pattern order (:func:`sequence_images`).
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from glsldiff.core.errors import InputError
from glsldiff.core.io import LDR_SUFFIXES, atomic_path


def bit_counts(size: tuple[int, int]) -> tuple[int, int]:
    """Number of column and row bits of a projector of ``size = (cols, rows)`` px."""
    w, h = (int(s) for s in size)
    if w < 2 or h < 2:
        raise InputError(f"projector size {w}x{h}: both sides must be >= 2 px")
    return math.ceil(math.log2(w)), math.ceil(math.log2(h))


def code_size(size: tuple[int, int], step: int = 1) -> tuple[int, int]:
    """Code pixels ``(ceil(W/step), ceil(H/step))`` of a projector of ``size = (W, H)`` px
    shown in ``step x step`` px blocks (procam-calibration's ``int((W-1)/step)+1``)."""
    w, h = (int(s) for s in size)
    bit_counts((w, h))
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 1:
        raise InputError(f"--step {step}: the Gray-code step must be an integer >= 1 (projector px per code pixel)")
    cw, ch = -(-w // int(step)), -(-h // int(step))
    if cw < 2 or ch < 2:
        raise InputError(f"--step {step}: a {w}x{h} projector has only {cw}x{ch} code pixels at this step; "
                         f"each side needs >= 2 (use --step {min(w, h) - 1} or less)")
    return cw, ch


def sequence_length(size: tuple[int, int], step: int = 1) -> int:
    """Images per sequence: 2 per Gray bit (pattern, inverse) + white + black."""
    nc, nr = bit_counts(code_size(size, step))
    return 2 * (nc + nr) + 2


def patterns(size: tuple[int, int], step: int = 1) -> list[NDArray[np.uint8]]:
    """The full sequence of 8-bit ``(rows, cols)`` projector images of a ``size = (cols, rows)``
    px projector, each code pixel an ``step x step`` block (see the module docstring)."""
    cw, ch = code_size(size, step)
    w, h = (int(s) for s in size)
    ok, seq = cv2.structured_light.GrayCodePattern.create(cw, ch).generate()
    if not ok:
        raise InputError(f"OpenCV could not generate Gray-code patterns for {cw}x{ch}")
    expand = [np.repeat(np.repeat(np.asarray(p, np.uint8), step, 0), step, 1)[:h, :w] for p in seq]
    white = np.full((h, w), 255, np.uint8)
    return [np.ascontiguousarray(p) for p in expand] + [white, np.zeros_like(white)]


def write_patterns(folder: str | os.PathLike, size: tuple[int, int], step: int = 1) -> list[Path]:
    """Write the sequence as ``folder/pattern_00.png`` ... (created if needed); returns the paths.
    Each file is written atomically."""

    seq = patterns(size, step)   # a bad size or step is refused before the folder is created
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, img in enumerate(seq):
        path = out / f"pattern_{i:02d}.png"
        with atomic_path(path) as tmp:
            if not cv2.imwrite(str(tmp), img):
                raise InputError(f"cannot write {path}")
        paths.append(path)
    return paths


@dataclass
class Decoded:
    """Per camera pixel projector coordinates (px, ``-1`` where not decoded) and masks."""

    col: NDArray[np.int32]
    row: NDArray[np.int32]
    valid: NDArray[np.bool_]
    lit: NDArray[np.bool_]
    col_max: int = -1            # largest decoded column / row over the lit, reliable pixels,
    row_max: int = -1            # before codes beyond the projector size are discarded
    out_of_range: float = 0.0    # fraction of the lit, reliable pixels whose code lies beyond it

    @property
    def fraction(self) -> float:
        """Fraction of lit pixels that decoded."""
        n = int(self.lit.sum())
        return float(self.valid.sum()) / n if n else 0.0


def _gray_to_binary(bits: NDArray[np.bool_]) -> NDArray[np.int32]:
    """Gray-code bits ``(n, rows, cols)``, most significant first -> integer values."""
    binary = np.logical_xor.accumulate(bits, axis=0)
    weights = (1 << np.arange(bits.shape[0] - 1, -1, -1)).astype(np.int32)
    return np.tensordot(weights, binary.astype(np.int32), axes=1).astype(np.int32)


def decode(images: NDArray, size: tuple[int, int], shadow_threshold: float = 20.0,
           bit_threshold: float = 3.0, step: int = 1) -> Decoded:
    """Decode a captured sequence ``(n, rows, cols)`` (grey levels, 8-bit scale) of a projector
    of ``size = (cols, rows)`` px shown with Gray-code ``step``; ``n`` must be
    :func:`sequence_length` (``size``, ``step``).

    Columns and rows are projector pixels: code ``c`` (of the :func:`code_size` projector)
    becomes ``step * c``, the first pixel of the code's block and not its centre
    ``step * c + (step - 1) / 2``. That is what kamino410/procam-calibration's calibrate.py does
    (``dst_points.append(gc_step * np.array(proj_pix))``), so a capture calibrates to the same
    projector as there. Its cost: every projector coordinate, hence the principal point
    (cx, cy), is ``(step - 1) / 2`` px lower than the truth (0.5 px at step 2, 1.5 px at step 4);
    focal lengths, distortion and the extrinsics are unaffected (a shift of all image points
    is a principal point shift)."""
    imgs = np.asarray(images)
    n = sequence_length(size, step)
    if imgs.ndim != 3 or imgs.shape[0] != n:
        raise InputError(f"decode: expected {n} images (rows, cols) for a {size[0]}x{size[1]} projector at "
                         f"step {step}, got array of shape {imgs.shape}")
    codes = code_size(size, step)
    nc, nr = bit_counts(codes)
    imgs = imgs.astype(np.float32)
    white, black = imgs[-2], imgs[-1]
    lit = (white - black) >= shadow_threshold
    diff = imgs[0:2 * (nc + nr):2] - imgs[1:2 * (nc + nr):2]  # pattern - inverse, per bit
    reliable = np.all(np.abs(diff) >= bit_threshold, axis=0)
    bits = diff > 0
    col = _gray_to_binary(bits[:nc])
    row = _gray_to_binary(bits[nc:])
    good = lit & reliable
    beyond = good & ((col >= codes[0]) | (row >= codes[1]))
    col *= np.int32(step)
    row *= np.int32(step)
    n_good = int(good.sum())
    col_max = int(col[good].max()) if n_good else -1
    row_max = int(row[good].max()) if n_good else -1
    valid = good & ~beyond
    col[~valid] = -1
    row[~valid] = -1
    return Decoded(col=col, row=row, valid=valid, lit=lit, col_max=col_max, row_max=row_max,
                   out_of_range=float(beyond.sum()) / n_good if n_good else 0.0)


#: Name prefix of the capture images in kamino410/procam-calibration's layout
#: (``capture_*/graycode_00.png`` ...); when a capture folder has such images, only they count.
REFERENCE_PREFIX = "graycode_"


def capture_folders(folder: str | os.PathLike) -> list[Path]:
    """The ``capture_*`` sub-folders of ``folder`` (one per board pose), sorted by name."""
    root = Path(folder)
    if not root.is_dir():
        raise InputError(f"{root}: no such folder")
    subs = sorted(p for p in root.glob("capture_*") if p.is_dir())
    if not subs:
        raise InputError(f"{root}: no capture_* sub-folders (one per board pose)")
    return subs


def _natural_key(path: Path) -> list:
    """Sort key comparing digit runs as numbers: ``graycode_2`` before ``graycode_10``."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def sequence_images(folder: str | os.PathLike) -> list[Path]:
    """The images of one capture folder in pattern order: the ``graycode_*`` images when there
    are any (procam-calibration's names; other files are ignored, as that tool does), else all
    images; sorted by name with numbers compared by value (``img_2`` before ``img_10``; the
    same order as plain sorting for zero-padded numbers)."""
    paths = list_images(folder)
    ref = [p for p in paths if p.name.startswith(REFERENCE_PREFIX)]
    return sorted(ref or paths, key=_natural_key)


def list_images(folder: str | os.PathLike) -> list[Path]:
    """Image files of ``folder`` (:data:`~glsldiff.core.io.LDR_SUFFIXES`: png, jpg, tif, ...), sorted by name."""
    d = Path(folder)
    if not d.is_dir():
        raise InputError(f"{d}: not a folder")
    return sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in LDR_SUFFIXES)


def read_gray(path: str | os.PathLike) -> NDArray[np.float32]:
    """An image as grey levels on the 8-bit scale (16-bit images are divided by 257)."""
    try:
        buf = np.fromfile(str(path), np.uint8)
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    img = cv2.imdecode(buf, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_GRAYSCALE) if buf.size else None
    if img is None or img.size == 0:
        raise InputError(f"{path}: unreadable or not an image")
    scale = 1.0 / 257.0 if img.dtype == np.uint16 else 1.0
    return img.astype(np.float32) * np.float32(scale)


def read_stack(paths: list[Path], what: str) -> NDArray[np.float32]:
    """Read equally sized images into ``(n, rows, cols)``; ``what`` names them in errors."""
    if not paths:
        raise InputError(f"{what}: no images")
    first = read_gray(paths[0])
    stack = np.empty((len(paths),) + first.shape, np.float32)
    stack[0] = first
    for i, p in enumerate(paths[1:], 1):
        img = read_gray(p)
        if img.shape != first.shape:
            raise InputError(f"{p}: size {img.shape[1]}x{img.shape[0]} differs from "
                             f"{paths[0].name}'s {first.shape[1]}x{first.shape[0]} in {what}")
        stack[i] = img
    return stack
