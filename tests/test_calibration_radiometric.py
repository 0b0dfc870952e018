"""Radiometric calibration (paper section 4.1) on simulated captures: camera response
(Debevec-Malik), HDR merge, white balance and projector black level from a ColorChecker,
file formats, commands and bad input.

Simulation (``glsldiff.calibration.synth_radiometric``): an 8-bit camera with response
``x^(1/2.2)``, shot and read noise and 10 % vignetting; brackets at 1/30, 1/8, 1/2, 2, 8 s.
"""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from glsldiff.calibration import color, hdr
from glsldiff.calibration import synth_radiometric as sr
from glsldiff.core.errors import InputError
from glsldiff.core.io import read_exr, write_exr

from calibration_rig import ERR, capture, error_lines   # tests/calibration_rig.py


@pytest.fixture(scope="module")
def ramp():
    """A 1e-4 .. 1e3 radiance ramp (columns), 128 rows of equal radiance, and its bracket."""
    cam = sr.camera((256, 128), gain=0.1)
    radiance = sr.ramp_radiance((128, 256))
    bracket = hdr.make_bracket(sr.capture_bracket(cam, radiance, seed=1), sr.EXPOSURES)
    return cam, radiance * cam.vignette()[..., None], bracket


@pytest.fixture(scope="module")
def response(ramp):
    return hdr.calibrate_response(ramp[2])


@pytest.fixture(scope="module")
def chart(response):
    """HDR images of the ColorChecker under projected white and black (colour cast CAST,
    projector black level 1 %), merged with the recovered response."""
    cam, proj = sr.camera((640, 480), gain=20.0), sr.projector(black=0.01)
    out = {}
    for k, (name, value) in enumerate((("white", 1.0), ("black", 0.0))):
        bracket = hdr.make_bracket(sr.capture_bracket(cam, sr.chart_radiance(pattern=value, proj=proj), seed=2 + k),
                                   sr.EXPOSURES)
        out[name], out[name + "_mask"] = hdr.merge_bracket(bracket, response)
        out[name + "_bracket"] = bracket
    return out


def expected_gains() -> np.ndarray:
    cast = np.asarray(sr.CAST)
    return cast[1] / cast


# ----------------------------------------------------------------------------- accuracy

def test_response_matches_simulated_gamma(ramp, response):
    """Max relative error of the recovered inverse response over pixel values 20..235 < 5 %."""
    cam, _, _ = ramp
    err = hdr.inverse_response_error(response, sr.true_inverse_response(cam))
    print(f"\nresponse max relative error (z = 20..235): {err:.4f}")
    assert response.shape == (256, 3) and np.all(np.diff(response[hdr.LO:hdr.HI + 1], axis=0) > 0)
    assert err < 0.05


def test_response_from_two_brackets(ramp, chart):
    """Brackets of one exposure series calibrate together; different series are refused."""
    cam, _, bracket = ramp
    resp = hdr.calibrate_response([bracket, chart["white_bracket"]])
    err = hdr.inverse_response_error(resp, sr.true_inverse_response(cam))
    print(f"\nresponse from two brackets: max relative error {err:.4f}")
    assert err < 0.05
    other = hdr.make_bracket(bracket.images[:3], bracket.times[:3])
    with pytest.raises(InputError, match="exposure times"):
        hdr.calibrate_response([bracket, other])


