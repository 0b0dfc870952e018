"""The whole acquisition on the virtual rig, end to end, with every step's error reported.

capture plan -> virtual captures (brackets of 8-bit images through the simulated camera)
-> camera response (Debevec-Malik) -> HDR merge -> measurements at the face nodes
(black level, incoming light from the white reference) -> ``glsldiff fit`` -> figure-11
error E of the fitted volume against the true one. With ``calibrate=True`` the camera and
projector are first calibrated from virtual chessboard / Gray-code views of the same devices
and the measurement uses the calibrated intrinsics.

Command: ``glsldiff capture virtual OUT`` (library: :func:`run`).
"""
from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from glsldiff.calibration import hdr
from glsldiff.calibration.camera import BoardSpec, calibrate_camera
from glsldiff.calibration.common import atomic_folder, save_json
from glsldiff.calibration.measure import measure
from glsldiff.calibration.plan import CapturePlan, write_plan
from glsldiff.calibration.projector import DecodeSettings, calibrate_folder
from glsldiff.calibration.simcam import SimCamera
from glsldiff.calibration.synth_radiometric import true_inverse_response
from glsldiff.calibration.rig import VirtualRig, default_devices, projector_homography, run_capture
from glsldiff.calibration.views import (SyntheticRig, board_poses, synthetic_rig, write_camera_dataset,
                                        write_projector_dataset)
from glsldiff.inverse.fit import FitOptions, fit_measurements, save_material
from glsldiff.inverse.measurements import save_measurements
from glsldiff.inverse.synthetic import bssrdf_error
from glsldiff.physics.procedural import synthetic_volume
from glsldiff.core.io import write_npz


def run(out: str | Path, size: tuple[int, int, int] = (24, 24, 8), h: float = 0.5, setup: str = "back",
        n: int = 4, volume: str = "mixed", seed: int = 1, max_evals: int = 60,
        calibrate: bool = False) -> dict[str, object]:
    """Run the virtual acquisition into folder ``out`` (created; must not exist or be empty) and
    return the report (also written to ``out/report.json``). The sample: a synthetic ``volume``
    (:data:`~glsldiff.physics.procedural.SYNTHETIC_KINDS`, random ``seed``) of ``size = (nx, ny,
    nz)`` nodes spaced ``h`` mm, lit in ``n x n`` projector regions from the back or the front
    (``setup``); ``max_evals`` bounds the fit's function evaluations; ``calibrate``: calibrate the
    camera and projector on virtual views first (module docstring)."""
    with atomic_folder(out) as tmp:       # nothing half-written: the folder appears when complete
        return _run(tmp, size, h, setup, n, volume, seed, max_evals, calibrate)


def _step(line: str) -> None:
    print(f"virtual: {line}", file=sys.stderr, flush=True)


