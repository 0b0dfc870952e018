"""glsldiff.physics.lights and glsldiff.physics.sh: light types, their falloff, spherical harmonics.

Pure numpy (no GL); pass 1 with shadow maps is tested in test_pass1.py.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.physics.lights import (KINDS, DirectionalLight, EnvironmentLight, PointLight, ProjectorLight,
                                     SpotLight, check_light, incidence, light_kind, projector_factor,
                                     spot_factor, to_light)
from glsldiff.physics.sh import latlong_directions, sh_basis, sh_project, transfer_coefficients


# ---- bad input -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("make, field", [
    (lambda: DirectionalLight((0, 0, 0), 1.0), "direction"),
    (lambda: DirectionalLight((0, 0, 1), (1.0, -1.0, 1.0)), "irradiance"),
    (lambda: DirectionalLight((0, 0, 1), (1.0, np.nan, 1.0)), "irradiance"),
    (lambda: DirectionalLight((0, 1), 1.0), "direction"),
    (lambda: PointLight((0, 0, np.inf), 1.0), "position"),
    (lambda: PointLight((0, 0, 1), (1.0, np.inf, 0.0)), "intensity"),
    (lambda: PointLight((0, 0, 1), -2.0), "intensity"),
    (lambda: SpotLight((0, 0, 1), (0, 0, 0), 1.0), "direction"),
    (lambda: SpotLight((0, 0, 1), (0, 0, -1), 1.0, cone_deg=0.0, falloff_deg=0.0), "cone_deg"),
    (lambda: SpotLight((0, 0, 1), (0, 0, -1), 1.0, cone_deg=180.0), "cone_deg"),
    (lambda: SpotLight((0, 0, 1), (0, 0, -1), 1.0, cone_deg=20.0, falloff_deg=30.0), "falloff_deg"),
    (lambda: SpotLight((0, 0, 1), (0, 0, -1), 1.0, cone_deg=20.0, falloff_deg=-1.0), "falloff_deg"),
    (lambda: EnvironmentLight(np.ones((4, 8))), "image"),
    (lambda: EnvironmentLight(np.full((4, 8, 3), np.nan)), "image"),
    (lambda: EnvironmentLight(-np.ones((4, 8, 3))), "image"),
    (lambda: EnvironmentLight(np.ones((4, 8, 3)), scale=-1.0), "scale"),
    (lambda: EnvironmentLight(np.ones((4, 8, 3)), order=9), "order"),
    (lambda: EnvironmentLight(np.ones((4, 8, 3)), directions=0), "directions"),
    (lambda: sh_project(np.ones((4, 8, 4))), "image"),
    (lambda: ProjectorLight((0, 0, 1), (0, 0, -1), np.ones((2, 2, 3)), 1.0, fov_deg=0.0), "fov_deg"),
    (lambda: ProjectorLight((0, 0, 1), (0, 0, -1), np.ones((2, 2, 3)), 1.0, fov_deg=180.0), "fov_deg"),
    (lambda: ProjectorLight((0, 0, 1), (0, 0, -1), np.ones((2, 2, 3)), 1.0, up=(0, 0, 2)), "parallel"),
    (lambda: ProjectorLight((0, 0, 1), (0, 1, 0), np.ones((2, 2, 3)), 1.0), "parallel"),  # default up
    (lambda: ProjectorLight((0, 0, 1), (0, 0, -1), np.ones((2, 2, 3)), 1.0, up=(0, 0, 0)), "up"),
    (lambda: ProjectorLight((0, 0, 1), (0, 0, -1), -np.ones((2, 2, 3)), 1.0), "image.*negative"),
    (lambda: ProjectorLight((0, 0, 1), (0, 0, -1), np.ones((2, 2)), 1.0), "image.*shape"),
    (lambda: ProjectorLight((0, 0, 1), (0, 0, -1), np.ones((2, 2, 4)), 1.0), "image.*shape"),
    (lambda: ProjectorLight((0, 0, 1), (0, 0, -1), np.full((2, 2, 3), np.inf), 1.0), "image"),
    (lambda: ProjectorLight((0, 0, 1), (0, 0, -1), np.ones((2, 2, 3)), -1.0), "intensity"),
    (lambda: projector_factor(SpotLight((0, 0, 1), (0, 0, -1), 1.0), np.zeros((1, 3))), "ProjectorLight"),
])
def test_bad_light_parameters(make, field):
    with pytest.raises(InputError, match=field) as exc:
        make()
    assert "\n" not in str(exc.value)


def test_sh_projection_is_orthonormal():
    d, omega = latlong_directions(64, 128)
    np.testing.assert_allclose(omega.sum(), 4.0 * math.pi, rtol=1e-12)
    Y = sh_basis(d.reshape(-1, 3), 2)
    gram = (Y * omega.reshape(-1, 1)).T @ Y
    np.testing.assert_allclose(gram, np.eye(9), atol=2e-3)
    # Y_1,-1, Y_10, Y_11 = sqrt(3 / 4 pi) (y, z, x)
    u = np.array([[0.6, 0.0, 0.8]])
    np.testing.assert_allclose(sh_basis(u, 1)[0], [1 / math.sqrt(4 * math.pi)] +
                               list(math.sqrt(3 / (4 * math.pi)) * np.array([0.0, 0.8, 0.6])), rtol=1e-12)
    np.testing.assert_allclose(transfer_coefficients(2), [math.pi, 2 * math.pi / 3, math.pi / 4], rtol=1e-10)


def test_incidence_is_the_normal_irradiance_of_each_kind():
    """Directional: E0; point: I / r^2; spot: I / r^2 times the cone factor; projector: I / r^2
    times its image factor (scale 0 where the image is black); a weight multiplies scale."""
    p = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 0.0, 10.0]])
    sun = DirectionalLight((0.0, 0.0, 2.0), (1.0, 2.0, 3.0))
    scale, colour = incidence(sun, p)
    np.testing.assert_array_equal(scale, 1.0)
    np.testing.assert_array_equal(colour, [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(to_light(sun, p), np.tile([0.0, 0.0, 1.0], (3, 1)))
    bulb = PointLight((0.0, 0.0, 10.0), 100.0)
    scale, colour = incidence(bulb, p, weight=[1.0, 2.0, 5.0])
    np.testing.assert_allclose(scale, [1.0 / 100.0, 2.0 / 109.0, 0.0])    # 0 at the light itself
    np.testing.assert_allclose(to_light(bulb, p)[1], np.array([-3.0, 0.0, 10.0]) / math.sqrt(109.0))
    assert np.all(to_light(bulb, p)[2] == 0.0)
    spot = SpotLight((0.0, 0.0, 10.0), (0.0, 0.0, -1.0), 100.0, cone_deg=20.0, falloff_deg=10.0)
    scale, _ = incidence(spot, p[:2])
    cos_axis = 10.0 / math.sqrt(109.0)
    np.testing.assert_allclose(scale, [1.0 / 100.0, spot_factor(spot, cos_axis) / 109.0])
    assert 0.0 < spot_factor(spot, cos_axis) < 1.0
    img = np.zeros((2, 2, 3))
    img[:, 0] = 1.0                                         # the projector's left half is white
    proj = ProjectorLight((0.0, 0.0, 10.0), (0.0, 0.0, -1.0), img, 100.0, fov_deg=60.0)
    q = np.array([[-5.0, 0.0, 0.0], [5.0, 0.0, 0.0]])        # beyond the bilinear ramp
    scale, colour = incidence(proj, q)
    np.testing.assert_allclose(colour, 100.0 * projector_factor(proj, q))
    assert scale[0] > 0.0 and scale[1] == 0.0
    with pytest.raises(InputError, match="environment"):
        incidence(EnvironmentLight(np.ones((2, 4, 3))), p)


def test_kinds_and_image_digests():
    """Every kind has one name; lights with an image name their pixels in their repr (render
    stages key on it), not the array."""
    assert list(KINDS) == ["directional", "point", "spot", "projector", "area", "environment"]
    assert light_kind(PointLight((0, 0, 0), 1.0)) == "point"
    with pytest.raises(InputError, match="light must be a DirectionalLight"):
        check_light("sun")
    a = EnvironmentLight(np.ones((4, 8, 3)))
    b = EnvironmentLight(np.ones((4, 8, 3)))
    c = EnvironmentLight(np.r_[np.ones((3, 8, 3)), np.full((1, 8, 3), 2.0)])
    assert repr(a) == repr(b) != repr(c) and "array" not in repr(a) and a.digest in repr(a)
    assert EnvironmentLight(np.ones((8, 4, 3))).digest != a.digest      # same pixels, other shape
    proj = ProjectorLight((0, 0, 1), (0, 0, -1), np.ones((2, 2, 3)), 1.0)
    assert "array" not in repr(proj) and proj.digest
