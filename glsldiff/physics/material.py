"""Material coefficients, measured presets and synthetic heterogeneous volumes.

The diffusion solver works with kappa = 1/(3 (sigma_a + sigma_s')) [mm] and mu = sigma_a
[mm^-1] per node and RGB channel (Wang et al. 2008, eq. 1). Volumes are arrays of shape
S + (3,), S = (nz, ny, nx) grid nodes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from glsldiff.core.errors import InputError
from glsldiff.physics.optics import _check, _finite, _out

__all__ = ["Preset", "PRESETS", "preset", "coefficients", "optical_properties",
           "validate_coefficients", "marble_volume", "random_volume"]

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
    sa, ss = np.broadcast_arrays(_finite("sigma_a", sigma_a), _finite("sigma_s_prime", sigma_s_prime))
    _check("sigma_a", sa, sa < 0.0, ">= 0", "absorption coefficients are non-negative, in mm^-1")
    _check("sigma_s_prime", ss, ss < 0.0, ">= 0", "reduced scattering is non-negative, in mm^-1")
    st = sa + ss
    _check("sigma_a + sigma_s_prime", st, st <= 0.0, "> 0", "make sigma_a or sigma_s_prime positive")
    return _out(1.0 / (3.0 * st)), _out(sa.copy())


def optical_properties(kappa: ArrayLike, mu: ArrayLike) -> tuple[ArrayOrScalar, ArrayOrScalar]:
    """Inverse of `coefficients`: (sigma_a, sigma_s') [mm^-1] from kappa [mm] and mu [mm^-1].

    Requires kappa > 0, mu >= 0 and 1/(3 kappa) >= mu (else sigma_s' < 0: not physical).
    """
    k, m = np.broadcast_arrays(_finite("kappa", kappa), _finite("mu", mu))
    _check("kappa", k, k <= 0.0, "> 0", "kappa = 1/(3 (sigma_a + sigma_s')) is a positive length in mm")
    _check("mu", m, m < 0.0, ">= 0", "mu = sigma_a is a non-negative absorption coefficient in mm^-1")
    st = 1.0 / (3.0 * k)
    ss = st - m
    tol = 1e-12 * st  # round-off of a coefficients() round trip
    _check("1/(3 kappa) - mu (= sigma_s')", ss, ss < -tol, ">= 0",
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
            a = np.array(_finite(f"{self.name}.{field}", getattr(self, field)), dtype=np.float64)
            if a.shape != (3,):
                raise InputError(f"{self.name}.{field} must have shape (3,) (RGB), got {a.shape}")
            a.flags.writeable = False
            object.__setattr__(self, field, a)
        coefficients(self.sigma_a, self.sigma_s_prime)  # validates signs
        eta = float(_finite(f"{self.name}.eta", self.eta))
        if eta <= 0.0:
            raise InputError(f"{self.name}.eta must be a relative index > 0 (e.g. 1.3), got {eta}")
        object.__setattr__(self, "eta", eta)

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
    k, m = _finite("kappa", kappa), _finite("mu", mu)
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

    k, m = np.array(rgb("kappa", k)), np.array(rgb("mu", m))
    _check("kappa", k, k <= 0.0, "> 0", "kappa = 1/(3 (sigma_a + sigma_s')) is a positive length in mm")
    _check("mu", m, m < 0.0, ">= 0", "mu = sigma_a is a non-negative absorption coefficient in mm^-1")
    return k, m


def _smooth_noise(shape: tuple[int, ...], rng: np.random.Generator, octaves: int, cells: int) -> Array:
    """Sum of `octaves` octaves of cubic-upsampled lattice noise in about [-1, 1]."""
    total = np.zeros(shape)
    for o in range(octaves):
        n = cells * 2**o  # lattice cells across the longest axis
        lattice = [max(2, int(np.ceil(n * s / max(shape))) + 1) for s in shape]
        field = ndimage.zoom(rng.uniform(-1.0, 1.0, lattice), [s / l for s, l in zip(shape, lattice)],
                             order=3, mode="nearest")
        total += 0.5**o * field[tuple(slice(0, s) for s in shape)]
    return total


def marble_volume(shape: tuple[int, ...], seed: int = 0, base: str | Preset = "marble",
                  vein: str | Preset | None = None, *, vein_absorption: float = 20.0,
                  vein_scattering: float = 0.5, stripes: float = 3.0, turbulence: float = 5.0,
                  sharpness: float = 6.0, octaves: int = 4) -> tuple[Array, Array]:
    """Deterministic synthetic "marble with veins" volume (sin-turbulence marble).

    Vein weight t = (1 - |sin(2 pi stripes u + turbulence n(x))|)^sharpness in [0, 1], with u the
    coordinate along a fixed oblique direction (0 to 1 across the longest axis) and n smooth
    lattice noise (`octaves` octaves, 2^o * 2 cells, amplitude 2^-o). sigma_a and sigma_s'
    [mm^-1] blend linearly from `base` (t = 0) to `vein` (t = 1), so kappa and mu stay within
    the two materials' values. vein=None means base.sigma_a * vein_absorption and
    base.sigma_s_prime * vein_scattering (a darker, more absorbing material).

    Returns
    -------
    (kappa [mm], mu [mm^-1]), each of shape shape + (3,); identical for equal arguments.
    """
    shape = (int(shape),) if np.isscalar(shape) else tuple(int(n) for n in shape)
    if not 1 <= len(shape) <= 3 or min(shape) < 1:
        raise InputError(f"shape must be 1 to 3 positive grid sizes (nz, ny, nx), got {shape}")
    for name, v in (("vein_absorption", vein_absorption), ("vein_scattering", vein_scattering),
                    ("sharpness", sharpness)):
        if not (np.isfinite(v) and v > 0):
            raise InputError(f"{name} must be a finite number > 0, got {v}")
    b = preset(base)
    if vein is None:
        sa1, ss1 = b.sigma_a * vein_absorption, b.sigma_s_prime * vein_scattering
    else:
        sa1, ss1 = preset(vein).sigma_a, preset(vein).sigma_s_prime
    rng = np.random.default_rng(seed)
    axes = np.meshgrid(*[np.arange(s) / max(max(shape) - 1, 1) for s in shape], indexing="ij")
    direction = np.array([0.3, 0.5, 1.0][-len(shape):])  # (z, y, x) weights: vein sheets roughly normal to x
    u = sum(w * x for w, x in zip(direction / np.linalg.norm(direction), axes))
    phase = 2.0 * np.pi * stripes * u + turbulence * _smooth_noise(shape, rng, octaves, 2)
    t = ((1.0 - np.abs(np.sin(phase))) ** sharpness)[..., None]
    return coefficients((1.0 - t) * b.sigma_a + t * sa1, (1.0 - t) * b.sigma_s_prime + t * ss1)


def random_volume(shape: tuple[int, ...], rng: np.random.Generator | int | None,
                  kappa_contrast: float = 100.0, mu_max: float = 10.0,
                  kappa_min: float = 0.01) -> tuple[Array, Array]:
    """Random (kappa, mu) volume of shape shape + (3,) for solver tests.

    kappa is log-uniform in [kappa_min, kappa_min * kappa_contrast] [mm] and mu uniform in
    [0, mu_max] [mm^-1], independently per node and channel. Pairs need not be physical
    (3 kappa mu may exceed 1); `optical_properties` would reject those.
    """
    if not (np.isfinite(kappa_contrast) and kappa_contrast >= 1.0):
        raise InputError(f"kappa_contrast must be a finite ratio >= 1, got {kappa_contrast}")
    if not (np.isfinite(mu_max) and mu_max >= 0.0):
        raise InputError(f"mu_max must be finite and >= 0 mm^-1, got {mu_max}")
    if not (np.isfinite(kappa_min) and kappa_min > 0.0):
        raise InputError(f"kappa_min must be finite and > 0 mm, got {kappa_min}")
    gen = np.random.default_rng(rng)
    full = ((int(shape),) if np.isscalar(shape) else tuple(int(n) for n in shape)) + (3,)
    kappa = kappa_min * kappa_contrast ** gen.uniform(0.0, 1.0, full)
    return kappa, gen.uniform(0.0, mu_max, full)
