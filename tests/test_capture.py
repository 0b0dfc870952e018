"""Capture plan, drivers, virtual rig, measurements from captures, and the virtual pipeline."""
from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from glsldiff.calibration import hdr
from glsldiff.calibration.measure import measure
from glsldiff.calibration.plan import CapturePlan, load_plan, write_plan
from glsldiff.calibration.rig import VirtualRig, default_devices, projector_homography, run_capture
from glsldiff.core.errors import InputError
from glsldiff.inverse.synthetic import synthetic_measurements
from glsldiff.physics.procedural import synthetic_volume

from calibration_rig import capture, check_cli_error   # tests/calibration_rig.py


def _rig(setup: str = "back", n: int = 2, shape=(6, 14, 14)) -> tuple[VirtualRig, CapturePlan]:
    k, m = synthetic_volume(shape, "mixed", seed=1)
    plan0 = CapturePlan(shape, 0.5, setup, n, exposures=(1 / 30, 1 / 4, 2.0, 8.0))
    cam, proj = default_devices(plan0, camera_size=(320, 256), pixels_per_node=8.0)
    plan = dataclasses.replace(plan0, face_to_projector=projector_homography(plan0, proj), conditions=[])
    return VirtualRig(k, m, 0.5, plan, cam, proj), plan


def test_plan_regions_tile_the_face_and_images_light_them(tmp_path) -> None:
    plan = CapturePlan((6, 14, 14), 0.5, "back", 3)
    assert len(plan.regions) == 9 and [c.name for c in plan.conditions[-3:]] == ["black", "white", "reference_black"]
    total = sum(plan.face_incoming(c) for c in plan.regions)
    np.testing.assert_array_equal(total, np.ones(plan.face_shape))
    folder = write_plan(plan, tmp_path / "plan")
    back = load_plan(folder)
    assert back.to_json() == plan.to_json()
    assert (folder / "region_00.png").is_file() and (folder / "black.png").is_file()


def test_projector_images_light_exactly_their_region() -> None:
    rig, plan = _rig(n=2)
    for cond in plan.regions:
        rig.show(plan.projector_image(cond))
        E = rig.irradiance()[..., 1]
        lit = plan.face_incoming(cond) > 0
        assert E[lit].min() > 0.9 and E[~lit].max() < 0.05  # black level 0.01 elsewhere


def test_plan_rejects_bad_input(tmp_path) -> None:
    with pytest.raises(InputError, match="n >= 2"):
        CapturePlan((6, 14, 14), 0.5, "front", 1)
    with pytest.raises(InputError, match="2 distinct"):
        CapturePlan((6, 14, 14), 0.5, exposures=(1.0,))
    with pytest.raises(InputError, match="setup"):
        CapturePlan((6, 14, 14), 0.5, "side")
    with pytest.raises(InputError, match="homography"):
        CapturePlan((6, 14, 14), 0.5, face_to_projector=np.zeros((3, 3)))
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(InputError, match="not empty"):
        write_plan(CapturePlan((6, 14, 14), 0.5), tmp_path / "full")
    with pytest.raises(InputError, match="does not exist"):
        load_plan(tmp_path / "nothing")


@pytest.fixture(scope="module")
def back_capture(tmp_path_factory):
    rig, plan = _rig("back", 2)
    out = tmp_path_factory.mktemp("cap") / "capture"
    run_capture(plan, rig, rig, out)
    return rig, plan, out


def test_capture_folder_layout(back_capture) -> None:
    rig, plan, out = back_capture
    for cond in plan.conditions:
        times = json.loads((out / cond.name / "exposures.json").read_text())
        assert sorted(times.values()) == list(plan.exposures)
        bracket = hdr.load_bracket(out / cond.name)
        assert bracket.images[0].shape == (256, 320, 3)
    assert load_plan(out).to_json() == plan.to_json()


def test_measurements_from_virtual_captures_match_the_solver(back_capture) -> None:
    """Incoming light and radiance extracted from 8-bit brackets agree with the forward solve
    up to the camera's (unknown) per-channel scale, which the fit does not see."""
    rig, plan, out = back_capture
    meas, rep = measure(out, rig.face_corners_px(), K=rig.camera.K, dist=rig.camera.dist)
    assert meas.M == 4 and meas.mask.mean() > 0.95
    assert np.allclose(rep.black_ratio, rig.projector.black, rtol=0.1)
    q_true = rig.true_incoming()
    scale = meas.incoming.sum(axis=(0, 1, 2)) / q_true.sum(axis=(0, 1, 2))
    np.testing.assert_allclose(scale / scale[1], np.array(rig.sensitivity) / rig.sensitivity[1], rtol=0.02)
    clean = synthetic_measurements(rig.kappa, rig.mu, rig.h, plan.n, "back", noise=0.0, read_noise=0.0)
    ratio = meas.radiance / scale
    bright = meas.mask & (clean.radiance > np.percentile(clean.radiance, 25))
    err = np.abs(ratio - clean.radiance)[bright].mean() / clean.radiance[bright].mean()
    assert err < 0.05, err


def test_measure_rejects_bad_captures(back_capture, tmp_path) -> None:
    rig, plan, out = back_capture
    with pytest.raises(InputError, match="beyond the image"):
        measure(out, rig.face_corners_px() * 3.0)
    with pytest.raises(InputError, match="plan file"):
        measure(tmp_path, rig.face_corners_px())
    with pytest.raises(InputError, match="not empty"):
        run_capture(plan, rig, rig, out)


