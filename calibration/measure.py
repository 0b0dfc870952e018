"""From captured brackets to the measurements file of the inverse fit.

Per condition of the plan: merge the bracket to linear HDR (Debevec-Malik response), sample
it at the observed face's nodes, and then

* ``L_m = HDR(region_m) - HDR(black)`` -- the projector's black level lights the whole
  sample, and diffusion is linear, so subtracting the all-black capture removes it exactly;
* incoming light ``q_m = F_t(eta, 1) pi (HDR(white) - HDR(reference_black)) / albedo`` on the
  nodes of region ``m``: the irradiance the projector adds when a region is switched on,
  measured on the white reference in camera units (so ``q`` and ``L`` share units, which is
  what the fit needs; a global exposure scale cancels);
* optional white-balance gains (from a colour chart) multiply both; kappa and mu do not
  depend on them, since q and L are measured through the same camera channel;
* front-lit: nodes of the lit region and their neighbours are masked out; nodes that are
  saturated (or dark) in every exposure are masked out; small negative values left by noise
  after the black subtraction are clipped to 0 and counted.

Node positions in the image come from the block face's four corner pixels (a homography
in undistorted coordinates; lens distortion from the camera calibration when given). Each
node's value is the mean over its cell (box filter of one node spacing) sampled bilinearly.

Command: ``glsldiff capture measure CAPTURE --corners X,Y X,Y X,Y X,Y -o measurements.npz``
(:func:`measure_to_file`).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from glsldiff.calibration import hdr as hdrlib
from glsldiff.calibration.common import save_json
from glsldiff.calibration.plan import CapturePlan, face_homography, load_plan
from glsldiff.core.checks import real
from glsldiff.core.errors import InputError
from glsldiff.core.io import check_output
from glsldiff.inverse.measurements import Measurements, save_measurements
from glsldiff.physics.optics import fresnel_transmittance

Array = NDArray[np.float64]


@dataclass
class MeasureReport:
    """What :func:`measure` did: clipped and masked counts, black-level ratio, seconds."""

    clipped: int
    masked_lit: int
    masked_exposure: int
    black_ratio: Array
    node_pixels: float


def node_pixels(plan: CapturePlan, corners_px: Array, K: Array | None = None,
                dist: Array | None = None) -> Array:
    """Raw-image pixel positions ``(ny-2, nx-2, 2)`` of the observed face's nodes."""
    c = np.asarray(corners_px, dtype=np.float64).reshape(4, 2)
    if K is not None:
        c = cv2.undistortPoints(c.reshape(-1, 1, 2), K, dist, P=K).reshape(4, 2)
    H = face_homography(c, plan.shape, plan.h)
    fy, fx = plan.face_shape
    r, col = np.mgrid[0:fy, 0:fx].astype(np.float64)
    mm = np.stack([(col + 1) * plan.h, (r + 1) * plan.h], axis=-1).reshape(-1, 1, 2)
    px = cv2.perspectiveTransform(mm, H).reshape(-1, 2)
    if K is not None:  # re-apply the lens distortion
        xy = cv2.undistortPoints(px.reshape(-1, 1, 2), K, None).reshape(-1, 2)
        obj = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        px, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
        px = px.reshape(-1, 2)
    return px.reshape(fy, fx, 2)


def node_spacing(px: Array) -> float:
    """Median distance (px) between neighbouring nodes along a face row."""
    return float(np.median(np.linalg.norm(np.diff(px, axis=1), axis=-1)))


def sample_nodes(hdr: Array, px: Array, footprint: float = 0.25) -> Array:
    """Values of an HDR image ``(rows, cols, 3)`` at node pixels ``(fy, fx, 2)``: the mean over
    a square of ``footprint`` node spacings (odd pixel width, at least 1), sampled bilinearly.
    A wide footprint biases fast-falling radiance upwards (a whole-cell mean read +5-12 %
    next to a lit region on the virtual rig), a narrow one keeps more noise."""
    k = 2 * int(round(footprint * node_spacing(px) / 2.0)) + 1
    img = cv2.blur(np.asarray(hdr, dtype=np.float32), (k, k))
    rows, cols = img.shape[:2]
    if px[..., 0].min() < 0 or px[..., 1].min() < 0 or px[..., 0].max() > cols - 1 or px[..., 1].max() > rows - 1:
        raise InputError("the sample's face extends beyond the image: check the corner pixels")
    out = cv2.remap(img, px[..., 0].astype(np.float32), px[..., 1].astype(np.float32), cv2.INTER_LINEAR)
    return out.astype(np.float64)


