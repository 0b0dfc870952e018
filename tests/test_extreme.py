"""Stiff and degenerate problems: pure scattering, extreme absorption, 1e4 kappa jumps, slabs one
or two interior nodes thick, fp16 overflow, and a paper-stencil system with rho(J) > 1.

Contract checked throughout: a solver returns a finite, non-negative solution that matches the
direct solve, or it says it did not converge (report.converged False) / raises SolverError.
The report's residual is the float64 Jacobi-scaled residual of the returned iterate; for the fp32
GLSL iterate it has a rounding floor (measured 3.6e-8 .. 2.8e-7 here), so a GLSL solve with a tol
at or below that floor ends "stalled" (converged False): accepted where the error vs the direct
solve still meets the bound ("budget" and "diverged" never are).
References: scipy's sparse LU (DirectSolver) of the same discrete system; the Jacobi matrix
J = I - D^-1 A (its spectral radius from scipy.sparse.linalg.eigs) for convergence speed.
Runs on the $GLSLDIFF_GL context (``ctx``) and numpy.
"""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from glsldiff.solve.jacobi import solve_glsl
from glsldiff.core.errors import SolverError
from glsldiff.grids.regular import RegularGrid
from glsldiff.system.problem import DiffusionProblem, relative_l2
from glsldiff.oracle.assembly import assemble, jacobi_radius_bound
from glsldiff.oracle.solvers import DirectSolver, jacobi

def _rho(p: DiffusionProblem) -> float:
    """Spectral radius of the Jacobi matrix, max over channels (Perron root: J >= 0 here)."""
    s = assemble(p)
    n, out = s.n, []
    for c in range(3):
        A = s.A[c * n:(c + 1) * n, c * n:(c + 1) * n]
        J = (sp.eye(n) - sp.diags(1.0 / s.diag[c * n:(c + 1) * n]) @ A).tocsr()
        out.append(abs(spla.eigs(J, k=1, which="LM", return_eigenvectors=False, tol=1e-10)[0]))
    return float(max(out))


def _factor(rep) -> float:
    """Average residual reduction per sweep from the initial guess (sweep 0) to the smallest
    residual, (r_best / r_0)^(1 / sweeps): a stalled tail at the fp32 floor is left out."""
    best = min(range(len(rep.history)), key=lambda i: rep.history[i][1])
    (n0, r0), (n1, r1) = rep.history[0], rep.history[best]
    return (r1 / r0) ** (1.0 / (n1 - n0))


def _ok(phi: np.ndarray) -> bool:
    return bool(np.isfinite(phi).all() and phi.min() >= 0.0)


def _ended_ok(rep) -> bool:
    """Converged, or (GLSL fp32) stalled at the rounding floor of its buffers."""
    return rep.status in ("converged", "stalled") and rep.converged == (rep.status == "converged")


# ---------------------------------------------------------------- mu = 0
@pytest.mark.parametrize("stencil", ["paper", "conservative"])
def test_pure_scattering_converges_slowly(ctx, stencil):
    """mu = 0 everywhere (no absorption, light only leaves through the faces): Jacobi still
    converges, but slowly: > 500 sweeps, residual factor per sweep > 0.95, approaching rho(J).
    The fp32 GLSL solve (tol 1e-7) stalls at its floor: measured 1550 sweeps, best residual
    2.77e-7 at 1150 sweeps, rel L2 vs direct 1.3e-6; its true residual falls at rho(J) (per-check
    factor 0.98737 vs rho 0.98737) until ~1e-5, then the floor flattens it."""
    g = RegularGrid(12, 12, 12, 0.5)
    p = DiffusionProblem(g, 0.5, 0.0, {"z-": 1.0, "x+": [0.2, 0.4, 0.6]}, stencil=stencil)
    ref, _ = DirectSolver(p).solve()
    rho = _rho(p)
    phi_np, rep_np = jacobi(p, tol=1e-9, maxiter=20000, check_every=10)
    phi_gl, rep_gl = solve_glsl(p, ctx, tol=1e-7, maxiter=20000)
    f_np, f_gl = _factor(rep_np), _factor(rep_gl)
    err_np, err_gl = relative_l2(phi_np, ref), relative_l2(phi_gl, ref)
    print(f"mu=0 {stencil}: rho(J)={rho:.5f}; numpy {rep_np.sweeps} sweeps, factor {f_np:.5f}, "
          f"err {err_np:.1e}; GLSL {rep_gl.sweeps} sweeps, factor {f_gl:.5f}, err {err_gl:.1e}")
    assert 0.95 < rho < 1.0
    assert rep_np.converged and rep_np.status == "converged" and _ended_ok(rep_gl)
    for rep, f in ((rep_np, f_np), (rep_gl, f_gl)):
        assert rep.sweeps > 500
        assert 0.95 < f < 1.0 and f <= rho + 3e-3
    tail = (rep_np.history[-1][1] / rep_np.history[-11][1]) ** (1 / 100)
    assert abs(tail - rho) < 2e-3
    # GLSL: the true residual of the fp32 iterate, above the floor (1e-5 .. 1e-2), falls at rho
    mid = [(n, r) for n, r in rep_gl.history if 1e-5 < r < 1e-2]
    (n0, r0), (n1, r1) = mid[0], mid[-1]
    assert n1 - n0 >= 200 and abs((r1 / r0) ** (1 / (n1 - n0)) - rho) < 2e-3
    assert err_np < 1e-7 and err_gl < 1e-4
    assert _ok(phi_np) and _ok(phi_gl)