def test_hdr_merge_error_and_masks(ramp, response):
    """Merged radiance vs truth (up to scale): the mean over each column of equal radiance
    within 5 % wherever every pixel has an exposure in 20..235; per pixel the median within
    5 % (the dark end is noise-limited: SNR ~7 at pixel value 20); both ends of the 1e7 ramp
    are masked, with bounds in the right direction."""
    _, truth, bracket = ramp
    img, mask = hdr.merge_bracket(bracket, response)
    assert img.dtype == np.float32 and np.all(np.isfinite(img)) and mask.shape == img.shape
    good = ~mask
    ratio = img / truth
    scale = np.exp(np.median(np.log(ratio[good])))
    per_pixel = np.abs(ratio[good] / scale - 1)
    full = good.all(axis=(0, 2))
    column = np.abs(ratio[:, full].mean(axis=0) / scale - 1)
    print(f"\nHDR: {full.sum()} fully exposed columns, column-mean max error {column.max():.4f}; per pixel "
          f"median {np.median(per_pixel):.4f}, p95 {np.percentile(per_pixel, 95):.4f}, max {per_pixel.max():.4f}; "
          f"masked {mask.mean():.3f}")
    assert full.sum() > 150 and column.max() < 0.05 and np.median(per_pixel) < 0.05
    bright = np.all([im > hdr.HI for im in bracket.images], axis=0)
    dark = np.all([im < hdr.LO for im in bracket.images], axis=0)
    assert bright[:, -20:].all() and dark[:, :20].all()
    assert np.array_equal(mask, bright | dark)
    assert np.all(img[bright] <= truth[bright] * scale * 1.01)   # lower bound
    assert np.median(img[dark] / (truth[dark] * scale)) > 1.0   # upper bound (up to noise)


def test_white_balance_mcc(chart):
    """cv2.mcc finds the synthetic chart; gains within 2 % of the simulated colour cast."""
    wb = color.white_balance(chart["white"])
    err = np.abs(wb.gains / expected_gains() - 1)
    print(f"\nwhite balance (mcc): gains {np.round(wb.gains, 4)}, expected {np.round(expected_gains(), 4)}, "
          f"error {np.round(err, 4)}")
    assert wb.method == "mcc" and wb.gains[1] == 1.0
    assert err.max() < 0.02
    wb_all = color.white_balance(chart["white"], patches="all")
    assert np.abs(wb_all.gains / expected_gains() - 1).max() < 0.02


def test_white_balance_corners(chart):
    """The corner-point path gives the same gains; no chart and no corners is a clear error."""
    wb = color.white_balance(chart["white"], corners=sr.CHART_CORNERS)
    err = np.abs(wb.gains / expected_gains() - 1)
    print(f"\nwhite balance (corners): error {np.round(err, 4)}")
    assert wb.method == "corners" and err.max() < 0.02
    blank = np.full((120, 160, 3), 0.5, np.float32)
    with pytest.raises(InputError, match=r"blank\.exr: no ColorChecker found.*corner"):
        color.white_balance(blank, name="blank.exr")
    with pytest.raises(InputError, match="decreasing grey ramp"):
        color.white_balance(chart["white"], corners=np.asarray(sr.CHART_CORNERS)[[1, 0, 3, 2]])


def test_black_level(chart):
    """Projector black level (1 %) from the chart under black and white: within 10 %."""
    polys = color.detect_chart(chart["white"])
    assert polys is not None
    bl = color.black_level(chart["black"], chart["white"], polys, "mcc")
    err = np.abs(bl.mean / 0.01 - 1)
    print(f"\nblack level: {np.round(bl.mean, 5)} +- {np.round(bl.std, 5)} over {bl.count} patches, "
          f"error {np.round(err, 4)}")
    assert bl.count == 24 and err.max() < 0.10 and np.all(bl.std < 0.002)
    roi = color.black_level(chart["black"], chart["white"], color.roi_cells((20, 20, 100, 60)), "roi")
    assert np.abs(roi.mean / 0.01 - 1).max() < 0.10
    with pytest.raises(InputError, match="not brighter"):
        color.black_level(chart["white"], chart["black"], polys)


# ----------------------------------------------------------------------------- files

