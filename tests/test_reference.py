"""Tests for the CPU oracle glsldiff.oracle.solvers (assemble, DirectSolver, solve_direct, jacobi,
jacobi_radius_bound) and the discrete-problem helpers of glsldiff.system.problem.

References: the discrete equations in the glsldiff.system.problem module docstring (Wang et al. 2008,
eq. 8), re-assembled here with explicit loops; scipy's dense solver / eigenvalues; pyamg's
Jacobi relaxation; Jacobi theory (asymptotic residual factor = spectral radius of I - D^-1 A).
"""
from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from glsldiff.physics import procedural
from glsldiff.grids.regular import BOUNDARY, INTERIOR, RegularGrid
from glsldiff.physics.optics import fresnel_transmittance
from glsldiff.system.problem import DiffusionProblem, relative_l2
from glsldiff.oracle.assembly import assemble, assemble_rhs, jacobi_radius_bound
from glsldiff.oracle.solvers import DirectSolver, jacobi, solve_amg, solve_direct

STENCILS = [("paper", "arithmetic"), ("conservative", "arithmetic"), ("conservative", "harmonic")]
STENCIL_IDS = ["paper", "conservative-arith", "conservative-harm"]


def _random_problem(stencil: str, face_mean: str = "arithmetic", shape=(7, 6, 8), h=0.25, seed=0,
             white: bool | None = None) -> DiffusionProblem:
    """A heterogeneous RGB problem. Conservative: node-wise (white) random kappa, 100x contrast;
    paper: mildly varying kappa (the paper's stencil needs it, see test_extreme)."""
    g = RegularGrid(*shape, h)
    rng = np.random.default_rng(seed)
    white = stencil == "conservative" if white is None else white
    if white:
        kappa, mu = procedural.random_volume(g.shape, seed, kappa_contrast=100.0, mu_max=2.0)
    else:
        kappa = 0.1 * np.exp(0.2 * rng.standard_normal(g.shape + (3,)))
        mu = rng.uniform(0.0, 2.0, g.shape + (3,))
    q = {"z-": rng.uniform(0.5, 1.5, g.face_shape("z-") + (3,)), "x+": 0.4, "y-": [0.1, 0.2, 0.3]}
    return DiffusionProblem(g, kappa, mu, q, stencil=stencil, face_mean=face_mean)


def _loop_system(p: DiffusionProblem, c: int) -> tuple[np.ndarray, np.ndarray]:
    """Dense (A, b) of channel ``c`` written row by row from the problem docstring:
    paper interior ``(6 + h^2 mu/k) u_i - sum u_j = 0``; conservative interior
    ``(sum k_ij + h^2 mu) phi_i - sum k_ij phi_j = 0``; boundary
    ``phi_b + 2 C k_b (phi_b - phi_j)/h = q_b`` times ``h`` (times ``k_b`` for u = k phi)."""
    g, h, C = p.grid, p.grid.h, float(p.C)
    k, m, q = p.kappa[..., c], p.mu[..., c], p.q[..., c]
    nz, ny, nx = g.shape
    nodes = [(z, y, x) for z, y, x in itertools.product(range(nz), range(ny), range(nx))
             if ((x in (0, nx - 1)) + (y in (0, ny - 1)) + (z in (0, nz - 1))) <= 1]
    pos = {node: i for i, node in enumerate(nodes)}
    A = np.zeros((len(nodes), len(nodes)))
    b = np.zeros(len(nodes))
    for i, (z, y, x) in enumerate(nodes):
        on = [(ax, v) for ax, v in enumerate((z, y, x)) if v in (0, g.shape[ax] - 1)]
        if not on:  # interior
            for dz, dy, dx in [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]:
                j = pos[(z + dz, y + dy, x + dx)]
                kj = k[z + dz, y + dy, x + dx]
                if p.stencil == "paper":
                    w = 1.0
                elif p.face_mean == "arithmetic":
                    w = 0.5 * (k[z, y, x] + kj)
                else:
                    w = 2 * k[z, y, x] * kj / (k[z, y, x] + kj)
                A[i, j] -= w
                A[i, i] += w
            A[i, i] += h * h * (m[z, y, x] / k[z, y, x] if p.stencil == "paper" else m[z, y, x])
        else:  # boundary: partner one step inward
            (ax, v), = on
            partner = [z, y, x]
            partner[ax] = 1 if v == 0 else g.shape[ax] - 2
            j = pos[tuple(partner)]
            kb, kj = k[z, y, x], k[tuple(partner)]
            A[i, i] = h + 2 * C * kb
            if p.stencil == "paper":
                A[i, j] = -2 * C * kb * kb / kj
                b[i] = h * kb * q[z, y, x]
            else:
                A[i, j] = -2 * C * kb
                b[i] = h * q[z, y, x]
    return A, b


