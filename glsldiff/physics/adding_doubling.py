r"""Exact light transport in a homogeneous plane-parallel medium with isotropic scattering and a
smooth Fresnel boundary, by the adding-doubling method (van de Hulst 1980; Prahl 1995, "The
adding-doubling method", in Optical-Thermal Response of Laser-Irradiated Tissue): the
half-space tables the renderer's local transport term (:mod:`glsldiff.physics.exitance`) is
built from, for any relative index ``eta`` (Chandrasekhar's H-function,
:mod:`glsldiff.physics.halfspace`, covers ``eta = 1`` only and is this module's check).

Angles: ``N_OUT`` Gauss-Legendre nodes ``nu`` on the outside cosine (0, 1); inside, their
refracted images ``t(nu) = sqrt(1 - (1 - nu^2) / eta^2)`` plus ``N_TIR`` Gauss nodes on (0,
``mu_c``), the cosines that total internal reflection keeps inside (none for ``eta = 1``). A
state is the flux per unit area in each angular bin; a layer is two matrices on it, the
reflection ``R`` and the transmission ``T`` (the same from either side for a homogeneous layer).

* Thin layer of optical depth ``dtau``: single scattering, exact in the attenuation. Flux in
  bin j scatters at depth ``tau`` at the rate ``a exp(-tau / mu_j) / mu_j``, half of it up and
  half down, into bin i in proportion to its weight ``w_i`` (an isotropic source puts the same
  flux into equal solid angles of ``mu``), attenuated on its way out:
  ``R_ij = (a w_i / 2) mu_i / (mu_i + mu_j) (1 - e^{-dtau / mu_i - dtau / mu_j})``,
  ``T_ij = delta_ij e^{-dtau / mu_j} + (a w_i / 2) mu_i (e^{-dtau / mu_i} - e^{-dtau / mu_j}) /
  (mu_i - mu_j)``; what scatters again inside the layer is spread the same way (times ``a``),
  so a conservative layer conserves energy exactly.
* Adding two layers (light from above): ``R_12 = R_1 + T_1 (I - R_2 R_1)^-1 R_2 T_1``, ``T_12 =
  T_2 (I - R_1 R_2)^-1 T_1``; doubling adds a layer to itself, 2^k times the depth in k steps.
* The boundary: outside flux at ``nu_j`` enters bin ``t(nu_j)`` times ``F_t(eta, nu_j)``
  (:func:`glsldiff.physics.optics.fresnel_transmittance`); flux rising in that bin leaves with
  the same factor and the rest is reflected down; the TIR bins reflect everything.
* Half-space: ``R_total = T_b (I - R_inf R_b)^-1 R_inf T_b``; its single-scattering part
  (``R_inf``'s first order, ``R1_ij = (a w_i / 2) mu_i / (mu_i + mu_j)``, with no internal
  reflection: what :mod:`glsldiff.render.single` computes) is taken out, so
  :func:`HalfspaceTables.multiple` is the light scattered two or more times.
* The escape distribution (:meth:`HalfspaceTables.escape`): the shape of the radiance a
  diffusive field sends out through the boundary, per unit flux leaving, for light that entered
  ``d`` mean free paths away: the scattered light crossing a slab of depth ``d`` (both faces
  smooth boundaries) lit diffusely from outside the far face, for ``d`` in
  :data:`ESCAPE_DEPTHS`. Its higher angular modes decay with ``d``: at ``d = 2`` the exit is
  more forward than a deep field's (normal exit 9 % brighter per unit flux at albedo 0.99, eta
  1.3); from ``d = 16`` on it is the deep field's.

Radiance leaving at ``nu_i`` per unit irradiance arriving at ``nu_j`` is the flux matrix over
``2 pi nu_i w_i``. Tables are on ``A_GRID`` albedos uniform in ``u = sqrt(1 - a)`` (as
:mod:`glsldiff.physics.halfspace`) times the ``N_OUT`` outside nodes, interpolated linearly in
``u`` and in ``nu`` (end nodes extended to ``nu`` = 0 and 1 by the nearest two); accurate to
about 1e-3 against the H-function at ``eta = 1``.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core import cache
from glsldiff.core.errors import InputError
from glsldiff.core.jit import kernel, prange
from glsldiff.physics.optics import fresnel_transmittance

__all__ = ["HalfspaceTables", "halfspace_tables", "slab_operators", "slab_transport", "N_OUT", "A_GRID",
           "ESCAPE_DEPTHS"]

#: Outside cosine nodes (Gauss-Legendre on (0, 1)).
N_OUT = 24
#: Inside nodes on the total-internal-reflection band (0, mu_c), eta > 1.
N_TIR = 12
#: Albedos of the tables (uniform in sqrt(1 - a)).
A_GRID = 33
#: Optical depth of the thin starting layer and of the half-space (doublings from one to the other).
_DTAU0 = 2.0 ** -14
_DEPTH = 2.0 ** 22
#: Depths (mean free paths) of the slabs whose transmission gives the escape distribution; the
#: last one stands for every larger depth (the deep field's shape).
ESCAPE_DEPTHS = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0)
#: Part of every cached table's key (with the sizes above): bump it when the tables' method changes.
TABLES_CACHE_VERSION = 1


@dataclass(frozen=True)
class _Angles:
    nu: NDArray[np.float64]       # outside nodes (N_OUT,)
    w_out: NDArray[np.float64]    # their weights (sum 1)
    mu: NDArray[np.float64]       # inside nodes: TIR band first, then t(nu)
    w: NDArray[np.float64]        # inside weights (sum 1 over (0, 1))
    ft: NDArray[np.float64]       # F_t(eta, nu) (N_OUT,)
    n_tir: int


def _angles(eta: float) -> _Angles:
    x, wx = np.polynomial.legendre.leggauss(N_OUT)
    nu, w_out = 0.5 * (x + 1.0), 0.5 * wx
    t = np.sqrt(1.0 - (1.0 - nu * nu) / (eta * eta))
    w_t = w_out * nu / (eta * eta * t)                  # d t = nu / (eta^2 t) d nu
    if eta > 1.0:
        mu_c = float(np.sqrt(1.0 - 1.0 / (eta * eta)))
        xa, wa = np.polynomial.legendre.leggauss(N_TIR)
        mu = np.concatenate([0.5 * mu_c * (xa + 1.0), t])
        w = np.concatenate([0.5 * mu_c * wa, w_t])
        n_tir = N_TIR
    else:
        mu, w, n_tir = t, w_t, 0
    ft = np.asarray(fresnel_transmittance(eta, nu), dtype=np.float64)
    return _Angles(nu, w_out, mu, w, ft, n_tir)


def _add(R1: NDArray, T1: NDArray, R2: NDArray, T2: NDArray) -> tuple[NDArray, NDArray]:
    """Layer 1 (symmetric) on top of layer 2: (R, T) of the pair for light from above."""
    I = np.eye(len(R1))
    R = R1 + T1 @ np.linalg.solve(I - R2 @ R1, R2 @ T1)
    T = T2 @ np.linalg.solve(I - R1 @ R2, T1)
    return R, T


def _thin_layer(a: float, mu: NDArray, w: NDArray, dtau: float) -> tuple[NDArray, NDArray]:
    """(R, T) of a layer of optical depth ``dtau`` to first order in the scattering, exact in
    the attenuation (so the grazing bins, ``dtau / mu`` not small, stay right)."""
    mi, mj = mu[:, None], mu[None, :]
    ei, ej = np.exp(-dtau / mi), np.exp(-dtau / mj)
    R = 0.5 * a * w[:, None] * mi / (mi + mj) * (1.0 - ei * ej)
    same = np.abs(mi - mj) < 1e-12
    diff = np.where(same, 1.0, mi - mj)
    Ts = 0.5 * a * w[:, None] * np.where(same, dtau / mi * ei, mi * (ei - ej) / diff)
    # what scatters again inside the layer (order dtau^2): a share a of it leaves, half up and
    # half down like the rest, so that a conservative layer (a = 1) conserves energy exactly
    again = a * (1.0 - np.exp(-dtau / mu)) - (R + Ts).sum(axis=0)
    extra = 0.5 * a * w[:, None] * np.maximum(again, 0.0)[None, :]
    return R + extra, np.diag(np.exp(-dtau / mu)) + Ts + extra


def slab_operators(albedo: float, depths: ArrayLike, eta: float = 1.0) -> dict[float, tuple[NDArray, NDArray]]:
    """``{depth: (R, T)}`` flux operators (inside bins) of medium layers of the given optical
    ``depths`` (mean free paths, > 0, rounded to a multiple of the thin layer's), by doubling the
    thin layer (module docstring) and adding the doubled layers of the depth's binary digits."""
    if not 0.0 <= albedo <= 1.0:
        raise InputError(f"albedo {albedo!r} must be in [0, 1]")
    ds = [float(d) for d in np.atleast_1d(depths)]
    if not all(d > 0 and np.isfinite(d) for d in ds):
        raise InputError(f"layer depths {ds} must be finite and > 0")
    ang = _angles(eta)
    counts = {d: max(1, int(round(d / _DTAU0))) for d in ds}
    top = max(counts.values()).bit_length()
    R, T = _thin_layer(albedo, ang.mu, ang.w, _DTAU0)
    powers = []
    for _ in range(top):
        powers.append((R, T))
        R, T = _add(R, T, R, T)
    out: dict[float, tuple[NDArray, NDArray]] = {}
    for d, n in counts.items():
        acc = None
        for bit in range(top):
            if n >> bit & 1:
                acc = powers[bit] if acc is None else _add(*acc, *powers[bit])
        out[d] = acc
    return out


def _boundaries(ang: _Angles) -> tuple[NDArray, NDArray]:
    """The smooth boundary: ``Tb`` (inside bins x outside nodes) the transmission of outside
    flux into the medium (and, transposed, out of it), ``Rb`` (inside bins) the internal
    reflection."""
    n_in, n_out = len(ang.mu), len(ang.nu)
    Tb = np.zeros((n_in, n_out))
    Tb[ang.n_tir + np.arange(n_out), np.arange(n_out)] = ang.ft
    Rb = np.ones(n_in)
    Rb[ang.n_tir:] = 1.0 - ang.ft
    return Tb, Rb


def _bounded_slab(ang: _Angles, Rl: NDArray, Tl: NDArray, depth: float) -> tuple[NDArray, NDArray]:
    """Flux matrices (outside node -> outside node) of a layer ``(Rl, Tl)`` of ``depth`` mean free
    paths between two smooth boundaries: the scattered light leaving the lit face (``R``) and
    the far face (``T``, the unscattered beam and its internal reflections taken out)."""
    Tb, Rb = _boundaries(ang)
    I = np.eye(len(ang.mu))
    # the slab with the far boundary below it, for light from above (inside): reflection, transmission out
    R_sb = Rl + Tl @ np.linalg.solve(I - Rb[:, None] * Rl, Rb[:, None] * Tl)
    T_sb = Tb.T @ np.linalg.solve(I - Rl * Rb[None, :], Tl)
    down = np.linalg.solve(I - Rb[:, None] * R_sb, Tb)                # down-going below the top boundary
    straight = np.zeros(len(ang.mu))
    straight[ang.n_tir:] = np.exp(-float(depth) / ang.mu[ang.n_tir:])
    beam = np.linalg.solve(I - np.diag(Rb * straight) @ np.diag(Rb * straight), np.diag(straight) @ Tb)
    return Tb.T @ (R_sb @ down), T_sb @ down - Tb.T @ beam


def slab_transport(albedo: float, depth: float, eta: float = 1.0) -> tuple[NDArray, NDArray, NDArray]:
    """A homogeneous slab of ``depth`` mean free paths between two smooth boundaries of relative
    index ``eta`` (outside on both faces): ``(nu, R, T)``, the outside nodes and the scattered
    radiance (sr^-1) leaving the lit face (``R[i, j]``) and the far face (``T[i, j]``, without
    the unscattered beam) at ``nu[i]`` per unit irradiance arriving at ``nu[j]``. The exact 1-D
    oracle of thin slabs (the specular surface reflection is left out)."""
    ang = _angles(eta)
    R, T = _bounded_slab(ang, *slab_operators(albedo, [depth], eta)[float(depth)], depth)
    to_radiance = 1.0 / (2.0 * np.pi * ang.nu * ang.w_out)
    return ang.nu, to_radiance[:, None] * R, to_radiance[:, None] * T


@kernel(inline=True)
def _nu_cell(nu: NDArray[np.float64], c: float) -> tuple[int, float]:
    """:meth:`HalfspaceTables._cosine_cell` of one cosine."""
    x = min(max(c, 0.0), 1.0)
    i = min(max(np.searchsorted(nu, x) - 1, 0), len(nu) - 2)
    return i, (x - nu[i]) / (nu[i + 1] - nu[i])


@kernel(parallel=True)
def _table_lookup(table: NDArray[np.float64], albedo: NDArray[np.float64], c1: NDArray[np.float64],
                  c2: NDArray[np.float64], nu: NDArray[np.float64], two: bool) -> NDArray[np.float64]:
    """``table[k, i, j]`` at each ``(albedo, c1, c2)``: linear in ``sqrt(1 - a)`` over ``k``, in
    ``c1`` over ``i`` and (``two``) in ``c2`` over ``j`` (else ``j = 0``); no Fresnel factor."""
    n_u = table.shape[0]
    out = np.empty(albedo.shape[0])
    for m in prange(albedo.shape[0]):
        fu = np.sqrt(1.0 - min(max(albedo[m], 0.0), 1.0)) * (n_u - 1)
        k = min(max(int(np.floor(fu)), 0), n_u - 2)
        du = fu - k
        i, f = _nu_cell(nu, c1[m])
        j, g = _nu_cell(nu, c2[m]) if two else (0, 0.0)
        acc = 0.0
        for dk in range(2):
            wk = du if dk else 1.0 - du
            if two:
                v = ((1 - f) * (1 - g) * table[k + dk, i, j] + f * (1 - g) * table[k + dk, i + 1, j]
                     + (1 - f) * g * table[k + dk, i, j + 1] + f * g * table[k + dk, i + 1, j + 1])
            else:
                v = (1 - f) * table[k + dk, i, 0] + f * table[k + dk, i + 1, 0]
            acc = acc + wk * v
        out[m] = acc
    return out


@dataclass(frozen=True)
class HalfspaceTables:
    """Half-space tables for one ``eta`` (module docstring): ``total[k, i, j]`` and
    ``single[k, i, j]`` radiance (sr^-1) leaving at outside cosine ``nu[i]`` per unit irradiance
    arriving at ``nu[j]`` for albedo ``a(u[k])``; ``escape_table`` (sr^-1) the far field's
    radiance per unit emergent flux. ``nu`` is the quadrature nodes with 0 and 1 added (values
    there extended linearly through the two nearest nodes); every table holds its values over
    ``F_t(eta, nu)`` of each cosine (smooth where ``F_t`` falls to 0 at grazing angles; the
    lookups multiply it back). ``escape_table[k, d, i]`` per depth ``ESCAPE_DEPTHS[d]``."""

    eta: float
    u: NDArray[np.float64]
    nu: NDArray[np.float64]
    total: NDArray[np.float64]
    single: NDArray[np.float64]
    escape_table: NDArray[np.float64]

    def _albedo_cell(self, albedo: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Lower table index and weight of the upper one, linear in ``u = sqrt(1 - a)``."""
        fu = np.sqrt(1.0 - np.clip(np.asarray(albedo, dtype=np.float64), 0.0, 1.0)) * (len(self.u) - 1)
        k = np.clip(np.floor(fu).astype(np.int64), 0, len(self.u) - 2)
        return k, fu - k

    def _cosine_cell(self, cosine: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Lower ``nu`` node index and weight of the upper one, linear in the cosine."""
        x = np.clip(np.asarray(cosine, dtype=np.float64), 0.0, 1.0)
        i = np.clip(np.searchsorted(self.nu, x) - 1, 0, len(self.nu) - 2)
        return i, (x - self.nu[i]) / (self.nu[i + 1] - self.nu[i])

    def _lookup(self, table: NDArray, albedo: ArrayLike, *cosines: ArrayLike) -> NDArray[np.float64]:
        """``table`` (albedo, one or two cosines) interpolated linearly in ``sqrt(1 - a)`` and in
        each cosine (a compiled kernel over the broadcast arguments), times ``F_t`` of each cosine."""
        args = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (albedo,) + cosines))
        flat = [np.ascontiguousarray(a).reshape(-1) for a in args]
        t = np.ascontiguousarray(table, dtype=np.float64)
        if len(cosines) == 1:
            out = _table_lookup(t[:, :, None], flat[0], flat[1], np.zeros_like(flat[1]), self.nu, False)
        else:
            out = _table_lookup(t, flat[0], flat[1], flat[2], self.nu, True)
        out = out.reshape(args[0].shape)
        for c in cosines:            # the tables hold the values over F_t of each cosine (smooth at 0)
            out = out * np.asarray(fresnel_transmittance(self.eta, np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)))
        return np.asarray(out, dtype=np.float64)

    def multiple(self, albedo: ArrayLike, nu_in: ArrayLike, nu_out: ArrayLike) -> NDArray[np.float64]:
        """Radiance (sr^-1) scattered two or more times, leaving at outside cosine ``nu_out``
        per unit irradiance arriving at ``nu_in``, broadcast."""
        return np.maximum(self._lookup(self._multiple_table, albedo, nu_out, nu_in), 0.0)

    @cached_property
    def _multiple_table(self) -> NDArray[np.float64]:
        """``total - single``: the lookup is linear in the table, so one lookup of the difference
        is the difference of the two lookups (one interpolation per frame instead of two)."""
        return self.total - self.single

    def total_reflection(self, albedo: ArrayLike, nu_in: ArrayLike, nu_out: ArrayLike) -> NDArray[np.float64]:
        """All scattering orders (sr^-1), as :meth:`multiple`."""
        return self._lookup(self.total, albedo, nu_out, nu_in)

    def single_reflection(self, albedo: ArrayLike, nu_in: ArrayLike, nu_out: ArrayLike) -> NDArray[np.float64]:
        """The once-scattered part (sr^-1), as :meth:`multiple`."""
        return self._lookup(self.single, albedo, nu_out, nu_in)

    def escape(self, albedo: ArrayLike, nu_out: ArrayLike, depth_mfp: ArrayLike | None = None) -> NDArray[np.float64]:
        """The far field's radiance (sr^-1) leaving at ``nu_out`` per unit flux leaving, for light
        that entered ``depth_mfp`` transport mean free paths away (module docstring; clamped to
        :data:`ESCAPE_DEPTHS`, linear between them; None: a deep field), broadcast."""
        if depth_mfp is None:
            return self._lookup(self.escape_table[:, -1], albedo, nu_out)
        a, x, d = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (albedo, nu_out, depth_mfp)))
        k, du = self._albedo_cell(a)
        i, f = self._cosine_cell(x)
        p = np.interp(d, ESCAPE_DEPTHS, np.arange(len(ESCAPE_DEPTHS), dtype=np.float64))
        j = np.clip(np.floor(p).astype(np.int64), 0, len(ESCAPE_DEPTHS) - 2)
        weights = (du, p - j, f)
        out = np.zeros(a.shape)
        for corner in np.ndindex(2, 2, 2):       # trilinear in sqrt(1 - albedo), depth and cosine
            w = np.prod([g if c else 1.0 - g for c, g in zip(corner, weights)], axis=0)
            out += w * self.escape_table[k + corner[0], j + corner[1], i + corner[2]]
        return out * np.asarray(fresnel_transmittance(self.eta, np.clip(x, 0.0, 1.0)))