@pytest.mark.parametrize("half", [False, True])
def test_exr_round_trip(tmp_path, ramp, response, half):
    img, _ = hdr.merge_bracket(ramp[2], response)
    path = write_exr(tmp_path / "hdr.exr", img, {"note": "test"}, half=half)
    back = read_exr(path)
    assert back.shape == img.shape and back.dtype == np.float32
    tol = 1e-3 if half else 0.0  # half: 10-bit mantissa
    assert np.all(np.abs(back - img) <= tol * np.abs(img) + 1e-7)
    assert [p.name for p in tmp_path.iterdir()] == ["hdr.exr"]


def test_half_overflow_refused(tmp_path):
    with pytest.raises(InputError, match="half-float range"):
        write_exr(tmp_path / "big.exr", np.full((2, 2, 3), 1e5), half=True)
    assert not any(tmp_path.iterdir())


def test_response_file_round_trip(tmp_path, response):
    path = hdr.save_response(tmp_path / "response.json", response)
    assert np.allclose(hdr.load_response(path), response, rtol=1e-8)
    data = json.loads(path.read_text())
    assert data["format"] == "glsldiff-camera-response" and len(data["response"]) == 256
    (tmp_path / "bad.json").write_text('{"format": "glsldiff-camera-response", "response": [[1, 2, 3]]}')
    with pytest.raises(InputError, match=r"bad\.json: response has shape \(1, 3\)"):
        hdr.load_response(tmp_path / "bad.json")


@pytest.fixture(scope="module")
def small_bracket():
    """A small ramp bracket (images, times) for the file and command tests."""
    cam = sr.camera((128, 16), gain=0.1)
    return sr.capture_bracket(cam, sr.ramp_radiance((16, 128), 1e-3, 1e2), seed=5), sr.EXPOSURES


@pytest.mark.parametrize("sidecar", ["json", "csv", "exif"])
def test_exposure_times_sources(tmp_path, small_bracket, sidecar):
    images, times = small_bracket
    folder = sr.write_bracket(tmp_path / sidecar, images, times, sidecar)
    bracket = hdr.load_bracket(folder)
    assert np.allclose(bracket.times, times, rtol=1e-6)
    assert all(np.array_equal(a, b) for a, b in zip(bracket.images, images))


def test_sidecar_fractions(tmp_path, small_bracket):
    images, _ = small_bracket
    folder = sr.write_bracket(tmp_path / "b", images[:2], (1 / 30, 0.5), "json")
    (folder / "exposures.json").unlink()
    (folder / "exposures.txt").write_text("# file seconds\nimg_00.png 1/30\nimg_01.png   0.5\n")
    assert np.allclose(hdr.load_bracket(folder).times, [1 / 30, 0.5])


def test_commands(tmp_path, small_bracket, capsys):
    images, times = small_bracket
    a = sr.write_bracket(tmp_path / "a", images, times)
    b = sr.write_bracket(tmp_path / "b", [np.ascontiguousarray(im[:, ::-1]) for im in images], times, "csv")
    assert capture(["response", str(a), str(b), "-o", str(tmp_path / "r.json")]) == 0
    assert hdr.load_response(tmp_path / "r.json").shape == (256, 3)
    assert capture(["merge", str(a), "-o", str(tmp_path / "m.exr"), "--response", str(tmp_path / "r.json"),
                    "--half", "--mask", str(tmp_path / "mask.png")]) == 0
    assert read_exr(tmp_path / "m.exr").shape == (16, 128, 3)
    assert cv2.imread(str(tmp_path / "mask.png")).shape == (16, 128, 3)
    assert capture(["merge", str(a), "-o", str(tmp_path / "self.exr")]) == 0  # response from the bracket
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        capture(["merge", "--help"])
    assert exc.value.code == 0 and "--response" in capsys.readouterr().out


