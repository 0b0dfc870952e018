"""Tests for glsldiff.physics.material (coefficients, presets, validation) and the synthetic
volumes of glsldiff.physics.procedural."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.physics import material
from glsldiff.core.errors import InputError
from glsldiff.physics.material import (
    PRESETS, Preset, coefficients, optical_properties, preset, validate_coefficients,
)
from glsldiff.physics.procedural import marble_volume, random_volume

# Jensen et al. 2001 measured parameters as transcribed in mertens.md 6.2: sigma_s' RGB, sigma_a RGB [mm^-1]
JENSEN_TABLE = {
    "apple": ([2.29, 2.39, 1.97], [0.0030, 0.0034, 0.046]),
    "chicken1": ([0.15, 0.21, 0.38], [0.015, 0.077, 0.19]),
    "chicken2": ([0.19, 0.25, 0.32], [0.018, 0.088, 0.20]),
    "cream": ([7.38, 5.47, 3.15], [0.0002, 0.0028, 0.0163]),
    "ketchup": ([0.18, 0.07, 0.03], [0.061, 0.97, 1.45]),
    "marble": ([2.19, 2.62, 3.00], [0.0021, 0.0041, 0.0071]),
    "potato": ([0.68, 0.70, 0.55], [0.0024, 0.0090, 0.12]),
    "skimmilk": ([0.70, 1.22, 1.90], [0.0014, 0.0025, 0.0142]),
    "skin1": ([0.74, 0.88, 1.01], [0.032, 0.17, 0.48]),
    "skin2": ([1.09, 1.59, 1.79], [0.013, 0.070, 0.145]),
    "spectralon": ([11.6, 20.4, 14.9], [0.00, 0.00, 0.00]),
    "wholemilk": ([2.55, 3.21, 3.77], [0.0011, 0.0024, 0.014]),
}


# ---------------------------------------------------------------- coefficients


def test_coefficients_definition():
    """kappa = 1/(3 (sigma_a + sigma_s')) [mm], mu = sigma_a (wang2008.md section 1)."""
    kappa, mu = coefficients(0.0021, 2.19)
    assert kappa == pytest.approx(0.15206, abs=5e-6)  # D of mertens.md 6.1
    assert mu == 0.0021
    assert np.ndim(kappa) == 0
    kappa, mu = coefficients(np.array([0.1, 0.2, 0.3]), 1.0)
    np.testing.assert_allclose(kappa, 1 / (3 * np.array([1.1, 1.2, 1.3])), rtol=1e-15)
    assert kappa.shape == mu.shape == (3,)


def test_coefficients_round_trip():
    """optical_properties inverts coefficients (random RGB volume, seed 7) to 1e-12 relative."""
    rng = np.random.default_rng(7)
    sa, ss = rng.uniform(0, 2, (4, 5, 3)), rng.uniform(0, 20, (4, 5, 3))
    sa[0, 0, 0] = 0.0
    ss[1, 1, 1] = 0.0  # pure absorber: 3 kappa mu = 1 exactly, must still be accepted
    sa2, ss2 = optical_properties(*coefficients(sa, ss))
    np.testing.assert_allclose(sa2, sa, rtol=1e-12, atol=0)
    np.testing.assert_allclose(ss2, ss, rtol=1e-12, atol=1e-12)
    assert (ss2 >= 0).all()


@pytest.mark.parametrize("sa, ss, field", [(np.nan, 1.0, "sigma_a"), (0.1, np.inf, "sigma_s_prime"),
                                           (-0.1, 1.0, "sigma_a"), (0.1, [1.0, -1.0, 1.0], "sigma_s_prime"),
                                           (0.0, 0.0, "sigma_a \\+ sigma_s_prime")])
def test_coefficients_bad_input(sa, ss, field):
    """NaN/inf, negative coefficients and sigma_t' = 0 raise InputError naming the field."""
    with pytest.raises(InputError, match=field):
        coefficients(sa, ss)


@pytest.mark.parametrize("kappa, mu, field", [(0.0, 0.1, "kappa"), (-1.0, 0.1, "kappa"),
                                              (np.nan, 0.1, "kappa"), (0.1, -0.1, "mu"),
                                              (1.0, 1.0, "not physical")])
def test_optical_properties_bad_input(kappa, mu, field):
    """kappa <= 0, mu < 0, NaN and 3 kappa mu > 1 (sigma_s' < 0) raise InputError."""
    with pytest.raises(InputError, match=field):
        optical_properties(kappa, mu)


# ---------------------------------------------------------------- presets


def test_presets_match_jensen_table():
    """PRESETS holds the Jensen et al. 2001 table of mertens.md 6.2 exactly, eta = 1.3 (Wang 2008)."""
    assert set(PRESETS) == set(JENSEN_TABLE)
    for name, (ss, sa) in JENSEN_TABLE.items():
        p = PRESETS[name]
        assert p.name == name and p.eta == 1.3
        np.testing.assert_array_equal(p.sigma_s_prime, ss)
        np.testing.assert_array_equal(p.sigma_a, sa)
        assert p.sigma_a.dtype == np.float64 and p.sigma_a.shape == (3,)


def test_preset_coefficients_and_immutability():
    """Preset.coefficients() gives kappa, mu of shape (3,); the arrays are read-only."""
    p = preset("marble")
    kappa, mu = p.coefficients()
    np.testing.assert_allclose(kappa, 1 / (3 * (np.array([2.19, 2.62, 3.00]) + [0.0021, 0.0041, 0.0071])))
    np.testing.assert_array_equal(mu, p.sigma_a)
    with pytest.raises(ValueError):
        p.sigma_a[0] = 1.0
    with pytest.raises(AttributeError):
        p.eta = 1.5  # type: ignore[misc]


def test_preset_lookup_and_aliases():
    """Names are case-insensitive; skim_milk, whole_milk and skin (-> skin1) are aliases."""
    assert preset("Marble") is PRESETS["marble"]
    assert preset("skim_milk") is PRESETS["skimmilk"]
    assert preset("whole_milk") is PRESETS["wholemilk"]
    assert preset("Skin") is PRESETS["skin1"]
    assert preset(PRESETS["apple"]) is PRESETS["apple"]


def test_preset_unknown_name():
    """An unknown preset raises InputError listing the valid names."""
    with pytest.raises(InputError, match="valid names: apple, chicken1.*wholemilk"):
        preset("jade")


def test_preset_validation():
    """A custom Preset with a wrong shape, negative values or eta <= 0 raises InputError."""
    Preset("ok", [1.0, 1.0, 1.0], [0.1, 0.1, 0.1], 1.4)
    for ss, sa, eta in [([1.0, 1.0], [0.1, 0.1], 1.3), ([1.0, 1.0, 1.0], [-0.1, 0.1, 0.1], 1.3),
                        ([1.0, 1.0, 1.0], [0.1, 0.1, 0.1], 0.0), ([1.0, np.nan, 1.0], [0.1] * 3, 1.3)]:
        with pytest.raises(InputError):
            Preset("bad", ss, sa, eta)


# ---------------------------------------------------------------- validate_coefficients


def test_validate_coefficients_shapes():
    """Accepts scalar, RGB constant, S, S+(1,) and S+(3,) inputs and returns float64 S+(3,) copies."""
    S = (2, 4, 5)
    k3 = np.full(S + (3,), 0.5)
    cases = [(k3, 0.1), (np.full(S, 0.5), np.ones(S + (3,))), (0.5, np.zeros(S + (1,))),
             (np.full(S + (1,), 0.5), np.array([0.1, 0.2, 0.3])), (np.ones(S, dtype=np.float32), np.zeros(S))]
    for kappa, mu in cases:
        k, m = validate_coefficients(kappa, mu)
        assert k.shape == m.shape == S + (3,)
        assert k.dtype == m.dtype == np.float64
        assert k.flags.writeable and m.flags.writeable
    k, _ = validate_coefficients(k3, 0.1)
    k[0, 0, 0, 0] = 9.0
    assert k3[0, 0, 0, 0] == 0.5  # a copy, not a view
    k, m = validate_coefficients(np.ones(3), np.zeros(3))  # one homogeneous RGB material
    assert k.shape == (3,)


def test_validate_coefficients_explicit_shape():
    """With shape given, a grey volume whose last axis has size 3 is not mistaken for RGB."""
    k, m = validate_coefficients(np.ones((4, 3)), 0.0, shape=(4, 3))
    assert k.shape == (4, 3, 3)
    k, m = validate_coefficients(np.ones((4, 3)), 0.0)
    assert k.shape == (4, 3)
    with pytest.raises(InputError, match="shape"):
        validate_coefficients(np.ones((4, 5)), 0.0, shape=(4, 6))


def test_validate_coefficients_errors():
    """NaN (with count and index), kappa <= 0, mu < 0 and shape mismatch raise InputError."""
    kappa = np.ones((2, 3, 4, 3))
    kappa[1, 2, 0, :] = np.nan
    with pytest.raises(InputError, match=r"kappa has 3 NaN value\(s\) at e.g. index \(1, 2, 0, 0\)"):
        validate_coefficients(kappa, 0.0)
    with pytest.raises(InputError, match="mu has .*inf"):
        validate_coefficients(1.0, np.array([0.0, np.inf, 0.0]))
    with pytest.raises(InputError, match="kappa must be > 0"):
        validate_coefficients(np.array([1.0, 0.0, 1.0]), 0.0)
    with pytest.raises(InputError, match="mu must be >= 0"):
        validate_coefficients(1.0, np.array([0.0, -1e-3, 0.0]))
    with pytest.raises(InputError, match=r"mu has shape \(4, 6\)"):
        validate_coefficients(np.ones((4, 5)), np.ones((4, 6)))
    with pytest.raises(InputError, match="shape"):
        validate_coefficients(np.ones((4, 5, 3)), np.ones((4, 5, 2)))
    with pytest.raises(InputError):
        validate_coefficients("a lot", 0.0)


# ---------------------------------------------------------------- synthetic volumes


def test_marble_volume_deterministic_and_bounded():
    """marble_volume: same seed -> identical arrays; values within [min, max] of the two materials."""
    shape = (6, 24, 32)
    kappa, mu = marble_volume(shape, seed=3)
    kappa2, mu2 = marble_volume(shape, seed=3)
    np.testing.assert_array_equal(kappa, kappa2)
    np.testing.assert_array_equal(mu, mu2)
    assert kappa.shape == mu.shape == shape + (3,)
    assert not np.array_equal(mu, marble_volume(shape, seed=4)[1])
    base = PRESETS["marble"]
    vein = Preset("vein", base.sigma_s_prime * 0.5, base.sigma_a * 20.0, 1.3)  # the documented default
    (k0, m0), (k1, m1) = base.coefficients(), vein.coefficients()
    lo_k, hi_k = np.minimum(k0, k1), np.maximum(k0, k1)
    assert (kappa >= lo_k * (1 - 1e-12)).all() and (kappa <= hi_k * (1 + 1e-12)).all()
    assert (mu >= m0 * (1 - 1e-12)).all() and (mu <= m1 * (1 + 1e-12)).all()
    t = (mu - m0) / (m1 - m0)  # vein weight, the same in every channel
    np.testing.assert_allclose(t, t[..., :1].repeat(3, -1), atol=1e-12)
    assert t.max() > 0.95 and np.median(t) < 0.1  # thin veins in a base-material matrix
    validate_coefficients(kappa, mu)
    optical_properties(kappa, mu)  # every node is a physical material


def test_marble_volume_custom_materials():
    """Named base/vein presets are blended; a 2-D shape works; bad arguments raise InputError."""
    kappa, mu = marble_volume((16, 16), seed=0, base="skimmilk", vein="ketchup")
    assert kappa.shape == (16, 16, 3)
    lo = np.minimum(PRESETS["skimmilk"].sigma_a, PRESETS["ketchup"].sigma_a)
    hi = np.maximum(PRESETS["skimmilk"].sigma_a, PRESETS["ketchup"].sigma_a)
    assert (mu >= lo - 1e-15).all() and (mu <= hi + 1e-15).all()
    for kwargs in [dict(shape=(0, 4, 4)), dict(shape=(2, 2, 2, 2)), dict(shape=(4, 4), base="jade"),
                   dict(shape=(4, 4), vein_absorption=-1.0)]:
        with pytest.raises(InputError):
            marble_volume(**kwargs)


def test_random_volume_bounds():
    """random_volume: kappa log-uniform in [k0, k0 * contrast], mu in [0, mu_max], reproducible."""
    kappa, mu = random_volume((8, 10, 12), np.random.default_rng(11), kappa_contrast=100.0, mu_max=10.0)
    assert kappa.shape == mu.shape == (8, 10, 12, 3)
    assert kappa.min() >= 0.01 and kappa.max() <= 1.0
    assert kappa.max() / kappa.min() > 90.0  # nearly the full contrast is used
    assert abs(np.median(np.log10(kappa)) - (-1.0)) < 0.05  # log-uniform: median at the log midpoint
    assert mu.min() >= 0.0 and mu.max() <= 10.0 and mu.max() > 9.9
    k2, m2 = random_volume((8, 10, 12), 11)
    np.testing.assert_array_equal(kappa, k2)
    np.testing.assert_array_equal(mu, m2)
    k, m = random_volume(5, 0, kappa_contrast=1.0, mu_max=0.0, kappa_min=0.2)
    np.testing.assert_allclose(k, 0.2)
    np.testing.assert_array_equal(m, 0.0)
    validate_coefficients(k, m)
    for kwargs in [dict(kappa_contrast=0.5), dict(mu_max=-1.0), dict(kappa_min=0.0)]:
        with pytest.raises(InputError):
            random_volume((2, 2), 0, **kwargs)


def test_public_api_listed():
    """Every name in material.__all__ exists."""
    assert all(hasattr(material, n) for n in material.__all__)


def test_sphere_weight_is_one_centred_ball_of_the_smallest_extent():
    """validate's absorbing inclusion: a ball at the box centre, radius 0.3 of the smallest
    extent, soft over 10 % of it; point_weight("sphere") is the same."""
    from glsldiff.physics.procedural import point_weight, sphere_weight

    x = np.linspace(-20.0, 20.0, 81)
    p = np.stack(np.meshgrid(x, x, np.linspace(-2.5, 2.5, 11), indexing="ij"), -1).reshape(-1, 3)
    w = sphere_weight(p)
    d = np.linalg.norm(p, axis=1)
    assert np.all(w[d < 1.5 * 0.95] == 1.0) and np.all(w[d > 1.5 * 1.05] == 0.0)
    assert np.any((w > 0) & (w < 1))                       # the soft rim
    np.testing.assert_array_equal(point_weight("sphere", p, seed=7), w)
