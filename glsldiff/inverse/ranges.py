"""How tightly the measurements pin the homogeneous material: profile ranges of sigma_a and
sigma_s' [mm^-1].

Back-lit captures of a thick block see mostly one combination of absorption and scattering:
more absorption can be traded for less scattering at almost the same images. The fit's
numbers alone do not show this, so the homogeneous stage reports, for each coefficient, the
range over which the data term stays within ``tolerance`` (relative) of its minimum while the
*other* coefficient is re-fitted along (a profile). Near the optimum the data term is the
Gauss-Newton quadratic ``f(p) = f0 + dp^T A dp`` with ``A = J^T J``, ``J`` the weighted
residual's Jacobian in ``p = (sigma_a, sigma_s')`` (the same Jacobian the least-squares fit
used, so it costs nothing). The profile of ``sigma_a`` rises as ``(A_aa - A_as^2 / A_ss)
d^2``, so its range is ``sigma_a +- sqrt(tolerance f0 / (A_aa - A_as^2 / A_ss))`` (clipped at
0), and likewise for ``sigma_s'``.

The default tolerance, 1 % of the data term, is well inside the diffusion model's own error
against transport (several per cent, see docs/guide/inverse.md), so materials inside the range explain
the measurements as well as the model can tell; a range that spans more than the value
itself means the capture does not determine that coefficient.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.checks import real
from glsldiff.core.errors import InputError

__all__ = ["CoefficientRanges", "profile_ranges", "PROFILE_TOLERANCE"]

PROFILE_TOLERANCE = 0.01


@dataclass(frozen=True)
class CoefficientRanges:
    """The homogeneous fit's sigma_a and sigma_s' [mm^-1] and the range of each that keeps the
    data term within ``tolerance`` of its minimum ``data`` (the other coefficient re-fitted)."""

    sigma_a: float
    sigma_a_range: tuple[float, float]
    sigma_s: float
    sigma_s_range: tuple[float, float]
    tolerance: float
    data: float

    @property
    def physical(self) -> bool:
        """Whether the homogeneous fit is a physical material (sigma_s' >= 0); its fit runs in
        (log kappa, log mu) and may end where 3 kappa mu > 1, and then has no ranges (NaN)."""
        return self.sigma_s >= 0.0

    @property
    def determined(self) -> tuple[bool, bool]:
        """Whether each range is narrower than the value itself (half-width < value); neither
        is when the fit is not physical."""
        return tuple(self.physical and 0.5 * (hi - lo) < v for v, (lo, hi) in
                     ((self.sigma_a, self.sigma_a_range), (self.sigma_s, self.sigma_s_range)))  # type: ignore

    def describe(self) -> str:
        """One line: both ranges and which coefficient the capture does not determine."""
        if not self.physical:
            return (f"homogeneous fit sigma_a {self.sigma_a:.4g} /mm, sigma_s' {self.sigma_s:.4g} /mm is not a "
                    "physical material (sigma_s' < 0, i.e. 3 kappa mu > 1): no ranges; the measurements do not "
                    "determine a homogeneous material")
        (a0, a1), (s0, s1) = self.sigma_a_range, self.sigma_s_range
        loose = [name for name, ok in zip(("sigma_a", "sigma_s'"), self.determined) if not ok]
        tail = (f"; the measurements do not determine {' or '.join(loose)} (its range is wider than its value)"
                if loose else "")
        return (f"homogeneous fit sigma_a {self.sigma_a:.4g} /mm (data within {100 * self.tolerance:g} % of its "
                f"minimum for {a0:.4g} .. {_fmt(a1)}), sigma_s' {self.sigma_s:.4g} /mm ({s0:.4g} .. {_fmt(s1)})"
                + tail)


def _fmt(x: float) -> str:
    return "inf" if math.isinf(x) else f"{x:.4g}"


def profile_ranges(jac_log: NDArray[np.float64], kappa: float, mu: float, data: float,
                   tolerance: float = PROFILE_TOLERANCE) -> CoefficientRanges:
    """Ranges of the homogeneous material ``(kappa mm, mu mm^-1)`` from the weighted residual's
    Jacobian ``jac_log`` ``(n, 2)`` in ``(log kappa, log mu)`` at the optimum and the data
    term ``data`` there (module docstring)."""
    real(tolerance, "tolerance", 0.0, lo_open=True)
    J = np.asarray(jac_log, dtype=np.float64)
    if J.ndim != 2 or J.shape[1] != 2 or not np.all(np.isfinite(J)):
        raise InputError(f"jac_log must be a finite (n, 2) array, got shape {J.shape}")
    real(kappa, "kappa (mm)", 0.0, lo_open=True)
    real(mu, "mu (mm^-1)", 0.0, lo_open=True)
    sigma_t = 1.0 / (3.0 * kappa)
    sa, ss = mu, sigma_t - mu
    # d log kappa / d sigma_a = d log kappa / d sigma_s' = -1/sigma_t;  d log mu / d sigma_a = 1/mu
    Ja = -J[:, 0] / sigma_t + J[:, 1] / mu
    Js = -J[:, 0] / sigma_t
    A = np.array([[Ja @ Ja, Ja @ Js], [Ja @ Js, Js @ Js]])
    rise = tolerance * max(float(data), 0.0)

    def half_width(i: int) -> float:
        j = 1 - i
        c = A[i, i] - A[i, j] ** 2 / A[j, j] if A[j, j] > 0 else A[i, i]
        if c <= 1e-14 * max(A[i, i], 1e-300):
            return math.inf
        return math.sqrt(rise / c)

    if ss < 0.0:   # not a physical material: no ranges (CoefficientRanges.physical)
        return CoefficientRanges(sa, (math.nan, math.nan), ss, (math.nan, math.nan), float(tolerance), float(data))
    da, ds = half_width(0), half_width(1)
    return CoefficientRanges(sa, (max(sa - da, 0.0), sa + da), ss, (max(ss - ds, 0.0), ss + ds),
                             float(tolerance), float(data))