def test_color_commands(tmp_path, chart):
    write_exr(tmp_path / "white.exr", chart["white"])
    write_exr(tmp_path / "black.exr", chart["black"])
    assert capture(["white-balance", str(tmp_path / "white.exr"), "-o", str(tmp_path / "wb.json")]) == 0
    wb = json.loads((tmp_path / "wb.json").read_text())
    assert wb["method"] == "mcc" and np.abs(np.asarray(wb["gains"]) / expected_gains() - 1).max() < 0.02
    corners = [f"{x},{y}" for x, y in sr.CHART_CORNERS]
    assert capture(["black-level", str(tmp_path / "black.exr"), str(tmp_path / "white.exr"),
                     "-o", str(tmp_path / "bl.json"), "--corners", *corners]) == 0
    bl = json.loads((tmp_path / "bl.json").read_text())
    assert bl["method"] == "corners" and np.abs(np.asarray(bl["mean"]) / 0.01 - 1).max() < 0.10


def test_radiometric_steps_help(capsys):
    """``glsldiff capture STEP --help`` of the radiometric steps: usage on stdout, status 0."""
    for step in ("response", "merge", "white-balance", "black-level"):
        with pytest.raises(SystemExit) as exc:
            capture([step, "--help"])
        out = capsys.readouterr().out
        assert exc.value.code == 0 and out.startswith(f"usage: glsldiff capture {step} "), out


# ----------------------------------------------------------------------------- bad input

def bad_folder(tmp_path, small_bracket, case: str):
    """A bracket folder broken in one way; returns (folder, expected message regex)."""
    images, times = small_bracket
    folder = sr.write_bracket(tmp_path / case, images, times, "json")
    if case == "one exposure":
        for p in folder.glob("img_0[1-9].png"):
            p.unlink()
        (folder / "exposures.json").write_text('{"img_00.png": 0.5}')
        return folder, r"1 image\(s\) with 1 distinct exposure time.*at least two"
    if case == "sizes":
        cv2.imwrite(str(folder / "img_02.png"), images[2][:8, :64, ::-1])
        return folder, r"img_02\.png: image size 64x8 differs"
    if case == "sidecar":
        (folder / "exposures.json").write_text(json.dumps({f"img_0{k}.png": t for k, t in enumerate(times) if k != 3}))
        return folder, r"img_03\.png: no exposure time in .*exposures\.json"
    if case == "sidecar value":
        (folder / "exposures.json").write_text(json.dumps({f"img_0{k}.png": "fast" for k in range(len(times))}))
        return folder, r"exposures\.json: img_00\.png: exposure time 'fast' is not a number"
    if case == "exif":
        (folder / "exposures.json").unlink()
        return folder, r"img_00\.png: no EXIF ExposureTime"
    if case == "image":
        (folder / "img_01.png").write_bytes(b"not a png")
        return folder, r"img_01\.png: cannot read the image"
    if case == "16 bit":
        cv2.imwrite(str(folder / "img_04.png"), (images[4].astype(np.uint16) * 257)[..., ::-1])
        return folder, r"img_04\.png: uint16 image; .*8-bit"
    raise AssertionError(case)


CASES = ["one exposure", "sizes", "sidecar", "sidecar value", "exif", "image", "16 bit"]


@pytest.mark.parametrize("case", CASES)
def test_bad_bracket(tmp_path, small_bracket, capsys, case):
    """Each broken bracket: InputError naming the file; the command prints one error line,
    returns 2 and writes nothing."""
    folder, match = bad_folder(tmp_path, small_bracket, case)
    with pytest.raises(InputError, match=match):
        hdr.load_bracket(folder)
    out = tmp_path / "out"
    capsys.readouterr()
    assert capture(["merge", str(folder), "-o", str(out / "m.exr"), "--mask", str(out / "mask.png")]) == 2
    assert capture(["response", str(folder), "-o", str(out / "r.json")]) == 2
    err = error_lines(capsys.readouterr().err)
    assert len(err) == 2 and all(line.startswith(ERR) for line in err)
    assert not out.exists() or not any(out.iterdir())


