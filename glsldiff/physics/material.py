"""Material coefficients, measured presets and volume checks.

The diffusion solver works with kappa = 1/(3 (sigma_a + sigma_s')) [mm] and mu = sigma_a
[mm^-1] per node and RGB channel (Wang et al. 2008, eq. 1). Volumes are arrays of shape
S + (3,), S = (nz, ny, nx) grid nodes; heterogeneous ones are built in
:mod:`glsldiff.physics.procedural`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.checks import finite_values, real, require
from glsldiff.core.errors import InputError
from glsldiff.physics.optics import _out, optical_pair

__all__ = ["Preset", "PRESETS", "preset", "coefficients", "optical_properties", "regime", "TRUSTED_ALBEDO",
           "validate_coefficients"]

Array = NDArray[np.float64]
ArrayOrScalar = NDArray[np.float64] | np.float64


def coefficients(sigma_a: ArrayLike, sigma_s_prime: ArrayLike) -> tuple[ArrayOrScalar, ArrayOrScalar]:
    """Diffusion coefficients from optical properties (broadcast together).

    Parameters
    ----------
    sigma_a, sigma_s_prime
        Absorption and reduced scattering coefficients [mm^-1], >= 0, sum > 0.

    Returns
    -------
    kappa = 1/(3 (sigma_a + sigma_s')) [mm], mu = sigma_a [mm^-1].
    """
    sa, _, st = optical_pair(sigma_a, sigma_s_prime)
    return _out(1.0 / (3.0 * st)), _out(sa.copy())


def _kappa_mu(k: Array, m: Array) -> tuple[Array, Array]:
    """``(kappa, mu)`` after checking kappa > 0 [mm] and mu >= 0 [mm^-1] entry by entry."""
    require(k, k <= 0.0, "kappa", "> 0", "kappa = 1/(3 (sigma_a + sigma_s')) is a positive length in mm")
    require(m, m < 0.0, "mu", ">= 0", "mu = sigma_a is a non-negative absorption coefficient in mm^-1")
    return k, m


def optical_properties(kappa: ArrayLike, mu: ArrayLike) -> tuple[ArrayOrScalar, ArrayOrScalar]:
    """Inverse of `coefficients`: (sigma_a, sigma_s') [mm^-1] from kappa [mm] and mu [mm^-1].

    Requires kappa > 0, mu >= 0 and 1/(3 kappa) >= mu (else sigma_s' < 0: not physical).
    """
    k, m = _kappa_mu(*np.broadcast_arrays(finite_values(kappa, "kappa"), finite_values(mu, "mu")))
    st = 1.0 / (3.0 * k)
    ss = st - m
    tol = 1e-12 * st  # round-off of a coefficients() round trip
    require(ss, ss < -tol, "1/(3 kappa) - mu (= sigma_s')", ">= 0",
            "that (kappa, mu) pair is not physical: lower kappa or mu so that 3 kappa mu <= 1")
    return _out(m.copy()), _out(np.maximum(ss, 0.0))


@dataclass(frozen=True, eq=False)
class Preset:
    """A homogeneous material: per-RGB reduced scattering and absorption [mm^-1], index eta."""

    name: str
    sigma_s_prime: Array
    sigma_a: Array
    eta: float

    def __post_init__(self) -> None:
        for field in ("sigma_s_prime", "sigma_a"):
            a = np.array(finite_values(getattr(self, field), f"{self.name}.{field}"), dtype=np.float64)
            if a.shape != (3,):
                raise InputError(f"{self.name}.{field} must have shape (3,) (RGB), got {a.shape}")
            a.flags.writeable = False
            object.__setattr__(self, field, a)
        coefficients(self.sigma_a, self.sigma_s_prime)  # validates signs
        object.__setattr__(self, "eta", real(self.eta, f"{self.name}.eta (relative index, e.g. 1.3)", 0.0,
                                             lo_open=True))

    def coefficients(self) -> tuple[Array, Array]:
        """(kappa [mm], mu [mm^-1]), each of shape (3,)."""
        return coefficients(self.sigma_a, self.sigma_s_prime)


# Jensen, Marschner, Levoy, Hanrahan 2001, Figure 5 (via pbrt-v4 SubsurfaceParameterTable),
# RGB in mm^-1: name -> (sigma_s', sigma_a). The table's own eta column was not transcribed;
# every preset uses eta = 1.3, which Wang et al. 2008 assume for all their materials.
_JENSEN_2001 = {
    "apple": ((2.29, 2.39, 1.97), (0.0030, 0.0034, 0.046)),
    "chicken1": ((0.15, 0.21, 0.38), (0.015, 0.077, 0.19)),
    "chicken2": ((0.19, 0.25, 0.32), (0.018, 0.088, 0.20)),
    "cream": ((7.38, 5.47, 3.15), (0.0002, 0.0028, 0.0163)),
    "ketchup": ((0.18, 0.07, 0.03), (0.061, 0.97, 1.45)),
    "marble": ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071)),
    "potato": ((0.68, 0.70, 0.55), (0.0024, 0.0090, 0.12)),
    "skimmilk": ((0.70, 1.22, 1.90), (0.0014, 0.0025, 0.0142)),
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48)),
    "skin2": ((1.09, 1.59, 1.79), (0.013, 0.070, 0.145)),
    "spectralon": ((11.6, 20.4, 14.9), (0.00, 0.00, 0.00)),
    "wholemilk": ((2.55, 3.21, 3.77), (0.0011, 0.0024, 0.014)),
}
PAPER_ETA = 1.3
PRESETS: dict[str, Preset] = {k: Preset(k, np.array(s), np.array(a), PAPER_ETA)
                              for k, (s, a) in _JENSEN_2001.items()}
_ALIASES = {"skin": "skin1"}  # plus any spelling with '_', '-' or ' ' (e.g. "skim_milk")


def preset(name: str | Preset) -> Preset:
    """Look up a measured preset by name (case-insensitive; "skim_milk", "skin" -> skin1)."""
    if isinstance(name, Preset):
        return name
    key = str(name).lower().strip()
    for sep in "_- ":
        key = key.replace(sep, "")
    key = _ALIASES.get(key, key)
    if key not in PRESETS:
        raise InputError(f"unknown material preset {name!r}; valid names: {', '.join(PRESETS)} "
                         f"(aliases: {', '.join(_ALIASES)}, skim_milk, whole_milk)")
    return PRESETS[key]


def validate_coefficients(kappa: ArrayLike, mu: ArrayLike,
                          shape: tuple[int, ...] | int | None = None) -> tuple[Array, Array]:
    """Check a (kappa [mm], mu [mm^-1]) volume and return both as float64 arrays S + (3,).

    Each input may be a scalar, an RGB constant (3,) or (1,), grey S, or S + (1,) / S + (3,).
    `shape` is the spatial shape S; if None, S comes from the input with more dimensions (its
    last axis is taken as RGB when it has size 3 or 1, so pass `shape` for grey volumes whose
    last spatial axis has size 3). Rejects NaN/inf, kappa <= 0, mu < 0 and shape mismatches.
    """
    k, m = finite_values(kappa, "kappa"), finite_values(mu, "mu")
    if shape is None:
        big = k if k.ndim >= m.ndim else m
        shape = big.shape[:-1] if big.ndim and big.shape[-1] in (1, 3) else big.shape
    S = (int(shape),) if np.isscalar(shape) else tuple(int(n) for n in shape)

    def rgb(name: str, a: Array) -> Array:
        if a.shape in (S + (3,), S + (1,)):
            return np.broadcast_to(a, S + (3,))
        if a.shape == S:
            return np.broadcast_to(a[..., None], S + (3,))
        if a.shape in ((), (1,), (3,)):
            return np.broadcast_to(a, S + (3,))
        raise InputError(f"{name} has shape {a.shape} but kappa {k.shape} and mu {m.shape} must share "
                         f"the spatial shape {S}: give {name} shape {S}, {S + (3,)} or a scalar")

    return _kappa_mu(np.array(rgb("kappa", k)), np.array(rgb("mu", m)))


#: Below this single-scattering albedo sigma_s' / sigma_t' the diffusion model is not trusted:
#: against Monte Carlo every diffusion variant was off by about 30 % at albedo 0.91 and within a
#: few percent at 0.99 and above (``../shared/notes/wang2008.md``, section 1).
TRUSTED_ALBEDO = 0.95


def regime(kappa: ArrayLike, mu: ArrayLike, h: float, model: str = "diffusion") -> str:
    """One line on the material at the nodes (``kappa`` mm, ``mu`` mm^-1 per node and channel)
    on a grid of spacing ``h`` mm: the albedo range and the transport mean free path ``1 /
    sigma_t'`` against ``h``; for ``model = "diffusion"`` also the share of nodes below
    :data:`TRUSTED_ALBEDO` (where its P1 exitance is not trusted) and that the light's
    first-collision depth is smeared when the mean free path is below ``h`` (the split takes the
    light near where it enters from exact half-space tables instead)."""
    k = np.asarray(kappa, dtype=np.float64)
    m = np.asarray(mu, dtype=np.float64)
    st = 1.0 / (3.0 * k)
    albedo = np.clip(1.0 - m / st, 0.0, 1.0)
    mfp = 1.0 / st
    text = f"regime: albedo {albedo.min():.3g}-{albedo.max():.3g}; "
    if model == "diffusion":
        low = float((albedo < TRUSTED_ALBEDO).reshape(len(albedo), -1).any(axis=1).mean())
        text += (f"{100 * low:.1f} % of nodes below {TRUSTED_ALBEDO} in some channel (diffusion off by up to ~30 % "
                 "there); ")
    text += f"mean free path {mfp.min():.3g}-{mfp.max():.3g} mm vs node spacing {h:.3g} mm"
    if model == "diffusion" and mfp.min() < h:
        text += " (finer than the grid: light entering and leaving within one spacing is smeared over it)"
    return text
