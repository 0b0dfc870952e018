"""glsldiff validate: the comparison machinery on tiny cases (Mitsuba 3 optional)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from glsldiff.core import io
from glsldiff.core.errors import InputError
from glsldiff.physics.lights import DirectionalLight, EnvironmentLight
from glsldiff.physics.sh import latlong_directions, sh_project
from glsldiff.validation.validate import CASES, _light, _scene, environment_map, mc_split, rmse, validate


def test_rmse_is_relative_and_masked():
    ref = np.ones((4, 4, 3))
    mask = np.zeros((4, 4), bool)
    mask[1:3, 1:3] = True
    ours = ref.copy()
    ours[mask] = 1.1
    ours[0, 0] = 100.0                     # outside the mask: ignored
    assert rmse(ours, ref, mask) == pytest.approx(0.1)


def test_mc_split_into_powers_of_four():
    """Mitsuba's low-discrepancy sampler takes 4^k samples per render; at least two renders."""
    assert [mc_split(s) for s in (8, 16, 32, 256, 512)] == [(2, 4), (4, 4), (2, 16), (4, 64), (2, 256)]
    for bad in (4, 100, 257, 0):
        with pytest.raises(InputError, match="power of two"):
            mc_split(bad)


def test_environment_maps_and_cases():
    """The sky is bright at the zenith (+z, row 0), dim at the nadir, brighter towards +y than -y,
    and exactly band limited to SH order 2; both renderers get it in the z-up convention."""
    sky = environment_map("sky", 32, 64)
    d, _ = latlong_directions(32, 64)
    lum = sky.mean(axis=2)
    assert lum[0].mean() > 1.0 > 0.3 > lum[-1].mean() > 0.0 and sky.min() > 0.0
    assert lum[d[..., 1] > 0.5].mean() > lum[d[..., 1] < -0.5].mean()
    c = sh_project(sky, 4)
    assert np.abs(c[9:]).max() < 1e-3 * np.abs(c[:9]).max()          # bands 3 and 4 vanish
    np.testing.assert_array_equal(environment_map("constant", 4, 8), 1.0)
    case = CASES["sphere-eta1.3-sky"]
    assert case.eta == 1.3 and CASES["sphere-sky"].eta == 1.0
    light = _light(case)
    assert isinstance(light, EnvironmentLight) and np.array_equal(light.image, environment_map("sky"))
    np.testing.assert_array_equal(_light(CASES["sphere-eta1.3-constant"]).image, 1.0)
    assert isinstance(_light(CASES["sphere"]), DirectionalLight)
    scene = _scene(case, None, 16)
    assert scene.material.eta == 1.3 and scene.lights[0].digest == light.digest and scene.specular.rho_s == 0
    with pytest.raises(InputError, match="environment light"):
        dataclasses.replace(CASES["sphere"], eta=1.3)
    with pytest.raises(InputError, match="not an environment"):
        dataclasses.replace(case, light="studio")
    with pytest.raises(InputError, match="unknown environment"):
        environment_map("studio")


def test_tiny_sphere_case_runs_and_agrees_roughly(tmp_path, ctx, monkeypatch):
    pytest.importorskip("mitsuba")
    tiny = dataclasses.replace(CASES["sphere"], name="tiny", n=6, cubes=8)
    monkeypatch.setitem(CASES, "tiny", tiny)
    rows = validate(["tiny"], tmp_path, size=24, spp=16)
    r = rows[0]
    assert r["pixels"] > 50 and np.isfinite(r["rmse_vs_mc_all_scattering"])
    # dense, high albedo: diffusion is within a factor 1.6 of Monte Carlo's scattered light
    assert 0.6 < r["mean_ratio"] * (1.0 - r["single_share"]) < 1.6
    assert r["surface_share"] == pytest.approx(0.0, abs=1e-6)     # directional light, null boundary
    assert (tmp_path / "validation.csv").is_file() and (tmp_path / "validation_tiny.png").is_file()
    with pytest.raises(InputError, match="unknown validation case"):
        validate(["cube"], tmp_path)
    with pytest.raises(InputError, match="power of two"):
        validate(["tiny"], tmp_path, spp=100)


def test_tiny_refractive_sphere_under_the_sky(tmp_path, ctx, monkeypatch):
    """eta = 1.3 under the sky map: both renderers brighten the zenith (+z) side, at the image's
    left; diffusion vs Monte Carlo's subsurface image (surface reflection removed).

    Measured at this size (24 px, 64 spp, 6-node 8-cube polygrid), seeds 0..36: RMSE 0.13-0.15
    (Monte Carlo noise 0.09), mean ratio 0.95-0.97, reflection share 0.024-0.032, left/right
    brightness 1.33 (diffusion) and 1.48-1.52 (Monte Carlo)."""
    pytest.importorskip("mitsuba")
    tiny = dataclasses.replace(CASES["sphere-eta1.3-sky"], name="tiny-sky", n=6, cubes=8)
    monkeypatch.setitem(CASES, "tiny-sky", tiny)
    r = validate(["tiny-sky"], tmp_path, size=24, spp=64)[0]
    assert r["eta"] == 1.3 and r["light"] == "sky" and r["pixels"] > 50
    assert np.isnan(r["rmse_vs_mc_multiple"]) and np.isnan(r["single_share"])
    assert np.isfinite(r["rmse_vs_mc_all_scattering"]) and r["rmse_vs_mc_all_scattering"] < 0.25
    assert 0.8 < r["mean_ratio_all_scattering"] < 1.2
    assert 0.01 < r["surface_share"] < 0.06           # Fresnel: 1.7 % at normal incidence, more at grazing
    env = io.read_exr(tmp_path / "validation_tiny-sky_environment.exr")
    np.testing.assert_allclose(env, environment_map("sky"), rtol=1e-6)
    for name in ("diffusion", "mc_subsurface"):
        img = io.read_exr(tmp_path / f"validation_tiny-sky_{name}.exr").mean(axis=2)
        left, right = img[:, :12], img[:, 12:]
        assert left[left > 0].mean() > 1.15 * right[right > 0].mean(), name
    full = io.read_exr(tmp_path / "validation_tiny-sky_mc_full.exr")
    assert full[0, 0].min() > 0.0                      # the environment seen past the sphere