def test_bad_exr_and_response(tmp_path, capsys):
    (tmp_path / "broken.exr").write_bytes(b"garbage")
    with pytest.raises(InputError, match=r"broken\.exr: cannot read the OpenEXR image"):
        hdr.read_hdr(tmp_path / "broken.exr")
    capsys.readouterr()
    assert capture(["white-balance", str(tmp_path / "broken.exr"), "-o", str(tmp_path / "wb.json")]) == 2
    assert capture(["black-level", str(tmp_path / "missing.exr"), str(tmp_path / "broken.exr"),
                     "-o", str(tmp_path / "bl.json")]) == 2
    err = error_lines(capsys.readouterr().err)
    assert len(err) == 2 and "broken.exr" in err[0] and "missing.exr" in err[1]
    assert all(line.startswith(ERR) for line in err)
    (tmp_path / "r.json").write_text("{not json")
    with pytest.raises(InputError, match=r"r\.json: cannot read the response file"):
        hdr.load_response(tmp_path / "r.json")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.exr", "r.json"]


def test_bad_corners_and_roi(tmp_path, capsys):
    img = np.ones((50, 60, 3), np.float32)
    with pytest.raises(InputError, match="4 .x, y. pixel points"):
        color.grid_patches([[0, 0], [1, 1]])
    with pytest.raises(InputError, match="outside the 60x50 image"):
        color.white_balance(img, corners=[[100, 100], [200, 100], [200, 180], [100, 180]])
    with pytest.raises(InputError, match="width and height must be positive"):
        color.roi_cells((0, 0, 0, 10))
    capsys.readouterr()
    assert capture(["white-balance", str(tmp_path / "x.exr"), "-o", str(tmp_path / "wb.json"),
                     "--corners", "1,2", "3", "4,5", "6,7"]) == 2
    assert capsys.readouterr().err.startswith(ERR + "--corners 1,2 3 4,5 6,7: expected 4 points")


def test_inverted_exposure_times_are_refused(tmp_path, small_bracket, capsys):
    """Exposure times listed in reverse (as some tools store them) pair the brightest image
    with the shortest time: refused in one line instead of a decreasing response with exit 0."""
    images, times = small_bracket
    with pytest.raises(InputError, match="exposure times are probably inverted"):
        hdr.make_bracket(images, list(times)[::-1])
    folder = sr.write_bracket(tmp_path / "inv", images, list(times)[::-1])
    assert capture(["response", str(folder), "-o", str(tmp_path / "r.json")]) == 2
    err = "\n".join(error_lines(capsys.readouterr().err))
    assert err.startswith(ERR) and "\n" not in err and "inverted" in err
    assert not (tmp_path / "r.json").exists()


def test_merge_noise_floor_option(tmp_path, ramp, response, capsys):
    """--low raises the noise floor: more dark pixels become bounds instead of noisy values;
    out-of-range cutoffs are refused."""
    _, _, bracket = ramp
    _, mask20 = hdr.merge_bracket(bracket, response)
    _, mask40 = hdr.merge_bracket(bracket, response, lo=40)
    assert mask40.sum() > mask20.sum()
    images, times = sr.capture_bracket(sr.camera((64, 16), gain=0.1), sr.ramp_radiance((16, 64), 1e-3, 1e2),
                                       seed=7), sr.EXPOSURES
    folder = sr.write_bracket(tmp_path / "b", images, times)
    assert capture(["merge", str(folder), "-o", str(tmp_path / "m.exr"), "--low", "30", "--high", "220"]) == 0
    assert capture(["merge", str(folder), "-o", str(tmp_path / "n.exr"), "--low", "0"]) == 2
    assert "0 < lo < hi < 255" in capsys.readouterr().err


# ----------------------------------------------------------------------------- noise floor