def _run(out: Path, size: tuple[int, int, int], h: float, setup: str, n: int, volume: str, seed: int,
         max_evals: int, calibrate: bool) -> dict[str, object]:
    nx, ny, nz = size
    report: dict[str, object] = {"size": list(size), "h": h, "setup": setup, "n": n, "volume": volume}
    kappa, mu = synthetic_volume((nz, ny, nx), volume, seed=seed)
    write_npz(out / "truth.npz", kappa=kappa, mu=mu, h=h)
    plan0 = CapturePlan((nz, ny, nx), h, setup, n)
    cam, proj = default_devices(plan0)
    plan = dataclasses.replace(plan0, face_to_projector=projector_homography(plan0, proj), conditions=[])
    write_plan(plan, out / "plan")
    K = dist = None
    if calibrate:
        _step("calibrating the camera (6 board views) and a Gray-code camera + projector rig (about 15 s)")
        K, dist, calib = _calibrate(cam, out)
        report.update(calib)
    rig = VirtualRig(kappa, mu, h, plan, cam, proj, seed=seed)
    t0 = time.perf_counter()
    _step(f"capturing {n * n} regions and the references, {len(plan.exposures)} exposures each, through the "
          "simulated camera (about 10 s)")
    run_capture(plan, rig, rig, out / "capture")
    report["capture_seconds"] = time.perf_counter() - t0
    brackets = [hdr.load_bracket(out / "capture" / c.name) for c in plan.conditions]
    response = hdr.calibrate_response(brackets)
    report["response_max_rel_error"] = hdr.inverse_response_error(response, true_inverse_response(cam))
    t0 = time.perf_counter()
    corners = rig.face_corners_px()
    report["face_corners_px"] = np.round(np.asarray(corners, dtype=float), 2).tolist()
    _step("camera response, HDR merge and measurements at the face nodes")
    meas, mrep = measure(out / "capture", corners, response, K, dist)
    report["measure_seconds"] = time.perf_counter() - t0
    report.update(clipped=mrep.clipped, masked_lit=mrep.masked_lit, masked_exposure=mrep.masked_exposure,
                  black_ratio=mrep.black_ratio.tolist(), true_black=proj.black,
                  pixels_per_node=mrep.node_pixels)
    save_measurements(out / "measurements.npz", meas)
    t0 = time.perf_counter()
    _step(f"fitting the material (at most {max_evals} evaluations per channel)")
    result = fit_measurements(meas, FitOptions(max_evals=max_evals))
    save_material(out / "material.npz", result)
    report["fit_seconds"] = time.perf_counter() - t0
    fitted = (result.kappa, result.mu)
    pairs = dict(sources=(plan.lit_face,), receivers=(plan.observed_face,))
    report["E"] = bssrdf_error(meas.grid, (kappa, mu), fitted, **pairs)
    k_h = np.broadcast_to(np.median(fitted[0].reshape(-1, 3), axis=0), kappa.shape)
    m_h = np.broadcast_to(np.median(fitted[1].reshape(-1, 3), axis=0), mu.shape)
    report["E_median_homogeneous"] = bssrdf_error(meas.grid, (kappa, mu), (k_h, m_h), **pairs)
    save_json(out / "report.json", report)
    return report


def _calibrate(cam: SimCamera, out: Path) -> tuple[np.ndarray, np.ndarray, dict[str, object]]:
    """Camera intrinsics of the rig's camera from 6 virtual chessboard views (3 mm squares, at
    the rig's working distance; the calibration exposure uses a board-suited gain), and a
    camera + projector + stereo calibration on a virtual Gray-code dataset (4 poses, 640x512
    camera, 512x384 projector). The rig's projector frames a face of a few mm, too small for
    a printed board, so its region placement uses its known geometry instead."""
    t0 = time.perf_counter()
    board = BoardSpec(9, 7, 3.0)
    dist0 = float(np.linalg.norm(cam.center))  # camera to the sample's corner, mm
    # same optics, placed at the origin (intrinsics do not depend on the pose), board exposure
    calib_cam = dataclasses.replace(cam, gain=1.05, R=np.eye(3), t=np.zeros(3))
    poses = board_poses(6, board, calib_cam, None, distance=(0.9 * dist0, 1.1 * dist0), margin=2.0, seed=3)
    write_camera_dataset(out / "calib_camera", SyntheticRig(calib_cam, None, board, poses, margin=2.0, seed=3))
    cc = calibrate_camera([out / "calib_camera"], board, output=out / "camera.json")
    rep: dict[str, object] = {"camera_rms_px": cc.intrinsics.rms,
                              "camera_focal_error": float(cc.intrinsics.K[0, 0] / cam.K[0, 0] - 1.0)}
    rig = synthetic_rig(4, (640, 512), (512, 384), seed=1)
    write_projector_dataset(out / "calib_projector", rig)
    rc = calibrate_folder(out / "calib_projector", rig.board, (512, 384), DecodeSettings(window=31),
                          output=out / "projector.json")
    rep.update(gray_camera_rms_px=rc.camera.rms, gray_projector_rms_px=rc.projector.rms,
               gray_stereo_rms_px=rc.stereo_rms,
               gray_projector_focal_error=float(rc.projector.K[0, 0] / rig.projector.K[0, 0] - 1.0),
               gray_baseline_mm=rc.baseline, calibration_seconds=time.perf_counter() - t0)
    return cc.intrinsics.K, cc.intrinsics.dist, rep