def _linear_ends(table: NDArray[np.float64], nu: NDArray[np.float64], dims: int) -> NDArray[np.float64]:
    """``table`` with its ``dims`` cosine axes (after the albedo axis) extended from the nodes
    ``nu`` to 0 and 1, linearly through the two nearest nodes (not below 0)."""
    out = table
    for ax in range(1, dims + 1):
        a0, a1 = np.take(out, [0], axis=ax), np.take(out, [1], axis=ax)
        b0, b1 = np.take(out, [-1], axis=ax), np.take(out, [-2], axis=ax)
        lo = a0 + (a0 - a1) * (0.0 - nu[0]) / (nu[0] - nu[1])
        hi = b0 + (b0 - b1) * (1.0 - nu[-1]) / (nu[-1] - nu[-2])
        out = np.concatenate([np.maximum(lo, 0.0), out, np.maximum(hi, 0.0)], axis=ax)
    return out


@lru_cache(maxsize=8)
def halfspace_tables(eta: float) -> HalfspaceTables:
    """The half-space tables of relative index ``eta`` (>= 1): computed once per eta (0.2 s)
    and kept in the on-disk cache (:mod:`glsldiff.core.cache`), then once per process."""
    eta = float(eta)
    if not (eta >= 1.0 and np.isfinite(eta)):
        raise InputError(f"eta = {eta!r}: the half-space tables need a relative index >= 1")
    key = cache.digest(f"halfspace tables v{TABLES_CACHE_VERSION}", eta, N_OUT, N_TIR, A_GRID, _DTAU0, _DEPTH,
                       ESCAPE_DEPTHS)
    return cache.memo("halfspace", key, HalfspaceTables, lambda: _build_tables(eta))


