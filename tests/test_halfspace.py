"""Chandrasekhar's H-function and the incidence split of the surface source, against closed
forms, the 1-D transport oracle, and the renderer on both discretisations."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.oracle.slab_transport import slab_diffusion, slab_monte_carlo
from glsldiff.physics.exitance import deep_irradiance, halfspace_bracket, local_bracket
from glsldiff.physics.halfspace import h_function, h_mean, reflected_share
from glsldiff.physics.lights import DirectionalLight
from glsldiff.render.renderer import Renderer
from glsldiff.render.scene import CameraSpec, MeshSpec, OptionsSpec, OutputSpec, PolygridSpec, Scene, parse_scene

_x, _w = np.polynomial.legendre.leggauss(32)
MU, W = 0.5 * (_x + 1.0), 0.5 * _w          # Gauss nodes on [0, 1]


def test_closed_forms():
    """Conservative scattering: H(1) = 2.9078, <H> = 2 alpha_1 = 4 / sqrt(3) (Chandrasekhar,
    table XI); no scattering: H = 1."""
    assert h_function(1.0, 1.0) == pytest.approx(2.90781, rel=2e-4)
    assert h_function(1.0, 0.0) == pytest.approx(1.0, abs=1e-9)
    assert h_mean(1.0) == pytest.approx(4.0 / math.sqrt(3.0), rel=2e-4)
    assert np.allclose(h_function(0.0, MU), 1.0) and h_mean(0.0) == pytest.approx(1.0)
    # H grows with the albedo and with mu
    assert np.all(np.diff(h_function(0.9, MU)) > 0) and h_function(0.5, 1.0) < h_function(0.9, 1.0)


@pytest.mark.parametrize("albedo", [1.0, 0.9, 0.3])
@pytest.mark.parametrize("view", [0.05, 0.5, 1.0])
def test_reflected_share_and_deep_share_average_to_one_over_diffuse_light(albedo, view):
    assert float((2 * MU * W * reflected_share(albedo, MU, view)).sum()) == pytest.approx(1.0, abs=3e-4)
    assert float((2 * MU * W * h_function(albedo, MU)).sum() / h_mean(albedo)) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("incidence", ["normal", "diffuse"])
def test_half_space_reflectance_against_photon_transport(incidence):
    """``1 - H(mu0) sqrt(1 - a)`` (total) and ``a H(mu) H(mu0) / (4 pi (mu + mu0))`` (radiance)
    against the 1-D Monte Carlo oracle on a 60 mm slab (a half-space at this albedo)."""
    a = 0.99
    mc = slab_monte_carlo(0.01, 0.99, 60.0, 1.0, incidence, photons=400_000, batches=4, seed=3)
    if incidence == "normal":
        total = 1.0 - h_function(a, 1.0) * math.sqrt(1.0 - a)
        radiance = a * h_function(a, 0.95) * h_function(a, 1.0) / (4.0 * math.pi * 1.95)
    else:
        total = 1.0 - h_mean(a) * math.sqrt(1.0 - a)
        radiance = float((2 * MU * W * a * h_function(a, 0.95) * h_function(a, MU) / (4 * math.pi * (0.95 + MU))).sum())
    assert mc.flux[0] == pytest.approx(total, abs=0.01)
    assert mc.scattered[0, 9] == pytest.approx(radiance, rel=0.03)     # exit cosines 0.9-1


def test_normal_light_reaches_the_deep_field_more_than_diffuse_light():
    """Transport: a thick slab transmits H(1) / <H> times more of normal than of diffuse light
    (1.26 at albedo 0.995, the Marshak source 1); the deep share of the incidence split says
    the same."""
    n = slab_monte_carlo(0.005, 1.0, 20.0, 1.0, "normal", photons=400_000, batches=4, seed=1)
    d = slab_monte_carlo(0.005, 1.0, 20.0, 1.0, "diffuse", photons=400_000, batches=4, seed=2)
    marshak = slab_diffusion(0.005, 1.0, 20.0, 1.0, "normal", "surface")[1] / slab_diffusion(
        0.005, 1.0, 20.0, 1.0, "diffuse", "surface")[1]
    assert marshak == pytest.approx(1.0)
    a = 1.0 / 1.005
    assert n.flux[1] / d.flux[1] == pytest.approx(h_function(a, 1.0) / h_mean(a), rel=0.05)


def test_split_keeps_diffuse_light_and_the_model_half_space():
    """Diffuse light (cosine-weighted beams) keeps the Marshak load and gets no local term; the
    model's half-space bracket is the 1-D diffusion's reflection."""
    kappa, mu = np.full((1, 3), 1.0 / (3 * 1.02)), np.full((1, 3), 0.02)
    beams = [(np.full((1, 3), 2 * m * w), np.array([m])) for m, w in zip(MU, W)]
    assert deep_irradiance(beams, kappa, mu) == pytest.approx(np.ones((1, 3)), abs=1e-5)
    beta = halfspace_bracket(kappa, mu, 1.0, "p1")
    for view in (0.2, 1.0):
        assert np.abs(local_bracket(beams, kappa, mu, np.array([view]), beta)).max() < 3e-4 * beta.max()
    one_d = slab_diffusion(0.02, 1.0, 200.0, 1.0, "normal", "surface")[0]
    assert beta[0, 0] == pytest.approx(one_d, rel=2e-3)
    # normal incidence: more into the deep field, the local term takes it back at the surface
    normal = [(np.ones((1, 3)), np.array([1.0]))]
    assert deep_irradiance(normal, kappa, mu)[0, 0] > 1.15
    assert local_bracket(normal, kappa, mu, np.array([1.0]), beta)[0, 0] < 0
    # "local": the Marshak load; the local term alone follows the half-space's incidence and view
    for view in (0.2, 1.0):
        assert np.abs(local_bracket(beams, kappa, mu, np.array([view]), beta, deep=False)).max() < 3e-4 * beta.max()
    grazing = [(np.ones((1, 3)), np.array([0.1]))]
    a = 1.0 - 3.0 * kappa[0, 0] * mu[0, 0]
    expect = beta[0, 0] * (h_function(a, 0.1) / (1.1 * float((2 * MU * W * h_function(a, MU) / (1.0 + MU)).sum())) - 1)
    assert local_bracket(grazing, kappa, mu, np.array([1.0]), beta, deep=False)[0, 0] == pytest.approx(expect, rel=2e-3)


def test_scene_option():
    base = {"mesh": {"source": "sphere"}, "lights": [{"type": "directional", "direction": [0, 0, 1],
                                                      "irradiance": [1, 1, 1]}]}
    assert parse_scene(base).options.incidence == "local"
    diffusion = {"model": "diffusion"}     # the incidence split belongs to the classical diffusion model
    assert parse_scene({**base, "options": {**diffusion, "incidence": "marshak"}}).options.incidence == "marshak"
    assert parse_scene({**base, "options": {**diffusion, "incidence": "transport"}}).options.incidence == "transport"
    with pytest.raises(InputError, match=r"\[options\]\.incidence"):
        parse_scene({**base, "options": {**diffusion, "incidence": "lambert"}})


@pytest.mark.parametrize("discretisation, incidence", [("fem", "transport"), ("conservative", "transport"),
                                                      ("fem", "local"), ("conservative", "local")])
def test_renderer_incidence(ctx, discretisation, incidence):
    """Front-lit sphere seen from the side: with ``incidence = "transport"`` or ``"local"`` the grazing-lit band
    near the terminator is brighter against the steeply lit side than with the Marshak source
    (Monte Carlo: 0.85x -> 1.15x from grazing to normal incidence with the Marshak source); the
    image stays finite and non-negative, the report says which was used, and a camera move
    re-evaluates the bracket without a new solve."""
    n = 4 if discretisation == "fem" else 6
    scene = Scene(mesh=MeshSpec("sphere", 20.0), polygrid=PolygridSpec(n, 8, 2, discretisation),
                  lights=(DirectionalLight((0.0, 0.0, 1.0), (1.0, 1.0, 1.0)),), output=OutputSpec(48, 48),
                  camera=CameraSpec(position=(60.0, 0.0, 0.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)),
                  options=OptionsSpec(flux="smoothed" if discretisation == "fem" else "boundary", incidence="marshak",
                                      model="diffusion"))
    scene = dataclasses.replace(scene, material=dataclasses.replace(scene.material, eta=1.0))   # index matched
    with Renderer(ctx) as r:
        old, _ = r.render(scene)
        new, rep = r.render(dataclasses.replace(scene, options=dataclasses.replace(scene.options,
                                                                                   incidence=incidence)))
        assert any(f"incidence: {incidence}" in line for line in rep.notes)
        moved, rep2 = r.render(dataclasses.replace(scene, camera=CameraSpec(position=(40.0, 0.0, 45.0)),
                                                   options=dataclasses.replace(scene.options, incidence=incidence)))
        assert not rep2.ran("pass2") and np.all(np.isfinite(moved)) and moved.min() >= 0.0
    assert np.all(np.isfinite(new)) and new.min() >= 0.0
    lum_o, lum_n = old.mean(axis=2), new.mean(axis=2)
    row_o, row_n = lum_o[24], lum_n[24]
    obj = np.flatnonzero(row_o > 0.02 * row_o.max())
    lit, grazing = obj[:3], obj[len(obj) // 2 - 2: len(obj) // 2 + 1]     # image left is +z (lit); the middle grazes
    assert (row_n[grazing].mean() / row_n[lit].mean()) > 1.02 * (row_o[grazing].mean() / row_o[lit].mean())
    assert lum_n.sum() == pytest.approx(lum_o.sum(), rel=0.15)


def test_local_bracket_is_finite_where_beam_and_view_are_both_grazing():
    """eta < 1: past the critical angle a beam's and the view's refracted cosines are 0 (the beam
    carries no light there); the local term is then 0, not 0/0 (which rendered black images)."""
    kappa, mu = np.full((2, 3), 1.0 / (3 * 1.02)), np.full((2, 3), 0.02)
    beta = halfspace_bracket(kappa, mu, 0.9, "p1")
    beams = [(np.array([[0.0] * 3, [1.0] * 3]), np.array([0.0, 0.5]))]
    out = local_bracket(beams, kappa, mu, np.array([0.0, 0.7]), beta)
    assert np.all(np.isfinite(out)) and np.all(out[0] == 0.0) and np.all(out[1] != 0.0)
