"""``glsldiff capture <step>``: the capture pipeline's steps (camera and projector calibration,
camera response and HDR merge, white balance and black level, capture plan, measurements, the
virtual rig, synthetic calibration views), one sub-command each.

Argument parsing and printing only: every step calls the library in :mod:`glsldiff.calibration`
(which holds no argparse and never imports this layer). A bad input, or a file that cannot be
read or written, is one error line and exit status 2, as in every ``glsldiff`` command.
"""
from __future__ import annotations

import argparse
import functools
from typing import Callable, Sequence

import numpy as np

from glsldiff.calibration import color, hdr, views, virtual
from glsldiff.calibration.camera import BoardSpec, calibrate_camera, calibration_flags, load_intrinsics
from glsldiff.calibration.graycode import write_patterns
from glsldiff.calibration.measure import measure_to_file
from glsldiff.calibration.plan import PAPER_EXPOSURES, CapturePlan, face_homography, write_plan
from glsldiff.calibration.projector import DecodeSettings, calibrate_folder
from glsldiff.core.arguments import integer
from glsldiff.core.errors import InputError
from glsldiff.inverse.measurements import SETUPS
from glsldiff.physics.procedural import SYNTHETIC_KINDS

#: The steps, in pipeline order (``glsldiff capture --help`` lists them so).
STEPS = ("camera", "patterns", "calibrate", "response", "merge", "white-balance", "black-level", "plan", "measure",
         "virtual", "synth-projector-views", "synth-camera-views")


# ---- argument types ---------------------------------------------------------------------------
def parse_size(text: str) -> tuple[int, int]:
    """``"1024x768"`` -> ``(1024, 768)`` (argparse type)."""
    try:
        a, b = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WxH, e.g. 9x7 or 1024x768") from None
    if a <= 0 or b <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: both numbers must be > 0")
    return a, b


def parse_points(text: Sequence[str] | None, option: str, count: int = 4) -> np.ndarray | None:
    """``["X,Y", ...]`` -> ``(count, 2)`` float pixels (None when not given)."""
    if not text:
        return None
    try:
        pts = np.array([[float(v) for v in p.split(",")] for p in text])
    except ValueError:
        pts = np.zeros(0)
    if pts.shape != (count, 2):
        raise InputError(f"{option} {' '.join(text)}: expected {count} points X,Y (pixels)")
    return pts


def _step(func: Callable[[argparse.Namespace], int | None]) -> Callable[[argparse.Namespace], int]:
    """A step's handler for ``glsldiff``'s main: a file that cannot be read or written (OSError)
    becomes an InputError, so it too is one error line with exit status 2, never a traceback."""
    @functools.wraps(func)
    def run(args: argparse.Namespace) -> int:
        try:
            return int(func(args) or 0)
        except OSError as exc:
            where = f"{str(exc.filename)!r}: " if exc.filename else ""
            raise InputError(f"{where}{exc.strerror or exc} (an input must exist and be readable; an output's "
                             "folder must exist and be writable)") from exc
    return run


# ---- camera and projector ---------------------------------------------------------------------
def _add_board_arguments(p: argparse.ArgumentParser) -> None:
    """``--board --square --charuco --marker --dictionary --fix-k3`` options."""
    p.add_argument("--board", type=parse_size, required=True, metavar="COLSxROWS",
                   help="inner corners, e.g. 9x7 (a ChArUco board with 9x7 inner corners has 10x8 squares)")
    p.add_argument("--square", type=float, required=True, help="square size, mm")
    p.add_argument("--charuco", action="store_true", help="ChArUco board instead of a plain chessboard")
    p.add_argument("--marker", type=float, help="ChArUco marker size, mm")
    p.add_argument("--dictionary", default="DICT_5X5_100", help="ChArUco ArUco dictionary (default %(default)s)")
    p.add_argument("--fix-k3", action=argparse.BooleanOptionalAction, default=True,
                   help="keep the k3 radial distortion term at 0 (default on)")


def _board(args: argparse.Namespace) -> BoardSpec:
    return BoardSpec(args.board[0], args.board[1], args.square, "charuco" if args.charuco else "chessboard",
                     args.marker, args.dictionary)


