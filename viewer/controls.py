"""The viewer's input state without a window: the orbit (trackball) camera, the light direction,
and the editing tool. Pure functions of numbers, tested headless.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from glsldiff.physics.editing import OPS, PROPERTIES, Brush, Edit
from glsldiff.physics.lights import DirectionalLight
from glsldiff.render.camera import Framing, frame_camera
from glsldiff.render.scene import CameraSpec, Scene

#: Radians per pixel of mouse drag.
DRAG_RADIANS = 0.01
MAX_ELEVATION = math.radians(89.0)


@dataclass(frozen=True)
class Orbit:
    """A camera on a sphere around ``target``: azimuth about +y (0 = on +z), elevation, distance (mm)."""

    target: tuple[float, float, float]
    azimuth: float
    elevation: float
    distance: float

    @classmethod
    def of(cls, eye: NDArray, target: NDArray) -> "Orbit":
        d = np.asarray(eye, float) - np.asarray(target, float)
        r = float(np.linalg.norm(d))
        return cls(tuple(float(x) for x in target), math.atan2(d[0], d[2]), math.asin(max(-1.0, min(1.0, d[1] / r))), r)

    @property
    def eye(self) -> NDArray[np.float64]:
        ce = math.cos(self.elevation)
        d = np.array([ce * math.sin(self.azimuth), math.sin(self.elevation), ce * math.cos(self.azimuth)])
        return np.asarray(self.target) + self.distance * d

    def dragged(self, dx: float, dy: float) -> "Orbit":
        """Turned by a drag of ``dx`` (right) and ``dy`` (up) pixels: the scene follows the mouse."""
        el = max(-MAX_ELEVATION, min(MAX_ELEVATION, self.elevation - dy * DRAG_RADIANS))
        return replace(self, azimuth=self.azimuth - dx * DRAG_RADIANS, elevation=el)

    def zoomed(self, clicks: float) -> "Orbit":
        """Closer by 10 % per scroll click up."""
        return replace(self, distance=self.distance * 0.9 ** clicks)

    def camera(self, fov_deg: float) -> CameraSpec:
        return CameraSpec(position=tuple(float(x) for x in self.eye), target=self.target, up=(0.0, 1.0, 0.0),
                          fov_deg=fov_deg)


def scene_orbit(scene: Scene, frame: Framing | NDArray) -> Orbit:
    """The orbit through the scene's camera (the mesh's :class:`~glsldiff.render.camera.Framing`, or
    its vertices, when it has no position)."""
    eye, target, _ = frame_camera(scene, frame)
    return Orbit.of(eye, target)


def turn_light(scene: Scene, dx: float, dy: float) -> tuple[Scene, bool]:
    """The scene with its first directional light turned by a drag (about +y, then up/down);
    ``False`` when it has none."""
    for i, lt in enumerate(scene.lights):
        if isinstance(lt, DirectionalLight):
            o = Orbit.of(np.asarray(lt.direction, float), np.zeros(3)).dragged(-dx, -dy)
            d = o.eye / np.linalg.norm(o.eye)
            lights = list(scene.lights)
            lights[i] = replace(lt, direction=tuple(float(x) for x in d))
            return replace(scene, lights=tuple(lights)), True
    return scene, False


#: Depth windows (mm below the visible surface) the D key cycles through; None: the whole depth.
DEPTHS: tuple[tuple[float, float] | None, ...] = (None, (-1.0, 2.0), (2.0, 6.0), (6.0, 1e9))
#: Values the V key cycles through, per operation (mm / mm^-1 for set, factors, mm / mm^-1 for add).
VALUES: dict[tuple[str, str], tuple[float, ...]] = {
    ("set", "mu"): (0.05, 0.2, 0.0), ("set", "kappa"): (0.05, 0.5, 2.0),
    ("multiply", "mu"): (10.0, 0.1, 2.0), ("multiply", "kappa"): (0.5, 2.0, 0.2),
    ("add", "mu"): (0.02, -0.02, 0.1), ("add", "kappa"): (0.1, -0.1, 0.5),
}


@dataclass(frozen=True)
class Tool:
    """The brush the left button paints with in edit mode."""

    prop: str = "mu"
    op: str = "multiply"
    value_index: int = 0
    radius: float = 24.0           # pixels
    strength: float = 0.5          # per dab
    depth_index: int = 1
    mask: NDArray[np.float32] | None = None
    use_mask: bool = False

    @property
    def value(self) -> float:
        vals = VALUES[(self.op, self.prop)]
        return vals[self.value_index % len(vals)]

    @property
    def depth(self) -> tuple[float, float] | None:
        return DEPTHS[self.depth_index % len(DEPTHS)]

    def cycled(self, what: str) -> "Tool":
        """The next property (``"prop"``), operation, value or depth window."""
        if what == "prop":
            return replace(self, prop=PROPERTIES[(PROPERTIES.index(self.prop) + 1) % len(PROPERTIES)], value_index=0)
        if what == "op":
            return replace(self, op=OPS[(OPS.index(self.op) + 1) % len(OPS)], value_index=0)
        if what == "value":
            return replace(self, value_index=self.value_index + 1)
        if what == "depth":
            return replace(self, depth_index=self.depth_index + 1)
        raise ValueError(what)

    def dab(self, u: float, v: float) -> Edit:
        """The edit of one brush dab at image pixel ``(u, v)`` (v down)."""
        return Edit(self.prop, self.op, self.value, brush=Brush((u, v), self.radius, 0.4),
                    mask=self.mask if self.use_mask else None, depth=self.depth, strength=self.strength)

    def describe(self) -> str:
        d = self.depth
        depth = "all depths" if d is None else f"depth {d[0]:g}..{d[1]:g} mm" if d[1] < 1e8 else f"depth > {d[0]:g} mm"
        mask = ", mask" if self.use_mask and self.mask is not None else ""
        return f"{self.op} {self.prop} {self.value:g}, r {self.radius:.0f} px, {depth}{mask}"


def with_size(scene: Scene, width: int, height: int) -> Scene:
    """The scene rendered at the window's framebuffer size."""
    return replace(scene, output=replace(scene.output, width=int(width), height=int(height)))


def fixed_exposure(scene: Scene, exposure: float) -> Scene:
    """The scene with a fixed exposure (edits must not be hidden by auto exposure)."""
    return replace(scene, output=replace(scene.output, exposure=float(exposure)))


__all__ = ["Orbit", "Tool", "scene_orbit", "turn_light", "with_size", "fixed_exposure", "DEPTHS", "VALUES"]
