"""Measured diffuse surface reflectance (paper sec. 6.1, Tong et al. 2005): the uniform
image minus the fitted material's multiple scattering, and its map on an object."""
import math

import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.grids.regular import RegularGrid
from glsldiff.inverse.measurements import Measurements
from glsldiff.inverse.model import ForwardModel
from glsldiff.inverse.reflectance import diffuse_reflectance
from glsldiff.physics.procedural import synthetic_volume
from glsldiff.physics.optics import fresnel_transmittance
from glsldiff.physics.exitance import exitant_bracket, source_from_irradiance


def _uniform_front(rho_true, E, eta=1.3):
    kappa, mu = synthetic_volume((6, 10, 12), "veins", seed=2)
    nz, ny, nx = kappa.shape[:3]
    grid = RegularGrid(nx, ny, nz, h=0.5)
    model = ForwardModel(grid, "conservative", eta=eta)
    q = np.ones(grid.face_shape("z-"))
    Q = grid.face_to_boundary("z-", q[..., None])
    L = np.zeros(grid.face_shape("z-") + (3,))
    s = source_from_irradiance(np.ones(1), eta, "p1")[0]
    for c in range(3):     # the renderer's P1 exitant radiance of the uniformly lit face
        fac = model.factorize(model.active_values(kappa[..., c]), model.active_values(mu[..., c]))
        phi_b = fac.boundary_phi(fac.solve(s * Q))[:, 0]
        L[..., c] = grid.boundary_to_face("z-", fresnel_transmittance(eta, 1.0)
                                          * exitant_bracket(phi_b, s * Q[:, 0], eta, "p1"))
    assert np.all(L > 0)
    measured = L + rho_true * E / math.pi
    meas = Measurements((nz, ny, nx), 0.5, "z-", "z-", np.repeat(q[None, ..., None], 3, -1), measured[None],
                        eta=eta)
    return meas, kappa, mu, L


def test_recovers_known_reflectance():
    E = np.array([2.0, 1.5, 1.0])
    rng = np.random.default_rng(0)
    rho_true = 0.02 + 0.03 * rng.uniform(size=(8, 10, 3))
    meas, kappa, mu, L = _uniform_front(rho_true, E)
    r = diffuse_reflectance(meas, kappa, mu, 0, E)
    np.testing.assert_allclose(r.multiple, L, rtol=1e-9)
    default = diffuse_reflectance(meas, kappa, mu, 0)   # E from q / F_t(normal)
    np.testing.assert_allclose(default.rho * (1.0 / fresnel_transmittance(1.3, 1.0)), r.rho * E, rtol=1e-9)
    np.testing.assert_allclose(r.rho, rho_true, rtol=1e-7, atol=1e-12)
    assert r.clipped == 0.0 and "rho_d" in r.summary()


def test_wrong_material_clips_and_counts():
    """A material that over-predicts the multiple scattering leaves negative differences:
    they are clipped to 0 and counted, never returned as negative albedo."""
    E = 1.0
    meas, kappa, mu, _ = _uniform_front(0.001, E)
    r = diffuse_reflectance(meas, kappa, 0.2 * mu, 0, E)   # less absorption: brighter prediction
    assert r.clipped > 0.5 and np.all(r.rho >= 0)


def test_bad_input():
    meas, kappa, mu, _ = _uniform_front(0.01, 1.0)
    with pytest.raises(InputError, match="irradiance"):
        diffuse_reflectance(meas, kappa, mu, 0, -1.0)
    with pytest.raises(InputError, match="condition"):
        diffuse_reflectance(meas, kappa, mu, 3, 1.0)
    back = Measurements(meas.shape, meas.h, "z-", "z+", meas.incoming, meas.radiance, eta=meas.eta)
    with pytest.raises(InputError, match="front-lit"):
        diffuse_reflectance(back, kappa, mu, 0, 1.0)


def test_command_writes_the_map_the_renderer_reads(tmp_path, capsys):
    from glsldiff.core import io
    from glsldiff.commands.cli import main
    from glsldiff.inverse.measurements import save_measurements

    E = np.array([2.0, 1.5, 1.0])
    rho_true = np.linspace(0.01, 0.05, 8 * 10 * 3).reshape(8, 10, 3)
    meas, kappa, mu, _ = _uniform_front(rho_true, E)
    save_measurements(tmp_path / "m.npz", meas)
    np.savez(tmp_path / "mat.npz", kappa=kappa, mu=mu, stencil="conservative")
    out = tmp_path / "rho.exr"
    assert main(["reflectance", str(tmp_path / "m.npz"), str(tmp_path / "mat.npz"), "--irradiance", "2", "1.5",
                 "1", "-o", str(out)]) == 0
    np.testing.assert_allclose(io.read_exr(out), rho_true, rtol=1e-5)
    assert "rho_d" in capsys.readouterr().out
    assert main(["reflectance", str(tmp_path / "m.npz"), str(tmp_path / "mat.npz"), "-o",
                 str(tmp_path / "r.png")]) != 0
    assert "must be an .exr" in capsys.readouterr().err and not (tmp_path / "r.png").exists()