def measure(capture: str | os.PathLike, corners_px: Array, response: Array | None = None,
            K: Array | None = None, dist: Array | None = None, gains: Array | None = None,
            reference_albedo: float = 0.9, eta: float = 1.3) -> tuple[Measurements, MeasureReport]:
    """Measurements from a capture folder written by :func:`glsldiff.calibration.rig.run_capture`
    (see the module docstring). ``response``: ``(256, 3)`` camera response; recovered from the
    captured brackets when not given."""
    folder = Path(capture)
    plan = load_plan(folder)
    real(reference_albedo, "reference_albedo", 0.0, 1.0, lo_open=True)
    brackets = {c.name: hdrlib.load_bracket(folder / c.name) for c in plan.conditions}
    if response is None:
        response = hdrlib.calibrate_response(list(brackets.values()))
    px = node_pixels(plan, corners_px, K, dist)
    nodes, bad = {}, {}
    for name, bracket in brackets.items():
        img, mask = hdrlib.merge_bracket(bracket, response)
        nodes[name] = sample_nodes(img, px)
        bad[name] = sample_nodes(mask.astype(np.float32), px) > 0.5  # (rows, cols, 3) from the merge
    white = nodes["white"] - nodes["reference_black"]
    if np.any(np.median(white.reshape(-1, 3), axis=0) <= 0):
        raise InputError("the white reference is not brighter than the projector's black: check the "
                         "'white' and 'reference_black' captures")
    black_ratio = np.median((nodes["reference_black"] / np.maximum(nodes["white"], 1e-30)).reshape(-1, 3), axis=0)
    E = np.pi * white / reference_albedo                       # irradiance per node, camera units
    E = ndimage.median_filter(E, size=(3, 3, 1), mode="nearest")  # the projector field is smooth
    ft = float(fresnel_transmittance(eta, 1.0))
    g = np.ones(3) if gains is None else np.asarray(gains, dtype=np.float64).reshape(3)
    incoming, radiance, mask = [], [], []
    clipped = masked_lit = masked_exp = 0
    for cond in plan.regions:
        lit = plan.face_incoming(cond)
        incoming.append(g * ft * E * lit[..., None])
        L = g * (nodes[cond.name] - nodes["black"])
        ok = ~(bad[cond.name] | bad["black"])
        masked_exp += int((~ok).sum())
        if plan.setup == "front":
            near = ndimage.binary_dilation(lit > 0, iterations=1)[..., None]
            masked_lit += int(np.broadcast_to(near & ok, ok.shape).sum())
            ok &= ~near
        neg = ok & (L < 0)
        clipped += int(neg.sum())
        radiance.append(np.maximum(L, 0.0))
        mask.append(ok)
    meas = Measurements(plan.shape, plan.h, plan.lit_face, plan.observed_face, np.stack(incoming),
                        np.stack(radiance), np.stack(mask), eta=eta)
    return meas, MeasureReport(clipped, masked_lit, masked_exp, black_ratio, node_spacing(px))


def _json_field(path: str | os.PathLike, keys: tuple[str, ...], what: str) -> list:
    try:
        data = json.loads(Path(path).read_text())
        for k in keys:
            data = data[k]
        return data
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: cannot read the {what} ({type(exc).__name__}: {exc})") from None


def measure_to_file(capture: str | os.PathLike, corners_px: Array, output: str | os.PathLike = "measurements.npz",
                    camera: str | os.PathLike | None = None, response: str | os.PathLike | None = None,
                    white_balance: str | os.PathLike | None = None, reference_albedo: float = 0.9,
                    eta: float = 1.3) -> tuple[Measurements, MeasureReport, Path]:
    """:func:`measure` from files, written to ``output`` (the measurements ``.npz`` of ``glsldiff
    fit``) and its report beside it (``.json``). ``corners_px``: camera pixels ``(4, 2)`` of the
    observed face's block corners (0, 0), (W, 0), (W, H), (0, H) mm; ``camera``: a camera.json
    (its ``K`` and ``dist``, for the lens distortion); ``response``: a response JSON (default:
    recovered from the captured brackets); ``white_balance``: a white-balance JSON (its
    ``gains``); ``reference_albedo`` of the white reference target; ``eta`` the sample's relative
    refractive index. Returns the measurements, the report and the output path."""
    out = check_output(output)
    K = dist = None
    if camera:
        K = np.array(_json_field(camera, ("K",), "camera matrix K"), dtype=np.float64)
        dist = np.array(_json_field(camera, ("dist",), "distortion"), dtype=np.float64)
    resp = hdrlib.load_response(response) if response else None
    gains = (np.array(_json_field(white_balance, ("gains",), "white-balance gains"))
             if white_balance else None)
    meas, rep = measure(capture, corners_px, resp, K, dist, gains, reference_albedo, eta)
    save_measurements(out, meas)
    save_json(out.with_suffix(".json"), {"clipped": rep.clipped, "masked_lit": rep.masked_lit,
                                          "masked_exposure": rep.masked_exposure,
                                          "black_ratio": rep.black_ratio.tolist(),
                                          "pixels_per_node": rep.node_pixels})
    return meas, rep, out
