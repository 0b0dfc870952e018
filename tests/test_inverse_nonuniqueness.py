"""What region-lit captures cannot determine: two materials with the same
``eta = mu / kappa + lap(sqrt kappa) / sqrt kappa`` and the same kappa near the faces give the
same steady-state (CW) captures (Arridge and Lionheart, "Nonuniqueness in diffusion-based
optical tomography", Opt. Lett. 23(11), 1998): absorption and scattering trade against each
other inside the sample. So no fit of such captures can promise sigma_a per node; the guide
(docs/guide/inverse.md, "What the captures determine") reports what the fit recovers instead."""
from __future__ import annotations

import numpy as np

from glsldiff.inverse.synthetic import synthetic_measurements
from glsldiff.physics.procedural import synthetic_volume


def _laplacian(a: np.ndarray, h: float) -> np.ndarray:
    """7-point Laplacian over the node axes (0, 1, 2), edge values repeated (mm^-2 x a)."""
    p = np.pad(a, [(1, 1)] * 3 + [(0, 0)], mode="edge")
    c = p[1:-1, 1:-1, 1:-1]
    return (p[2:, 1:-1, 1:-1] + p[:-2, 1:-1, 1:-1] + p[1:-1, 2:, 1:-1] + p[1:-1, :-2, 1:-1]
            + p[1:-1, 1:-1, 2:] + p[1:-1, 1:-1, :-2] - 6.0 * c) / h ** 2


def _window(t: np.ndarray, lo: float, hi: float) -> np.ndarray:
    s = np.clip((t - lo) / (hi - lo), 0.0, 1.0)
    return np.sin(np.pi * s) ** 2


def test_an_interior_trade_of_absorption_for_scattering_leaves_the_captures_unchanged():
    nz, ny, nx, h = 10, 20, 20, 1.0
    kappa, mu = synthetic_volume((nz, ny, nx), "bands", seed=0)
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    # kappa scaled by up to 7 % by a smooth bump, zero within two nodes of every face
    bump = _window(z, 1.5, nz - 2.5) * _window(y, 1.5, ny - 2.5) * _window(x, 1.5, nx - 2.5)
    kappa2 = kappa * np.exp(0.07 * bump)[..., None]
    eta = mu / kappa + _laplacian(np.sqrt(kappa), h) / np.sqrt(kappa)
    mu2 = kappa2 * (eta - _laplacian(np.sqrt(kappa2), h) / np.sqrt(kappa2))
    assert mu2.min() > 0.0                                     # a physical material
    sa_change = np.abs(mu2 / mu - 1.0).max(axis=(0, 1, 2))
    ss_change = np.abs((1 / (3 * kappa2) - mu2) / (1 / (3 * kappa) - mu) - 1.0).max(axis=(0, 1, 2))
    assert sa_change.min() > 0.25 and ss_change.max() < 0.12, (sa_change, ss_change)
    a = synthetic_measurements(kappa, mu, h, 4, "both", noise=0.0)
    b = synthetic_measurements(kappa2, mu2, h, 4, "both", noise=0.0)
    for c in range(3):
        diff = sum(((getattr(b, f)[..., c] - getattr(a, f)[..., c]) ** 2).sum() for f in ("radiance", "reflected"))
        power = sum((getattr(a, f)[..., c] ** 2).sum() for f in ("radiance", "reflected"))
        # far below the fit's stop (1e-4 of the measured power) and 1 % noise (~1e-4)
        assert diff / power < 1e-8, (c, diff / power)


def test_the_verdict_says_why_sigma_a_per_node_is_not_recovered():
    from types import SimpleNamespace

    from glsldiff.commands.fit_output import verdict

    ch = SimpleNamespace(converged=True, ranges=None, trace=SimpleNamespace(status="converged (f < eps)"))
    result = SimpleNamespace(channels=[ch] * 3, shared=False, interrupted=False,
                             options=SimpleNamespace(max_evals=60, max_seconds=float("inf")))
    bad = [{"sigma_a_median_rel_err": 0.5, "sigma_s_median_rel_err": 0.07}] * 3
    good = [{"sigma_a_median_rel_err": 0.1, "sigma_s_median_rel_err": 0.3}] * 3
    line = verdict(result, 0.001, bad)
    assert "NOT recovered: worst median error per node 50 %" in line and "do not fix sigma_a per node" in line
    line = verdict(result, 0.001, good)
    assert "NOT recovered: worst median error per node 30 %" in line and "sigma_a per node" not in line
