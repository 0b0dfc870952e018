"""Capture plan: the paper's acquisition protocol as projector images plus a plan file.

Wang et al. 2008, section 4.1: the face of the block sample that receives light is split
into ``n x n`` regions (4 x 4 in the paper); each region is lit alone and captured with an
exposure bracket (1/30 s .. 8 s) that is merged to HDR. Thin samples are back-lit (camera on
the opposite face), thick ones front-lit (camera beside the projector, only points not
directly lit are used). Three extra conditions calibrate the capture: ``black`` (all-black
image on the sample: the projector's black level lights the whole sample, and this capture is
subtracted from every region), and ``white`` / ``reference_black`` (all-white and all-black
images on a white reference target of known albedo, in the sample's place: the incoming
irradiance in camera units, and the projector's black-level ratio).

Regions are defined on the sample's face nodes (the measurement grid), and drawn into the
projector image through the homography that maps the lit face's corners (in mm, face
coordinates) to projector pixels: from the projector calibration or measured directly.

``plan.json`` (written by :func:`write_plan`)::

    {"version": 1, "setup": "back"|"front", "n": 4, "shape": [nz, ny, nx], "h": mm,
     "lit_face": "z-", "observed_face": "z+", "exposures": [s, ...],
     "projector_size": [cols, rows], "face_to_projector": 3x3 homography,
     "conditions": [{"name": "region_00", "image": "region_00.png",
                     "rows": [y0, y1], "cols": [x0, x1]}, ...,   # face-node index ranges, end exclusive
                    {"name": "black", ...}, {"name": "white", ...}, {"name": "reference_black", ...}]}

Command: ``glsldiff capture plan OUT --shape NZ NY NX --h MM --face-corners X,Y X,Y X,Y X,Y``
(:func:`face_homography`, :class:`CapturePlan`, :func:`write_plan`).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from glsldiff.calibration.common import atomic_folder
from glsldiff.core.checks import choice, integer, real
from glsldiff.core.errors import InputError
from glsldiff.inverse.measurements import SETUPS, face_regions

REFERENCE_CONDITIONS = ("white", "reference_black")  # captured with the white reference in place
PAPER_EXPOSURES = (1 / 30, 1 / 15, 1 / 8, 1 / 4, 1 / 2, 1.0, 2.0, 4.0, 8.0)  # s: the paper's 1/30 .. 8 s, one stop apart


@dataclass
class Condition:
    """One illumination condition: a projector image, and for region conditions the lit
    face-node index ranges (end exclusive) on the ``(ny-2, nx-2)`` face array."""

    name: str
    image: str
    rows: tuple[int, int] | None = None
    cols: tuple[int, int] | None = None

    @property
    def is_region(self) -> bool:
        return self.rows is not None


@dataclass
class CapturePlan:
    """What to project and capture for one block sample (see the module docstring)."""

    shape: tuple[int, int, int]
    h: float
    setup: str = "back"
    n: int = 4
    exposures: tuple[float, ...] = PAPER_EXPOSURES
    projector_size: tuple[int, int] = (1024, 768)
    face_to_projector: NDArray[np.float64] = field(default_factory=lambda: np.eye(3))
    conditions: list[Condition] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.shape = tuple(int(s) for s in self.shape)  # type: ignore[assignment]
        if len(self.shape) != 3 or min(self.shape) < 3:
            raise InputError(f"shape={self.shape}: the sample grid needs (nz, ny, nx), each >= 3 nodes")
        self.h = real(self.h, "h (node spacing, mm)", 0.0, lo_open=True)
        choice(self.setup, "setup", tuple(SETUPS))
        integer(self.n, "n (regions per side)", 1, min(self.face_shape))
        if self.setup == "front" and self.n < 2:
            raise InputError("a front-lit plan needs n >= 2: with one region every observed node is lit")
        ex = tuple(float(e) for e in self.exposures)
        if len(ex) < 2 or min(ex) <= 0 or len(set(ex)) != len(ex):
            raise InputError(f"exposures={self.exposures!r}: an HDR bracket needs >= 2 distinct times > 0 s")
        self.exposures = tuple(sorted(ex))
        H = np.asarray(self.face_to_projector, dtype=np.float64)
        if H.shape != (3, 3) or not np.all(np.isfinite(H)) or abs(np.linalg.det(H)) < 1e-12:
            raise InputError("face_to_projector must be an invertible 3x3 homography")
        self.face_to_projector = H
        if not self.conditions:
            self.conditions = self._default_conditions()

    @property
    def lit_face(self) -> str:
        return SETUPS[self.setup][0]

    @property
    def observed_face(self) -> str:
        return SETUPS[self.setup][1]

    @property
    def face_shape(self) -> tuple[int, int]:
        """Face-node array shape ``(ny-2, nx-2)`` of the z faces."""
        return self.shape[1] - 2, self.shape[2] - 2

    @property
    def regions(self) -> list[Condition]:
        return [c for c in self.conditions if c.is_region]

    def condition(self, name: str) -> Condition:
        for c in self.conditions:
            if c.name == name:
                return c
        raise InputError(f"the plan has no condition {name!r}")

    def _default_conditions(self) -> list[Condition]:
        out = [Condition(f"region_{k:02d}", f"region_{k:02d}.png", (rows.start, rows.stop), (cols.start, cols.stop))
               for k, (rows, cols) in enumerate(face_regions(self.face_shape, self.n))]
        return out + [Condition("black", "black.png"), Condition("white", "white.png"),
                      Condition("reference_black", "reference_black.png")]

    # ---- geometry -----------------------------------------------------------------------
    def node_mm(self, row: float, col: float) -> tuple[float, float]:
        """Face coordinates (mm) of face-node index ``(row, col)``; node (0, 0) is the first
        boundary node, one spacing in from the block's corner."""
        return ((col + 1) * self.h, (row + 1) * self.h)

    def face_incoming(self, cond: Condition) -> NDArray[np.float64]:
        """``(ny-2, nx-2)`` mask of the face nodes a region condition lights (1) or not (0)."""
        q = np.zeros(self.face_shape)
        if cond.is_region:
            q[cond.rows[0]:cond.rows[1], cond.cols[0]:cond.cols[1]] = 1.0
        return q

    def projector_image(self, cond: Condition) -> NDArray[np.uint8]:
        """8-bit projector image of a condition: the region's quadrilateral (half a node
        spacing beyond its outer nodes) in white, the rest black."""
        w, h = self.projector_size
        img = np.zeros((h, w), dtype=np.uint8)
        if cond.name == "white":
            img[:] = 255
        elif cond.is_region:
            (r0, r1), (c0, c1) = cond.rows, cond.cols
            corners = [self.node_mm(r - 0.5, c - 0.5) for r, c in ((r0, c0), (r0, c1), (r1, c1), (r1, c0))]
            pts = cv2.perspectiveTransform(np.array(corners, dtype=np.float64).reshape(-1, 1, 2),
                                           self.face_to_projector).reshape(-1, 2)
            cv2.fillConvexPoly(img, np.round(pts * 16).astype(np.int32), 255, lineType=cv2.LINE_AA, shift=4)
        return img

    # ---- file ---------------------------------------------------------------------------
    def to_json(self) -> dict:
        return {"version": 1, "setup": self.setup, "n": self.n, "shape": list(self.shape), "h": self.h,
                "lit_face": self.lit_face, "observed_face": self.observed_face,
                "exposures": list(self.exposures), "projector_size": list(self.projector_size),
                "face_to_projector": self.face_to_projector.tolist(),
                "conditions": [{k: v for k, v in (("name", c.name), ("image", c.image),
                                                  ("rows", list(c.rows) if c.rows else None),
                                                  ("cols", list(c.cols) if c.cols else None)) if v is not None}
                               for c in self.conditions]}

    @classmethod
    def from_json(cls, data: dict) -> "CapturePlan":
        try:
            conds = [Condition(c["name"], c["image"], tuple(c["rows"]) if "rows" in c else None,
                               tuple(c["cols"]) if "cols" in c else None) for c in data["conditions"]]
            return cls(tuple(data["shape"]), float(data["h"]), data["setup"], int(data["n"]),
                       tuple(data["exposures"]), tuple(data["projector_size"]),
                       np.array(data["face_to_projector"]), conds)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"plan file is malformed: {type(exc).__name__}: {exc}") from None


