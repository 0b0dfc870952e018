"""Capture folders as kamino410/procam-calibration lays them out (``capture_*/graycode_NN.png``,
white and black last, ``camera_config.json`` for ``-camera``), and the camera command reading
the white frames of a projector capture directly. Synthetic captures from
``glsldiff.calibration.views`` (640x512 camera, 512x384 projector, 4 poses)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from glsldiff.calibration import camera, graycode, projector, views
from glsldiff.core.errors import InputError

from calibration_rig import BOARD, BOARD_ARGS, CAM, PROJ, capture, check_cli_error, rel_err   # tests/calibration_rig.py


@pytest.fixture(scope="module")
def procam(tmp_path_factory) -> tuple[Path, views.SyntheticRig]:
    """A dataset with procam-calibration's exact names, plus files that tool ignores: another
    image in a capture folder and its own pattern folder beside the captures."""
    rig = views.synthetic_rig(4, CAM, PROJ, BOARD)
    root = views.write_projector_dataset(tmp_path_factory.mktemp("procam") / "data", rig, layout="procam")
    shutil.copy(root / "capture_1" / "graycode_36.png", root / "capture_1" / "preview.png")
    graycode.write_patterns(root / "graycode_pattern", PROJ)
    return root, rig


def camera_config(truth: dict, size: bool = True) -> dict:
    """procam-calibration's camera_config.json for the true camera (P row by row)."""
    cam = {"P": np.ravel(truth["camera"]["K"]).tolist(), "distortion": truth["camera"]["dist"],
           "other properties will be ignored": ""}
    if size:
        cam.update(width=truth["camera"]["image_size"][0], height=truth["camera"]["image_size"][1])
    return {"camera": cam}


def test_reference_layout_calibrates_as_it_is(procam, tmp_path, capsys):
    """capture_K/graycode_NN.png (only the graycode_* images count) with procam-calibration's
    camera_config.json for --camera: the camera is taken as given, the projector recovered."""
    root, rig = procam
    assert sorted(p.name for p in root.glob("capture_*")) == ["capture_0", "capture_1", "capture_2", "capture_3"]
    n = graycode.sequence_length(PROJ)
    assert [p.name for p in graycode.sequence_images(root / "capture_1")] == [f"graycode_{i:02d}.png"
                                                                              for i in range(n)]
    truth = json.loads((root / "truth.json").read_text())
    config = tmp_path / "camera_config.json"
    config.write_text(json.dumps(camera_config(truth)))
    out = tmp_path / "rig.json"
    rc = capture(["calibrate", str(root), *BOARD_ARGS, "--projector", "512x384", "--window", "31",
                  "--camera", str(config), "-o", str(out)])
    assert rc == 0, capsys.readouterr().err
    data = json.loads(out.read_text())
    np.testing.assert_allclose(data["camera"]["K"], truth["camera"]["K"])
    assert data["camera"]["image_size"] == list(CAM) and len(data["poses"]) == 4
    Kp, Kpt = np.array(data["projector"]["K"]), np.array(truth["projector"]["K"])
    assert rel_err(Kp[0, 0], Kpt[0, 0]) < 0.02 and rel_err(Kp[1, 1], Kpt[1, 1]) < 0.02
    assert data["stereo"]["rms"] < 0.5 and rel_err(data["stereo"]["baseline_mm"], truth["baseline_mm"]) < 0.02
    assert all(Path(p["folder"]).name.startswith("capture_") for p in data["poses"])


def test_reference_camera_file_without_size_and_bad_ones(procam, tmp_path, capsys):
    """procam-calibration reads only P and distortion: without width/height the captures' size is
    used; a file of another size, or one that is neither format, is refused in one line."""
    root, _ = procam
    truth = json.loads((root / "truth.json").read_text())
    config = tmp_path / "camera_config.json"
    config.write_text(json.dumps(camera_config(truth, size=False)))
    intr = camera.load_intrinsics(config)
    assert intr.size is None and np.allclose(intr.K, truth["camera"]["K"])
    sub = tmp_path / "three"
    for k in range(3):
        shutil.copytree(root / f"capture_{k}", sub / f"capture_{k}")
    rig = projector.calibrate_folder(sub, BOARD, PROJ, projector.DecodeSettings(window=31), camera=intr)
    assert rig.camera.size == CAM
    assert rig.to_json(BOARD, projector.DecodeSettings(), 0)["camera"]["image_size"] == list(CAM)

    bad = camera_config(truth)
    bad["camera"]["width"] = 1280
    config.write_text(json.dumps(bad))
    rc = capture(["calibrate", str(sub), *BOARD_ARGS, "--projector", "512x384", "--window", "31",
                  "--camera", str(config), "-o", str(tmp_path / "r.json")])
    check_cli_error(capsys, rc, "--camera", "1280x512")
    config.write_text(json.dumps({"camera": {"P": [1.0, 0.0, 2.0], "distortion": [0, 0, 0, 0, 0]}}))
    with pytest.raises(InputError, match=r"camera_config\.json: not a camera calibration .*camera\.P"):
        camera.load_intrinsics(config)
    assert not (tmp_path / "r.json").exists()


def test_unpadded_image_numbers_keep_pattern_order(procam, tmp_path):
    """graycode_0 ... graycode_37 (no zero padding) are read in numeric order, not as text
    (graycode_10 before graycode_2); the decoded sequence is the padded one's."""
    root, _ = procam
    src, dst = root / "capture_2", tmp_path / "capture_2"
    dst.mkdir()
    for i, p in enumerate(graycode.sequence_images(src)):
        shutil.copy(p, dst / f"graycode_{i}.png")
    names = [p.name for p in graycode.sequence_images(dst)]
    assert names[:3] == ["graycode_0.png", "graycode_1.png", "graycode_2.png"] and names[-1] == "graycode_37.png"
    np.testing.assert_array_equal(projector.read_sequence(dst, PROJ), projector.read_sequence(src, PROJ))


def test_camera_from_projector_captures(procam, tmp_path, capsys):
    """The camera command takes the capture root (or capture_* folders) and uses the white frame
    of each pose (graycode_36.png of 38): K within 1 % of the truth, as from plain views."""
    root, rig = procam
    out = tmp_path / "camera.json"
    assert capture(["camera", str(root), *BOARD_ARGS, "-o", str(out)]) == 0
    capsys.readouterr()
    data = json.loads(out.read_text())
    assert [Path(f).name for f in data["files_used"]] == ["graycode_36.png"] * 4
    assert [Path(f).parent.name for f in data["files_used"]] == ["capture_0", "capture_1", "capture_2", "capture_3"]
    K, Kt = np.array(data["K"]), rig.camera.K
    assert data["rms"] < 0.5 and rel_err(K[0, 0], Kt[0, 0]) < 0.01 and rel_err(K[1, 1], Kt[1, 1]) < 0.01
    folders = [str(root / f"capture_{k}") for k in range(4)]
    assert capture(["camera", *folders, *BOARD_ARGS, "-o", str(tmp_path / "c2.json")]) == 0
    assert json.loads((tmp_path / "c2.json").read_text())["files_used"] == data["files_used"]

    odd = tmp_path / "capture_odd"
    shutil.copytree(root / "capture_0", odd)
    (odd / "graycode_37.png").unlink()
    capsys.readouterr()
    check_cli_error(capsys, capture(["camera", str(odd), *BOARD_ARGS, "-o", str(tmp_path / "c3.json")]),
                   "capture_odd: 37 images", "white frame")
    assert not (tmp_path / "c3.json").exists()