def test_front_lit_measurements_mask_lit_nodes(tmp_path) -> None:
    rig, plan = _rig("front", 2)
    out = run_capture(plan, rig, rig, tmp_path / "front")
    meas, rep = measure(out, rig.face_corners_px(), K=rig.camera.K, dist=rig.camera.dist)
    assert rep.masked_lit > 0
    assert not np.any(meas.mask & (meas.incoming > 0))


def test_node_sampling_keeps_fast_falloff_unbiased() -> None:
    """Reflectance next to a lit region falls by e^-1 over about half a node spacing; the
    node sampler must read the value at the node, not a cell mean (which reads high)."""
    from glsldiff.calibration.measure import sample_nodes

    spacing, decay = 6.0, 3.0  # px
    u = np.arange(200, dtype=np.float64)
    img = np.repeat(np.exp(-u / decay)[None, :, None], 64, axis=0).repeat(3, axis=2)
    cols = 20.0 + spacing * np.arange(5)
    px = np.stack(np.meshgrid(cols, [30.0, 30.0 + spacing]), axis=-1)
    truth = np.exp(-cols / decay)
    rel = sample_nodes(img, px)[0, :, 1] / truth - 1.0
    assert np.all(np.abs(rel) < 0.05), rel  # 3x3 px mean: +3.7 % here
    wide = sample_nodes(img, px, footprint=1.0)[0, :, 1] / truth - 1.0
    assert np.all(wide > 0.2)  # the whole-cell mean the first version used


def test_virtual_pipeline_end_to_end(tmp_path) -> None:
    """Calibration, capture, response, HDR, measurements, ``glsldiff fit``: the fitted
    volume's appearance matches the truth better than the best homogeneous one."""
    from glsldiff.calibration.virtual import run

    rep = run(tmp_path / "v", size=(16, 16, 6), n=3, max_evals=40, calibrate=True)
    assert rep["camera_rms_px"] < 0.5 and rep["gray_stereo_rms_px"] < 0.5
    assert rep["gray_projector_rms_px"] < 0.5 and rep["gray_camera_rms_px"] < 0.5
    assert rep["response_max_rel_error"] < 0.06
    assert rep["E"] < 0.01 and rep["E"] < rep["E_median_homogeneous"]
    assert (tmp_path / "v" / "report.json").is_file() and (tmp_path / "v" / "material.npz").is_file()


def test_plan_and_measure_commands(back_capture, tmp_path, capsys) -> None:
    args = ["--shape", "6", "14", "14", "--h", "0.5", "--n", "2", "--face-corners", "100,100", "400,100",
            "400,400", "100,400"]
    assert capture(["plan", tmp_path / "p", *args]) == 0
    assert load_plan(tmp_path / "p").n == 2
    capsys.readouterr()
    check_cli_error(capsys, capture(["plan", tmp_path / "p", *args]), "not empty")  # never overwrites a plan
    rig, plan, out = back_capture
    corners = [f"{x},{y}" for x, y in rig.face_corners_px()]
    assert capture(["measure", out, "--corners", *corners, "-o", tmp_path / "m.npz"]) == 0
    from glsldiff.inverse.measurements import load_measurements
    assert load_measurements(tmp_path / "m.npz").M == 4
    assert capture(["measure", out, "--corners", *corners[:3], "-o", tmp_path / "n.npz"]) == 2
    capsys.readouterr()
    check_cli_error(capsys, capture(["measure", out, "--corners", *corners, "-o", tmp_path / "no" / "n.npz"]),
                    "no' does not exist")
    assert not (tmp_path / "n.npz").exists()


def test_capture_help_lists_every_step_and_bad_input_is_one_line() -> None:
    """``glsldiff capture --help`` (the installed command) names every step with its one-line
    help; a step given bad input, or a bad option, exits 2 with one error line, no traceback;
    the old ``python -m glsldiff.calibration.X`` programs are gone."""
    from glsldiff.commands.capture import STEPS

    glsldiff = str(Path(sys.executable).with_name("glsldiff"))
    r = subprocess.run([glsldiff, "capture", "--help"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stderr == "", r.stderr
    listed = re.findall(r"^    ([a-z-]+)(?:  +\S|$)", r.stdout, re.MULTILINE)
    assert listed == list(STEPS), r.stdout
    assert len(STEPS) == 12 and {"camera", "patterns", "calibrate", "response", "merge", "white-balance",
                                 "black-level", "plan", "measure", "virtual"} < set(STEPS)
    r = subprocess.run([glsldiff, "--help"], capture_output=True, text=True, timeout=120)
    assert re.search(r"^    capture  +\S", r.stdout, re.MULTILINE), r.stdout
    for argv, needle in ((["merge", "no-such-bracket", "-o", "m.exr"], "no-such-bracket"),
                         (["plan", "p", "--shape", "6", "14", "--h", "0.5"], "glsldiff capture plan: argument --shape"),
                         (["calibrate", "x", "--board", "9by7", "--square", "20", "--projector", "512x384"], "9by7"),
                         (["no-such-step"], "invalid choice")):
        r = subprocess.run([glsldiff, "capture", *argv], capture_output=True, text=True, timeout=120)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("glsldiff: error: "), r.stderr
        assert needle in lines[0] and "Traceback" not in r.stderr and r.stdout == "", (argv, r.stderr)
    r = subprocess.run([sys.executable, "-c", "import glsldiff.calibration.camera as c; "
                        "assert not hasattr(c, 'main') and not hasattr(c, 'build_parser')"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