def _build_tables(eta: float) -> HalfspaceTables:
    """:func:`halfspace_tables` of ``eta`` computed."""
    ang = _angles(eta)
    n_in, n_out = len(ang.mu), len(ang.nu)
    Tb, Rb = _boundaries(ang)                                            # outside -> inside bins, internal reflection
    to_radiance = 1.0 / (2.0 * np.pi * ang.nu * ang.w_out)              # outside flux -> radiance
    diffuse = 2.0 * ang.nu * ang.w_out                                   # unit Lambertian irradiance per node
    u = np.linspace(0.0, 1.0, A_GRID)
    total = np.zeros((A_GRID, n_out, n_out))
    single = np.zeros_like(total)
    escape = np.zeros((A_GRID, len(ESCAPE_DEPTHS), n_out))
    I = np.eye(n_in)
    mu, w = ang.mu, ang.w
    for k, uk in enumerate(u):
        a = 1.0 - uk * uk
        ops = slab_operators(min(a, 1.0 - 1e-9), [*ESCAPE_DEPTHS, _DEPTH], eta)
        R_inf = ops[_DEPTH][0]
        R1 = 0.5 * a * w[:, None] * mu[:, None] / (mu[:, None] + mu[None, :])
        up = np.linalg.solve(I - R_inf * Rb[None, :], R_inf @ Tb)
        total[k] = to_radiance[:, None] * (Tb.T @ up)
        single[k] = to_radiance[:, None] * (Tb.T @ R1 @ Tb)
        for d, depth in enumerate(ESCAPE_DEPTHS):                       # the far face of a diffusely lit slab
            flux = _bounded_slab(ang, *ops[depth], depth)[1] @ diffuse
            total_flux = flux.sum()
            escape[k, d] = to_radiance * flux / total_flux if total_flux > 0 else to_radiance / n_out
    f2 = ang.ft[:, None] * ang.ft[None, :]
    nu = np.concatenate([[0.0], ang.nu, [1.0]])
    return HalfspaceTables(eta, u, nu, _linear_ends(total / f2, ang.nu, 2), _linear_ends(single / f2, ang.nu, 2),
                           np.moveaxis(_linear_ends(np.moveaxis(escape / ang.ft, 2, 1), ang.nu, 1), 1, 2))
