"""Closed-form solutions of the continuous boundary-value problem, for validation."""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def slab_fluence(z: ArrayLike, thickness: float, kappa: float, mu: float, C: float,
                 q_minus: float, q_plus: float) -> NDArray[np.float64]:
    """Fluence of a laterally infinite homogeneous slab, ``0 <= z <= thickness`` (mm).

    Solves ``kappa phi'' - mu phi = 0`` with the paper's boundary condition
    ``phi + 2 C kappa dphi/dn = q`` on both faces (outward normals -z at ``z = 0``
    with source ``q_minus``, +z at ``z = thickness`` with ``q_plus``). With
    ``s = sqrt(mu / kappa)``, ``phi = a cosh(s z) + b sinh(s z) / s`` (linear for mu = 0).
    """
    if kappa <= 0 or mu < 0 or thickness <= 0:
        raise ValueError("slab_fluence needs kappa > 0, mu >= 0, thickness > 0")
    s = np.sqrt(mu / kappa)
    L, k2 = thickness, 2.0 * C * kappa

    def sinhc(x: ArrayLike) -> NDArray:  # sinh(s x) / s, -> x as s -> 0
        x = np.asarray(x, dtype=np.float64)
        return np.sinh(s * x) / s if s > 0 else x

    # a - k2 b = q_minus;  a (cosh sL + k2 s sinh sL) + b (sinhc L + k2 cosh sL) = q_plus
    M = np.array([[1.0, -k2],
                  [np.cosh(s * L) + k2 * s * np.sinh(s * L), sinhc(L) + k2 * np.cosh(s * L)]])
    a, b = np.linalg.solve(M, [q_minus, q_plus])
    z = np.asarray(z, dtype=np.float64)
    return a * np.cosh(s * z) + b * sinhc(z)


def sphere_fluence(r: ArrayLike, radius: float, kappa: float, mu: float, C: float,
                   q: float) -> NDArray[np.float64]:
    """Fluence of a homogeneous sphere of ``radius`` (mm) under a uniform boundary source ``q``.

    Solves ``kappa Laplacian phi - mu phi = 0`` with ``phi + 2 C kappa dphi/dr = q`` at
    ``r = radius``: ``phi(r) = a sinh(s r) / r``, ``s = sqrt(mu / kappa)`` (``phi = q``
    everywhere for ``mu = 0``). ``r`` (mm) is the distance from the centre. Evaluated as
    ``q / D0 * (R / r) e^{s (r - R)} expm1(-2 s r) / expm1(-2 s R)`` with
    ``D0 = 1 + 2 C kappa (s coth(s R) - 1 / R)``, which does not overflow for large ``s R``.
    """
    if kappa <= 0 or mu < 0 or radius <= 0:
        raise ValueError("sphere_fluence needs kappa > 0, mu >= 0, radius > 0")
    r = np.asarray(r, dtype=np.float64)
    if mu == 0:
        return np.full_like(r, float(q))
    s = np.sqrt(mu / kappa)
    R = float(radius)
    x, X = s * r, s * R
    D0 = 1.0 + 2.0 * C * kappa * (s / np.tanh(X) - 1.0 / R)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        shape = R / r * np.exp(x - X) * np.expm1(-2.0 * x) / np.expm1(-2.0 * X)
    centre = 2.0 * X * np.exp(-X) / -np.expm1(-2.0 * X)          # the limit r -> 0
    return q / D0 * np.where(r > 1e-12 * R, shape, centre)
