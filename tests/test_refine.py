"""Transport refinement by defect correction (glsldiff.validation.refine)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.inverse.fit import FitOptions, fit_measurements
from glsldiff.inverse.synthetic import bssrdf_error, synthetic_measurements
from glsldiff.physics.procedural import synthetic_volume
from glsldiff.validation.refine import diffusion_captures, mitsuba_transport, transport_refine


@pytest.fixture(scope="module")
def biased():
    """Captures of a 'transport' that is the diffusion model at 0.8x its power (a model
    defect independent of the material), their plain diffusion fit, and the truth."""
    k, m = synthetic_volume((6, 14, 14), "mixed", seed=3)
    k, m = np.repeat(k[..., 1:2], 3, -1), np.repeat(m[..., 1:2], 3, -1)
    clean = synthetic_measurements(k, m, 0.5, 3, "both", noise=0.0, read_noise=0.0)
    options = FitOptions(max_evals=80)

    def transport(kappa, mu, _round):
        rad, ref = diffusion_captures(clean, kappa, mu, options)
        return dataclasses.replace(clean, radiance=0.8 * rad, reflected=0.8 * ref)

    meas = transport(k, m, 0)
    return k, m, meas, options, transport, fit_measurements(meas, options)


def test_diffusion_captures_are_the_synthetic_ones(biased) -> None:
    k, m, _, options, _, _ = biased
    clean = synthetic_measurements(k, m, 0.5, 3, "both", noise=0.0, read_noise=0.0)
    rad, ref = diffusion_captures(clean, k, m, options)
    np.testing.assert_allclose(rad, clean.radiance, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(np.where(clean.reflected_mask, ref, 0.0), clean.reflected, rtol=1e-10, atol=1e-14)


def test_defect_correction_removes_a_model_defect(biased) -> None:
    """A fit of 0.8x-power captures is off (the model's defect goes into the material); two
    rounds of defect correction bring the material back to the truth (the defect shrinks
    0.2x per round here), and the Monte Carlo-side misfit falls round by round."""
    k, m, meas, options, transport, plain = biased
    E0 = bssrdf_error(meas.grid, (k, m), (plain.kappa, plain.mu), channels=(1,))
    rounds = transport_refine(meas, options, plain, 2, transport)
    E = [bssrdf_error(meas.grid, (k, m), (r.result.kappa, r.result.mu), channels=(1,)) for r in rounds]
    assert E0 > 0.01, E0                              # the defect spoils the plain fit
    assert E[1] < 0.05 * E0 and E[1] < 1e-3, (E0, E)
    assert rounds[1].transport_misfit < 0.2 * rounds[0].transport_misfit
    assert rounds[0].defect == pytest.approx(0.2, rel=0.15)   # T - D = -0.2 D(m_0) ~ -0.2 Y


def test_mitsuba_transport_refuses_other_rigs(biased) -> None:
    _, _, meas, *_ = biased
    with pytest.raises(InputError, match="index-matched rig"):
        mitsuba_transport(meas, 16)                   # eta 1.3: not the Mitsuba rig
    with pytest.raises(InputError, match="n x n lit regions"):
        mitsuba_transport(dataclasses.replace(meas, eta=1.0, incoming=meas.incoming[:5], radiance=meas.radiance[:5],
                                              mask=None, reflected=meas.reflected[:5], reflected_mask=None), 16)
