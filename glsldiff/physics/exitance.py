"""Exitance and source conventions: the one home of the formulas that turn light into the
diffusion's boundary source ``q`` and the fluence ``phi`` back into exitant radiance.

Notation: ``phi`` fluence, ``E_t`` irradiance transmitted through the boundary,
``C = (1 + Fdr) / (1 - Fdr)`` (:func:`glsldiff.physics.optics.boundary_constant`); the
solver's boundary condition is ``phi + 2 C kappa dphi/dn = q``. The multiple-scattering
radiance leaving a boundary point towards ``w_o`` is ``L = F_t(eta, n.w_o) B`` with the
view-independent bracket ``B = a phi - b q`` (:func:`exitance_coefficients`).

Conventions (``EXITANT``):

* ``"p1"``: Marshak source ``q = 4 E_t / (1 - Fdr)`` and the P1 radiance along the normal,
  refracted out: ``B = [phi + 3 E.n] / (4 pi eta^2)`` with ``E.n = -kappa dphi/dn =
  (phi - q) / (2 C)``. In ``../shared/notes/wang2008.md`` this was 0.97-1.02x of Monte Carlo
  on a slab's unlit face.
* ``"arbree"``: same source, TransCut eq. 3 (Arbree et al.): ``B = [(1 + 1/C) phi - q / C] /
  (4 pi)``, i.e. ``1/pi`` times the outgoing partial current ``J+``.
* ``"paper"``: ``q = E_t``, ``B = (phi - q) / (2 pi)``, the net flux of Wang et al. eq. 3
  (negative where light enters: meaningful on unlit surfaces only).

The ``q`` of the bracket is local: where ``q`` steps (a spot's rim, a projector pattern's edge,
a cast shadow) ``B`` steps with it, a dark ring just inside the lit edge and a bright one just
outside, which transport does not show: the diffuse radiance at the surface is made by light
that entered within about a transport mean free path ``l = 1 / sigma_t' = 3 kappa``.
The renderer's default ``[options].flux = "smoothed"`` evaluates the bracket with ``q`` spread
along the surface over :data:`FLUX_SMOOTHING_MFP` mean free paths and ``phi`` over
:data:`FLUENCE_SMOOTHING_MFP` (:func:`glsldiff.mesh.smoothing.screened_smoothing`;
:func:`bracket_smoothing_lengths` gives both in mm). The load of the diffusion keeps the local
``q``.

The Marshak source puts the same light into the diffusion whatever direction it arrives
from. Transport does not: light arriving at grazing incidence scatters out near where it
entered, light arriving along the normal goes deeper and diffuses further (the 1-D oracle
:mod:`glsldiff.oracle.slab_transport`: a 20 mm slab transmits 1.26x more of normally incident
light than of diffuse light, the surface source the same for both). ``[options].incidence =
"transport"`` follows the half-space's exact transport
(:mod:`glsldiff.physics.halfspace`) per beam of refracted cosine ``t``: the diffusion's load
takes the share ``H(t) / <H>`` of the beam (:func:`deep_irradiance`; 1 on average over diffuse
light, which the Marshak source was calibrated on), and the bracket gets the local term that
makes a homogeneous half-space reflect towards the view cosine ``mu`` what transport does,
``beta E (H(t) / ((mu + t) D(mu)) - H(t) / <H>)`` (:func:`local_bracket`; ``beta`` the
half-space's own bracket per unit irradiance, :func:`halfspace_bracket`). ``"marshak"``: the
same source for every incidence, as before. ``"local"`` (the default with the surface source):
the Marshak load, and the local term
with the load's share 1 (``beta E (H(t) / ((mu + t) D(mu)) - 1)``): the half-space's exact
dependence of the light reflected near where it entered on the incidence and the view, the
diffusion's far field left as the Marshak source makes it.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError
from glsldiff.physics.halfspace import d_function, h_function, h_mean
from glsldiff.physics.optics import boundary_constant, fdr

__all__ = ["EXITANT", "FLUENCE_SMOOTHING_MFP", "FLUX_SMOOTHING_MFP", "INCIDENCE", "bracket_smoothing_lengths",
           "deep_irradiance", "exitance_coefficients", "exitant_bracket", "halfspace_bracket", "local_bracket",
           "source_from_irradiance"]

EXITANT = ("p1", "arbree", "paper")
#: How the surface source depends on the light's incidence (module docstring).
INCIDENCE = ("marshak", "local", "transport")
#: The screening length of the bracket's ``q`` in transport mean free paths: chosen on a 10 mm
#: slab under a hard-edged 6-degree spot (mean free path 0.82 mm; relative L2 against Monte
#: Carlo 0.249 local -> 0.048, best between 0.45 and 0.55) and kept for the cases not used to
#: choose it: mean free paths 2.0 mm (0.71 -> 0.13) and 0.33 mm (0.051 -> 0.041).
FLUX_SMOOTHING_MFP = 0.5
#: ... and of the bracket's ``phi``: without it the fluence's response to the grid's sampling
#: of a sharp edge (which the local ``-b q`` used to cancel) shows as a mottled rim. Best
#: between 0.12 and 0.15 on the spot slabs at both 0.82 and 1.96 mm mean free paths (so it
#: scales with the mean free path, not the node spacing; 0.25 is worse than none).
FLUENCE_SMOOTHING_MFP = 0.125


def _check(convention: str) -> None:
    if convention not in EXITANT:
        raise InputError(f"exitant convention {convention!r}; choose one of {', '.join(EXITANT)}")


def _robin_constant(eta: float, C: float | None) -> float:
    """``C``, by default :func:`glsldiff.physics.optics.boundary_constant` of ``eta``."""
    return float(boundary_constant(eta)) if C is None else float(C)


def exitance_coefficients(eta: float, convention: str, C: float | None = None) -> tuple[float, float]:
    """``(a, b)`` of the bracket ``B = a phi - b q`` (sr^-1); ``C`` defaults to
    ``boundary_constant(eta)`` (the ``paper`` bracket does not depend on it)."""
    _check(convention)
    if convention == "paper":
        return 1.0 / (2.0 * math.pi), 1.0 / (2.0 * math.pi)
    C = _robin_constant(eta, C)
    if convention == "p1":
        s = 4.0 * math.pi * eta * eta
        return (1.0 + 1.5 / C) / s, 1.5 / (C * s)
    return (1.0 + 1.0 / C) / (4.0 * math.pi), 1.0 / (C * 4.0 * math.pi)


def exitant_bracket(phi_b: ArrayLike, q_b: ArrayLike, eta: float, convention: str,
                    C: float | None = None) -> NDArray[np.float64]:
    """The view-independent factor ``B`` of ``L = F_t(eta, n.w_o) B`` per boundary node."""
    a, b = exitance_coefficients(eta, convention, C)
    return a * np.asarray(phi_b, dtype=np.float64) - b * np.asarray(q_b, dtype=np.float64)


def bracket_smoothing_lengths(kappa: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The screening lengths (mm) over which the bracket's ``phi`` and ``q`` are smoothed, per
    node and channel: :data:`FLUENCE_SMOOTHING_MFP` and :data:`FLUX_SMOOTHING_MFP` transport mean
    free paths ``3 kappa`` (kappa in mm)."""
    mfp = 3.0 * np.asarray(kappa, dtype=np.float64)
    return FLUENCE_SMOOTHING_MFP * mfp, FLUX_SMOOTHING_MFP * mfp


