"""Regular block grids (the acquisition sample of Wang et al. 2008, section 4.4).

A block sample is an ``nx x ny x nz`` lattice of nodes with spacing ``h`` (mm).
Volume arrays are indexed ``[z, y, x]`` (C order, z slowest), optionally with a
trailing RGB axis.

Node kinds
----------
* **interior**: ``1 <= x <= nx-2`` and likewise in y and z; the diffusion equation
  (paper eq. 8, first line) holds there.
* **boundary**: on exactly one of the six faces, e.g. ``x == 0`` with y, z inside.
  Each is linked to the interior node one step along the inward normal and carries
  the boundary condition (eq. 8, second line) with source ``q``.
* **inactive**: on an edge or corner of the block. The 6-point stencil of no interior
  node reaches them and no boundary condition is defined there (the regular-grid
  counterpart of the polygrid's removed nodes, paper figure 4 (c)); they hold 0.

Face arrays (``q`` in, radiance out) cover only the boundary nodes of one face:

=======  ======================  ==================
face     volume slice            face array shape
=======  ======================  ==================
``z-``   ``[0, 1:-1, 1:-1]``     ``(ny-2, nx-2)``
``z+``   ``[-1, 1:-1, 1:-1]``    ``(ny-2, nx-2)``
``y-``   ``[1:-1, 0, 1:-1]``     ``(nz-2, nx-2)``
``y+``   ``[1:-1, -1, 1:-1]``    ``(nz-2, nx-2)``
``x-``   ``[1:-1, 1:-1, 0]``     ``(nz-2, ny-2)``
``x+``   ``[1:-1, 1:-1, -1]``    ``(nz-2, ny-2)``
=======  ======================  ==================

GPU packing: each z-slice is a texture block of ``nx x ny`` texels, blocks laid out
row by row in a ``tiles_x x tiles_y`` mosaic by increasing z (paper section 5.2,
figure 6, for a single cube).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
from typing import Mapping

from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError
from glsldiff.grids.graph import BOUNDARY, INACTIVE, INTERIOR, NodeGraph
from glsldiff.packing import Mosaic

__all__ = ["RegularGrid", "FACES", "INACTIVE", "INTERIOR", "BOUNDARY"]

# face name -> (axis of the volume array [z, y, x], side index 0 or -1)
FACES: dict[str, tuple[int, int]] = {
    "x-": (2, 0), "x+": (2, -1),
    "y-": (1, 0), "y+": (1, -1),
    "z-": (0, 0), "z+": (0, -1),
}


def _face_index(name: str) -> tuple[slice | int, ...]:
    if name not in FACES:
        raise InputError(f"unknown face {name!r}; valid faces: {', '.join(FACES)}")
    axis, side = FACES[name]
    idx: list[slice | int] = [slice(1, -1)] * 3
    idx[axis] = side
    return tuple(idx)


@dataclass(frozen=True)
class RegularGrid:
    """An ``nx x ny x nz`` node lattice with spacing ``h`` in mm.

    Parameters
    ----------
    nx, ny, nz
        Node counts per axis, boundary layer included (each >= 3).
    h
        Node spacing in mm.
    max_texture_size
        Largest texture edge the packing may use (texels).
    kept_blocks
        z-slices held in the packed textures (default all), see :meth:`with_blocks`.
    """

    nx: int
    ny: int
    nz: int
    h: float = 1.0
    max_texture_size: int = 16384
    kept_blocks: tuple[bool, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("nx", "ny", "nz"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool):
                raise InputError(f"grid {name} must be an integer, got {v!r}")
            if v < 3:
                raise InputError(
                    f"grid {name}={v}: a block needs at least 3 nodes per axis "
                    "(one interior layer between two boundary faces); the grid is empty")
        if not (isinstance(self.h, (int, float, np.floating)) and math.isfinite(self.h) and self.h > 0):
            raise InputError(f"grid spacing h={self.h!r} mm must be a finite number > 0")
        self.mosaic  # validates the texture size

    # ---- node classification -------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int]:
        """Volume array shape ``(nz, ny, nx)``."""
        return (self.nz, self.ny, self.nx)

    @property
    def size(self) -> int:
        """Number of lattice points, inactive ones included."""
        return self.nx * self.ny * self.nz

    @cached_property
    def kind(self) -> NDArray[np.int8]:
        """``(nz, ny, nx)`` int8: INACTIVE, INTERIOR or BOUNDARY per node."""
        on_face = np.zeros(self.shape, dtype=np.int8)
        for axis in range(3):
            sl = [slice(None)] * 3
            for side in (0, -1):
                sl[axis] = side
                on_face[tuple(sl)] += 1
        kind = np.full(self.shape, INACTIVE, dtype=np.int8)
        kind[on_face == 0] = INTERIOR
        kind[on_face == 1] = BOUNDARY
        return kind

    @cached_property
    def active(self) -> NDArray[np.bool_]:
        """``(nz, ny, nx)`` bool: nodes that carry an unknown."""
        return self.kind != INACTIVE

    @cached_property
    def positions(self) -> NDArray[np.float64]:
        """``(size, 3)`` node positions ``(x h, y h, z h)`` in mm, flat (C) order."""
        z, y, x = np.indices(self.shape).reshape(3, -1)
        return np.stack([x, y, z], axis=1) * float(self.h)

    @property
    def boundary_positions(self) -> NDArray[np.float64]:
        """``(n_boundary, 3)`` positions of the boundary nodes (``graph.boundary`` order), mm."""
        return self.positions[self.graph.boundary]

    @property
    def n_interior(self) -> int:
        return (self.nx - 2) * (self.ny - 2) * (self.nz - 2)

    @property
    def n_boundary(self) -> int:
        return 2 * ((self.nx - 2) * (self.ny - 2) + (self.ny - 2) * (self.nz - 2)
                    + (self.nx - 2) * (self.nz - 2))

    @property
    def n_active(self) -> int:
        """Number of unknowns (interior + boundary nodes)."""
        return self.n_interior + self.n_boundary

    @cached_property
    def link(self) -> NDArray[np.int64]:
        """``(nz, ny, nx)`` flat index of each boundary node's interior partner (-1 elsewhere)."""
        link = np.full(self.shape, -1, dtype=np.int64)
        flat = np.arange(self.size).reshape(self.shape)
        for name, (axis, side) in FACES.items():
            idx = _face_index(name)
            inner = list(idx)
            inner[axis] = 1 if side == 0 else -2
            link[idx] = flat[tuple(inner)]
        return link

    @cached_property
    def graph(self) -> NodeGraph:
        """Connectivity for the generic assembler: 6 neighbours of weight ``1/h^2`` (scaled
        weight 1, row scale ``h^2``), boundary partner at ``d = h``."""
        kind = self.kind.ravel()
        interior = np.flatnonzero(kind == INTERIOR)
        strides = (1, self.nx, self.nx * self.ny)
        nb = np.stack([interior + sign * s for s in strides for sign in (-1, 1)], axis=1)
        boundary = np.flatnonzero(kind == BOUNDARY)
        return NodeGraph(kind, nb, np.ones(nb.shape), np.full(interior.size, float(self.h) ** 2),
                         self.link.ravel()[boundary], np.full(boundary.size, float(self.h)))

    # ---- faces ---------------------------------------------------------------
    def face_shape(self, name: str) -> tuple[int, int]:
        """Shape of the face array of face ``name`` (see module docstring)."""
        return tuple(np.empty(self.shape, dtype=np.int8)[_face_index(name)].shape)  # type: ignore[return-value]

    def face(self, volume: ArrayLike, name: str) -> NDArray:
        """The boundary-node values of face ``name`` from a volume array."""
        return np.asarray(volume)[_face_index(name)]

    def face_volume(self, faces: dict[str, ArrayLike], channels: int = 3) -> NDArray[np.float64]:
        """Scatter per-face arrays into a ``(nz, ny, nx, channels)`` volume (0 elsewhere).

        Each face array has the face shape, optionally with a trailing channel axis
        of 1 or ``channels``, or is a scalar / ``(channels,)`` value for the whole
        face; faces not given are 0.
        """
        out = np.zeros(self.shape + (channels,), dtype=np.float64)
        for name, values in faces.items():
            want = self.face_shape(name)
            arr = np.asarray(values, dtype=np.float64)
            if arr.ndim == 0 or arr.shape == (channels,):  # uniform over the face
                arr = np.broadcast_to(arr, want + (channels,))
            elif arr.shape == want:
                arr = arr[..., None]
            if arr.shape[:2] != want or arr.ndim != 3 or arr.shape[2] not in (1, channels):
                raise InputError(
                    f"face {name!r} array has shape {np.shape(values)}, expected {want} or "
                    f"{want + (channels,)} for a {self.nx}x{self.ny}x{self.nz} grid")
            out[_face_index(name)] = arr
        return out

    def source_volume(self, q: ArrayLike | Mapping[str, ArrayLike] | None) -> NDArray[np.float64]:
        """Boundary source ``q`` as a ``(nz, ny, nx, 3)`` volume, 0 off the boundary.

        ``q`` is either a mapping face name -> face array (see :mod:`glsldiff.grids.regular`) or a
        full volume of shape ``(nz, ny, nx)`` / ``(nz, ny, nx, 3)`` that is zero at every
        non-boundary node; ``None`` is zero. Negative values are allowed (adjoint sources
        are signed).
        """
        if q is None:
            q = {}
        if isinstance(q, Mapping):
            vol = self.face_volume(q)
        else:
            vol = np.asarray(q, dtype=np.float64)
            if vol.shape == self.shape:
                vol = vol[..., None]
            if vol.shape[:3] != self.shape or vol.ndim != 4 or vol.shape[3] not in (1, 3):
                raise InputError(
                    f"q has shape {np.shape(q)}; expected {self.shape} or {self.shape + (3,)} "
                    "(or a dict of face arrays)")
            vol = np.broadcast_to(vol, self.shape + (3,)).copy()
            off = (self.kind != BOUNDARY) & np.any(vol != 0, axis=-1)
            if off.any():
                z, y, x = np.argwhere(off)[0]
                raise InputError(
                    f"q is non-zero at {int(off.sum())} nodes that are not boundary nodes "
                    f"(e.g. x={x}, y={y}, z={z}); q is only defined on the six faces, "
                    "edges and corners excluded")
        bad = ~np.isfinite(vol)
        if bad.any():
            z, y, x, c = np.argwhere(bad)[0]
            raise InputError(f"q has {int(bad.sum())} non-finite values (e.g. x={x}, y={y}, z={z}, channel {c})")
        return vol

    def boundary_values(self, volume: ArrayLike) -> dict[str, NDArray]:
        """The boundary-node values of a volume array, as a dict of face arrays."""
        return {name: self.face(volume, name) for name in FACES}

    @cached_property
    def _face_slots(self) -> dict[str, NDArray[np.int64]]:
        """Per face, the position in ``graph.boundary`` order of each face-array node."""
        slot = np.full(self.size, -1, dtype=np.int64)
        slot[self.graph.boundary] = np.arange(self.graph.boundary.size)
        flat = slot.reshape(self.shape)
        return {name: flat[_face_index(name)] for name in FACES}

    def _slots(self, name: str) -> NDArray[np.int64]:
        _face_index(name)  # InputError for an unknown face name
        return self._face_slots[name]

    def face_to_boundary(self, name: str, values: ArrayLike) -> NDArray[np.float64]:
        """Face array ``face_shape + (k...)`` -> ``(n_boundary, k...)`` values in the order of
        ``graph.boundary``, 0 at the boundary nodes of the other faces."""
        slots = self._slots(name)
        v = np.asarray(values, dtype=np.float64)
        if v.shape[:2] != slots.shape:
            raise InputError(f"face {name!r} values have shape {v.shape}, expected {slots.shape} first")
        out = np.zeros((self.graph.boundary.size,) + v.shape[2:])
        out[slots.ravel()] = v.reshape((-1,) + v.shape[2:])
        return out

    def boundary_to_face(self, name: str, values: ArrayLike) -> NDArray:
        """Inverse of :meth:`face_to_boundary`: ``(n_boundary, k...)`` -> ``face_shape + (k...)``."""
        slots = self._slots(name)
        return np.asarray(values)[slots]

    # ---- texture packing -----------------------------------------------------
    @cached_property
    def mosaic(self) -> Mosaic:
        """The z-slices as ``nx x ny`` texel blocks (see :class:`glsldiff.packing.Mosaic`), only
        the :attr:`kept_blocks` where given."""
        kept = None if self.kept_blocks is None else np.array(self.kept_blocks, dtype=bool)
        return Mosaic(self.nx, self.ny, self.nz, self.max_texture_size, kept)

    def with_blocks(self, kept: NDArray[np.bool_] | None) -> "RegularGrid":
        """The same grid packed with only the ``kept`` z-slices (``(nz,)`` bool; ``None``: all):
        node arrays keep their shape, the textures drop the other slices, whose nodes no
        solver pass may then read."""
        return replace(self, kept_blocks=None if kept is None else tuple(bool(k) for k in np.asarray(kept)))

    @property
    def tiles(self) -> tuple[int, int]:
        """``(tiles_x, tiles_y)``: z-slice blocks per texture row and column."""
        return self.mosaic.tiles

    @property
    def texture_size(self) -> tuple[int, int]:
        """``(width, height)`` of the packed texture in texels."""
        return self.mosaic.texture_size

    def tile_origin(self, z: int) -> tuple[int, int]:
        """Texel ``(x, y)`` of node ``(x=0, y=0)`` of z-slice ``z``."""
        x, y = self.mosaic.block_origin(z)
        return int(x), int(y)

    def pack(self, volume: ArrayLike, components: int = 4) -> NDArray[np.float32]:
        """``(nz, ny, nx[, c])`` volume -> ``(height, width, components)`` float32 texture."""
        vol = np.asarray(volume, dtype=np.float32)
        if vol.shape[:3] != self.shape:
            raise InputError(f"volume shape {vol.shape} does not match grid {self.shape}")
        return self.mosaic.pack(vol.reshape(self.size, -1), components)

    def unpack(self, texture: ArrayLike, channels: int = 3) -> NDArray[np.float32]:
        """Inverse of :meth:`pack`: ``(height, width, c)`` -> ``(nz, ny, nx, channels)``."""
        return self.mosaic.unpack(texture, channels)