def speckle_fraction(img: np.ndarray, mask: np.ndarray, truth: np.ndarray, dark: np.ndarray) -> float:
    """Fraction of the dark-region pixel values (``dark``, per channel) that the merge reports
    as usable (not masked) but off by more than a factor 2 from the truth (after each
    channel's scale is fitted on well-exposed pixels): the speckle of a noise floor set too low."""
    ratio = img / truth
    scale = [np.exp(np.median(np.log(ratio[..., c][~mask[..., c] & (truth[..., c] > 0.1)]))) for c in range(3)]
    r = ratio / np.asarray(scale)
    return float((~mask & ((r > 2.0) | (r < 0.5)) & dark).sum() / dark.sum())


@pytest.fixture(scope="module")
def noisy():
    """A camera with a dark offset (25 / 40 / 30 e-) and 8 e- read noise: its black frame reaches
    17 / 20 / 18 levels at the 99.9th percentile (max 19-21), like real brackets; a 1e-4 .. 1e3
    ramp bracket of it; the dark region: pixels below 40 levels at the longest exposure
    (noise-free, offset excluded)."""
    cam = sr.noisy_camera((256, 128), gain=0.1)
    radiance = sr.ramp_radiance((128, 256))
    black = sr.black_frame(cam, seed=11)
    bracket = hdr.make_bracket(sr.capture_bracket(cam, radiance, seed=1), sr.EXPOSURES, black=black)
    truth = radiance * cam.vignette()[..., None]
    clean = 255 * (truth * sr.EXPOSURES[-1] * cam.gain) ** (1 / cam.gamma)
    return bracket, hdr.calibrate_response(bracket), truth, clean


def test_black_frame_noise_floor_removes_dark_speckle(noisy):
    """Acceptance: merged with the black frame's noise floor (ceil(99.9th percentile) + 3 per
    channel), < 0.3 % of the dark region's pixel values are usable-but-off-by-2x; the old fixed
    cutoff of 20 leaves more (measured 0.067 % against 0.72 %, green alone 1.9 %). Pixels well
    above the floor (>= 60 levels at the longest exposure) are masked as before (only if saturated)."""
    bracket, response, truth, clean = noisy
    np.testing.assert_array_less(np.percentile(bracket.black.reshape(-1, 3), 99.9, axis=0), [22, 22, 22])
    assert bracket.black[..., 1].max() >= 18  # a real bracket's green noise floor
    floor = hdr.low_cutoff(bracket)
    np.testing.assert_array_equal(floor, hdr.noise_floor(bracket.black))
    assert floor.tolist() == [20, 23, 21], floor  # differs per channel
    dark = clean < 40
    auto_img, auto_mask = hdr.merge_bracket(bracket, response)
    old_img, old_mask = hdr.merge_bracket(bracket, response, lo=20)
    auto, old = (speckle_fraction(i, m, truth, dark) for i, m in ((auto_img, auto_mask), (old_img, old_mask)))
    print(f"\ndark speckle (usable, off by > 2x): noise floor {floor.tolist()} {auto:.4%}, fixed 20 {old:.4%}")
    assert auto < 0.003 < old, f"speckle fraction: black-frame floor {auto:.4%}, fixed --low 20 {old:.4%}"
    assert np.array_equal(auto_mask[clean >= 60], old_mask[clean >= 60])  # only the dark end changes


def test_noise_floor_from_the_bracket_itself_without_a_black_frame(noisy):
    """Issue 44's acceptance: the same noisy bracket without its black frame, default options:
    the floor estimated from the shortest exposure (23 / 24 / 23), dark speckle <= 0.5 % in every
    channel (the fixed 20 left 1.9 % in green); a noise-free bracket keeps the floor of 20."""
    bracket, response, truth, clean = noisy
    bare = hdr.make_bracket(bracket.images, bracket.times)
    floor = hdr.low_cutoff(bare)
    assert np.array_equal(floor, hdr.bracket_noise_floor(bare)) and np.all(floor >= hdr.noise_floor(bracket.black) - 1)
    img, mask = hdr.merge_bracket(bare, response)
    dark = clean < 40
    per = [speckle_fraction(img, mask, truth, dark & (np.arange(3) == c)) for c in range(3)]
    old_img, old_mask = hdr.merge_bracket(bare, response, lo=20)
    old = [speckle_fraction(old_img, old_mask, truth, dark & (np.arange(3) == c)) for c in range(3)]
    print(f"\nbracket floor {floor.tolist()}: speckle {[f'{p:.3%}' for p in per]}; fixed 20: {[f'{p:.3%}' for p in old]}")
    assert max(per) <= 0.005 < max(old)
    clean_bracket = hdr.make_bracket(sr.capture_bracket(sr.camera((64, 16), gain=0.1),
                                                        sr.ramp_radiance((16, 64), 1e-3, 1e2), seed=7), sr.EXPOSURES)
    assert hdr.low_cutoff(clean_bracket).tolist() == [hdr.LO] * 3