@_step
def cmd_camera(args: argparse.Namespace) -> int:
    res = calibrate_camera(args.inputs, _board(args), calibration_flags(args.fix_k3), args.drop_outliers,
                           skip_bad=args.skip_bad, output=args.output)
    i = res.intrinsics
    for f, e, o in zip(res.files, i.per_view_rms, res.outlier):
        print(f"  {f}: {e:.3f} px{'  OUTLIER' if o else ''}")
    for r in res.rejected:
        print(f"  rejected {r['file']}: {r['reason']}")
    print(f"camera RMS {i.rms:.3f} px over {len(res.files)} views; fx {i.K[0, 0]:.2f} fy {i.K[1, 1]:.2f} "
          f"cx {i.K[0, 2]:.2f} cy {i.K[1, 2]:.2f} px -> {args.output}")
    return 0


@_step
def cmd_patterns(args: argparse.Namespace) -> int:
    paths = write_patterns(args.output, args.projector, args.step)
    print(f"wrote {len(paths)} patterns ({paths[0].name} .. {paths[-1].name}) to {args.output}")
    return 0


@_step
def cmd_calibrate(args: argparse.Namespace) -> int:
    if args.window < 5:
        raise InputError(f"--window {args.window}: must be >= 5 px")
    settings = DecodeSettings(args.window, args.shadow_threshold, args.bit_threshold, step=args.step)
    camera = load_intrinsics(args.camera) if args.camera else None
    rig = calibrate_folder(args.folder, _board(args), args.projector, settings, calibration_flags(args.fix_k3),
                           args.skip_bad, args.output, camera)
    for r in rig.rejected:
        print(f"  rejected {r['folder']}: {r['reason']}")
    for p in rig.poses:
        if p.dropped:
            print(f"  {p.folder}: {len(p.dropped)} corners dropped for the projector (no decoded window: "
                  f"{p.dropped[:10]}{'...' if len(p.dropped) > 10 else ''}); the camera calibration keeps them")
    print(f"poses {len(rig.poses)}; camera RMS {rig.camera.rms:.3f} px; projector RMS {rig.projector.rms:.3f} px; "
          f"stereo RMS {rig.stereo_rms:.3f} px; baseline {rig.baseline:.1f} mm -> {args.output}")
    return 0


# ---- radiometry -------------------------------------------------------------------------------
@_step
def cmd_response(args: argparse.Namespace) -> int:
    _, brackets = hdr.response_from_folders(args.folders, args.output, samples=args.samples,
                                            smoothness=args.smoothness)
    print(f"{args.output}: response from {len(brackets)} bracket(s) of {len(brackets[0].times)} exposures")
    return 0


@_step
def cmd_merge(args: argparse.Namespace) -> int:
    m = hdr.merge_folder(args.folder, args.output, response=args.response, half=args.half, mask=args.mask,
                         low=args.low, black=args.black, high=args.high)
    print(f"lower cutoff R G B = {' '.join(map(str, m.low))} ({m.low_source})")
    print(f"{args.output}: {m.image.shape[1]}x{m.image.shape[0]} HDR from {len(m.bracket.times)} exposures; "
          f"{int(m.mask.any(axis=2).sum())} pixels unusable (dark or saturated in every exposure)")
    return 0


@_step
def cmd_white_balance(args: argparse.Namespace) -> int:
    corners = parse_points(args.corners, "--corners")
    wb = color.white_balance_file(args.image, args.output, corners, args.patches)
    print(f"{args.output}: gains R G B = {np.round(wb.gains, 4).tolist()} (chart by {wb.method})")
    return 0


@_step
def cmd_black_level(args: argparse.Namespace) -> int:
    corners = parse_points(args.corners, "--corners")
    bl = color.black_level_files(args.black, args.white, args.output, corners, args.roi)
    print(f"{args.output}: black level R G B = {np.round(bl.mean, 5).tolist()} "
          f"+- {np.round(bl.std, 5).tolist()} over {bl.count} {bl.method} regions")
    return 0


# ---- plan, measurements, virtual rig ----------------------------------------------------------
@_step
def cmd_plan(args: argparse.Namespace) -> int:
    corners = parse_points(args.face_corners, "--face-corners")
    shape = tuple(args.shape)
    H = face_homography(corners, shape, args.h)
    plan = CapturePlan(shape, args.h, args.setup, args.n, tuple(args.exposures), args.projector, H)
    write_plan(plan, args.out)
    print(f"wrote {len(plan.conditions)} projector images and plan.json to {args.out}")
    return 0


