"""The whole acquisition on the virtual rig, end to end, with every step's error reported.

capture plan -> virtual captures (brackets of 8-bit images through the simulated camera)
-> camera response (Debevec-Malik) -> HDR merge -> measurements at the face nodes
(black level, incoming light from the white reference) -> ``glsldiff fit`` -> figure-11
error E of the fitted volume against the true one. With ``calibrate=True`` the camera and
projector are first calibrated from virtual chessboard / Gray-code views of the same devices
and the measurement uses the calibrated intrinsics.

Command: ``python -m glsldiff.calibration.virtual OUT --help``.
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from glsldiff.calibration import hdr
from glsldiff.calibration.camera import BoardSpec, calibrate_camera
from glsldiff.calibration.common import run_command, save_json
from glsldiff.calibration.measure import measure
from glsldiff.calibration.plan import CapturePlan, write_plan
from glsldiff.calibration.projector import DecodeSettings, calibrate_folder
from glsldiff.calibration.simcam import SimCamera
from glsldiff.calibration.synth_radiometric import true_inverse_response
from glsldiff.calibration.rig import VirtualRig, default_devices, projector_homography, run_capture
from glsldiff.calibration.views import (SyntheticRig, board_poses, synthetic_rig, write_camera_dataset,
                                        write_projector_dataset)
from glsldiff.core.arguments import CommandParser
from glsldiff.core.errors import InputError
from glsldiff.inverse.fit import FitOptions, fit_measurements, save_material
from glsldiff.inverse.measurements import save_measurements
from glsldiff.inverse.synthetic import bssrdf_error
from glsldiff.physics.procedural import SYNTHETIC_KINDS, synthetic_volume
from glsldiff.core.io import write_npz


def run(out: str | Path, size: tuple[int, int, int] = (24, 24, 8), h: float = 0.5, setup: str = "back",
        n: int = 4, volume: str = "mixed", seed: int = 1, max_evals: int = 60,
        calibrate: bool = False) -> dict[str, object]:
    """Run the virtual acquisition into folder ``out`` and return the report (also written
    to ``out/report.json``)."""
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise InputError(f"output folder {str(out)!r} exists and is not empty")
    out.mkdir(parents=True, exist_ok=True)
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
        K, dist, calib = _calibrate(cam, out)
        report.update(calib)
    rig = VirtualRig(kappa, mu, h, plan, cam, proj, seed=seed)
    t0 = time.perf_counter()
    run_capture(plan, rig, rig, out / "capture")
    report["capture_seconds"] = time.perf_counter() - t0
    brackets = [hdr.load_bracket(out / "capture" / c.name) for c in plan.conditions]
    response = hdr.calibrate_response(brackets)
    report["response_max_rel_error"] = hdr.inverse_response_error(response, true_inverse_response(cam))
    t0 = time.perf_counter()
    meas, mrep = measure(out / "capture", rig.face_corners_px(), response, K, dist)
    report["measure_seconds"] = time.perf_counter() - t0
    report.update(clipped=mrep.clipped, masked_lit=mrep.masked_lit, masked_exposure=mrep.masked_exposure,
                  black_ratio=mrep.black_ratio.tolist(), true_black=proj.black,
                  pixels_per_node=mrep.node_pixels)
    save_measurements(out / "measurements.npz", meas)
    t0 = time.perf_counter()
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


def main(argv: Sequence[str] | None = None) -> int:
    parser = CommandParser(prog="python -m glsldiff.calibration.virtual", description=__doc__,
                               formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", help="output folder (created; must be empty)")
    parser.add_argument("--size", type=int, nargs=3, default=(24, 24, 8), metavar=("NX", "NY", "NZ"))
    parser.add_argument("--h", type=float, default=0.5, help="node spacing, mm")
    parser.add_argument("--setup", choices=("back", "front"), default="back")
    parser.add_argument("--n", type=int, default=4, help="n x n projector regions")
    parser.add_argument("--volume", choices=SYNTHETIC_KINDS, default="mixed")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--max-evals", type=int, default=60)
    parser.add_argument("--calibrate", action="store_true", help="also calibrate camera and projector")

    def go(args: argparse.Namespace) -> int:
        rep = run(args.out, tuple(args.size), args.h, args.setup, args.n, args.volume, args.seed,
                  args.max_evals, args.calibrate)
        for k, v in rep.items():
            print(f"{k:>24}: {v}")
        return 0

    parser.set_defaults(func=go)
    return run_command(parser, argv)


if __name__ == "__main__":
    raise SystemExit(main())
