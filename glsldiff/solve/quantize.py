"""The paper's rendering precision for the material (Wang et al. 2008, section 6): each
channel of kappa and mu quantised to 8 bits (RGB8 textures), radiance in fp16.

The paper does not say how the 8 bits map to values. Here kappa (> 0, spanning decades in
a heterogeneous material) is stored on a log scale and mu (which may be 0) linearly, each
over the range of the active nodes per channel::

    kappa = exp(lo_k + t (hi_k - lo_k)),   mu = lo_m + t (hi_m - lo_m),   t = code / 255

so a homogeneous channel is exact, a kappa contrast of 1e4 costs at most 1.8 % per node
(half a step of ln(1e4) / 255) and mu has an absolute error of at most (hi_m - lo_m) / 510.
:func:`decode` gives the values the shaders see, for the CPU twin of an 8-bit solve.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

MATERIAL_PRECISIONS = ("fp32", "8bit")


def _range(values: NDArray, active: NDArray[np.bool_]) -> tuple[NDArray, NDArray]:
    v = values[active] if active.any() else values
    return v.min(axis=0), v.max(axis=0)


def _codes(x: NDArray, lo: NDArray, hi: NDArray) -> NDArray[np.uint8]:
    span = np.where(hi > lo, hi - lo, 1.0)
    return np.clip(np.rint((x - lo) / span * 255.0), 0, 255).astype(np.uint8)


def encode(kappa: NDArray, mu: NDArray, active: NDArray[np.bool_]) -> tuple[NDArray[np.uint8], NDArray[np.uint8],
                                                                           dict[str, tuple[float, float, float]]]:
    """``(N, 3)`` kappa (mm) and mu (mm^-1) -> 8-bit codes and the decode uniforms
    ``u_kappa_lo/hi`` (ln mm) and ``u_mu_lo/hi`` (mm^-1); ranges over the ``active`` nodes."""
    lk = np.log(np.asarray(kappa, dtype=np.float64))
    m = np.asarray(mu, dtype=np.float64)
    klo, khi = _range(lk, active)
    mlo, mhi = _range(m, active)
    uniforms = {"u_kappa_lo": tuple(map(float, klo)), "u_kappa_hi": tuple(map(float, khi)),
                "u_mu_lo": tuple(map(float, mlo)), "u_mu_hi": tuple(map(float, mhi))}
    return _codes(lk, klo, khi), _codes(m, mlo, mhi), uniforms


def decode(kappa: NDArray, mu: NDArray, active: NDArray[np.bool_]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """kappa and mu as an 8-bit solve sees them (encode, then decode)."""
    ck, cm, u = encode(kappa, mu, active)
    lo, hi = np.array(u["u_kappa_lo"]), np.array(u["u_kappa_hi"])
    k = np.exp(lo + ck / 255.0 * (hi - lo))
    lo, hi = np.array(u["u_mu_lo"]), np.array(u["u_mu_hi"])
    return k, lo + cm / 255.0 * (hi - lo)
