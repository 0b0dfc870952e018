"""Measurements of a block sample rendered by Monte Carlo (Mitsuba 3), for the inverse fit.

:func:`glsldiff.inverse.synthetic.synthetic_measurements` renders the region-lit captures with
glsldiff's own diffusion model, so a fit of them can only show that the optimiser inverts that
model. :func:`mitsuba_measurements` renders the same captures by path tracing instead, so the
fit must bridge the model's own error too, and the recovered coefficients are compared with
the physical truth:

* the block: nodes ``(nz, ny, nx)`` at spacing ``h`` (mm) span a box of ``(n - 1) h`` on each
  axis centred at the origin (boundary nodes on its faces), filled with the node material as Mitsuba's grid
  volume (cell centred on the nodes, trilinear): ``sigma_a = mu``, ``sigma_s = 1/(3 kappa) - mu``
  with the isotropic phase function; index matched (eta = 1, Mitsuba's null boundary);
* each of the ``n x n`` regions of the lit face ``z-`` (:func:`glsldiff.inverse.measurements.
  face_regions`) is lit by a Lambertian rectangle of radiance ``1/pi`` covering the region's
  node cells, ``GAP_MM`` below the face (reached by phase sampling only: Mitsuba's next-event
  estimation through the index-matched boundary lost light depending on the region's position,
  see :mod:`glsldiff.validation.mitsuba`): the incoming ``q`` at each lit-face node is its exact
  irradiance (:func:`glsldiff.physics.area.area_beams`; 1 inside the region, a narrow
  penumbra at its edge);
* the observed face ``z+`` is imaged by an orthographic camera with one pixel per face node (pixel
  centres on the nodes, box filter over the node's cell; parallel rays, no perspective); the unscattered light (the
  rectangle seen straight through the block) is removed exactly, path by path
  (:func:`glsldiff.validation.mitsuba.render_scattering_orders`), as the capture's projector
  would not send it to the camera. Single and multiple scattering stay: the diffusion model is
  calibrated against both (``glsldiff validate``);
* setup ``both``: the lit face ``z-`` is imaged too (the reflection), by a second orthographic
  camera below it, one pixel per face node. The rectangles then get a ``null`` BSDF: they emit
  (one-sided, towards ``+z``) but let everything through, so that camera sees the face through
  them (Mitsuba's default for an emitter's shape, a black diffuse BSDF, hides the lit region
  from it); light leaving the lit face towards them is lost either way, so the ``z+`` images
  are the same as ``back``'s (equal bit for bit in the tests). The ``z-`` image's unscattered
  part is removed as well (it is 0: the camera sees the rectangles from behind). Its
  ``reflected_mask`` keeps the nodes with q < :data:`UNLIT_Q` (the region and a ring of penumbra
  are left out, as a front-lit capture leaves out the directly lit nodes), and with
  ``reflection_from_mm`` only those at least that far from the region.
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.checks import choice, real
from glsldiff.core.errors import InputError
from glsldiff.inverse.measurements import Measurements, face_regions
from glsldiff.mesh import box_mesh
from glsldiff.physics.area import area_beams
from glsldiff.physics.lights import AreaLight
from glsldiff.validation.mitsuba import McCamera, check_ldsampler_spp, render_scattering_orders

__all__ = ["mitsuba_measurements", "MITSUBA_SETUPS", "GAP_MM", "CAMERA_DISTANCE_MM"]

GAP_MM = 0.02
#: ``both``: lit-face nodes whose incoming q is below this (1 inside a region) count as not lit, the
#: only ones whose reflection is fitted (the penumbra's far tail is never exactly 0).
UNLIT_Q = 1e-3
CAMERA_DISTANCE_MM = 100.0      # an orthographic camera: one pixel per face node, any distance
#: What :func:`mitsuba_measurements` renders: back-lit, observed on z+ (``back``) or on both faces.
MITSUBA_SETUPS = ("back", "both")


def _region_light(r: tuple[slice, slice], h: float, low: NDArray) -> AreaLight:
    """The rectangle lighting face region ``r`` (rows = y, columns = x of the face-node array;
    face node (i, j) sits at ``low + ((j + 1) h, (i + 1) h, 0)``, ``low`` the block's corner)."""
    sy, sx = r
    x0, x1 = (sx.start + 0.5) * h, (sx.stop + 0.5) * h
    y0, y1 = (sy.start + 0.5) * h, (sy.stop + 0.5) * h
    return AreaLight((low[0] + 0.5 * (x0 + x1), low[1] + 0.5 * (y0 + y1), low[2] - GAP_MM), (0.0, 0.0, 1.0),
                     (x1 - x0, y1 - y0), (1.0 / math.pi,) * 3, up=(0.0, 1.0, 0.0), samples=4)


def _face_camera(face: str, low: NDArray, ext: NDArray, h: float, fx: int, fy: int) -> McCamera:
    """Orthographic camera imaging face ``z+`` or ``z-`` of the block, pixel (i, j) centred on
    face node (i, j) (after :func:`_to_face`)."""
    side = 1.0 if face == "z+" else -1.0
    z = low[2] + (ext[2] if face == "z+" else 0.0)
    return McCamera((0.0, 0.0, z + side * CAMERA_DISTANCE_MM), (0.0, 0.0, z), (0.0, 1.0, 0.0), 30.0, fx, fy,
                    width_mm=fx * h)


def _to_face(face: str, img: NDArray) -> NDArray:
    """A face camera's image as the face-node array ``[y, x]``: image row 0 is the top (+y)
    from either side; columns run along +x seen from ``z+``, along -x from ``z-``."""
    return img[::-1] if face == "z+" else img[::-1, ::-1]


def _region_distance(regions: list[tuple[slice, slice]], face_shape: tuple[int, int]) -> NDArray:
    """``(M, rows, cols)``: each face node's distance in nodes (the larger of its row and column
    offsets) from the nearest node of each region; 0 inside it."""
    i, j = np.indices(face_shape)

    def off(k: NDArray, sl: slice) -> NDArray:
        return np.maximum(np.maximum(sl.start - k, k - (sl.stop - 1)), 0)

    return np.stack([np.maximum(off(i, sy), off(j, sx)) for sy, sx in regions])


def mitsuba_measurements(kappa: NDArray, mu: NDArray, h: float, n: int, spp: int = 1024, seed: int = 0,
                         progress: Callable[[int, int, float], None] | None = None, setup: str = "back",
                         reflection_from_mm: float = 0.0) -> tuple[Measurements, dict[str, Any]]:
    """Back-lit measurements (lit ``z-``, observed ``z+``, and with ``setup="both"`` the lit face
    ``z-`` too, as ``reflected``) of the block ``(kappa, mu)`` (each ``(nz, ny, nx, 3)``, mm and
    mm^-1) with ``n x n`` regions, rendered by Mitsuba with ``spp`` samples per pixel (a power
    of 4). ``reflection_from_mm`` (``both``): fit the reflection only at nodes at least this far
    (mm, along x or y) from every node of the lit region, beyond the model's excess next to it
    (docs/guide/inverse.md: 2 mm there). Returns the measurements and an info dict (seconds, spp,
    regions, the unscattered share of each observed face's image). ``progress(done, total,
    seconds)`` after each region."""
    check_ldsampler_spp(spp)                 # before any rendering
    choice(setup, "setup", MITSUBA_SETUPS)
    reflection_from_mm = real(reflection_from_mm, "reflection_from_mm (mm)", 0.0)
    if reflection_from_mm > 0 and setup != "both":
        raise InputError(f"reflection_from_mm = {reflection_from_mm} masks the reflection, which only setup 'both' "
                         "captures; use setup='both' or leave it at 0")
    kappa, mu = np.asarray(kappa, dtype=np.float64), np.asarray(mu, dtype=np.float64)
    if kappa.ndim != 4 or kappa.shape[-1] != 3 or mu.shape != kappa.shape:
        raise InputError(f"kappa and mu must both have shape (nz, ny, nx, 3), got {kappa.shape} and {mu.shape}")
    nz, ny, nx = kappa.shape[:3]
    ext = np.array([(nx - 1) * h, (ny - 1) * h, (nz - 1) * h])
    low = -0.5 * ext                                                          # the block centred at the origin
    mesh = box_mesh(tuple(ext), origin=tuple(low))
    sigma_s = np.maximum(1.0 / (3.0 * kappa) - mu, 0.0)
    box = {"bbox_min": low - 0.5 * h, "bbox_max": low + ext + 0.5 * h}
    volume = {"sigma_a": mu, "sigma_s": sigma_s, **box}
    fy, fx = ny - 2, nx - 2
    faces = ("z+", "z-") if setup == "both" else ("z+",)
    cams = {face: _face_camera(face, low, ext, h, fx, fy) for face in faces}
    jj, ii = np.meshgrid(np.arange(fx), np.arange(fy))
    lit_nodes = low + np.stack([(jj.ravel() + 1) * h, (ii.ravel() + 1) * h, np.zeros(fx * fy)], 1)
    down = np.tile([0.0, 0.0, -1.0], (len(lit_nodes), 1))
    regions = face_regions((fy, fx), n)
    incoming = np.zeros((len(regions), fy, fx, 3))
    images = {face: np.zeros_like(incoming) for face in faces}
    unsc = dict.fromkeys(faces, 0.0)
    total = dict.fromkeys(faces, 0.0)
    t0 = time.perf_counter()
    for k, r in enumerate(regions):
        light = _region_light(r, h, low)
        g, _ = area_beams(light, lit_nodes, down, 1.0)
        incoming[k] = (g.sum(axis=1)[:, None] * np.asarray(light.radiance)).reshape(fy, fx, 3)
        for face, cam in cams.items():
            img, _ = render_scattering_orders(mesh, None, None, 1.0, cam, light, spp, seed + k, volume,
                                              area_light_transparent=setup == "both")
            sub = _to_face(face, np.asarray(img["single"] + img["multiple"], dtype=np.float64))
            images[face][k] = np.maximum(sub, 0.0)  # float32 differences of equal paths: -1e-9 at worst
            unsc[face] += float(img["unscattered"].sum())
            total[face] += float(img["full"].sum())
        if progress is not None:
            progress(k + 1, len(regions), time.perf_counter() - t0)
    reflected, reflected_mask = None, None
    if setup == "both":
        reflected = images["z-"]
        reflected_mask = (incoming.max(axis=-1) < UNLIT_Q) & (_region_distance(regions, (fy, fx)) * h
                                                              >= reflection_from_mm - 1e-9 * h)
    meas = Measurements((nz, ny, nx), h, "z-", "z+", incoming, images["z+"], None, eta=1.0,
                        reflected=reflected, reflected_mask=reflected_mask)
    share = {face: unsc[face] / max(total[face], 1e-300) for face in faces}
    return meas, {"seconds": time.perf_counter() - t0, "spp": spp, "regions": len(regions), "setup": setup,
                  "unscattered_shares": share}