@_step
def cmd_measure(args: argparse.Namespace) -> int:
    corners = parse_points(args.corners, "--corners")
    meas, rep, out = measure_to_file(args.capture, corners, args.output, camera=args.camera, response=args.response,
                                     white_balance=args.white_balance, reference_albedo=args.albedo, eta=args.eta)
    print(f"wrote {meas.M} conditions ({meas.lit_face} lit, {meas.observed_face} observed) to {out}; black level "
          f"{np.round(rep.black_ratio, 4).tolist()}; {rep.clipped} values clipped "
          f"at 0, {rep.masked_lit} lit and {rep.masked_exposure} badly exposed node values masked")
    return 0


@_step
def cmd_virtual(args: argparse.Namespace) -> int:
    rep = virtual.run(args.out, tuple(args.size), args.h, args.setup, args.n, args.volume, args.seed,
                      args.max_evals, args.calibrate)
    for k, v in rep.items():
        print(f"{k:>26}: {_short(v)}")
    print(f"wrote {args.out}/ (report.json, truth.npz, measurements.npz, material.npz, plan/, capture/"
          + (", calib_camera/, calib_projector/, camera.json, projector.json)" if args.calibrate else ")"))
    return 0


def _short(v: object) -> str:
    """A report value for the terminal: 4 significant digits, lists on one line."""
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_short(x) for x in v) + "]"
    return str(v)


@_step
def cmd_synth_views(args: argparse.Namespace) -> int:
    board = BoardSpec(args.board[0], args.board[1], args.square)
    proj = args.projector if args.kind == "projector" else None
    rig = views.synthetic_rig(args.poses, args.camera, proj, board, seed=args.seed)
    if proj:
        out = views.write_projector_dataset(args.out, rig, args.step, args.layout)
    else:
        out = views.write_camera_dataset(args.out, rig)
    print(f"wrote {out}")
    return 0


