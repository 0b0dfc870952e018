"""Transport refinement of a diffusion fit by defect correction (Mitsuba 3).

The diffusion model's own error (too bright next to a lit region on the lit face, 0.935x Monte
Carlo's power on the far face: docs/guide/inverse.md) is fitted into the material when the
measurements are real light transport. Defect correction takes it out: with ``D(m)`` the
diffusion model's captures of material ``m``, ``T(m)`` the same captures path traced and ``Y``
the measurements, each round

    delta_k = T(m_k) - D(m_k),        m_{k+1} = argmin_m | D(m) - (Y - delta_k) |^2,

so a fixed point has ``T(m) = Y`` wherever the defect depends little on the material (it is
mostly geometry: the lit region's edge, the block's faces). Each round costs one Monte Carlo
render of the captures (:func:`glsldiff.validation.measure.mitsuba_measurements`) and one
diffusion fit (:func:`glsldiff.inverse.fit.fit_measurements`, from the homogeneous stage,
with the fit's options). Only measurements of that module's rig can be refined so: index
matched (eta = 1), ``n x n`` lit regions of the ``z-`` face, observed on ``z+`` (and ``z-``).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.checks import integer
from glsldiff.core.errors import InputError
from glsldiff.inverse.fit import FitOptions, FitResult, fit_measurements
from glsldiff.inverse.measurements import Measurements
from glsldiff.inverse.model import ForwardModel
from glsldiff.inverse.synthetic import face_captures
from glsldiff.validation.measure import mitsuba_measurements

__all__ = ["RefineRound", "diffusion_captures", "transport_refine"]

Array = NDArray[np.float64]
#: Render of a material's captures by light transport: ``(kappa, mu, round) -> Measurements``.
Transport = Callable[[Array, Array, int], Measurements]


@dataclass
class RefineRound:
    """One defect-correction round."""

    round: int
    defect: float        # rms of T(m_k) - D(m_k) over the fitted values, relative to the rms of Y
    transport_misfit: float  # |T(m_k) - Y|^2 / |Y|^2 over the fitted values: m_k against the measurements
    data: float          # the new diffusion fit's data term (worst channel) on Y - delta_k
    seconds: float
    result: FitResult    # m_{k+1}


def diffusion_captures(meas: Measurements, kappa: Array, mu: Array, options: FitOptions
                       ) -> tuple[Array, Array | None]:
    """``D(m)``: the captures the fit's forward model predicts for the volume ``(kappa, mu)``
    (``(nz, ny, nx, 3)``) under ``meas``' lighting, as ``(radiance, reflected)`` face stacks
    shaped like ``meas.radiance`` and ``meas.reflected`` (None without a reflection)."""
    model = ForwardModel(meas.grid, options.stencil, options.face_mean, meas.eta, meas.C, options.exitant,
                         solver=options.solver)
    return face_captures(model, kappa, mu, [meas.channel(c)[0] for c in range(3)], meas.observed_face,
                         None if meas.reflected is None else meas.lit_face)


def _fitted(meas: Measurements, radiance: Array, reflected: Array | None) -> Array:
    """The values the fit uses (its masks), flattened."""
    parts = [radiance[meas.mask]]
    if reflected is not None:
        parts.append(reflected[meas.reflected_mask])
    return np.concatenate(parts)


def mitsuba_transport(meas: Measurements, spp: int, seed: int = 0,
                      progress: Callable[[int, int, float], None] | None = None) -> Transport:
    """``T``: the captures of a material path traced by Mitsuba in ``meas``' rig (checked
    against ``meas``' lighting at the first render)."""
    if abs(meas.eta - 1.0) > 1e-12 or (meas.lit_face, meas.observed_face) != ("z-", "z+"):
        raise InputError(f"transport refinement renders the index-matched rig of glsldiff.validation.measure (eta 1, "
                         f"lit z-, observed z+); these measurements have eta {meas.eta:g}, lit "
                         f"{meas.lit_face}, observed {meas.observed_face}: measure with `glsldiff synth --renderer "
                         "mitsuba` or fit without --transport-rounds")
    n = math.isqrt(meas.M)
    if n * n != meas.M:
        raise InputError(f"transport refinement needs n x n lit regions; these measurements have {meas.M} conditions")
    setup = "back" if meas.reflected is None else "both"

    def transport(kappa: Array, mu: Array, k: int) -> Measurements:
        mc, _ = mitsuba_measurements(kappa, mu, meas.h, n, spp, seed + 7919 * (k + 1), progress, setup)
        if not np.allclose(mc.incoming, meas.incoming, rtol=1e-6, atol=1e-9):
            raise InputError("transport refinement: these measurements' lighting is not the n x n region rig of "
                             "glsldiff.validation.measure (their incoming light differs from its exact irradiance)")
        return mc

    return transport


def transport_refine(meas: Measurements, options: FitOptions, fitted: FitResult, rounds: int,
                     transport: Transport, report: Callable[[RefineRound], None] | None = None
                     ) -> list[RefineRound]:
    """``rounds`` defect-correction rounds (module docstring) from the diffusion fit
    ``fitted`` of ``meas``; ``transport`` renders a material's captures (e.g.
    :func:`mitsuba_transport`). Returns the rounds; the last one's ``result`` is the refined
    material. ``report`` after each round."""
    integer(rounds, "rounds", 1, 100)
    Y = _fitted(meas, meas.radiance, meas.reflected)
    scale = float(np.sqrt(np.mean(Y**2))) or 1.0
    current, out = fitted, []
    for k in range(rounds):
        t0 = time.perf_counter()
        mc = transport(current.kappa, current.mu, k)
        radiance, reflected = diffusion_captures(meas, current.kappa, current.mu, options)
        T = _fitted(meas, mc.radiance, mc.reflected)
        defect = T - _fitted(meas, radiance, reflected)
        corrected = dataclasses.replace(
            meas, radiance=np.maximum(meas.radiance - (mc.radiance - radiance), 0.0),
            reflected=None if reflected is None else np.maximum(meas.reflected - (mc.reflected - reflected), 0.0))
        current = fit_measurements(corrected, options)
        rnd = RefineRound(k + 1, float(np.sqrt(np.mean(defect**2))) / scale, float(np.sum((T - Y) ** 2) / np.sum(Y**2)),
                          max(f.data for f in current.channels), time.perf_counter() - t0, current)
        out.append(rnd)
        if report is not None:
            report(rnd)
        if current.interrupted:
            break
    return out