def source_from_irradiance(E_t: ArrayLike, eta: float, convention: str) -> NDArray[np.float64]:
    """The solver's boundary source ``q`` for transmitted irradiance ``E_t``."""
    _check(convention)
    E = np.array(E_t, dtype=np.float64)
    return E if convention == "paper" else 4.0 * E / (1.0 - float(fdr(eta)))


Beams = Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]]


def _albedo(kappa: ArrayLike, mu: ArrayLike) -> NDArray[np.float64]:
    """Reduced single-scattering albedo ``sigma_s' / sigma_t' = 1 - 3 kappa mu``."""
    return np.clip(1.0 - 3.0 * np.asarray(kappa, dtype=np.float64) * np.asarray(mu, dtype=np.float64), 0.0, 1.0)


def deep_irradiance(beams: Beams, kappa: ArrayLike, mu: ArrayLike) -> NDArray[np.float64]:
    """``sum_k E_k H(t_k) / <H>`` per node and channel: the transmitted irradiance the
    diffusion's load is made of under ``incidence = "transport"`` (module docstring). ``beams``:
    ``(E (N, 3), t (N,))`` pairs, ``t`` the refracted cosine; ``kappa`` (mm), ``mu`` (mm^-1)
    ``(N, 3)`` at the same nodes."""
    a = _albedo(kappa, mu)
    out = np.zeros_like(a)
    mean = h_mean(a)
    for E, t in beams:
        out += np.asarray(E, dtype=np.float64) * h_function(a, np.asarray(t)[:, None]) / mean
    return out


def halfspace_bracket(kappa: ArrayLike, mu: ArrayLike, eta: float, convention: str,
                      C: float | None = None) -> NDArray[np.float64]:
    """The bracket ``B`` of a homogeneous half-space of the node's material under uniform light,
    per unit transmitted irradiance (sr^-1): the diffusion's ``phi = q / (1 + 2 C sqrt(kappa mu))``
    at the surface put into ``a phi - b q``."""
    a, b = exitance_coefficients(eta, convention, C)
    C = _robin_constant(eta, C)
    q1 = float(source_from_irradiance(np.ones(1), eta, convention)[0])
    root = np.sqrt(np.asarray(kappa, dtype=np.float64) * np.asarray(mu, dtype=np.float64))
    return q1 * (a / (1.0 + 2.0 * C * root) - b)


def local_bracket(beams: Beams, kappa: ArrayLike, mu: ArrayLike, view_cos: ArrayLike, beta: ArrayLike,
                  deep: bool = True) -> NDArray[np.float64]:
    """The local term added to the bracket (sr^-1 times the irradiance's units), per node and
    channel: ``sum_k beta E_k (H(t_k) / ((mu + t_k) D(mu)) - s_k)`` with ``mu = view_cos``
    ``(N,)`` (refracted), ``beta`` from :func:`halfspace_bracket` and ``s_k`` the beam's share in
    the load: ``H(t_k) / <H>`` under ``incidence = "transport"`` (``deep``), 1 under ``"local"``
    (the Marshak load). Its sum over diffuse light is 0."""
    a = _albedo(kappa, mu)
    m = np.clip(np.asarray(view_cos, dtype=np.float64), 0.0, 1.0)[:, None]
    out = np.zeros_like(a)
    mean = h_mean(a) if deep else None
    D = d_function(a, m)                     # the view's part: once, not per beam
    for E, t in beams:
        tt = np.asarray(t)[:, None]
        H = h_function(a, tt)                # reflected_share(a, t, mu) = H / ((mu + t) D)
        share = H / mean if deep else 1.0
        den = (m + tt) * D                   # 0 where beam and view are both grazing inside (eta < 1: past
        reflected = np.divide(H, den, out=np.zeros(np.broadcast(H, den).shape), where=den > 0)   # the critical angle)
        out += np.asarray(E, dtype=np.float64) * (reflected - share)
    return np.asarray(beta, dtype=np.float64) * out
