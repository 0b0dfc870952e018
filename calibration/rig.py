"""Capture drivers: the interface real hardware plugs into, the capture loop, and a virtual
rig that renders captures of a sample with the glsldiff forward solver.

A real setup implements :class:`ProjectorDriver` (``show`` an 8-bit image) and
:class:`CameraDriver` (``capture`` an exposure, returning 8-bit RGB) and, where the
operator must swap the sample for the white reference, :meth:`CameraDriver.set_scene`.
:func:`run_capture` executes a :class:`~glsldiff.calibration.plan.CapturePlan`: for every
condition it shows the projector image and captures the exposure bracket into
``OUT/<condition>/img_XX.png`` with an ``exposures.json`` sidecar ({file: seconds}).

Conditions and scenes: every region condition and ``black`` are captured with the sample in
place (``black`` is subtracted from each region: the projector's black level lights the whole
sample); ``white`` and ``reference_black`` are captured with the white reference target
(known albedo) in the sample's place: the incoming irradiance in camera units.

:class:`VirtualRig` simulates it all. Geometry (mm): the block spans
``[0, (nx-1) h] x [0, (ny-1) h] x [0, (nz-1) h]``, the lit face is ``z = 0`` with the projector
on the ``-z`` side; face node ``(row, col)`` sits at ``x = (col+1) h, y = (row+1) h``. The
camera looks at the observed face (``z+`` from the ``+z`` side when back-lit, ``z-`` beside the
projector when front-lit). Simplification: the white reference is rendered as if placed at
the observed face, lit by the projector with the irradiance the lit face receives.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from glsldiff.calibration.common import atomic_folder
from glsldiff.calibration.plan import REFERENCE_CONDITIONS, CapturePlan
from glsldiff.calibration.simcam import SimCamera, SimProjector, intersect_plane
from glsldiff.core.camera import opencv_pose
from glsldiff.core.checks import choice
from glsldiff.core.errors import InputError
from glsldiff.grids.regular import RegularGrid
from glsldiff.inverse.model import ForwardModel
from glsldiff.physics.optics import fresnel_transmittance

Array = NDArray[np.float64]
SCENES = ("sample", "reference")


class ProjectorDriver(Protocol):
    size: tuple[int, int]

    def show(self, image: NDArray[np.uint8]) -> None:
        """Display an 8-bit ``(rows, cols)`` or ``(rows, cols, 3)`` image full screen."""


class CameraDriver(Protocol):
    def set_scene(self, scene: str) -> None:
        """``"sample"`` or ``"reference"``: prompt the operator (or move a stage)."""

    def capture(self, seconds: float) -> NDArray[np.uint8]:
        """One 8-bit RGB exposure ``(rows, cols, 3)`` of ``seconds``."""


def run_capture(plan: CapturePlan, projector: ProjectorDriver, camera: CameraDriver,
                out: str | os.PathLike, progress: bool = False) -> Path:
    """Capture every condition of ``plan`` into ``out`` (see the module docstring). The
    captures go to a temporary folder renamed to ``out`` only when all succeeded."""
    if tuple(projector.size) != tuple(plan.projector_size):
        raise InputError(f"projector size {projector.size} differs from the plan's {plan.projector_size}")
    conds = plan.conditions
    if progress:
        conds = tqdm(conds, desc="capture", unit="condition")
    with atomic_folder(out) as tmp:
        for cond in conds:
            camera.set_scene("reference" if cond.name in REFERENCE_CONDITIONS else "sample")
            projector.show(plan.projector_image(cond))
            folder = tmp / cond.name
            folder.mkdir()
            times = {}
            for k, seconds in enumerate(plan.exposures):
                name = f"img_{k:02d}.png"
                img = np.asarray(camera.capture(seconds))
                if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
                    raise InputError(f"camera returned {img.dtype} {img.shape}; 8-bit RGB is required")
                if not cv2.imwrite(str(folder / name), img[..., ::-1]):
                    raise InputError(f"cannot write {folder / name}")
                times[name] = seconds
            (folder / "exposures.json").write_text(json.dumps(times, indent=1))
        (tmp / "plan.json").write_text(json.dumps(plan.to_json(), indent=1))
    return Path(out)


@dataclass
class VirtualRig:
    """Simulated camera + projector + sample (implements both driver protocols).

    Parameters
    ----------
    kappa, mu
        The sample, ``(nz, ny, nx, 3)`` in mm and mm^-1.
    h
        Node spacing, mm.
    plan
        The capture plan (setup, regions, projector size).
    camera, projector
        Simulated devices; default ones are placed by :func:`default_devices`.
    sensitivity
        Camera channel sensitivities (what white balance corrects).
    reference_albedo
        Albedo of the white reference target.
    surface_reflection
        Albedo of the direct surface reflection seen on lit nodes (front-lit only).
    """

    kappa: Array
    mu: Array
    h: float
    plan: CapturePlan
    camera: SimCamera | None = None
    projector: SimProjector | None = None
    sensitivity: tuple[float, float, float] = (1.0, 0.85, 0.7)
    reference_albedo: float = 0.9
    surface_reflection: float = 0.04
    eta: float = 1.3
    seed: int = 0
    scene: str = "sample"
    _pattern: NDArray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        nz, ny, nx = self.kappa.shape[:3]
        if tuple(self.plan.shape) != (nz, ny, nx):
            raise InputError(f"sample shape {(nz, ny, nx)} differs from the plan's {self.plan.shape}")
        self.grid = RegularGrid(nx, ny, nz, h=self.h)
        if self.camera is None or self.projector is None:
            cam, proj = default_devices(self.plan)
            self.camera = self.camera or cam
            self.projector = self.projector or proj
        self.size = self.projector.size
        self._rng = np.random.default_rng(self.seed)
        self._model = ForwardModel(self.grid, eta=self.eta)
        self._factors = [self._model.factorize(self._model.active_values(self.kappa[..., c]),
                                               self._model.active_values(self.mu[..., c])) for c in range(3)]
        self._ft = float(fresnel_transmittance(self.eta, 1.0))
        self._cache: dict[bytes, Array] = {}

    # ---- driver protocol ----------------------------------------------------------------
    def set_scene(self, scene: str) -> None:
        choice(scene, "scene", SCENES)
        self.scene = scene

    def show(self, image: NDArray[np.uint8]) -> None:
        self._pattern = np.asarray(image)

    def capture(self, seconds: float) -> NDArray[np.uint8]:
        L = self.radiance_image()
        img = self.camera.capture(L * np.asarray(self.sensitivity), seconds, self._rng)
        return img

    # ---- rendering ----------------------------------------------------------------------
    def face_points(self, z: float) -> Array:
        """World positions ``(ny-2, nx-2, 3)`` of the face nodes of the plane ``z``."""
        fy, fx = self.plan.face_shape
        r, c = np.mgrid[0:fy, 0:fx].astype(np.float64)
        return np.stack([(c + 1) * self.h, (r + 1) * self.h, np.full(r.shape, z)], axis=-1)

    def irradiance(self) -> Array:
        """Projector irradiance ``(ny-2, nx-2, 3)`` at the lit face's nodes for the current image."""
        if self._pattern is None:
            raise InputError("the projector shows nothing yet: call show() first")
        pat = self._pattern.astype(np.float64) / 255.0
        X = self.face_points(0.0).reshape(-1, 3)
        E = self.projector.illuminate(pat, X)
        if E.ndim == 1:
            E = np.repeat(E[:, None], 3, axis=1)
        return E.reshape(self.plan.face_shape + (3,))

    def face_radiance(self) -> Array:
        """Radiance ``(ny-2, nx-2, 3)`` leaving the observed face's nodes towards the camera."""
        E = self.irradiance()
        if self.scene == "reference":
            return self.reference_albedo * E / np.pi
        key = self._pattern.tobytes()
        if key in self._cache:
            return self._cache[key]
        g = self.grid
        lit, obs = self.plan.lit_face, self.plan.observed_face
        Q = g.face_to_boundary(lit, self._ft * E)  # (n_boundary, 3): one column per channel
        out = np.stack([g.boundary_to_face(obs, fac.radiance(fac.solve(Q[:, c:c + 1]), Q[:, c:c + 1])[:, 0])
                        for c, fac in enumerate(self._factors)], axis=-1)
        if lit == obs:
            # front-lit: the camera sees the model's outgoing part F_t a phi (its radiance
            # F_t (a phi - b q) plus the F_t b q it subtracts, which can dip below 0 where light
            # enters) plus the surface reflection: linear in the light and >= 0, and equal to the
            # fit's model where q = 0
            out = out + self._ft * self._model.exit_b * (self._ft * E) + self.surface_reflection * E / np.pi
        self._cache[key] = out
        return out

    def _pixel_map(self) -> tuple[NDArray, NDArray, NDArray]:
        """Per camera pixel: face-node coordinates (col, row) of its ray's hit on the observed
        face, and whether it hits the face (computed once per rig)."""
        if not hasattr(self, "_map"):
            z = 0.0 if self.plan.observed_face == "z-" else (self.grid.nz - 1) * self.h
            origin, dirs = self.camera.pixel_rays()
            X, hit = intersect_plane(origin, dirs, np.array([0.0, 0.0, z]), np.array([0.0, 0.0, 1.0]))
            W, H = (self.grid.nx - 1) * self.h, (self.grid.ny - 1) * self.h
            on = hit & (X[..., 0] >= 0) & (X[..., 0] <= W) & (X[..., 1] >= 0) & (X[..., 1] <= H)
            self._map = ((X[..., 0] / self.h - 1.0).astype(np.float32),
                         (X[..., 1] / self.h - 1.0).astype(np.float32), on)
        return self._map

    def radiance_image(self) -> Array:
        """Radiance ``(rows, cols, 3)`` reaching every camera pixel (0 off the sample)."""
        mx, my, on = self._pixel_map()
        img = cv2.remap(self.face_radiance().astype(np.float32), mx, my, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        return np.where(on[..., None], img, 0.0).astype(np.float64)

    def face_corners_px(self) -> Array:
        """Camera pixels of the observed face's block corners (0,0), (W,0), (W,H), (0,H) mm."""
        z = 0.0 if self.plan.observed_face == "z-" else (self.grid.nz - 1) * self.h
        W, H = (self.grid.nx - 1) * self.h, (self.grid.ny - 1) * self.h
        return self.camera.project(np.array([[0, 0, z], [W, 0, z], [W, H, z], [0, H, z]], dtype=np.float64))

    def true_incoming(self) -> Array:
        """What the measurement step should recover as ``q`` for each region ``(M, ny-2, nx-2, 3)``
        (projector white minus black, Fresnel-transmitted), in radiance units before the camera."""
        shown = self._pattern
        self.show(self.plan.projector_image(self.plan.condition("black")))
        black = self.irradiance()
        out = []
        for cond in self.plan.regions:
            self.show(self.plan.projector_image(cond))
            out.append(self._ft * (self.irradiance() - black))
        self._pattern = shown
        return np.stack(out)


def default_devices(plan: CapturePlan, camera_size: tuple[int, int] = (640, 512),
                    pixels_per_node: float = 6.0) -> tuple[SimCamera, SimProjector]:
    """A camera framing the observed face with about ``pixels_per_node`` pixels per node
    spacing, and a projector whose frame covers the lit face, both along the z axis (the
    front-lit camera sits 15 degrees beside the projector). The camera's ``gain`` puts the
    reference white (0.29) just below saturation at 1/30 s, so that 8 s reaches radiance ~1e-5."""
    nz, ny, nx = plan.shape
    h = plan.h
    W, H, D = (nx - 1) * h, (ny - 1) * h, (nz - 1) * h
    centre = np.array([W / 2, H / 2, 0.0])
    f = pixels_per_node / h * 300.0  # camera 300 mm from the face
    K = np.array([[f, 0, (camera_size[0] - 1) / 2], [0, f, (camera_size[1] - 1) / 2], [0, 0, 1.0]])
    if plan.observed_face == "z+":
        R, t = opencv_pose(centre + [0, 0, D + 300.0], centre + [0, 0, D], up=(0, -1, 0))
    else:
        ang = np.radians(15.0)
        eye = centre + 300.0 * np.array([np.sin(ang), 0.0, -np.cos(ang)])
        R, t = opencv_pose(eye, centre, up=(0, -1, 0))
    cam = SimCamera(K, camera_size, R, t, dist=np.array([-0.05, 0.01, 0, 0, 0]), gain=50.0, vignetting=0.1)
    pw, ph = plan.projector_size
    fp = 0.9 * min(pw / W, ph / H) * 500.0  # the face fills ~90 % of the frame from 500 mm
    Kp = np.array([[fp, 0, (pw - 1) / 2], [0, fp, (ph - 1) / 2], [0, 0, 1.0]])
    Rp, tp = opencv_pose(centre - [0, 0, 500.0], centre, up=(0, -1, 0))
    proj = SimProjector(Kp, (pw, ph), Rp, tp, black=0.01)
    return cam, proj


def projector_homography(plan: CapturePlan, projector: SimProjector) -> Array:
    """Face (mm) -> projector pixel homography of the lit face, from a (calibrated) projector."""
    nz, ny, nx = plan.shape
    W, H = (nx - 1) * plan.h, (ny - 1) * plan.h
    src = np.array([[0, 0], [W, 0], [W, H], [0, H]], dtype=np.float64)
    dst = projector.project(np.concatenate([src, np.zeros((4, 1))], axis=1))
    return cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32)).astype(np.float64)