def face_homography(corners_px: NDArray, plan_shape: tuple[int, int, int], h: float) -> NDArray[np.float64]:
    """Homography from face coordinates (mm) to image pixels given the pixels of the face's
    four block corners in the order (0, 0), (W, 0), (W, H), (0, H) mm, ``W = (nx-1) h``,
    ``H = (ny-1) h``."""
    c = np.asarray(corners_px, dtype=np.float64).reshape(4, 2)
    _, ny, nx = plan_shape
    W, H = (nx - 1) * h, (ny - 1) * h
    src = np.array([[0, 0], [W, 0], [W, H], [0, H]], dtype=np.float64)
    return cv2.getPerspectiveTransform(src.astype(np.float32), c.astype(np.float32)).astype(np.float64)


def write_plan(plan: CapturePlan, folder: str | os.PathLike) -> Path:
    """Write the projector images and ``plan.json`` into ``folder`` (created; must not
    exist or be empty). Written to a temporary folder first and renamed, so a failure never
    leaves a partial plan."""
    with atomic_folder(folder) as tmp:
        for cond in plan.conditions:
            if not cv2.imwrite(str(tmp / cond.image), plan.projector_image(cond)):
                raise InputError(f"cannot write {tmp / cond.image}")
        (tmp / "plan.json").write_text(json.dumps(plan.to_json(), indent=1))
    return Path(folder)


def load_plan(folder_or_file: str | os.PathLike) -> CapturePlan:
    """Read ``plan.json`` (a folder holding it, or the file itself)."""
    p = Path(folder_or_file)
    f = p / "plan.json" if p.is_dir() else p
    if not f.is_file():
        raise InputError(f"plan file {str(f)!r} does not exist")
    try:
        data = json.loads(f.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"cannot read plan file {str(f)!r}: {exc}") from None
    return CapturePlan.from_json(data)