# ---------------------------------------------------------------- huge absorption
@pytest.mark.parametrize("mu", [100.0, 1e4], ids=["h2mu/k=1e4", "h2mu/k=1e6"])
@pytest.mark.parametrize("stencil", ["paper", "conservative"])
def test_extreme_absorption_converges_fast(ctx, stencil, mu):
    """h^2 mu / kappa >= 1e4: the interior rows are dominated by absorption, Jacobi converges at
    the first check (history: initial guess, one check); the solution (about q on the boundary,
    ~0 inside) is finite, >= 0, = direct. Measured: numpy 10 sweeps, error <= 1.2e-16; GLSL
    converged after 50 sweeps at residual 2.9e-8 .. 6.8e-8, error 2.8e-8 .. 6.8e-8."""
    g = RegularGrid(10, 9, 8, 1.0)
    p = DiffusionProblem(g, 0.01, mu, {"z-": 1.0, "x+": [0.5, 1.0, 2.0]}, stencil=stencil)
    assert (g.h ** 2 * mu / 0.01) >= 1e4
    ref, _ = DirectSolver(p).solve()
    phi_np, rep_np = jacobi(p, tol=1e-12)
    phi_gl, rep_gl = solve_glsl(p, ctx, tol=1e-7)
    print(f"mu={mu:g} {stencil}: numpy {rep_np.sweeps} sweeps err {relative_l2(phi_np, ref):.1e}; "
          f"GLSL {rep_gl.sweeps} sweeps err {relative_l2(phi_gl, ref):.1e}")
    assert rep_np.converged and rep_np.sweeps <= 20
    assert rep_gl.converged and rep_gl.status == "converged"
    assert [n for n, _ in rep_gl.history] == [0, 50] and rep_gl.history[0] == (0, 1.0)
    assert relative_l2(phi_np, ref) < 1e-12 and relative_l2(phi_gl, ref) < 1e-5
    assert _ok(ref) and _ok(phi_np) and _ok(phi_gl)
    assert ref[g.shape[0] // 2, g.shape[1] // 2, g.shape[2] // 2].max() < 1e-6  # deep inside: dark


# ---------------------------------------------------------------- 1e4 kappa contrast
def _checkerboard(g: RegularGrid) -> np.ndarray:
    z, y, x = np.indices(g.shape)
    return np.where((x + y + z) % 2 == 0, 0.01, 100.0)


def _jump_plane(g: RegularGrid) -> np.ndarray:
    z = np.indices(g.shape)[0]
    return np.where(z < g.nz // 2, 0.01, 100.0)


@pytest.mark.parametrize("face_mean", ["arithmetic", "harmonic"])
def test_checkerboard_1e4_conservative(ctx, face_mean):
    """kappa alternating 0.01 / 100 mm node by node (contrast 1e4), conservative stencil:
    diagonally dominant, so numpy and GLSL Jacobi converge to the (non-negative) direct solution.
    GLSL tol 1e-8 is below the fp32 floor here: measured stalled at residual 5.8e-8 (arithmetic,
    750 sweeps) / 4.4e-8 (harmonic, 450), rel L2 vs direct 6.4e-8 / 4.5e-8."""
    g = RegularGrid(10, 9, 8, 0.5)
    p = DiffusionProblem(g, _checkerboard(g), 0.5, {"z-": 1.0}, stencil="conservative", face_mean=face_mean)
    ref, _ = DirectSolver(p).solve()
    phi_np, rep_np = jacobi(p, tol=1e-10, maxiter=50000)
    phi_gl, rep_gl = solve_glsl(p, ctx, tol=1e-8, maxiter=50000)
    print(f"checkerboard conservative/{face_mean}: numpy {rep_np.sweeps} sweeps err "
          f"{relative_l2(phi_np, ref):.1e}; GLSL {rep_gl.sweeps} sweeps err {relative_l2(phi_gl, ref):.1e}")
    assert rep_np.converged and _ended_ok(rep_gl)
    assert relative_l2(phi_np, ref) < 1e-7 and relative_l2(phi_gl, ref) < 1e-5
    assert _ok(ref) and _ok(phi_np) and _ok(phi_gl)


def test_checkerboard_1e4_paper_raises(ctx):
    """Same checkerboard, paper stencil: boundary nodes with kappa 100 linked to interior nodes with
    kappa 0.01 break diagonal dominance (J_bj J_jb ~ (kappa_b/kappa_j)/6 >> 1): the exact discrete
    solution goes negative and both iterative solvers raise SolverError ('diverged ... spectral
    radius >= ...') instead of returning garbage."""
    g = RegularGrid(10, 9, 8, 0.5)
    p = DiffusionProblem(g, _checkerboard(g), 0.5, {"z-": 1.0}, stencil="paper")
    ref, _ = DirectSolver(p).solve()
    bound = jacobi_radius_bound(assemble(p))
    print(f"checkerboard paper: radius bound {bound:.2f}, direct min {ref.min():.2e}")
    assert bound > 1.0 and ref.min() < 0.0
    with pytest.raises(SolverError, match=r"numpy Jacobi diverged .*spectral radius >= \d+\.\d+.*conservative"):
        jacobi(p, tol=1e-8)
    with pytest.raises(SolverError, match=r"GLSL Jacobi diverged .*spectral radius >= \d+\.\d+.*conservative"):
        solve_glsl(p, ctx, tol=1e-7)


@pytest.mark.parametrize("stencil", ["paper", "conservative"])
def test_jump_plane_1e4(ctx, stencil):
    """kappa 0.01 below z = nz/2, 100 above (one 1e4 jump plane parallel to the lit face).
    Conservative: converges, slowly in the kappa = 100 half (rho(J) ~ 0.9996: nearly pure
    scattering there), so the GLSL tolerance is 1e-8 (error <= residual / (1 - rho)).
    Paper: also converges, because every boundary node shares kappa with its interior partner
    (no jump across a boundary link), so the matrix stays an M-matrix; the answer is finite,
    non-negative and equals its own direct solve.
    Measured (GLSL, tol 1e-8, below the fp32 floor): both stall, paper after 750 sweeps at
    residual 3.6e-8, error 3.6e-8; conservative after 4450 sweeps at residual 3.7e-8, error
    2.9e-5 (with tol 1e-7 it "converges" after 50 sweeps with error 1.5e-4 > 1e-4, hence 1e-8)."""
    g = RegularGrid(10, 9, 8, 0.5)
    p = DiffusionProblem(g, _jump_plane(g), 0.5, {"z-": 1.0}, stencil=stencil)
    ref, _ = DirectSolver(p).solve()
    phi_np, rep_np = jacobi(p, tol=1e-10, maxiter=100000)
    phi_gl, rep_gl = solve_glsl(p, ctx, tol=1e-8, maxiter=100000)
    err_np, err_gl = relative_l2(phi_np, ref), relative_l2(phi_gl, ref)
    print(f"jump plane {stencil}: rho {_rho(p):.5f}; numpy {rep_np.sweeps} sweeps err {err_np:.1e}; "
          f"GLSL {rep_gl.sweeps} sweeps err {err_gl:.1e}")
    assert jacobi_radius_bound(assemble(p)) < 1.0
    assert rep_np.converged and _ended_ok(rep_gl)
    assert err_np < 1e-5 and err_gl < 1e-4
    assert _ok(ref) and _ok(phi_np) and _ok(phi_gl)


# ---------------------------------------------------------------- thin slabs
@pytest.mark.parametrize("nz", [4, 3], ids=["2-interior-layers", "1-interior-layer"])
@pytest.mark.parametrize("stencil", ["paper", "conservative"])
def test_thin_slab(ctx, stencil, nz):
    """A slab two (nz=4) or one (nz=3) interior nodes thick, lit on both z faces and one side:
    the z- and z+ boundary nodes link to the same or adjacent interior layer; GLSL and numpy
    match the direct solve. kappa varies smoothly in x, y only (+-30 %) and mu per node: with
    node-wise random kappa the paper stencil diverges here (an interior node of a 1-2 layer slab
    has two z-boundary neighbours, so kappa_b/kappa_j > 1 feeds back twice).
    Measured (GLSL, tol 1e-7): all four stall at residual 1.9e-7 .. 2.5e-7 (650 .. 700 sweeps),
    rel L2 vs direct 1.6e-7 .. 2.9e-7."""
    g = RegularGrid(12, 10, nz, 0.25)
    z, y, x = np.indices(g.shape)
    kappa = 0.3 * (1 + 0.3 * np.sin(2 * np.pi * x / g.nx) * np.cos(2 * np.pi * y / g.ny))
    mu = np.random.default_rng(nz).uniform(0.5, 2.0, g.shape + (3,))
    p = DiffusionProblem(g, kappa, mu, {"z-": 1.0, "z+": 0.2, "x-": 0.4}, stencil=stencil)
    ref, _ = DirectSolver(p).solve()
    phi_np, rep_np = jacobi(p, tol=1e-11)
    phi_gl, rep_gl = solve_glsl(p, ctx, tol=1e-7)
    print(f"thin slab nz={nz} {stencil}: GLSL {rep_gl.status} after {rep_gl.sweeps} sweeps, residual "
          f"{rep_gl.residual:.1e}, err {relative_l2(phi_gl, ref):.1e}")
    assert rep_np.converged and _ended_ok(rep_gl)
    assert relative_l2(phi_np, ref) < 1e-9 and relative_l2(phi_gl, ref) < 1e-5
    assert _ok(phi_gl) and _ok(ref)


# ---------------------------------------------------------------- fp16 overflow
@pytest.mark.parametrize("stencil", ["paper", "conservative"])
def test_fp16_overflow_raises(ctx, stencil):
    """q so large that the iterate exceeds the fp16 range (65504; llvmpipe saturates there instead
    of writing inf): SolverError naming fp16, not a 'converged' fluence ~99 % too small. The same
    problem in fp32 is fine (measured: converged, rel L2 vs direct 6.6e-6 / 4.7e-6)."""
    g = RegularGrid(11, 9, 8, 0.2)
    p = DiffusionProblem(g, 0.3, 0.5, {"z-": 1e8}, stencil=stencil)
    with pytest.raises(SolverError, match=r"overflowed the fp16 buffers .*65504.*precision='fp32'"):
        phi, rep = solve_glsl(p, ctx, precision="fp16")
        print(f"fp16 q=1e8 {stencil}: {rep.status}, max phi {phi.max():.3g}")
    assert ctx.error == "GL_NO_ERROR"
    phi32, rep32 = solve_glsl(p, ctx, tol=1e-6)
    assert rep32.converged and relative_l2(phi32, DirectSolver(p).solve()[0]) < 1e-4


# ---------------------------------------------------------------- rho(J) slightly above 1
def _steep_paper_problem(smooth_kappa) -> DiffusionProblem:
    """Smooth-looking kappa (Gaussian filter sigma 1.5 nodes, 100x contrast, neighbour ratio up to
    ~4) on a 20x16x6 grid: the paper-stencil Jacobi matrix has rho = 1.006 although the pair bound
    is 0.6, and the exact discrete solution is negative somewhere."""
    g = RegularGrid(20, 16, 6, 0.1)
    kappa = smooth_kappa(g.shape, 1, sigma=1.5)
    mu = np.random.default_rng(1).uniform(0.0, 10.0, g.shape + (3,))
    return DiffusionProblem(g, kappa, mu, {"z-": 1.0, "x+": 0.3}, stencil="paper")


def test_paper_stencil_rho_above_one_is_not_reported_converged(ctx, smooth_kappa):
    """rho(J) = 1.006 (> 1): neither iterative solver may claim convergence (each either raises
    SolverError or returns converged=False); the direct solution itself has negative values."""
    p = _steep_paper_problem(smooth_kappa)
    rho = _rho(p)
    ref, _ = DirectSolver(p).solve()
    assert rho > 1.0 and ref.min() < 0.0
    for name, run in (("numpy", lambda: jacobi(p, tol=1e-10, maxiter=20000)),
                      ("GLSL", lambda: solve_glsl(p, ctx, tol=1e-7))):
        try:
            phi, rep = run()
        except SolverError as exc:
            print(f"rho={rho:.4f} {name}: SolverError {exc}")
            continue
        print(f"rho={rho:.4f} {name}: status {rep.status} after {rep.sweeps} sweeps, residual "
              f"{rep.residual:.1e}, error vs direct {relative_l2(phi, ref):.2e}")
        assert not rep.converged


@pytest.mark.parametrize("solver, check_every", [
    ("numpy", 10),
    ("numpy", 50),
    ("glsl", 50),
], ids=["numpy-check10", "numpy-check50", "glsl-check50"])
def test_slow_divergence_is_reported_as_divergence(smooth_kappa, request, solver, check_every):
    """A Jacobi iteration with rho(J) = 1.006 ends in SolverError ('diverged'), not 'stalled'.
    Measured: numpy and GLSL with check_every=50 raise after 450 sweeps."""
    p = _steep_paper_problem(smooth_kappa)
    with pytest.raises(SolverError, match=r"Jacobi diverged after \d+ sweeps"):
        if solver == "numpy":
            jacobi(p, tol=1e-10, maxiter=20000, check_every=check_every)
        else:
            solve_glsl(p, request.getfixturevalue("ctx"), tol=1e-7, check_every=check_every)
