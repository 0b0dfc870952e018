r"""First-collision (reduced-intensity) volume source of the diffusion equation.

Light refracted into the medium first travels unscattered, as *reduced intensity*; where it
first scatters it becomes an isotropic source of diffuse light (the extended-source treatment,
Mertens' thesis section 2.3, Jensen et al. 2001 section 2.2: ``L_ri`` attenuated by
``exp(-integral sigma_t')``):

.. math:: \nabla\cdot(\kappa\nabla\phi) - \mu\phi = -Q, \qquad Q = \sigma_s'\,\phi_{ri},

with no diffuse light entering through the boundary (``q = 0`` in the Robin condition
``phi + 2 C kappa dphi/dn = q``; the first moment of Q vanishes for the isotropic phase
function of the similarity relation, so the boundary condition needs no flux term).

The reduced fluence below a lit surface point, per *beam* (transmitted irradiance ``E``
arriving at the refracted cosine ``t``, :func:`glsldiff.render.pass1.incident_light`), is that
of a plane-parallel medium at depth z:

.. math:: \phi_{ri}(z) = \sum_k \frac{E_k}{t_k}\, e^{-\bar\sigma_t z / t_k},

``sigma_t_bar`` the mean of sigma_t' at the node and at the surface point (heterogeneous
media: a two-point path average; lateral offsets of the refracted path, at most about
one mean free path times tan(theta_t), are ignored).

Discretisation (:func:`node_source`): a node at depth ``d`` below the surface gets the load
``V_i <Q>_i`` (mm^-3 x source), ``V_i`` its lumped volume and ``<Q>_i`` the average of Q over
the 1-D hat function of half-width ``h`` centred at ``d`` and clipped to ``z >= 0`` (a
surface node's hat is the falling ramp on [0, h]). The hat averages of the exponential are
written in closed form, so a layer of nodes h apart receives the exact integral of Q across
its depth whatever ``sigma_t h`` is (stiff, absorbing media included).

When to use which (``[options].source``): ``"surface"`` (the Marshak source ``q`` on the
boundary, Wang et al.'s model) is right where light enters far (many mean free paths) from
where it is seen: smooth lighting of thick media. ``"volume"`` places the light where it first
scatters, one mean free path deep: it matters near localized light (spots, projector regions,
back-lit thin parts) and for thin media.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError

__all__ = ["hat_average_exp", "node_source", "SOURCES"]

#: Source models (``[options].source``).
SOURCES = ("surface", "volume")
#: Beams arriving flatter than this refracted cosine carry no volume source (grazing light).
T_MIN = 1e-6


def _ramp_up(L: NDArray[np.float64]) -> NDArray[np.float64]:
    """``int_0^1 e^{-L s} s ds`` (stable for small L)."""
    small = L < 1e-4
    Ls = np.where(small, 1.0, L)
    exact = (1.0 - np.exp(-Ls) * (1.0 + Ls)) / (Ls * Ls)
    return np.where(small, 0.5 - L / 3.0, exact)


def _flat(L: NDArray[np.float64]) -> NDArray[np.float64]:
    """``int_0^1 e^{-L s} ds``."""
    small = L < 1e-4
    Ls = np.where(small, 1.0, L)
    return np.where(small, 1.0 - L / 2.0, -np.expm1(-Ls) / Ls)


def hat_average_exp(a: ArrayLike, d: ArrayLike, h: float) -> NDArray[np.float64]:
    """Average of ``exp(-a z)`` over the hat function of half-width ``h`` (mm) centred at depth
    ``d`` (mm), clipped to ``z >= 0``; ``a`` (mm^-1) >= 0, broadcast with ``d``.

    Falling side ``z = d + s``: ``h e^{-a d} int_0^1 e^{-a h u} (1 - u) du``; rising side, its
    clipped width ``w = min(d, h)``, ``z = d - w + w v``: ``w e^{-a (d - w)} int_0^1 e^{-a w v}
    (1 - r + r v) dv`` with ``r = w / h``; divided by the clipped hat's integral
    ``h / 2 + w (1 - w / (2 h))``. Every exponential has a non-positive argument."""
    a, d = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.maximum(np.asarray(d, dtype=np.float64), 0.0))
    w = np.minimum(d, h)
    r = w / h
    fall = h * np.exp(-a * d) * (_flat(a * h) - _ramp_up(a * h))   # int e^{-L u} (1 - u)
    L = a * w
    rise = w * np.exp(-a * (d - w)) * ((1.0 - r) * _flat(L) + r * _ramp_up(L))
    return (fall + rise) / (0.5 * h + w * (1.0 - 0.5 * r))


def node_source(depth: ArrayLike, volume: ArrayLike, beams_E: ArrayLike, beams_t: ArrayLike,
                sigma_s: ArrayLike, sigma_t: ArrayLike, h: float) -> NDArray[np.float64]:
    """``(N, 3)`` load ``V_i <Q>_i`` of the first-collision source at N nodes.

    Parameters
    ----------
    depth
        ``(N,)`` node depth below the surface, mm (>= 0).
    volume
        ``(N,)`` lumped node volumes, mm^3.
    beams_E, beams_t
        ``(N, K, 3)`` transmitted irradiance and ``(N, K)`` refracted cosine of the K beams at
        each node's surface point.
    sigma_s, sigma_t
        ``(N, 3)`` sigma_s' at the node and the path's mean sigma_t' (mm^-1).
    h
        Node spacing, mm (> 0).
    """
    d = np.asarray(depth, dtype=np.float64)
    V = np.asarray(volume, dtype=np.float64)
    E = np.asarray(beams_E, dtype=np.float64)
    t = np.asarray(beams_t, dtype=np.float64)
    ss = np.asarray(sigma_s, dtype=np.float64)
    st = np.asarray(sigma_t, dtype=np.float64)
    if not (h > 0 and np.isfinite(h)):
        raise InputError(f"node spacing h = {h!r} mm must be finite and > 0")
    if E.ndim != 3 or t.shape != E.shape[:2] or d.shape != (len(E),) or st.shape != (len(E), 3):
        raise InputError(f"beams: E {E.shape}, t {t.shape}, depth {d.shape}, sigma_t {st.shape} do not match "
                         "(N, K, 3), (N, K), (N,), (N, 3)")
    if np.any(st <= 0):
        raise InputError("sigma_t' must be > 0 at every node with a volume source")
    out = np.zeros((len(d), 3))
    ok = t > T_MIN
    ts = np.where(ok, t, 1.0)
    for c in range(3):
        a = st[:, c, None] / ts                                      # (N, K) attenuation per mm of depth
        avg = hat_average_exp(a, d[:, None], h)                      # (N, K)
        out[:, c] = np.where(ok, E[..., c] / ts * avg, 0.0).sum(axis=1)
    return V[:, None] * ss * out