def _channel(system, c):
    n = system.n
    return system.A[c * n:(c + 1) * n, c * n:(c + 1) * n], system.b[c * n:(c + 1) * n]


def _jacobi_rho(p: DiffusionProblem) -> float:
    """Exact spectral radius of I - D^-1 A (max over channels), dense eigenvalues."""
    s = assemble(p)
    rhos = []
    for c in range(3):
        A, _ = _channel(s, c)
        A = A.toarray()
        rhos.append(np.abs(np.linalg.eigvals(np.eye(len(A)) - A / np.diag(A)[:, None])).max())
    return float(max(rhos))


# ---------------------------------------------------------------- assembly
@pytest.mark.parametrize("stencil, face_mean", STENCILS, ids=STENCIL_IDS)
def test_assembly_matches_loop_assembly(stencil, face_mean):
    """assemble() equals the docstring equations assembled node by node (all three channels)."""
    p = _random_problem(stencil, face_mean, shape=(5, 4, 6))
    s = assemble(p)
    for c in range(3):
        A, b = _channel(s, c)
        A_ref, b_ref = _loop_system(p, c)
        np.testing.assert_allclose(A.toarray(), A_ref, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(b, b_ref, rtol=1e-14, atol=0)
    np.testing.assert_array_equal(s.diag, s.A.diagonal())
    np.testing.assert_array_equal(s.b, assemble_rhs(p))


def test_paper_interior_row():
    """Paper stencil, interior node i: diagonal 6 + h^2 mu_i/kappa_i, -1 at its six neighbours, 0 elsewhere."""
    p = _random_problem("paper")
    g = p.grid
    s = assemble(p)
    A0, _ = _channel(s, 0)
    A0 = A0.tocsr()
    pos = {int(f): i for i, f in enumerate(s.active)}
    for z, y, x in np.argwhere(g.kind == INTERIOR)[::7]:
        i = pos[int(np.ravel_multi_index((z, y, x), g.shape))]
        row = A0.getrow(i)
        cols = dict(zip(row.indices, row.data))
        assert cols.pop(i) == pytest.approx(6 + g.h ** 2 * p.mu[z, y, x, 0] / p.kappa[z, y, x, 0], rel=1e-15)
        want = {pos[int(np.ravel_multi_index((z + dz, y + dy, x + dx), g.shape))] for dz, dy, dx in
                [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]}
        assert set(cols) == want
        assert all(v == -1.0 for v in cols.values())


@pytest.mark.parametrize("face_mean", ["arithmetic", "harmonic"])
def test_conservative_rows_are_diagonally_dominant(face_mean):
    """Conservative stencil, white 100x kappa: off-diagonals <= 0 and |a_ii| >= sum_j |a_ij|, strictly
    on boundary rows and where mu > 0 (an irreducibly diagonally dominant Z-matrix: an M-matrix)."""
    p = _random_problem("conservative", face_mean)
    s = assemble(p)
    A = s.A.tocsr()
    off = A - sp.diags(A.diagonal())
    assert off.max() <= 0.0
    margin = A.diagonal() - np.asarray(abs(off).sum(axis=1)).ravel()
    assert margin.min() >= -1e-12 * A.diagonal().max()
    kind = np.tile(p.grid.kind.ravel()[s.active], 3)
    mu = p.mu.reshape(-1, 3)[s.active].T.ravel()
    strict = (kind == BOUNDARY) | (mu > 0)
    assert np.all(margin[strict] > 0)
    assert jacobi_radius_bound(s) < 1.0


def test_constant_kappa_stencils_agree():
    """For constant kappa both stencils discretise the same equation: identical phi (1e-12)."""
    g = RegularGrid(9, 7, 6, 0.3)
    rng = np.random.default_rng(4)
    mu = rng.uniform(0, 3, g.shape + (3,))
    q = {"z-": rng.random(g.face_shape("z-")), "y+": 0.5}
    phis = [solve_direct(DiffusionProblem(g, [0.2, 0.4, 0.8], mu, q, stencil=st))[0]
            for st in ("paper", "conservative")]
    assert relative_l2(phis[0], phis[1]) < 1e-12


# ---------------------------------------------------------------- direct solver
@pytest.mark.parametrize("stencil, face_mean", STENCILS, ids=STENCIL_IDS)
def test_direct_residual(stencil, face_mean):
    """The LU solution satisfies A x = b to round-off (report residual and ||Ax-b||/||b|| < 1e-12)."""
    p = _random_problem(stencil, face_mean, shape=(12, 10, 9))
    phi, rep = solve_direct(p)
    s = assemble(p)
    x = s.from_volume(p.from_phi(phi))
    assert np.linalg.norm(s.A @ x - s.b) / np.linalg.norm(s.b) < 1e-13
    assert rep.residual < 1e-12
    assert rep.method == "scipy-direct" and rep.converged and rep.sweeps == 0
    assert rep.nodes == p.grid.n_active
    assert np.all(phi[~p.grid.active] == 0.0)
    assert phi.min() >= 0.0  # an M-matrix with b >= 0


@pytest.mark.parametrize("stencil, face_mean", STENCILS, ids=STENCIL_IDS)
def test_amg_solver_matches_direct(stencil, face_mean):
    """solve_amg (pyamg smoothed aggregation + GMRES, the large-grid reference) equals the LU solve."""
    pytest.importorskip("pyamg")
    p = _random_problem(stencil, face_mean, shape=(12, 10, 9))
    phi, rep = solve_amg(p, tol=1e-12)
    assert rep.converged and rep.residual < 1e-9
    assert relative_l2(phi, solve_direct(p)[0]) < 1e-9


@pytest.mark.parametrize("stencil, face_mean", STENCILS, ids=STENCIL_IDS)
def test_direct_solver_reuse_with_new_q(stencil, face_mean):
    """DirectSolver.solve(q2) on one factorisation equals a fresh solve of the problem with q2."""
    p = _random_problem(stencil, face_mean)
    g = p.grid
    q2 = {"y+": np.random.default_rng(9).random(g.face_shape("y+") + (3,)), "x-": 2.0}
    solver = DirectSolver(p)
    phi1, _ = solver.solve()
    phi2, rep2 = solver.solve(q2)
    fresh, _ = solve_direct(p.with_q(q2))
    assert relative_l2(phi2, fresh) < 1e-12
    assert relative_l2(phi1, solve_direct(p)[0]) < 1e-12
    np.testing.assert_array_equal(rep2.radiance["x-"], p.with_q(q2).exitant_radiance(phi2)["x-"])


@pytest.mark.parametrize("stencil, face_mean", STENCILS, ids=STENCIL_IDS)
def test_solution_is_linear_in_q(stencil, face_mean):
    """phi(a q1 + b q2) = a phi(q1) + b phi(q2) (the operator is linear, q enters only b)."""
    p = _random_problem(stencil, face_mean)
    g = p.grid
    rng = np.random.default_rng(5)
    q1 = {"z-": rng.random(g.face_shape("z-") + (3,))}
    q2 = {"x+": rng.random(g.face_shape("x+")), "z+": [1.0, -0.5, 0.25]}  # signed sources allowed
    solver = DirectSolver(p)
    a, b = 2.5, -0.75
    both = {"z-": a * q1["z-"], "x+": b * q2["x+"], "z+": b * np.array(q2["z+"])}
    lhs = solver.solve(both)[0]
    rhs = a * solver.solve(q1)[0] + b * solver.solve(q2)[0]
    assert relative_l2(lhs, rhs) < 1e-12


@pytest.mark.parametrize("stencil", ["paper", "conservative"])
def test_exitant_radiance_equals_boundary_flux(stencil):
    """L = F_t (phi - q)/(2 pi) on each face equals -(C/pi) F_t kappa_b (phi_b - phi_j)/h, the
    boundary condition's flux form (problem.exitant_radiance docstring, paper eq. 3)."""
    p = replace(_random_problem(stencil), exitant="paper")
    g = p.grid
    phi, rep = solve_direct(p)
    ft = float(fresnel_transmittance(p.eta, 1.0))
    link = g.link
    flat_phi = phi.reshape(-1, 3)
    flux = np.zeros_like(phi)
    bnd = g.kind == BOUNDARY
    flux[bnd] = -(p.C / np.pi) * ft * p.kappa[bnd] * (phi[bnd] - flat_phi[link[bnd]]) / g.h
    for name, L in rep.radiance.items():
        np.testing.assert_allclose(L, ft * (g.face(phi, name) - g.face(p.q, name)) / (2 * np.pi), rtol=1e-13)
        np.testing.assert_allclose(L, g.face(flux, name), rtol=1e-9, atol=1e-12 * np.abs(L).max())


# ---------------------------------------------------------------- numpy Jacobi
@pytest.mark.parametrize("stencil, face_mean", STENCILS, ids=STENCIL_IDS)
def test_numpy_jacobi_converges_to_direct(stencil, face_mean):
    """numpy Jacobi with tol 1e-11 reaches the direct solution to < 1e-8 relative L2; the history
    starts with the zero initial guess (residual exactly 1) and ends with the reported residual."""
    p = _random_problem(stencil, face_mean)
    ref, _ = solve_direct(p)
    phi, rep = jacobi(p, tol=1e-11, maxiter=20000)
    assert rep.converged and rep.status == "converged" and rep.residual <= 1e-11
    assert relative_l2(phi, ref) < 1e-8
    assert rep.sweeps % 10 == 0 and rep.history[-1] == (rep.sweeps, rep.residual)
    assert rep.history[0] == (0, 1.0)
    assert [n for n, _ in rep.history] == list(range(0, rep.sweeps + 1, 10))
    s = assemble(p)
    assert rep.residual == pytest.approx(s.residual(s.from_volume(p.from_phi(phi))), rel=1e-6)


@pytest.mark.parametrize("sweeps", [1, 3, 17])
@pytest.mark.parametrize("stencil, face_mean", STENCILS, ids=STENCIL_IDS)
def test_numpy_jacobi_matches_pyamg_jacobi(stencil, face_mean, sweeps):
    """N sweeps of reference.jacobi equal N sweeps of pyamg's Jacobi relaxation on the same system."""
    relaxation = pytest.importorskip("pyamg.relaxation.relaxation")
    p = _random_problem(stencil, face_mean)
    s = assemble(p)
    x = np.zeros_like(s.b)
    relaxation.jacobi(s.A.tocsr(), x, s.b.copy(), iterations=sweeps, omega=1.0)
    want = p.to_phi(s.to_volume(x, p.grid.shape))
    phi, rep = jacobi(p, tol=0.0, maxiter=sweeps, check_every=sweeps)
    assert rep.sweeps == sweeps and not rep.converged
    assert relative_l2(phi, want) < 1e-13


@pytest.mark.parametrize("stencil, face_mean", STENCILS, ids=STENCIL_IDS)
def test_jacobi_convergence_factor_is_spectral_radius(stencil, face_mean):
    """pyamg-style check on the residual history (check_every=1, initial residual included, so
    len(res) = sweeps + 1): the average factor (r_n/r_0)^(1/n) is below rho(I - D^-1 A) and the
    last-50-sweep factor equals it (1e-3)."""
    p = _random_problem(stencil, face_mean)
    rho = _jacobi_rho(p)
    res: list[float] = []
    _, rep = jacobi(p, tol=1e-12, maxiter=5000, check_every=1, residuals=res)
    assert rep.converged and len(res) == rep.sweeps + 1 and res[0] == 1.0
    assert res == [r for _, r in rep.history]
    factor = (res[-1] / res[0]) ** (1.0 / (len(res) - 1))
    tail = (res[-1] / res[-51]) ** (1.0 / 50)
    print(f"{stencil}/{face_mean}: rho={rho:.5f} average factor={factor:.5f} tail factor={tail:.5f}")
    assert rho < 1.0
    assert factor <= rho + 1e-3
    assert abs(tail - rho) < 1e-3
    assert jacobi_radius_bound(assemble(p)) <= rho + 1e-12  # documented as a lower bound


@pytest.mark.parametrize("stencil", ["paper", "conservative"])
def test_jacobi_warm_start_and_zero_source(stencil):
    """x0 = the direct solution already satisfies tol: converged after 0 sweeps, x0 returned
    (history: the initial guess only; measured residual 9e-16 / 3e-16); q = 0 gives phi = 0
    after 0 sweeps with residual 0."""
    p = _random_problem(stencil)
    ref, _ = solve_direct(p)
    phi, rep = jacobi(p, x0=ref, tol=1e-10, check_every=5)
    assert rep.converged and rep.status == "converged" and rep.sweeps == 0
    assert rep.history == [(0, rep.residual)] and rep.residual < 1e-14
    assert relative_l2(phi, ref) < 1e-12
    phi0, rep0 = jacobi(p.with_q({}), tol=1e-10)
    assert rep0.converged and rep0.sweeps == 0 and np.all(phi0 == 0.0)
    assert rep0.history == [(0, 0.0)]


def test_jacobi_zero_budget_returns_initial_guess():
    """maxiter=0 must not relax: the result is the initial guess (zero, or x0 at the active
    nodes), sweeps == 0, status 'budget' with the initial residual as the only history entry."""
    p = _random_problem("conservative")
    phi, rep = jacobi(p, maxiter=0)
    assert rep.sweeps == 0
    assert np.all(phi == 0.0), f"one sweep was applied: max phi = {phi.max():.3g}"
    assert rep.status == "budget" and not rep.converged and rep.history == [(0, 1.0)]
    x0 = np.random.default_rng(2).uniform(0.1, 1.0, p.grid.shape + (3,))
    phi, rep = jacobi(p, x0=x0, maxiter=0)
    assert rep.sweeps == 0 and rep.status == "budget"
    np.testing.assert_array_equal(phi, np.where(p.grid.active[..., None], x0, 0.0))


# ---------------------------------------------------------------- uniform solver interface
def test_uniform_interface_fills_residuals_and_calls_back():
    """Every oracle solver takes the pyamg-style arguments (glsldiff.system.report): ``residuals``
    gets the history (initial residual first, the report's history), ``callback(x)`` sees the
    unknown vector, ``x0`` starts the iteration; direct: one residual, one callback."""
    p = _random_problem("conservative")
    s = assemble(p)
    ref, _ = solve_direct(p)
    seen: list[np.ndarray] = []
    res: list[float] = []
    phi, rep = jacobi(p, tol=1e-8, maxiter=5000, x0=0.5 * ref, callback=seen.append, residuals=res)
    assert rep.converged and res == [r for _, r in rep.history] and len(seen) == len(res) - 1
    assert res[0] < 1.0  # started from x0, not zero
    np.testing.assert_array_equal(seen[-1], s.from_volume(p.from_phi(phi)))
    res_d, seen_d = [], []
    _, rep_d = solve_direct(p, callback=seen_d.append, residuals=res_d)
    assert res_d == [rep_d.residual] and len(seen_d) == 1 and rep_d.history == [(0, rep_d.residual)]
    pytest.importorskip("pyamg")
    res_a, seen_a = [], []
    phi_a, rep_a = solve_amg(p, tol=1e-10, x0=ref, callback=seen_a.append, residuals=res_a)
    assert len(seen_a) == 1 and res_a[0] < 1e-10 and rep_a.sweeps == len(res_a) - 1
    assert relative_l2(phi_a, ref) < 1e-9