# ---- the parser -------------------------------------------------------------------------------
def add_capture_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``glsldiff capture`` and its steps (:data:`STEPS`) on ``glsldiff``'s sub-parsers."""
    cap = sub.add_parser("capture", help="capture pipeline: camera/projector calibration, HDR, measurements "
                                         "for fit (steps: glsldiff capture --help)",
                         description="The capture pipeline of Wang et al. 2008, section 4.1, one step per "
                                     "sub-command (glsldiff capture STEP --help).")
    steps = cap.add_subparsers(dest="capture_step", required=True, metavar="STEP", title="steps")

    p = steps.add_parser("camera", help="camera intrinsics from board images (Zhang)",
                         description="Camera intrinsics from chessboard/ChArUco images (Zhang's method).")
    p.add_argument("inputs", nargs="+",
                   help="image files and/or folders of images; a projector capture folder (with capture_* "
                        "sub-folders) or a capture_* folder gives the white frame of each pose (the second to "
                        "last image of its Gray-code sequence), so the projector captures calibrate the camera too")
    _add_board_arguments(p)
    p.add_argument("-o", "--output", default="camera.json", help="output JSON (default %(default)s)")
    p.add_argument("--drop-outliers", action="store_true",
                   help="drop views with RMS > 3x median and > 1 px, then recalibrate")
    p.add_argument("--skip-bad", action="store_true", help="skip images where the board is not found")
    p.set_defaults(func=cmd_camera)

    step_help = ("Gray-code step: each code pixel is an N x N block of projector pixels, for a "
                 "ceil(W/N) x ceil(H/N) code (procam-calibration's graycode_step; raise it against moire "
                 "or defocus; calibrate with the step the patterns were made with; default %(default)s)")
    p = steps.add_parser("patterns", help="write the projector images pattern_00.png ... into a folder",
                         description="Gray-code projector images (Moreno & Taubin 2012): column and row bits, "
                                     "each followed by its inverse, then white and black.")
    p.add_argument("--projector", type=parse_size, required=True, metavar="WxH", help="projector size, px")
    p.add_argument("--step", type=integer(1), default=1, metavar="N", help=step_help)
    p.add_argument("-o", "--output", default="patterns", help="output folder (default %(default)s)")
    p.set_defaults(func=cmd_patterns)

    p = steps.add_parser("calibrate", help="calibrate camera + projector from FOLDER/capture_*/",
                         description="Gray-code projector-camera calibration (Moreno & Taubin 2012).")
    p.add_argument("folder", help="folder with one capture_* sub-folder per board pose (images in pattern "
                                  "order, white and black last; procam-calibration's graycode_*.png too)")
    _add_board_arguments(p)
    p.add_argument("--projector", type=parse_size, required=True, metavar="WxH", help="projector size, px")
    p.add_argument("--step", type=integer(1), default=1, metavar="N", help=step_help)
    p.add_argument("-o", "--output", default="rig.json", help="output JSON (default %(default)s)")
    d = DecodeSettings()
    p.add_argument("--window", type=int, default=d.window,
                   help="local homography window, camera px (default %(default)s)")
    p.add_argument("--shadow-threshold", type=float, default=d.shadow_threshold,
                   help="min white - black, 8-bit levels (default %(default)s)")
    p.add_argument("--bit-threshold", type=float, default=d.bit_threshold,
                   help="min |pattern - inverse| per bit, 8-bit levels (default %(default)s)")
    p.add_argument("--skip-bad", action="store_true", help="skip poses that fail instead of stopping")
    p.add_argument("--camera", metavar="camera.json",
                   help="reuse these camera intrinsics (glsldiff capture camera, or "
                        "procam-calibration's camera_config.json) instead of calibrating the camera from "
                        "the board poses again")
    p.set_defaults(func=cmd_calibrate)

    brackets = ("exposure brackets: folders of 8-bit images + exposure times (exposures.json/.csv/.txt or "
                "EXIF ExposureTime)")
    p = steps.add_parser("response", help="recover the camera response from one or more brackets",
                         description=f"Camera response (Debevec-Malik) from {brackets}.")
    p.add_argument("folders", nargs="+", metavar="FOLDER", help="bracket folder(s) with the same exposure times")
    p.add_argument("-o", "--output", required=True, help="response JSON file to write")
    p.add_argument("--samples", type=int, default=256, help="pixels used by the solve (default 256)")
    p.add_argument("--smoothness", type=float, default=50.0, help="Debevec-Malik lambda (default 50)")
    p.set_defaults(func=cmd_response)

    p = steps.add_parser("merge", help="merge one bracket into a linear OpenEXR image",
                         description=f"HDR merge (Debevec-Malik) of one of the {brackets}.")
    p.add_argument("folder", metavar="FOLDER", help="bracket folder")
    p.add_argument("-o", "--output", required=True, help="OpenEXR file to write")
    p.add_argument("--response", help="response JSON (default: recovered from this bracket)")
    p.add_argument("--half", action="store_true", help="write 16-bit half floats instead of float32")
    p.add_argument("--mask", help="also write an 8-bit PNG, 255 where a channel is unusable")
    p.add_argument("--low", type=int, default=None,
                   help=f"pixel values below this are noise, not signal (default: the noise floor of the black "
                        f"frame, ceil(99.9th percentile) + 3 per channel; {hdr.LO} without one)")
    p.add_argument("--black", metavar="FILE",
                   help="black frame (lens capped, settings of the longest exposure) for the noise floor "
                        "(default: black.png / black.* in the bracket folder, if there)")
    p.add_argument("--high", type=int, default=hdr.HI,
                   help=f"pixel values above this count as clipped (default {hdr.HI})")
    p.set_defaults(func=cmd_merge)

    chart = "linear HDR (OpenEXR) images of a Macbeth ColorChecker"
    corners_help = ("chart corners in pixels when cv2.mcc does not find it: outer corners of patches "
                    "1, 6, 24, 19 (X,Y X,Y X,Y X,Y)")
    p = steps.add_parser("white-balance", help="per-channel gains from the chart under a projected white image",
                         description=f"White balance from {chart}.")
    p.add_argument("image", help="HDR image (OpenEXR) of the chart under projected white")
    p.add_argument("-o", "--output", required=True, help="JSON file to write")
    p.add_argument("--corners", nargs=4, metavar="X,Y", help=corners_help)
    p.add_argument("--patches", choices=("neutral", "all"), default="neutral",
                   help="patches of the fit (default: the 6 grey patches)")
    p.set_defaults(func=cmd_white_balance)

    p = steps.add_parser("black-level", help="projector black/white ratio per channel",
                         description=f"Projector black level from {chart} (or a rectangle).")
    p.add_argument("black", help="HDR image (OpenEXR) under a projected black image")
    p.add_argument("white", help="HDR image (OpenEXR) under a projected white image")
    p.add_argument("-o", "--output", required=True, help="JSON file to write")
    p.add_argument("--corners", nargs=4, metavar="X,Y", help=corners_help)
    p.add_argument("--roi", nargs=4, type=float, metavar=("X", "Y", "W", "H"),
                   help="use this rectangle (pixels) instead of the chart")
    p.set_defaults(func=cmd_black_level)

    p = steps.add_parser("plan", help="capture plan: projector images and plan.json",
                         description="Write a capture plan: projector images (n x n regions lit one at a "
                                     "time, black, white, reference_black) and plan.json.")
    p.add_argument("out", help="plan folder to create (must not exist or be empty)")
    p.add_argument("--shape", type=int, nargs=3, required=True, metavar=("NZ", "NY", "NX"),
                   help="sample grid nodes, boundary layer included")
    p.add_argument("--h", type=float, required=True, help="node spacing, mm")
    p.add_argument("--setup", choices=tuple(SETUPS), default="back", help="back-lit or front-lit sample")
    p.add_argument("--n", type=int, default=4, help="n x n regions (paper: 4)")
    p.add_argument("--exposures", type=float, nargs="+", default=list(PAPER_EXPOSURES), help="seconds")
    p.add_argument("--projector", type=parse_size, default=(1024, 768), metavar="WxH", help="projector size, px")
    p.add_argument("--face-corners", nargs=4, metavar="X,Y", required=True,
                   help="projector pixels of the lit face's block corners (0,0), (W,0), (W,H), (0,H) mm")
    p.set_defaults(func=cmd_plan)

    p = steps.add_parser("measure", help="measurements for glsldiff fit from a capture",
                         description="Measurements for `glsldiff fit` from a capture folder (plan.json + one "
                                     "exposure bracket per condition).")
    p.add_argument("capture", help="capture folder written by the capture driver")
    p.add_argument("--corners", nargs=4, metavar="X,Y", required=True,
                   help="camera pixels of the observed face's block corners (0,0), (W,0), (W,H), (0,H) mm")
    p.add_argument("-o", "--output", default="measurements.npz", help="measurements for glsldiff fit (.npz)")
    p.add_argument("--camera", help="camera.json from the camera calibration (lens distortion)")
    p.add_argument("--response", help="response JSON (default: recovered from the captured brackets)")
    p.add_argument("--white-balance", help="white-balance JSON (gains) from the colour chart")
    p.add_argument("--albedo", type=float, default=0.9, help="albedo of the white reference target")
    p.add_argument("--eta", type=float, default=1.3, help="relative refractive index of the sample")
    p.set_defaults(func=cmd_measure)

    p = steps.add_parser("virtual", help="the whole chain on the virtual rig, then fit",
                         description=virtual.__doc__,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", help="output folder (created; must be empty)")
    p.add_argument("--size", type=int, nargs=3, default=(24, 24, 8), metavar=("NX", "NY", "NZ"),
                   help="nodes per axis of the simulated sample")
    p.add_argument("--h", type=float, default=0.5, help="node spacing, mm")
    p.add_argument("--setup", choices=("back", "front"), default="back", help="back-lit or front-lit sample")
    p.add_argument("--n", type=int, default=4, help="n x n projector regions")
    p.add_argument("--volume", choices=SYNTHETIC_KINDS, default="mixed", help="the simulated material")
    p.add_argument("--seed", type=int, default=1, help="random seed of the material and the camera noise")
    p.add_argument("--max-evals", type=int, default=60, help="fit evaluations per channel")
    p.add_argument("--calibrate", action="store_true", help="also calibrate camera and projector")
    p.set_defaults(func=cmd_virtual)

    for kind, helptext in (("projector", "Gray-code captures: OUT/capture_XXX/img_YY.png"),
                           ("camera", "plain board views: OUT/view_XX.png")):
        s = steps.add_parser(f"synth-{kind}-views", help=helptext,
                             description="Write synthetic calibration captures with ground truth.")
        s.add_argument("out", help="output folder (must not exist or be empty)")
        s.add_argument("--poses", type=int, default=5, help="number of board poses (default %(default)s)")
        s.add_argument("--camera", type=parse_size, default=(1280, 1024), help="camera size (default 1280x1024)")
        s.add_argument("--projector", type=parse_size, default=(1024, 768), help="projector size (default 1024x768)")
        s.add_argument("--board", type=parse_size, default=(9, 7), help="inner corners (default 9x7)")
        s.add_argument("--square", type=float, default=20.0, help="square size, mm (default %(default)s)")
        s.add_argument("--seed", type=int, default=0, help="random seed of the poses and the noise")
        if kind == "projector":
            s.add_argument("--step", type=integer(1), default=1, metavar="N",
                           help="Gray-code step, projector px per code pixel (default %(default)s)")
            s.add_argument("--layout", choices=tuple(views.LAYOUTS), default="glsldiff",
                           help="file names: capture_XXX/img_YY.png, or procam-calibration's "
                                "capture_K/graycode_YY.png (default %(default)s)")
        s.set_defaults(func=cmd_synth_views, kind=kind)
