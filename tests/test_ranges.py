"""How tightly the data pin the homogeneous material (glsldiff.inverse.ranges): the
Gauss-Newton profile ranges against explicitly re-fitted profiles, and their report."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import optimize

from glsldiff.core.errors import InputError
from glsldiff.grids.regular import RegularGrid
from glsldiff.inverse.fit import fit_homogeneous
from glsldiff.inverse.model import ForwardModel
from glsldiff.inverse.objective import Objective
from glsldiff.inverse.ranges import CoefficientRanges, profile_ranges


def _objective(setup: str, noise: float = 0.03) -> Objective:
    """Back- or front-lit quadrants of a 3 mm homogeneous block (sigma_a 0.02, sigma_s' 1.5 /mm)
    rendered by the model, with seeded multiplicative noise so the data term has a floor."""
    grid = RegularGrid(10, 10, 7, h=0.5)
    model = ForwardModel(grid, eta=1.0)
    fs = grid.face_shape("z-")
    Q = np.zeros((model.n_boundary, 4))
    for m, (sy, sx) in enumerate([(slice(0, 4), slice(0, 4)), (slice(0, 4), slice(4, 8)),
                                  (slice(4, 8), slice(0, 4)), (slice(4, 8), slice(4, 8))]):
        pat = np.zeros(fs + (1,))
        pat[sy, sx] = 1.0
        Q[:, m] = grid.face_to_boundary("z-", pat)[:, 0]
    observed = "z+" if setup == "back" else "z-"
    W = np.repeat(grid.face_to_boundary(observed, np.ones(grid.face_shape(observed) + (1,))), 4, axis=1)
    W = (W > 0).astype(float)
    sa, ss = 0.02, 1.5
    fac = model.factorize(np.full(model.n, 1.0 / (3.0 * (sa + ss))), np.full(model.n, sa))
    L = fac.radiance(fac.solve(Q), Q)
    Y = L * (1.0 + noise * np.random.default_rng(3).standard_normal(L.shape))
    return Objective(model, Q, np.maximum(Y, 0.0) * W, W)


def _profile(obj: Objective, sa: float | None = None, ss: float | None = None) -> float:
    """The data term with one coefficient fixed and the other re-fitted (bounded 1-D search)."""
    n = obj.model.n

    def data(sa_: float, ss_: float) -> float:
        return obj.evaluate(np.full(n, 1.0 / (3.0 * (sa_ + ss_))), np.full(n, sa_), gradient=False).data

    if sa is not None:
        r = optimize.minimize_scalar(lambda t: data(sa, math.exp(t)), bounds=(math.log(0.3), math.log(8.0)),
                                     method="bounded", options={"xatol": 1e-5})
    else:
        r = optimize.minimize_scalar(lambda t: data(math.exp(t), ss), bounds=(math.log(1e-4), math.log(0.3)),
                                     method="bounded", options={"xatol": 1e-5})
    return float(r.fun)


@pytest.mark.parametrize("setup", ["back", "front"])
def test_ranges_match_the_refitted_profile(setup: str) -> None:
    """At each end of each range the explicitly re-fitted profile has risen by the tolerance
    (within 25 %): the quadratic model of the data term is right where it is used."""
    obj = _objective(setup)
    k, m, _, r = fit_homogeneous(obj, 0.3, 0.01, 60)
    assert r.sigma_a == pytest.approx(m) and r.sigma_s == pytest.approx(1.0 / (3.0 * k) - m)
    f0 = r.data
    assert f0 > 1e-5                      # the noise gives the data term a floor
    assert obj.evaluate(np.full(obj.model.n, k), np.full(obj.model.n, m), gradient=False).data == \
        pytest.approx(f0, rel=1e-6)
    rise = r.tolerance * f0
    for end in (r.sigma_a_range[1], r.sigma_a_range[0]):
        if end > 0:
            assert (_profile(obj, sa=end) - f0) / rise == pytest.approx(1.0, abs=0.25)
    for end in r.sigma_s_range:
        assert (_profile(obj, ss=end) - f0) / rise == pytest.approx(1.0, abs=0.25)


def test_reflection_pins_absorption_better_than_transmission() -> None:
    """The same block seen in reflection constrains sigma_a relative to sigma_s' more
    tightly than seen in transmission (the trade-off a back-lit capture cannot resolve)."""
    rel = {}
    for setup in ("back", "front"):
        _, _, _, r = fit_homogeneous(_objective(setup), 0.3, 0.01, 60)
        rel[setup] = (r.sigma_a_range[1] - r.sigma_a_range[0]) / r.sigma_a / math.sqrt(r.data)
    assert rel["front"] < rel["back"]


def test_describe_names_the_undetermined_coefficient() -> None:
    loose = CoefficientRanges(0.004, (0.0, 0.023), 2.19, (1.64, 2.74), 0.01, 0.11)
    assert loose.determined == (False, True)
    line = loose.describe()
    assert "do not determine sigma_a" in line and "0 .. 0.023" in line and "\n" not in line
    tight = CoefficientRanges(0.02, (0.019, 0.021), 1.5, (1.49, 1.51), 0.01, 1e-4)
    assert tight.determined == (True, True) and "do not determine" not in tight.describe()
    flat = profile_ranges(np.array([[1.0, 0.0], [2.0, 0.0]]), 0.2, 0.01, 0.1)   # mu has no effect
    assert math.isinf(flat.sigma_a_range[1]) and "inf" in flat.describe()


def test_an_unphysical_homogeneous_fit_has_no_ranges() -> None:
    """The homogeneous fit runs in (log kappa, log mu) and can end where 3 kappa mu > 1 (the
    high-absorption stiff case ends at kappa 0.77 mm, mu 4.67 /mm): no ranges, said so."""
    r = profile_ranges(np.array([[1.0, 0.5], [0.2, 2.0]]), 0.7727, 4.665, 0.1)
    assert r.sigma_s < 0 and not r.physical and r.determined == (False, False)
    assert all(math.isnan(x) for x in (*r.sigma_a_range, *r.sigma_s_range))
    line = r.describe()
    assert "not a physical material" in line and "no ranges" in line and "\n" not in line
    assert profile_ranges(np.array([[1.0, 0.5], [0.2, 2.0]]), 0.2, 0.01, 0.1).physical


@pytest.mark.parametrize("jac,kappa,mu,tol", [(np.ones((4, 3)), 0.2, 0.01, 0.01),
                                              (np.full((4, 2), np.nan), 0.2, 0.01, 0.01),
                                              (np.ones((4, 2)), 0.0, 0.01, 0.01),
                                              (np.ones((4, 2)), 0.2, 0.01, 0.0)])
def test_bad_input_is_one_clear_error(jac, kappa, mu, tol) -> None:
    with pytest.raises(InputError):
        profile_ranges(jac, kappa, mu, 0.1, tol)
