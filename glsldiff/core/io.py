"""Image and table files: OpenEXR (HDR, linear), PNG/JPEG (8-bit sRGB), CSV. Writes are atomic.

One reader for images, :func:`read_image`, and one list of the image files it reads,
:data:`IMAGE_SUFFIXES` (:data:`LDR_SUFFIXES`: the same without OpenEXR, e.g. camera captures).

Every writer goes to a temporary file in the destination folder and renames it into
place, so an interrupted run never leaves a truncated file under the final name.
"""
from __future__ import annotations

import csv
import os
import tempfile
import zipfile
import zlib
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from PIL import Image

from glsldiff.core.checks import finite_array
from glsldiff.core.errors import GlsldiffError, InputError


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` on success. The file gets
    the permissions of a newly created file under the umask (``mkstemp`` alone makes it 0600)."""
    with atomic_paths([path], [suffix]) as (tmp,):
        yield tmp


@contextmanager
def atomic_paths(paths: Sequence[str | os.PathLike], suffixes: Sequence[str] | None = None
                 ) -> Iterator[list[Path]]:
    """Temporary paths beside each of ``paths``, renamed into place together once every one
    is written: an interrupted write leaves the old files (or none), never a new file beside
    a stale or missing partner (e.g. an EXR and its PNG)."""
    dests = [Path(p) for p in paths]
    suffixes = list(suffixes or [""] * len(dests))
    tmps: list[str] = []
    try:
        for dest, suffix in zip(dests, suffixes):
            dest.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=suffix or dest.suffix, dir=dest.parent)
            os.close(fd)
            tmps.append(tmp)
        yield [Path(t) for t in tmps]
        for dest in dests:           # all or none: a destination that is a folder fails before any rename
            if dest.is_dir():
                raise InputError(f"output {str(dest)!r} is a folder; nothing was written (remove it or choose "
                                 "another name)")
        mode = 0o666 & ~_umask()
        for tmp in tmps:
            os.chmod(tmp, mode)
        for tmp, dest in zip(tmps, dests):
            os.replace(tmp, dest)
    finally:
        for tmp in tmps:
            if os.path.exists(tmp):
                os.unlink(tmp)


#: 8/16-bit image files OpenCV decodes (captures, projector images); sRGB-encoded.
LDR_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".ppm", ".pgm")
#: Every image file :func:`read_image` reads: OpenEXR (linear) and :data:`LDR_SUFFIXES`.
IMAGE_SUFFIXES = (".exr",) + LDR_SUFFIXES


def _rgb(image: ArrayLike, name: str) -> NDArray[np.float32]:
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3 or img.size == 0:
        raise InputError(f"{name}: expected an (h, w, 3) or (h, w) image, got shape {np.shape(image)}")
    return finite_array(img, f"{name}: image").astype(np.float32)  # float32 first: values beyond its range are inf


def _exr_file(tmp: Path, image: ArrayLike, attributes: Mapping[str, str] | None, half: bool, name: str) -> None:
    import OpenEXR  # heavy import (~60 ms): only EXR files need it

    img = np.ascontiguousarray(_rgb(image, name))
    if half:
        if np.abs(img).max() > np.finfo(np.float16).max:
            raise InputError(f"{name}: values up to {np.abs(img).max():.4g} exceed the half-float range "
                             f"(65504); write float32 instead or rescale")
        img = img.astype(np.float16)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update({k: str(v) for k, v in (attributes or {}).items()})
    with OpenEXR.File(header, {"RGB": img}) as f:
        f.write(str(tmp))


def write_exr(path: str | os.PathLike, image: ArrayLike,
              attributes: Mapping[str, str] | None = None, half: bool = False) -> Path:
    """Write a linear RGB image (row 0 = top) as ZIP-compressed OpenEXR: float32 pixels, or
    16-bit half floats with ``half=True`` (values beyond the half range, 65504, are refused)."""
    with atomic_path(path) as tmp:
        _exr_file(tmp, image, attributes, half, str(path))
    return Path(path)


def write_exr_png(path: str | os.PathLike, image: ArrayLike, image8: NDArray[np.uint8],
                  attributes: Mapping[str, str] | None = None, sidecar: str | None = None) -> tuple[Path, Path]:
    """An EXR (linear) and its 8-bit PNG beside it (same name, ``.png``), and with ``sidecar``
    that text as ``.json``, written together: all appear, or none changes."""
    exr = Path(path)
    png = exr.with_suffix(".png")
    paths = [exr, png] + ([exr.with_suffix(".json")] if sidecar is not None else [])
    with atomic_paths(paths) as tmps:
        _exr_file(tmps[0], image, attributes, False, str(exr))
        _png_file(tmps[1], image8)
        if sidecar is not None:
            tmps[2].write_text(sidecar, encoding="utf-8")
    return exr, png


def read_exr(path: str | os.PathLike) -> NDArray[np.float32]:
    """Read the RGB channels of an OpenEXR file as ``(h, w, 3)`` float32."""
    import OpenEXR  # heavy import (~60 ms): only EXR files need it

    if not Path(path).is_file():
        raise GlsldiffError(f"{path}: no such EXR file")
    with OpenEXR.File(str(path)) as f:
        ch = f.channels()
        if "RGB" in ch:
            return np.asarray(ch["RGB"].pixels, dtype=np.float32)
        try:
            return np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in "RGB"], axis=-1)
        except KeyError as exc:
            raise GlsldiffError(f"{path}: no R, G, B channels (has {sorted(ch)})") from exc


def srgb_to_linear(c: ArrayLike) -> NDArray[np.float64]:
    """sRGB-encoded values in [0, 1] to linear (IEC 61966-2-1)."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def read_image(path: str | os.PathLike, exr_only: bool = False) -> NDArray[np.float64]:
    """``(h, w, 3)`` linear RGB of an image file (row 0 = top): OpenEXR (``.exr``, or any
    file with ``exr_only``) as stored; any other file as 8-bit (OpenCV), BGR -> RGB and
    sRGB-decoded to [0, 1]. InputError naming the file when it is missing or cannot be read."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such image file")
    if exr_only or p.suffix.lower() == ".exr":
        try:
            return np.asarray(read_exr(p), dtype=np.float64)
        except (GlsldiffError, RuntimeError, OSError, ValueError) as exc:  # no RGB; OpenEXR's errors on a corrupt file
            raise InputError(f"{p}: cannot read the OpenEXR image ({' '.join(str(exc).split())})") from None
    import cv2  # OpenCV is a heavy import; only 8-bit files need it

    bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(f"{p}: OpenCV cannot read it as an 8-bit PNG or JPEG (image files: "
                         f"{', '.join(IMAGE_SUFFIXES)})")
    return srgb_to_linear(bgr[..., ::-1] / 255.0)


def read_mask(path: str | os.PathLike) -> NDArray[np.float32]:
    """``(h, w)`` weights in [0, 1] of a mask image (row 0 = top): an 8- or 16-bit PNG/JPEG's
    grey value over its maximum, not sRGB-decoded (a mask is data, not colour), or an OpenEXR
    file's channel mean, clipped. InputError naming the file when it cannot be read."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such mask image")
    if p.suffix.lower() == ".exr":
        return np.clip(read_image(p).mean(axis=2), 0.0, 1.0).astype(np.float32)
    import cv2

    img = cv2.imread(str(p), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(f"{p}: OpenCV cannot read it as a PNG or JPEG mask (or give an .exr)")
    top = 65535.0 if img.dtype == np.uint16 else 255.0
    return (img.astype(np.float32) / np.float32(top)).clip(0.0, 1.0)


def tonemap(image: ArrayLike, exposure: float, gamma: float = 2.2) -> NDArray[np.uint8]:
    """``clip(exposure * L, 0, 1) ** (1 / gamma)`` as 8-bit sRGB-like values."""
    img = np.clip(np.asarray(image, dtype=np.float64) * exposure, 0.0, 1.0) ** (1.0 / gamma)
    return np.round(img * 255.0).astype(np.uint8)


def _png_file(tmp: Path, image8: NDArray[np.uint8]) -> None:
    Image.fromarray(np.ascontiguousarray(image8), "RGB").save(tmp, format="PNG")


def write_png(path: str | os.PathLike, image8: NDArray[np.uint8]) -> Path:
    """Write an 8-bit RGB image (row 0 = top) as PNG."""
    with atomic_path(path) as tmp:
        _png_file(tmp, image8)
    return Path(path)


def contact_sheet(images: Sequence[ArrayLike], columns: int, exposure: float,
                  pad: int = 2, gamma: float = 2.2, scale: int = 1) -> NDArray[np.uint8]:
    """Tile equally sized HDR images into one tone-mapped 8-bit sheet (shared exposure),
    each enlarged ``scale`` times by pixel replication."""
    tiles = [np.repeat(np.repeat(tonemap(_rgb(im, "contact sheet tile"), exposure, gamma), scale, 0), scale, 1)
             for im in images]
    h, w = tiles[0].shape[:2]
    rows = -(-len(tiles) // columns)
    sheet = np.full((rows * (h + pad) + pad, columns * (w + pad) + pad, 3), 32, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, columns)
        sheet[pad + r * (h + pad):pad + r * (h + pad) + h, pad + c * (w + pad):pad + c * (w + pad) + w] = t
    return sheet


def write_npz(path: str | os.PathLike, **arrays: object) -> Path:
    """Write arrays to a compressed ``.npz`` file atomically (no half-written file on failure)."""
    with atomic_path(path, ".npz") as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    return Path(path)


def write_csv(path: str | os.PathLike, rows: Sequence[Mapping[str, object]]) -> Path:
    """Write dict rows as CSV; the columns are the union of the keys in first-seen order
    (a row without a key leaves its cell empty)."""
    if not rows:
        raise InputError(f"{path}: no rows to write")
    fields = list(dict.fromkeys(k for row in rows for k in row))
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    return Path(path)


def check_output(path: str | os.PathLike, suffixes: Sequence[str] = (), note: str = "",
                 beside: Sequence[str] = ()) -> Path:
    """Refuse an output path that cannot be written, before any work is done.

    The folder must exist, the path must not be a folder, an existing file must be writable,
    and when ``suffixes`` are given the name must end in one of them (``note`` says why, e.g.
    what is written beside it). ``beside``: suffixes of the files written next to it under the
    same name (``(".png",)`` for an EXR's PNG), checked the same way. The check creates and
    removes a file in the folder, so a folder that refuses new files (read-only mounts, /proc)
    fails here, not after the work.
    """
    p = Path(path)
    if suffixes and p.suffix.lower() not in suffixes:
        why = f" ({note})" if note else ""
        raise InputError(f"output {str(p)!r}: must end in {' or '.join(suffixes)}{why}")
    parent = p.parent if str(p.parent) else Path(".")
    for q in dict.fromkeys([p, *(p.with_suffix(b) for b in beside)]):
        also = "" if q == p else f" (written beside {str(p)!r})"
        if q.is_dir():
            raise InputError(f"output {str(q)!r}{also} is a folder; give another file name")
        if q.exists() and not os.access(q, os.W_OK):
            raise InputError(f"output {str(q)!r}{also}: the existing file is not writable")
    if not parent.is_dir():
        raise InputError(f"output {str(p)!r}: folder {str(parent)!r} does not exist; create it first")
    try:
        fd, probe = tempfile.mkstemp(prefix=".glsldiff-write-test-", dir=parent)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(f"output {str(p)!r}: cannot create files in {str(parent)!r} "
                         f"({exc.strerror or exc}); choose another folder") from None
    return p


#: Folders :func:`check_output_folder` created, deepest last (see :func:`created_folders_removed_on_failure`).
_CREATED: list[Path] = []


def check_output_folder(folder: str | os.PathLike) -> Path:
    """Create ``folder`` if needed and check that files can be created in it, before any work.
    A command run inside :func:`created_folders_removed_on_failure` that then fails leaves no
    empty folder behind."""
    f = Path(folder)
    if f.exists() and not f.is_dir():
        raise InputError(f"output folder {str(f)!r} is a file; give a folder name")
    missing = [p for p in [f, *f.parents] if not p.exists()]
    try:
        f.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"output folder {str(f)!r} cannot be created ({exc.strerror or exc})") from None
    _CREATED.extend(reversed(missing))
    check_output(f / "probe")
    return f


@contextmanager
def created_folders_removed_on_failure() -> Iterator[None]:
    """Around one command: the folders :func:`check_output_folder` creates inside it are removed
    again, if still empty, when the command raises (failed or interrupted: a folder holding
    any file is kept); they are forgotten when it ends either way."""
    _CREATED.clear()
    try:
        yield
    except BaseException:
        while _CREATED:
            try:
                _CREATED.pop().rmdir()
            except OSError:   # not empty (finished outputs are kept) or already gone
                pass
        raise
    finally:
        _CREATED.clear()


def not_a_file(path: str | os.PathLike) -> str:
    """Why ``path`` is not a readable file, for an error message: "is a folder, not a file" or
    "does not exist"."""
    return "is a folder, not a file" if Path(path).is_dir() else "does not exist"


def read_npz(path: str | os.PathLike, what: str, required: Sequence[str] = ()) -> dict[str, NDArray]:
    """All arrays of an ``.npz`` file (no pickled objects), read once; ``required`` names
    must be present. Every way a file can be bad (missing, empty, truncated, not a zip, a
    pickle, a missing array) is one :class:`InputError` naming ``what`` and the file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what} {str(p)!r} {not_a_file(p)}")
    with open(p, "rb") as f:
        magic = f.read(4)
    if not magic:
        raise InputError(f"{what} {str(p)!r} is empty; write it with numpy.savez")
    if not magic.startswith(b"PK"):
        raise InputError(f"{what} {str(p)!r} is not an .npz archive (a zip of .npy arrays, as "
                         "numpy.savez writes); check the file name")
    try:
        with np.load(p, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(f"{what} {str(p)!r} is damaged or truncated ({exc}); write it again") from None
    except ValueError as exc:
        if "pickle" in str(exc):
            raise InputError(f"{what} {str(p)!r} holds pickled objects, which are not read; store "
                             "plain numeric arrays") from None
        raise InputError(f"{what} {str(p)!r} is not a readable .npz archive ({exc})") from None
    except (OSError, EOFError) as exc:
        raise InputError(f"{what} {str(p)!r} is empty, truncated or unreadable ({exc})") from None
    missing = [k for k in required if k not in arrays]
    if missing:
        raise InputError(f"{what} {str(p)!r} lacks {', '.join(missing)} (has "
                         f"{', '.join(arrays) or 'no arrays'}; needs {', '.join(required)})")
    return arrays
