"""Grid convergence of the discrete diffusion problem against the closed-form slab solution.

PDE (Wang et al. 2008, eqs. 1-2) for a homogeneous slab 0 <= z <= T, laterally infinite:
``kappa phi'' - mu phi = 0`` with ``phi + 2 C kappa dphi/dn = q`` on both faces (q = 1 on z = 0,
q = 0 on z = T). Exact solution (glsldiff.oracle.closed_forms.slab_fluence): with s = sqrt(mu/kappa),
``phi(z) = a cosh(s z) + b sinh(s z)/s``, a and b fixed by the two boundary conditions.

Laterally-uniform trick: the block is W x W x T with W >= 2 T, and each side-face node gets
q = phi(z) (the exact fluence at its height: dphi/dn = 0 there, so the 1D solution is the exact
3D solution). The error is measured on the centre column x = y = W/2, all z nodes, as
max |phi_h - phi| / max |phi|; the order is the slope of log(error) against log(h).
"""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.oracle.closed_forms import slab_fluence
from glsldiff.grids.regular import RegularGrid
from glsldiff.physics.optics import boundary_constant
from glsldiff.system.problem import DiffusionProblem
from glsldiff.oracle.solvers import DirectSolver

KAPPA, MU = 0.3, 1.0  # mm, mm^-1
C_ROBIN = float(boundary_constant(1.3))  # 2.60
C_DIRICHLET = 1e-9  # phi = q on the faces


def _slab_error(thickness: float, width: float, h: float, C: float, kappa: float = KAPPA,
                mu: float = MU) -> float:
    n, nz = int(round(width / h)) + 1, int(round(thickness / h)) + 1
    g = RegularGrid(n, n, nz, h)
    z = np.arange(nz) * h
    exact = slab_fluence(z, thickness, kappa, mu, C, 1.0, 0.0)
    side = np.broadcast_to(exact[1:-1, None], (nz - 2, n - 2))
    q = {"z-": 1.0, "z+": 0.0, "x-": side, "x+": side, "y-": side, "y+": side}
    phi, rep = DirectSolver(DiffusionProblem(g, kappa, mu, q, C=C)).solve()
    assert rep.residual < 1e-10
    column = phi[:, n // 2, n // 2, :]
    assert np.ptp(column, axis=1).max() == 0.0  # RGB channels are identical
    return float(np.abs(column[:, 0] - exact).max() / np.abs(exact).max())


def _rate(hs, errs) -> float:
    return float(np.polyfit(np.log(hs), np.log(errs), 1)[0])


def test_slab_fluence_solves_the_boundary_value_problem():
    """slab_fluence satisfies kappa phi'' = mu phi and both Robin conditions (central differences,
    step 1e-4 mm); with mu = 0 it is the straight line through the two conditions."""
    T, C = 2.0, C_ROBIN
    f = lambda z: slab_fluence(z, T, KAPPA, MU, C, 1.0, 0.25)  # noqa: E731
    d = 1e-4
    z = np.linspace(0.1, T - 0.1, 9)
    second = (f(z + d) - 2 * f(z) + f(z - d)) / d**2
    np.testing.assert_allclose(KAPPA * second, MU * f(z), rtol=1e-5)
    d0 = (f(d) - f(-d)) / (2 * d)
    dT = (f(T + d) - f(T - d)) / (2 * d)
    assert f(0.0) - 2 * C * KAPPA * d0 == pytest.approx(1.0, rel=1e-8)
    assert f(T) + 2 * C * KAPPA * dT == pytest.approx(0.25, rel=1e-8)
    lin = slab_fluence(np.array([0.0, T]), T, KAPPA, 0.0, C, 1.0, 0.0)
    k2 = 2 * C * KAPPA  # phi = a + b z: a - k2 b = 1, a + b (T + k2) = 0
    b = -1.0 / (T + 2 * k2)
    np.testing.assert_allclose(lin, [1.0 + k2 * b, 1.0 + k2 * b + b * T], rtol=1e-12)


def test_linear_slab_is_reproduced_exactly():
    """mu = 0: the exact fluence is linear in z; both the 7-point interior stencil and the
    one-sided boundary difference are exact for linear functions, so the discrete solution
    equals it to round-off at any h."""
    for h in (0.5, 0.25):
        assert _slab_error(2.0, 4.0, h, C_ROBIN, mu=0.0) < 1e-10


CASES = [
    # name, C, expected order, |rate - order| tolerance, thickness, width, h values, finest-error bound
    pytest.param("robin", C_ROBIN, 1.0, 0.15, 2.0, 4.0, (1.0, 0.5, 0.25), 0.2, id="robin-C2.60"),
    pytest.param("dirichlet", C_DIRICHLET, 2.0, 0.15, 2.0, 4.0, (0.5, 0.25), 4e-3, id="dirichlet-C1e-9"),
]
SLOW_CASES = [
    pytest.param("robin", C_ROBIN, 1.0, 0.1, 2.0, 4.0, (0.5, 0.25, 0.125), 0.1, id="robin-C2.60"),
    pytest.param("dirichlet", C_DIRICHLET, 2.0, 0.1, 2.0, 4.0, (0.5, 0.25, 0.125), 1e-3, id="dirichlet-C1e-9"),
]


def _check_rate(name, C, order, eps, thickness, width, hs, bound):
    errs = [_slab_error(thickness, width, h, C) for h in hs]
    rate = _rate(hs, errs)
    print(f"slab {name} C={C:.3g} T={thickness} W={width} h={hs}: errors "
          f"{', '.join(f'{e:.3e}' for e in errs)}; observed order {rate:.3f}")
    assert abs(rate - order) < eps, f"observed order {rate:.3f}, expected {order} +- {eps} (errors {errs})"
    assert errs[-1] < bound, f"finest error {errs[-1]:.3e} >= {bound}"
    assert all(b < a for a, b in zip(errs, errs[1:])), f"error not decreasing: {errs}"


@pytest.mark.parametrize("name, C, order, eps, thickness, width, hs, bound", CASES)
def test_slab_convergence_order(name, C, order, eps, thickness, width, hs, bound):
    """Observed order on the slab, h down to 0.25 mm. With C = boundary_constant(1.3) the boundary
    row ``phi_b + 2 C kappa (phi_b - phi_j)/h = q`` is a one-sided (O(h)) difference for dphi/dn
    at the face: first order. With C -> 0 (Dirichlet limit) it becomes phi_b = q and the 7-point
    interior stencil gives second order."""
    _check_rate(name, C, order, eps, thickness, width, hs, bound)


@pytest.mark.slow
@pytest.mark.parametrize("name, C, order, eps, thickness, width, hs, bound", SLOW_CASES)
def test_slab_convergence_order_fine(name, C, order, eps, thickness, width, hs, bound):
    """As test_slab_convergence_order with three resolutions down to h = 0.125 mm (18k nodes; the
    Dirichlet-limit LU takes ~30 s): order 1 (Robin, one-sided boundary difference) and 2 (C -> 0)."""
    _check_rate(name, C, order, eps, thickness, width, hs, bound)
