"""Exact diffusion on a homogeneous sphere under an arbitrary boundary source (series solution).

Problem (lengths in mm, coefficients in mm^-1): inside the sphere ``|x - c| <= R``

    kappa Laplacian phi - mu phi = 0,      phi + 2 C kappa dphi/dn = q   on |x - c| = R

(outward normal; ``C = glsldiff.physics.optics.boundary_constant(eta)``), the continuous
problem the solvers discretise. With ``s = sqrt(mu / kappa)`` and ``q = sum_lm q_lm Y_lm``

    phi(r, n) = sum_lm q_lm  rho_l(r) / D_l  Y_lm(n),
    rho_l(r)  = i_l(s r) / i_l(s R)                         (-> (r / R)^l for mu = 0),
    D_l       = 1 + 2 C kappa s i_l'(s R) / i_l(s R)
              = 1 + 2 C kappa [ l / R + (mu / kappa) R t_l(s R) / (2 l + 3) ],

``i_l`` the modified spherical Bessel function of the first kind and ``t_l(x) = (2 l + 3)
i_{l+1}(x) / (x i_l(x))`` in (0, 1] (1 at x = 0). Nothing here overflows: ``t_l`` comes from
the stable backward recurrence ``t_l = 1 / (1 + x^2 t_{l+1} / ((2l+3)(2l+5)))`` (i_l is the
minimal solution of the three-term recurrence), and ``rho_l`` from logarithms:
``log rho_l = l log(r / R) + log G_l(s r) - log G_l(s R)`` with ``G_l(x) = (2l+1)!! i_l(x) / x^l``,
``log G_0 = log(sinh x / x)`` and ``log G_{l+1} = log G_l + log t_l``. This is exact for mu = 0
(t = 1, G = 1) and for stiff media (s R in the thousands) alike, where scipy's
``spherical_in`` overflows near s R ~ 700. The Bessel ratio test in the test suite checks it
against ``scipy.special.ive``.

Sources
-------
* Axisymmetric ``q(cos theta)`` about a unit ``axis`` (:meth:`SphereSeries.with_axisymmetric_source`):
  Legendre coefficients ``q_l = (2l+1)/2 int q P_l`` by piecewise Gauss-Legendre quadrature,
  split at the source's kinks and edges (``breakpoints``), with Newton-refined nodes and weights
  (scipy's ``roots_legendre`` weights are off by ~4e-10 relative at n = 4000, which shows in
  the small high-degree coefficients, and it takes ~10 s at n = 20000). ``l_max`` doubles from 32 until
  the boundary fluence on a 1025-angle test grid (plus the breakpoints) changes by less than
  ``tol`` (default 1e-10) relative to its maximum; :attr:`SphereSeries.truncation_error` is
  that last change (an upper estimate of the error of the result).
* Any ``q(n)`` (:meth:`SphereSeries.with_source_function`): complex spherical harmonics (m >= 0,
  the m < 0 halves by conjugate symmetry for a real q; the same span as real SH) to
  ``l_max`` (default 64) by Gauss-Legendre (polar) x uniform (azimuth, FFT) quadrature,
  oversampled (default 4x) because light sources have kinks; ``truncation_error`` is the
  change of the boundary fluence between ``l_max / 2`` and ``l_max`` on a Fibonacci test set.
* Lights (:mod:`glsldiff.oracle.sphere_lights`: ``sphere_directional``, ``sphere_point_light``,
  ``sphere_spot``, ``sphere_from_light``): transmitted irradiance ``E_t = E F_t(eta, cos_i) cos_i^+`` (r^-2
  and the spot cone of :func:`glsldiff.physics.lights.spot_factor` for positional lights,
  computed by :func:`glsldiff.physics.lights.incidence` as pass 1 does), turned into ``q`` by
  :func:`glsldiff.physics.exitance.source_from_irradiance`. A convex sphere shadows nothing
  beyond the visible cap ``cos_i > 0``. Directional lights, point lights and spots aimed at
  the centre are axisymmetric; other spots and projectors take the general path.

Convergence (measured; R = 10 mm, kappa = 1/3 mm, mu = 0.01 mm^-1, eta = 1.3; errors relative to
the maximum boundary fluence, against l_max = 32768):

* Directional light: ~l_max^-3 (kink at the terminator, softened by F_t -> 0 at grazing):
  5e-7 at l_max = 256, 8e-10 at 2048; the adaptive rule stops at l_max = 8192 (estimate 3e-11,
  error 1.5e-11) in ~0.3 s. The same for a point light at 30 mm. A stiff sphere (s R = 1000,
  kappa = 1/30 mm) reaches the cap 16384 with an estimate of 1.1e-9.
* Spot at 30 mm from the centre aimed at it, cone 10 deg (edge at 21 deg on the sphere):
  with a smooth falloff from 8 deg, ~l_max^-3 (6e-7 at 1024, 8e-9 at 4096; estimate 4.9e-10 at
  the cap 16384, error 6e-11); hard-edged (falloff = cone, q jumps), only ~l_max^-1 near the edge:
  1.2e-3 at 1024, 1.6e-4 at 4096, 1.5e-5 at 16384 (estimate 3e-5).
* The floor is ~1e-11: rounding in the Legendre recurrence at degree ~10^4 (tol below that
  just runs to ``max_l_max``).
* General path, directional light: 2.3e-4 at l_max = 32, 3.1e-5 at 64, 4.0e-6 at 128, 5.1e-7 at 256
  (4x oversampling; the estimate is 5-8x above the error).

Output: :meth:`SphereSeries.fluence` anywhere in the ball, :meth:`SphereSeries.boundary_fluence`,
:meth:`SphereSeries.source` (the exact ``q``, not its series), the renderer's exitant bracket
``B = a phi - b q`` (:meth:`SphereSeries.exitant_bracket`) and radiance ``F_t(eta, n.w_o) B``
(:meth:`SphereSeries.exitant_radiance`).
"""
from __future__ import annotations

