"""Measured diffuse surface reflectance of a block sample (Wang et al. 2008, section 6.1).

The paper's marble has a noticeable surface reflection. It "obtain[s] an approximate measure
of its reflectance component with the front-lighting setup and the method in [Tong et al.
2005], which records one image of the sample under uniform lighting. The diffuse surface
reflectance term is obtained by subtracting the multiple scattering contribution from it."

:func:`diffuse_reflectance` does exactly that, per node of the observed (= lit) face:

    rho_d = pi (L_uniform - L_ms) / E

with ``L_uniform`` the measured radiance of the uniformly lit face (one condition of a
front-lit :class:`~glsldiff.inverse.measurements.Measurements`), ``L_ms`` the multiple
scattering that the fitted material predicts for the same incoming light, and ``E`` the
irradiance of the uniform light in the camera's radiance units times sr (from a white
reference: ``E = pi L_white / rho_white``; by default the incoming ``q`` of that condition,
which is the Fresnel-transmitted irradiance, divided by ``F_t`` at normal incidence).

``L_ms`` is solved with the inverse fit's forward model (the same discrete system, so the
subtraction is consistent with the fit) but read out with the renderer's exitant formula
(:func:`glsldiff.physics.exitance.exitant_bracket`, default ``"p1"``), not the fit's net-flux
``F_t (phi - q) / (2 pi)``: the latter is negative on lit nodes (wang2008.md section 1),
which is why front-lit fits mask them, and on a uniformly lit face every node is lit.
Rendering ``L_ms + rho_d E / pi`` with the same formula then reproduces the uniform image.
Negative differences (noise, or a fit that over-predicts) are clipped to 0 and counted. The map is over the block's captured face,
``(ny - 2, nx - 2, 3)`` (the face layout of :mod:`glsldiff.grids.regular`); the renderer tiles it
over an object's surface like the block volume (:func:`glsldiff.render.shellmap.map_surface`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.checks import choice, integer
from glsldiff.core.errors import InputError
from glsldiff.inverse.measurements import Measurements
from glsldiff.inverse.model import ForwardModel
from glsldiff.physics.exitance import EXITANT
from glsldiff.physics.optics import fresnel_transmittance

Array = NDArray[np.float64]


@dataclass
class Reflectance:
    """``rho`` ``(a, b, 3)`` diffuse albedo map of the observed face (dimensionless), the
    predicted multiple scattering ``multiple`` and measured ``measured`` radiance on it,
    and the share of clipped (negative) values."""

    rho: Array
    multiple: Array
    measured: Array
    clipped: float

    def summary(self) -> str:
        m = self.rho.reshape(-1, 3)
        share = float(np.mean((self.measured - self.multiple) / np.maximum(self.measured, 1e-300)))
        return (f"diffuse reflectance: mean rho_d {', '.join(f'{v:.4f}' for v in m.mean(axis=0))} "
                f"(R, G, B), max {m.max():.4f}; surface share of the uniform image {100 * share:.1f} %; "
                f"{100 * self.clipped:.1f} % of values clipped at 0")


def diffuse_reflectance(meas: Measurements, kappa: ArrayLike, mu: ArrayLike, condition: int,
                        irradiance: ArrayLike | None = None, stencil: str = "conservative",
                        face_mean: str = "arithmetic", exitant: str = "p1") -> Reflectance:
    """The diffuse surface reflectance (module docstring) from condition ``condition`` of
    front-lit ``meas`` (the uniformly lit image) and the fitted material ``kappa`` (mm),
    ``mu`` (mm^-1), node volumes ``(nz, ny, nx[, 3])`` of ``meas.grid``; ``irradiance``
    (scalar or RGB) is the uniform light's irradiance (default: from ``q``)."""

    choice(exitant, "exitant", EXITANT)
    if meas.lit_face != meas.observed_face:
        raise InputError(f"the reflectance needs a front-lit measurement (lit face = observed face); this one "
                         f"lights {meas.lit_face} and observes {meas.observed_face}")
    integer(condition, "condition (index of an illumination condition)", 0, meas.M - 1)
    if irradiance is None:
        lit = meas.incoming[condition].reshape(-1, 3)
        irradiance = lit.max(axis=0) / float(fresnel_transmittance(meas.eta, 1.0))
    E = np.broadcast_to(np.asarray(irradiance, dtype=np.float64), (3,)).copy()
    if not np.all(np.isfinite(E)) or np.any(E <= 0):
        raise InputError(f"irradiance={irradiance!r} must be finite and > 0 (scalar or R, G, B)")
    shape = meas.shape
    k = np.broadcast_to(np.asarray(kappa, dtype=np.float64).reshape(shape + (-1,)), shape + (3,))
    m = np.broadcast_to(np.asarray(mu, dtype=np.float64).reshape(shape + (-1,)), shape + (3,))
    model = ForwardModel(meas.grid, stencil, face_mean, meas.eta, meas.C, exitant)
    face = meas.observed_face
    multiple = np.zeros(meas.radiance.shape[1:])
    for c in range(3):
        Q = meas.channel(c)[0][:, condition:condition + 1]
        fac = model.factorize(model.active_values(k[..., c]), model.active_values(m[..., c]))
        L = fac.radiance(fac.solve(Q), Q)[:, 0]
        multiple[..., c] = meas.grid.boundary_to_face(face, L)
    measured = meas.radiance[condition]
    diff = measured - multiple
    if meas.saturation is not None:
        diff = np.where(measured >= meas.saturation, np.nan, diff)
    bad = ~np.isfinite(diff)
    if bad.all():
        raise InputError(f"condition {condition} has no unsaturated pixel")
    diff = np.where(bad, np.nanmean(diff, axis=(0, 1)), diff)  # saturated: the face mean
    clipped = float(np.mean(diff < 0))
    rho = math.pi * np.maximum(diff, 0.0) / E
    return Reflectance(rho, multiple, measured, clipped)


__all__ = ["Reflectance", "diffuse_reflectance"]