def test_one_column_exposure_list_in_file_order(tmp_path, ramp):
    _, _, bracket = ramp
    images, times = bracket.images, bracket.times
    folder = sr.write_bracket(tmp_path / "b", images, times, sidecar="exif")
    (folder / "exposures.txt").write_text("seconds\n" + "\n".join(f"1/{round(1 / t)}" if t < 1 else f"{t:g}"
                                                                   for t in times) + "\n")
    np.testing.assert_allclose(hdr.load_bracket(folder).times, times, rtol=1e-3)
    (folder / "exposures.txt").write_text("0.5\n1\n")
    with pytest.raises(InputError, match=r"2 exposure times for the 5 images"):
        hdr.load_bracket(folder)


def test_merge_command_takes_the_floor_from_a_black_frame(tmp_path, noisy, capsys):
    """``black.png`` in the bracket folder (no exposure time needed) or ``--black FILE`` sets the
    cutoff; ``--low`` overrides it; a black frame of another size or one too bright is refused."""
    bracket, _, _, _ = noisy
    folder = sr.write_bracket(tmp_path / "b", bracket.images, bracket.times)
    cv2.imwrite(str(folder / "black.png"), bracket.black[..., ::-1])
    loaded = hdr.load_bracket(folder)
    assert len(loaded.images) == 5 and loaded.black_file.name == "black.png"
    resp = tmp_path / "r.json"
    assert capture(["response", str(folder), "-o", str(resp)]) == 0
    assert capture(["merge", str(folder), "-o", str(tmp_path / "a.exr"), "--response", str(resp)]) == 0
    assert "lower cutoff R G B = 20 23 21 (noise floor of" in capsys.readouterr().out
    img, _ = hdr.merge_bracket(loaded, hdr.load_response(resp))
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), img)
    assert capture(["merge", str(folder), "-o", str(tmp_path / "b.exr"), "--response", str(resp), "--low", "20"]) == 0
    assert "= 20 20 20 (--low)" in capsys.readouterr().out
    other = tmp_path / "dark.png"
    cv2.imwrite(str(other), np.full_like(bracket.black, 2))
    assert capture(["merge", str(folder), "-o", str(tmp_path / "c.exr"), "--black", str(other)]) == 0
    assert "= 5 5 5 (noise floor of " + str(other) + ")" in capsys.readouterr().out

    cv2.imwrite(str(other), np.full((16, 16, 3), 2, np.uint8))
    assert capture(["merge", str(folder), "-o", str(tmp_path / "d.exr"), "--black", str(other)]) == 2
    err = "\n".join(error_lines(capsys.readouterr().err))
    assert err.startswith(ERR) and "\n" not in err and "dark.png: black frame" in err and "--low" in err
    cv2.imwrite(str(folder / "black.png"), np.full_like(bracket.black, 240))
    assert capture(["merge", str(folder), "-o", str(tmp_path / "e.exr")]) == 2
    err = "\n".join(error_lines(capsys.readouterr().err))
    assert err.startswith(ERR) and "\n" not in err and "black.png: noise floor" in err and "--low N" in err
    assert not any((tmp_path / f"{x}.exr").exists() for x in "de")
