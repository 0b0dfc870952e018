"""glsldiff bench frames: the orbit keeps the camera's distance, and (slow) the command writes
its rows, a light change converges and the camera frames run pass 3 alone."""
from __future__ import annotations

import csv

import numpy as np
import pytest

from glsldiff.bench.frames import _orbit, mode_scene
from glsldiff.commands.cli import main


def test_orbit_turns_the_eye_about_the_target():
    scene = mode_scene("render", 32)
    eye, target, up = np.array([0.0, 10.0, 200.0]), np.array([0.0, 10.0, 0.0]), np.array([0.0, 1.0, 0.0])
    quarter = np.array(_orbit(scene, eye, target, up, 90.0).camera.position)
    assert np.allclose(quarter, [200.0, 10.0, 0.0], atol=1e-9)
    assert np.allclose(_orbit(scene, eye, target, up, 360.0).camera.position, eye, atol=1e-9)
    assert _orbit(scene, eye, target, up, 5.0).camera.target == tuple(target)


@pytest.mark.slow
def test_bench_frames_writes_rows_and_the_light_change_converges(tmp_path):
    out = tmp_path / "out"
    assert main(["bench", "frames", "--modes", "render", "--size", "64", "--orbit", "2", "--out", str(out)]) == 0
    rows = list(csv.DictReader(open(out / "frames_frames.csv")))
    (summary,) = list(csv.DictReader(open(out / "frames_summary.csv")))
    assert summary["single scattering"] == "3-D march" and float(summary["camera ms"]) > 0
    assert all(r["passes"] == "pass3" for r in rows if r["phase"] in ("unchanged", "camera"))
    light = [float(r["rel_l2"]) for r in rows if r["phase"] == "light"]
    assert light[0] > light[-1] and light[-1] < 5e-3
    assert (out / "frames.png").stat().st_size > 0
