"""Measurements of a block sample: what inverse diffusion fits (paper section 4.1-4.2).

For each of ``M`` illumination conditions a measurement holds

* ``incoming`` -- the diffuse incoming light ``q`` (paper eq. 2, already Fresnel-transmitted)
  at every boundary node of the lit face, per RGB channel;
* ``radiance`` -- the measured multiple-scattering radiance ``L_o`` at every boundary node
  of the observed face, per RGB channel;
* ``mask`` -- which observed values to use: thick front-lit samples use only nodes that are
  not directly lit, and saturated pixels are dropped;
* optionally ``reflected`` -- the radiance a second camera sees on the *lit* face of a back-lit
  sample in the same condition (front-lit reflection and back-lit transmission of one capture,
  fitted together), with ``reflected_mask`` (default: the nodes the condition does not light
  directly; saturated ones dropped).

Face arrays follow :mod:`glsldiff.grids.regular` (``z-`` face: ``(ny-2, nx-2)``, indexed ``[y, x]``).
Back-lit thin samples: ``lit_face="z-"``, ``observed_face="z+"``; front-lit thick samples:
both ``"z-"`` (:data:`SETUPS`). The projector lights the lit face one region at a time, the
face split into ``n x n`` regions (:func:`face_regions`; paper: 4 x 4).

``.npz`` layout (:func:`save_measurements` / :func:`load_measurements`)::

    shape          int (3,)      grid nodes (nz, ny, nx), boundary layer included
    h              float         node spacing, mm
    eta            float         relative refractive index
    lit_face       str           e.g. "z-"
    observed_face  str           e.g. "z+"
    incoming       (M, a, b, 3)  q on the lit face (radiometric units of the camera)
    radiance       (M, c, d, 3)  measured L_o on the observed face (same units)
    mask           (M, c, d) or (M, c, d, 3) bool, optional (default: all observed)
    saturation     float, optional: radiance >= saturation is masked out
    reflected      (M, a, b, 3)  optional: L_o on the lit face (observed_face must differ)
    reflected_mask (M, a, b) or (M, a, b, 3) bool, optional (default: nodes with q = 0)
    C              float, optional: boundary constant (default from eta)
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.checks import integer, real
from glsldiff.core.errors import InputError
from glsldiff.core.io import read_npz, write_npz
from glsldiff.grids.regular import FACES, RegularGrid

REQUIRED = ("shape", "h", "lit_face", "observed_face", "incoming", "radiance")
SETUPS = {"back": ("z-", "z+"), "front": ("z-", "z-")}  # setup -> (lit face, observed face)


def face_regions(face_shape: tuple[int, int], n: int) -> list[tuple[slice, slice]]:
    """The ``n x n`` projector regions of a face-node array of shape ``(rows, cols)``: the
    ``(rows, cols)`` slices of each, row-major over the regions; sizes differ by at most one
    node (``np.array_split``)."""
    fy, fx = face_shape
    integer(n, "n (regions per side)", 1, min(fy, fx))
    return [(slice(int(ys[0]), int(ys[-1]) + 1), slice(int(xs[0]), int(xs[-1]) + 1))
            for ys in np.array_split(np.arange(fy), n) for xs in np.array_split(np.arange(fx), n)]


@dataclass
class Measurements:
    """Validated measurements of one block sample (see the module docstring)."""

    shape: tuple[int, int, int]
    h: float
    lit_face: str
    observed_face: str
    incoming: NDArray[np.float64]
    radiance: NDArray[np.float64]
    mask: NDArray[np.bool_] | None = None
    eta: float = 1.3
    saturation: float | None = None
    C: float | None = None
    reflected: NDArray[np.float64] | None = None
    reflected_mask: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        shape = tuple(int(s) for s in np.asarray(self.shape).ravel())
        if len(shape) != 3:
            raise InputError(f"shape must be (nz, ny, nx), got {self.shape!r}")
        self.shape = shape  # type: ignore[assignment]
        nz, ny, nx = shape
        self.grid = RegularGrid(nx, ny, nz, h=float(self.h))  # validates sizes and h
        for name in ("lit_face", "observed_face"):
            face = str(getattr(self, name))
            if face not in FACES:
                raise InputError(f"{name}={face!r}; valid faces: {', '.join(FACES)}")
            setattr(self, name, face)
        self.eta = real(self.eta, "eta (relative refractive index)", 0.0, lo_open=True)
        self.incoming = self._face_stack("incoming", self.incoming, self.lit_face)
        self.radiance = self._face_stack("radiance", self.radiance, self.observed_face)
        M = self.incoming.shape[0]
        if M == 0:
            raise InputError("incoming/radiance hold M = 0 illumination conditions; at least one is needed")
        if self.radiance.shape[0] != M:
            raise InputError(f"incoming has M = {M} illumination conditions but radiance has "
                             f"{self.radiance.shape[0]}")
        if np.any(self.incoming < 0):
            raise InputError(f"incoming has {int((self.incoming < 0).sum())} negative values; "
                             "incoming light q must be >= 0")
        if not np.any(self.incoming > 0):
            raise InputError("incoming is zero everywhere: no illumination condition lights the sample")
        self.mask = self._mask("mask", self.mask, self.radiance)
        self._nonnegative("radiance", self.radiance, self.mask)
        if self.reflected is not None:
            if self.observed_face == self.lit_face:
                raise InputError(f"reflected radiance is for samples observed on another face than the lit one; "
                                 f"this one lights and observes {self.lit_face}: put it in radiance")
            self.reflected = self._face_stack("reflected", self.reflected, self.lit_face)
            if self.reflected.shape[0] != M:
                raise InputError(f"incoming has M = {M} illumination conditions but reflected has "
                                 f"{self.reflected.shape[0]}")
            unlit = np.all(self.incoming == 0, axis=-1)   # the nodes a condition does not light directly
            self.reflected_mask = self._mask("reflected_mask", unlit if self.reflected_mask is None
                                             else self.reflected_mask, self.reflected)
            self._nonnegative("reflected", self.reflected, self.reflected_mask)
        elif self.reflected_mask is not None:
            raise InputError("reflected_mask is given without reflected radiance")
        if not self.mask.any():
            raise InputError("the mask observes nothing: no radiance value is used")
        for c in range(3):
            if not self.mask[..., c].any():
                raise InputError(f"the mask observes nothing in channel {c}")
            if not np.any(self.radiance[..., c][self.mask[..., c]] > 0):
                raise InputError(f"every used radiance value of channel {c} is 0; nothing to fit")
        if self.C is not None:
            self.C = real(self.C, "C (boundary constant)", 0.0, lo_open=True)

    def _face_stack(self, name: str, values: ArrayLike, face: str) -> NDArray[np.float64]:
        arr = np.asarray(values, dtype=np.float64)
        want = self.grid.face_shape(face)
        if arr.ndim == 3 and arr.shape[1:] == want:
            arr = np.repeat(arr[..., None], 3, axis=-1)
        if arr.ndim != 4 or arr.shape[1:3] != want or arr.shape[3] != 3:
            raise InputError(f"{name} has shape {arr.shape}; face {face!r} of a {self.shape} grid needs "
                             f"(M, {want[0]}, {want[1]}, 3) or (M, {want[0]}, {want[1]})")
        bad = ~np.isfinite(arr)
        if bad.any():
            m, a, b, c = np.argwhere(bad)[0]
            raise InputError(f"{name} has {int(bad.sum())} non-finite values "
                             f"(e.g. condition {m}, node [{a}, {b}], channel {c})")
        return arr

    def _mask(self, name: str, given: ArrayLike | None, radiance: NDArray[np.float64]) -> NDArray[np.bool_]:
        shape = radiance.shape
        if given is None:
            mask = np.ones(shape, dtype=bool)
        else:
            mask = np.asarray(given)
            if mask.dtype != bool:
                raise InputError(f"{name} must be boolean, got dtype {mask.dtype}")
            if mask.shape == shape[:3]:
                mask = np.repeat(mask[..., None], 3, axis=-1)
            if mask.shape != shape:
                raise InputError(f"{name} has shape {mask.shape}; expected {shape[:3]} or {shape}")
            mask = mask.copy()
        if self.saturation is not None:
            real(self.saturation, "saturation", 0.0, lo_open=True)
            mask &= radiance < self.saturation
        return mask

    @staticmethod
    def _nonnegative(name: str, radiance: NDArray[np.float64], mask: NDArray[np.bool_]) -> None:
        if np.any(radiance[mask] < 0):
            raise InputError(f"{name} has {int((radiance[mask] < 0).sum())} negative values among the used "
                             "(masked-in) nodes; radiance must be >= 0 (subtract the black level and clip, or "
                             "mask those pixels out)")

    # ---- derived --------------------------------------------------------------
    @property
    def M(self) -> int:
        return int(self.incoming.shape[0])

    @property
    def saturated(self) -> int:
        """Number of (condition, node, channel) values dropped as saturated."""
        if self.saturation is None:
            return 0
        return sum(int(np.sum(r >= self.saturation)) for r in (self.radiance, self.reflected) if r is not None)

    @property
    def observed_faces(self) -> tuple[str, ...]:
        """The faces whose radiance is measured (the lit one too when ``reflected`` is given)."""
        return (self.observed_face,) + ((self.lit_face,) if self.reflected is not None else ())

    def channel(self, c: int) -> tuple[NDArray, NDArray, NDArray]:
        """Sources ``Q``, measurements ``Y`` and weights ``W``, each ``(n_boundary, M)`` in the
        order of ``grid.graph.boundary``, for channel ``c``."""
        def stack(face: str, a: NDArray) -> NDArray:  # (M, a, b) -> (n_boundary, M)
            return self.grid.face_to_boundary(face, np.moveaxis(a[..., c], 0, -1))

        Y, W = stack(self.observed_face, self.radiance), stack(self.observed_face, self.mask.astype(np.float64))
        if self.reflected is not None:   # another face: its boundary nodes are other rows
            Y = Y + stack(self.lit_face, self.reflected)
            W = W + stack(self.lit_face, self.reflected_mask.astype(np.float64))
        return stack(self.lit_face, self.incoming), Y, W

    def grey(self) -> bool:
        """True when the three channels hold identical data (one fit serves all three)."""
        arrays = [a for a in (self.incoming, self.radiance, self.mask, self.reflected, self.reflected_mask)
                  if a is not None]
        return all(np.array_equal(a[..., 0], a[..., c]) for a in arrays for c in (1, 2))


def save_measurements(path: str | os.PathLike, m: Measurements) -> Path:
    """Write ``m`` to an ``.npz`` file atomically (no half-written file on failure)."""
    arrays: dict[str, object] = dict(shape=np.array(m.shape), h=m.h, eta=m.eta, lit_face=m.lit_face,
                                     observed_face=m.observed_face, incoming=m.incoming,
                                     radiance=m.radiance, mask=m.mask)
    if m.saturation is not None:
        arrays["saturation"] = m.saturation
    if m.C is not None:
        arrays["C"] = m.C
    if m.reflected is not None:
        arrays.update(reflected=m.reflected, reflected_mask=m.reflected_mask)
    return write_npz(path, **arrays)


def load_measurements(path: str | os.PathLike) -> Measurements:
    """Read and validate an ``.npz`` measurement file (layout in the module docstring)."""
    data = read_npz(path, "measurements file", REQUIRED)

    def scalar(key: str, default: float | None) -> float | None:
        return float(data[key]) if key in data else default

    try:
        shape = tuple(int(s) for s in np.asarray(data["shape"]).reshape(-1))
        h = float(data["h"])
    except (TypeError, ValueError):
        raise InputError(f"measurements file {str(path)!r}: shape must be 3 integers and h one number "
                         "(mm)") from None
    return Measurements(shape=shape, h=h,
                        lit_face=str(data["lit_face"]), observed_face=str(data["observed_face"]),
                        incoming=data["incoming"], radiance=data["radiance"],
                        mask=data.get("mask"),
                        eta=scalar("eta", 1.3), saturation=scalar("saturation", None),
                        C=scalar("C", None), reflected=data.get("reflected"),
                        reflected_mask=data.get("reflected_mask"))
