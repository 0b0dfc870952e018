"""glsldiff validate: the comparison machinery on a tiny case (Mitsuba 3 optional)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from glsldiff.errors import InputError
from glsldiff.validate import CASES, rmse, validate


def test_rmse_is_relative_and_masked():
    ref = np.ones((4, 4, 3))
    mask = np.zeros((4, 4), bool)
    mask[1:3, 1:3] = True
    ours = ref.copy()
    ours[mask] = 1.1
    ours[0, 0] = 100.0                     # outside the mask: ignored
    assert rmse(ours, ref, mask) == pytest.approx(0.1)


def test_tiny_sphere_case_runs_and_agrees_roughly(tmp_path, ctx, monkeypatch):
    pytest.importorskip("mitsuba")
    tiny = dataclasses.replace(CASES["sphere"], name="tiny", n=6, cubes=8)
    monkeypatch.setitem(CASES, "tiny", tiny)
    rows = validate(["tiny"], tmp_path, size=24, spp=16)
    r = rows[0]
    assert r["pixels"] > 50 and np.isfinite(r["rmse_vs_mc_all_scattering"])
    # dense, high albedo: diffusion is within a factor 1.6 of Monte Carlo's scattered light
    assert 0.6 < r["mean_ratio"] * (1.0 - r["single_share"]) < 1.6
    assert (tmp_path / "validation.csv").is_file() and (tmp_path / "validation_tiny.png").is_file()
    with pytest.raises(InputError, match="unknown validation case"):
        validate(["cube"], tmp_path)