import copy
import math
from typing import Any, Callable, Sequence

import numpy as np
from numpy.polynomial import legendre as npleg
from numpy.typing import ArrayLike, NDArray
from scipy import special

from glsldiff.core import checks
from glsldiff.core.errors import InputError
from glsldiff.oracle.special import bessel_ratio_t, gauss_legendre, log_bessel_g, log_sinhc
from glsldiff.physics.exitance import EXITANT, exitant_bracket as _exitant_bracket
from glsldiff.physics.optics import fresnel_transmittance
from glsldiff.physics.sh import fibonacci_directions

__all__ = ["SphereSeries", "from_axisymmetric_source", "from_source_function", "sphere_uniform"]

QOfCos = Callable[[NDArray[np.float64]], ArrayLike]
QOfDirs = Callable[[NDArray[np.float64]], ArrayLike]

_CHUNK_FLOATS = 4_000_000      # floats per (points x terms) block in evaluation
_TEST_ANGLES = 1025            # polar test angles of the adaptive Legendre rule
_NODES_PER_DEGREE = 0.55       # Gauss-Legendre nodes per (stretched) degree of the Legendre rule
_NODE_BLOCK = 4096             # nodes per block of the Legendre recurrence



# ----------------------------------------------------------------------------------------------
# The series

def _frame(axis: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Two unit vectors completing ``axis`` to an orthonormal frame."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


class SphereSeries:
    """Series solution of the diffusion equation in a homogeneous sphere.

    Parameters
    ----------
    radius
        Sphere radius R, mm (> 0).
    kappa
        Diffusion coefficient, mm (> 0).
    mu
        Absorption coefficient, mm^-1 (>= 0).
    C
        Boundary constant (> 0), e.g. ``boundary_constant(eta)``.
    centre
        ``(3,)`` centre, mm.

    A new series has no source (phi = 0); ``with_*_source`` return copies with one. Attributes
    after a source is set: ``kind`` (``"zero"``, ``"uniform"``, ``"axisymmetric"``,
    ``"general"``), ``l_max``, ``n_terms`` (coefficients used), ``truncation_error`` (estimated,
    relative to the maximum boundary fluence), ``legendre`` ``(l_max+1,)`` and ``axis`` (3,) for
    axisymmetric sources, ``sh`` ``(l_max+1, l_max+1)`` complex ``[l, m >= 0]`` for general ones,
    and ``eta`` / ``convention`` when built from a light (defaults of the exitant methods).
    """

    def __init__(self, radius: float, kappa: float, mu: float, C: float,
                 centre: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        self.radius = checks.real(radius, "radius", 0.0, math.inf, lo_open=True, hi_open=True)
        self.kappa = checks.real(kappa, "kappa", 0.0, math.inf, lo_open=True, hi_open=True)
        self.mu = checks.real(mu, "mu", 0.0, math.inf, hi_open=True)
        self.C = checks.real(C, "C", 0.0, math.inf, lo_open=True, hi_open=True)
        self.centre = checks.vector3(centre, "centre")
        self.s = math.sqrt(self.mu / self.kappa)          # mm^-1
        self.kind = "zero"
        self.l_max = 0
        self.legendre: NDArray[np.float64] = np.zeros(1)
        self.axis: NDArray[np.float64] = np.array([0.0, 0.0, 1.0])
        self.sh: NDArray[np.complex128] | None = None
        self.truncation_error = 0.0
        self.eta: float | None = None
        self.convention: str | None = None
        self._source: QOfDirs = lambda n: np.zeros(len(n))

    def __repr__(self) -> str:
        return (f"SphereSeries(radius={self.radius:g}, kappa={self.kappa:g}, mu={self.mu:g}, C={self.C:g}, "
                f"kind={self.kind!r}, l_max={self.l_max}, truncation_error={self.truncation_error:.2g})")

    @property
    def n_terms(self) -> int:
        """Number of series coefficients used: l_max + 1 (axisymmetric) or (l_max + 1)^2."""
        if self.kind == "general":
            return (self.l_max + 1) ** 2
        return self.l_max + 1

    # -- radial part -------------------------------------------------------------------------

    def denominators(self, l_max: int) -> NDArray[np.float64]:
        """``D_l = 1 + 2 C kappa s i_l'(sR) / i_l(sR)``, l = 0..l_max (dimensionless)."""
        l = np.arange(l_max + 1, dtype=np.float64)
        R = self.radius
        t = bessel_ratio_t(np.array(self.s * R), l_max)
        return 1.0 + 2.0 * self.C * self.kappa * (l / R + (self.mu / self.kappa) * R * t / (2.0 * l + 3.0))

    def radial_factors(self, r: ArrayLike, l_max: int) -> NDArray[np.float64]:
        """``rho_l(r) / D_l = i_l(s r) / (i_l(s R) D_l)`` for r (N,) mm in [0, R]: ``(N, l_max+1)``.

        phi at distance r is ``sum_lm q_lm (this)[l] Y_lm``; 1 / D_l on the boundary.
        """
        r = np.clip(np.asarray(r, dtype=np.float64).ravel(), 0.0, self.radius)
        R = self.radius
        logGr, _ = log_bessel_g(self.s * r, l_max)
        logGR, _ = log_bessel_g(np.array([self.s * R]), l_max)
        l = np.arange(l_max + 1, dtype=np.float64)
        with np.errstate(divide="ignore"):
            lr = np.log(r / R)                                        # -inf at the centre
        with np.errstate(invalid="ignore"):
            power = np.where(l[None, :] == 0, 0.0, l[None, :] * lr[:, None])
        return np.exp(power + logGr - logGR) / self.denominators(l_max)[None, :]

    def _terms_needed(self, r_max: float, l_max: int) -> int:
        """Smallest L <= l_max with (r_max / R)^L < 1e-18 (rho_l <= (r/R)^l)."""
        ratio = r_max / self.radius
        if ratio >= 1.0 - 1e-15:
            return l_max
        if ratio <= 0.0:
            return 0
        return int(min(l_max, math.ceil(math.log(1e-18) / math.log(ratio))))

    # -- sources -----------------------------------------------------------------------------

    def _copy(self) -> "SphereSeries":
        out = copy.copy(self)
        out.sh = None
        return out

    def with_uniform_source(self, q: float) -> "SphereSeries":
        """Copy with the uniform source ``q`` (phi is radial; the closed form's case)."""
        qv = checks.real(q, "q")
        out = self._copy()
        out.kind, out.l_max, out.truncation_error = "uniform", 0, 0.0
        out.legendre = np.array([qv])
        out._source = lambda n: np.full(len(n), qv)
        return out

    def with_axisymmetric_source(self, q_of_cos: QOfCos, axis: ArrayLike, *,
                                 breakpoints: Sequence[float] = (), tol: float = 1e-10,
                                 l_max: int | None = None, max_l_max: int = 16384,
                                 l_start: int = 32) -> "SphereSeries":
        """Copy with the source ``q(cos theta)``, theta the angle from the unit ``axis``.

        Parameters
        ----------
        q_of_cos
            Vectorised ``q`` of ``cos theta`` in [-1, 1] (the solver's source units).
        axis
            ``(3,)`` symmetry axis (normalised here).
        breakpoints
            Values of ``cos theta`` where q has a kink or jump (quadrature is split there).
        tol
            Adaptive rule: stop doubling ``l_max`` once the boundary fluence changes by less
            than ``tol`` times its maximum absolute value.
        l_max
            Fixed truncation instead of the adaptive rule.
        max_l_max
            Cap of the adaptive rule (the estimate is then above ``tol``).
        l_start
            First ``l_max`` of the adaptive rule.
        """
        ax = np.asarray(checks.unit_vector(axis, "axis"))
        tol = checks.real(tol, "tol", 0.0, 1.0, lo_open=True)
        cuts = sorted({-1.0, 1.0, *(float(checks.real(b, "breakpoint", -1.0, 1.0)) for b in breakpoints)})
        pieces = [(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b - a > 1e-14]
        x_test = np.concatenate([np.cos(np.linspace(0.0, math.pi, _TEST_ANGLES)), np.array(cuts)])

        def coeffs(L: int) -> NDArray[np.float64]:
            return _legendre_coefficients(q_of_cos, L, pieces)

        out = self._copy()
        out.kind, out.axis = "axisymmetric", ax
        if l_max is not None:
            L = checks.integer(l_max, "l_max", 0, 1 << 17)
            c = coeffs(L)
            D = self.denominators(L)
            full = npleg.legval(x_test, c / D)
            half = npleg.legval(x_test, (c / D)[: L // 2 + 1])
            err = float(np.abs(full - half).max() / max(np.abs(full).max(), 1e-300))
        else:
            cap = checks.integer(max_l_max, "max_l_max", 1, 1 << 17)
            L = checks.integer(l_start, "l_start", 1, cap)
            prev, err = None, math.inf
            while True:
                c = coeffs(L)
                D = self.denominators(L)
                full = npleg.legval(x_test, c / D)
                if prev is not None:
                    err = float(np.abs(full - prev).max() / max(np.abs(full).max(), 1e-300))
                    if err <= tol:
                        break
                if L >= cap:
                    break
                prev, L = full, min(2 * L, cap)
        out.l_max, out.legendre, out.truncation_error = L, c, err
        out._source = lambda n: np.asarray(q_of_cos(np.clip(n @ ax, -1.0, 1.0)), dtype=np.float64)
        return out

    def with_source_function(self, q_of_dirs: QOfDirs, *, l_max: int = 64,
                             oversample: int = 4) -> "SphereSeries":
        """Copy with an arbitrary source ``q(n)``, n unit directions (N, 3) from the centre.

        Complex spherical harmonics up to ``l_max``; quadrature on ``oversample (l_max + 1)``
        Gauss-Legendre polar nodes x twice as many azimuths (exact for band-limited q when
        ``oversample >= 1``; more resolves kinks and edges of lights). ``truncation_error``: the
        boundary fluence's change between ``l_max // 2`` and ``l_max`` (2000 Fibonacci points),
        relative to its maximum.
        """
        L = checks.integer(l_max, "l_max", 1, 256)
        ov = checks.integer(oversample, "oversample", 1, 64)
        n_t = ov * (L + 1)
        n_p = 2 * n_t
        x, w = gauss_legendre(n_t)
        theta = np.arccos(x)
        az = 2.0 * math.pi * np.arange(n_p) / n_p
        st = np.sin(theta)[:, None]
        dirs = np.stack([st * np.cos(az)[None], st * np.sin(az)[None],
                         np.broadcast_to(x[:, None], (n_t, n_p))], axis=-1).reshape(-1, 3)
        qg = np.asarray(q_of_dirs(dirs), dtype=np.float64).reshape(n_t, n_p)
        if not np.isfinite(qg).all():
            raise InputError("q_of_dirs returned non-finite values")
        Q = np.fft.fft(qg, axis=1)[:, : L + 1] * (2.0 * math.pi / n_p)   # int q e^{-i m phi} dphi
        sh = np.zeros((L + 1, L + 1), dtype=np.complex128)
        step = max(1, _CHUNK_FLOATS // ((L + 1) * (2 * L + 1)))
        for a in range(0, n_t, step):                                    # Y_lm(theta, 0), m >= 0
            A = special.sph_legendre_p_all(L, L, theta[a:a + step])[0][:, : L + 1, :]
            sh += np.einsum("j,jm,lmj->lm", w[a:a + step], Q[a:a + step], A)
        sh[np.triu_indices(L + 1, 1)] = 0.0
        out = self._copy()
        out.kind, out.l_max, out.sh = "general", L, sh
        out._source = lambda n: np.asarray(q_of_dirs(n), dtype=np.float64)
        test = fibonacci_directions(2000)
        full = out._general_boundary(test, L)
        half = out._general_boundary(test, L // 2)
        out.truncation_error = float(np.abs(full - half).max() / max(np.abs(full).max(), 1e-300))
        return out

    # -- evaluation --------------------------------------------------------------------------

    def _general_boundary(self, n: NDArray[np.float64], L: int) -> NDArray[np.float64]:
        assert self.sh is not None
        D = self.denominators(L)
        out = np.empty(len(n))
        step = max(1, _CHUNK_FLOATS // ((L + 1) * (2 * L + 1)))
        for a in range(0, len(n), step):
            m = n[a:a + step]
            out[a:a + step] = self._general_chunk(m, L, np.broadcast_to(1.0 / D, (len(m), L + 1)))
        return out

    def _general_chunk(self, n: NDArray[np.float64], L: int, F: NDArray[np.float64]) -> NDArray[np.float64]:
        theta = np.arccos(np.clip(n[:, 2], -1.0, 1.0))
        az = np.arctan2(n[:, 1], n[:, 0])
        A = special.sph_legendre_p_all(L, L, theta)[0][:, : L + 1, :]       # [l, m, point]
        E = np.exp(1j * np.arange(L + 1)[None, :] * az[:, None])            # [point, m]
        wm = np.full(L + 1, 2.0)
        wm[0] = 1.0
        c = self.sh[: L + 1, : L + 1] * wm[None, :]                        # type: ignore[index]
        vals = np.einsum("lm,lmp,pm->pl", c, A, E).real                     # [point, l]
        return (vals * F[:, : L + 1]).sum(axis=1)

    def _evaluate(self, d: NDArray[np.float64], r: NDArray[np.float64], boundary: bool) -> NDArray[np.float64]:
        """phi at offsets ``d`` (N, 3) from the centre with lengths ``r``."""
        N = len(d)
        out = np.zeros(N)
        if self.kind == "zero" or N == 0:
            return out
        n = d / np.where(r > 0.0, r, 1.0)[:, None]
        n[r == 0.0] = self.axis
        L = self.l_max
        if self.kind in ("uniform", "axisymmetric"):
            x = np.clip(n @ self.axis, -1.0, 1.0)
            coef = self.legendre / self.denominators(L)
            if boundary:
                return npleg.legval(x, coef)
            need = np.array([self._terms_needed(float(v), L) for v in r])
            bucket = np.ceil(np.log2(need + 1.0)).astype(int)          # similar truncations together
            for k in np.unique(bucket):
                idx = np.nonzero(bucket == k)[0]
                Le = int(need[idx].max())
                out[idx] = self._legendre_interior(x[idx], r[idx], coef[: Le + 1])
            return out
        if boundary:                                     # "general" from here on
            return self._general_boundary(n, L)
        step = max(1, _CHUNK_FLOATS // ((L + 1) * (2 * L + 1)))
        order = np.argsort(r)                            # chunks of similar radius: fewer terms inside
        for a in range(0, N, step):
            idx = order[a:a + step]
            rr = r[idx]
            Le = self._terms_needed(float(rr.max()), L)
            out[idx] = self._general_chunk(n[idx], Le, self.radial_factors(rr, Le))
        return out

    def _legendre_interior(self, x: NDArray[np.float64], r: NDArray[np.float64],
                           coef: NDArray[np.float64]) -> NDArray[np.float64]:
        """``sum_l coef_l rho_l(r) P_l(x)`` for interior points, without an (N, L) array.

        Clenshaw's recurrence runs downwards in l; ``rho_l = exp(l log(r/R) + Delta_l)`` with
        ``Delta_l = log G_l(s r) - log G_l(s R)`` updated downwards from ``Delta_L``, which a
        first pass of the t recurrence (the same recurrence, rerun in the second pass) sums up.
        """
        L = len(coef) - 1
        R = self.radius
        out = np.empty(len(x))
        centre = r <= 0.0
        if centre.any():                                    # only l = 0 survives at r = 0
            out[centre] = coef[0] * math.exp(-float(log_sinhc(np.array([self.s * R]))[0]))
        x, r = x[~centre], r[~centre]
        if len(x) == 0:
            return out
        xr = self.s * r
        x2 = xr * xr
        lr = np.log(r / R)
        stiff = self.s > 0.0
        tR = bessel_ratio_t(np.array(self.s * R), L)
        logtR = np.log(tR)
        top = max(L, int(math.ceil(2.0 * float(xr.max())))) + 64
        delta = log_sinhc(xr) - float(log_sinhc(np.array([self.s * R]))[0]) - logtR[:L].sum()
        if stiff:                                            # pass 1: Delta_L
            t = np.ones_like(xr)
            for l in range(top, -1, -1):
                t = 1.0 / (1.0 + x2 * t / ((2 * l + 3) * (2 * l + 5)))
                if l < L:
                    delta += np.log(t)
        t = np.ones_like(xr)
        b1, b2 = np.zeros_like(xr), np.zeros_like(xr)
        for l in range(top if stiff else L, -1, -1):        # pass 2: Clenshaw
            if stiff:
                t = 1.0 / (1.0 + x2 * t / ((2 * l + 3) * (2 * l + 5)))
            if l > L:
                continue
            if l < L and stiff:
                delta -= np.log(t) - logtR[l]
            a = coef[l] * np.exp(l * lr + delta)
            b0 = a + ((2 * l + 1) / (l + 1)) * x * b1 - ((l + 1) / (l + 2)) * b2
            b1, b2 = b0, b1
        out[~centre] = b1
        return out

    def _offsets(self, points: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        d = checks.points(points) - self.centre
        return d, np.linalg.norm(d, axis=1)

    def fluence(self, points: ArrayLike) -> NDArray[np.float64]:
        """Fluence at ``points`` (N, 3) mm inside or on the sphere (|p - c| <= R (1 + 1e-9));
        points within 1e-12 R of the surface count as on it."""
        d, r = self._offsets(points)
        R = self.radius
        if (r > R * (1.0 + 1e-9)).any():
            raise InputError(f"fluence: {int((r > R * (1.0 + 1e-9)).sum())} points lie outside the sphere "
                             f"(radius {R:g} mm); use boundary_fluence for surface points")
        out = np.empty(len(d))
        on = r >= R * (1.0 - 1e-12)
        out[on] = self._evaluate(d[on], np.full(int(on.sum()), R), True)
        out[~on] = self._evaluate(d[~on], r[~on], False)
        return out

    def _boundary_dirs(self, points: ArrayLike) -> NDArray[np.float64]:
        d, r = self._offsets(points)
        if (r <= 1e-12 * self.radius).any():
            raise InputError("boundary points must not be at the sphere's centre (they are projected radially)")
        return d / r[:, None]

    def boundary_fluence(self, points: ArrayLike) -> NDArray[np.float64]:
        """Fluence on the surface at ``points`` (N, 3) mm, projected radially onto the sphere."""
        n = self._boundary_dirs(points)
        return self._evaluate(n * self.radius, np.full(len(n), self.radius), True)

    def source(self, points: ArrayLike) -> NDArray[np.float64]:
        """The exact boundary source ``q`` (not its series) at ``points`` projected onto the sphere."""
        return self._source(self._boundary_dirs(points))

    def _eta_conv(self, eta: float | None, convention: str | None) -> tuple[float, str]:
        e = self.eta if eta is None else checks.real(eta, "eta", 0.0, math.inf, lo_open=True)
        if e is None:
            raise InputError("eta is needed (this series was not built from a light)")
        conv = convention or self.convention or "p1"
        checks.choice(conv, "convention", EXITANT)
        return e, conv

    def exitant_bracket(self, points: ArrayLike, eta: float | None = None,
                        convention: str | None = None) -> NDArray[np.float64]:
        """The renderer's view-independent ``B = a phi - b q`` (sr^-1 times fluence units) at
        surface ``points`` (N, 3), with this series' ``C``; ``eta`` / ``convention`` default to
        the light's."""
        e, conv = self._eta_conv(eta, convention)
        return _exitant_bracket(self.boundary_fluence(points), self.source(points), e, conv, self.C)

    def exitant_radiance(self, points: ArrayLike, view_dirs: ArrayLike, eta: float | None = None,
                         convention: str | None = None) -> NDArray[np.float64]:
        """Multiple-scattering radiance ``F_t(eta, n.w_o) B`` leaving surface ``points`` (N, 3)
        towards unit ``view_dirs`` (N, 3) (0 where n.w_o <= 0)."""
        e, conv = self._eta_conv(eta, convention)
        n = self._boundary_dirs(points)
        w = checks.unit_rows(view_dirs, "view_dirs", len(n))
        c = np.clip((n * w).sum(axis=1), 0.0, 1.0)
        ft = np.asarray(fresnel_transmittance(e, c))
        return np.where(c > 0.0, ft, 0.0) * self.exitant_bracket(points, e, conv)


def _angular_stretch(a: float, b: float) -> float:
    """max |d theta / d psi| on the piece x = cos theta in [a, b], x = (a+b)/2 + (b-a)/2 cos psi.

    P_l(cos theta) oscillates like cos(l theta); in the piece's Chebyshev angle psi its frequency
    is l times this (1 for the whole interval, 1/sqrt(2) for [0, 1]), which sets the
    Gauss-Legendre degree the piece needs.
    """
    psi = np.linspace(1e-6, math.pi - 1e-6, 512)
    x = 0.5 * (a + b) + 0.5 * (b - a) * np.cos(psi)
    sin_t = np.sqrt(np.clip(1.0 - x * x, 1e-300, None))
    return float(min(1.0, (0.5 * (b - a) * np.sin(psi) / sin_t).max()))


def _legendre_coefficients(q_of_cos: QOfCos, L: int, pieces: Sequence[tuple[float, float]]) -> NDArray[np.float64]:
    """``q_l = (2l+1)/2 int_{-1}^{1} q(x) P_l(x) dx``, l = 0..L, piecewise Gauss-Legendre."""
    xs, ws = [], []
    for a, b in pieces:
        n = int(math.ceil(_NODES_PER_DEGREE * L * _angular_stretch(a, b))) + 40
        g, gw = gauss_legendre(n)
        xs.append(0.5 * (b - a) * g + 0.5 * (a + b))
        ws.append(0.5 * (b - a) * gw)
    x, w = np.concatenate(xs), np.concatenate(ws)
    qv = np.asarray(q_of_cos(x), dtype=np.float64)
    if qv.shape != x.shape or not np.isfinite(qv).all():
        raise InputError("q_of_cos must return finite values of the shape of its argument")
    keep = qv != 0.0                       # e.g. the unlit side: no contribution
    x, f = x[keep], (qv * w)[keep]
    c = np.zeros(L + 1)
    # P_{l+1} = a_l x P_l - b_l P_{l-1}, in place, in node blocks that stay in cache
    for s0 in range(0, len(x), _NODE_BLOCK):
        xb, fb = x[s0:s0 + _NODE_BLOCK], f[s0:s0 + _NODE_BLOCK]
        p0, p1, tmp = np.ones_like(xb), xb.copy(), np.empty_like(xb)
        c[0] += fb.sum()
        if L >= 1:
            c[1] += fb @ xb
        for l in range(1, L):
            np.multiply(xb, p1, out=tmp)
            tmp *= (2 * l + 1) / (l + 1)
            p0 *= l / (l + 1)
            np.subtract(tmp, p0, out=p0)
            p0, p1 = p1, p0
            c[l + 1] += fb @ p1
    return c * (np.arange(L + 1) + 0.5)


# ----------------------------------------------------------------------------------------------
# Constructors



def sphere_uniform(radius: float, kappa: float, mu: float, C: float, q: float,
                   centre: ArrayLike = (0.0, 0.0, 0.0)) -> SphereSeries:
    """Series for the uniform source ``q`` (the radial closed form's problem)."""
    return SphereSeries(radius, kappa, mu, C, centre).with_uniform_source(q)


def from_axisymmetric_source(radius: float, kappa: float, mu: float, C: float, q_of_cos: QOfCos,
                             axis: ArrayLike, centre: ArrayLike = (0.0, 0.0, 0.0), **kw: Any) -> SphereSeries:
    """Series for ``q(cos theta)`` about ``axis``; keywords of :meth:`SphereSeries.with_axisymmetric_source`."""
    return SphereSeries(radius, kappa, mu, C, centre).with_axisymmetric_source(q_of_cos, axis, **kw)


def from_source_function(radius: float, kappa: float, mu: float, C: float, q_of_dirs: QOfDirs,
                         centre: ArrayLike = (0.0, 0.0, 0.0), **kw: Any) -> SphereSeries:
    """Series for any ``q(n)`` (unit directions from the centre); keywords of
    :meth:`SphereSeries.with_source_function`."""
    return SphereSeries(radius, kappa, mu, C, centre).with_source_function(q_of_dirs, **kw)
